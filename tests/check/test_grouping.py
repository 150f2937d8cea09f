"""Frames of one condition grouped by their temperature set point, not the thermistor's reading
(``forensics.check.measurements.group_frames``)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from forensics.check.measurements import group_frames
from forensics.io.dataset import Dataset, Frame


def _frame(name: str, exposure: float, measured: float | None, setpoint: float | None, subject: str = "dark") -> Frame:
    extra = {"set_temperature_c": "" if setpoint is None else str(setpoint)}
    return Frame(Path(name), name, subject=subject, temperature_c=measured, extra=extra, _exposure_s=exposure,
                 _exif_done=True)


def test_a_wandering_thermistor_does_not_split_a_condition():
    """Ten 60 s darks at the −5 °C set point read −5.6 … −4.4 °C (a wander of 0.6 °C, as a thermistor's read-out
    gives): one condition of ten frames at their mean measured temperature; a frame 3 °C off its set point (never
    settled) is a condition of its own at the temperature measured; biases stay apart from darks."""
    readings = np.linspace(-5.6, -4.4, 10)
    frames = [_frame(f"d{i}.fit", 60.0, float(t), -5.0) for i, t in enumerate(readings)]
    frames.append(_frame("hot.fit", 60.0, -2.0, -5.0))
    frames += [_frame(f"b{i}.fit", 0.0, -5.1, -5.0) for i in range(3)]
    groups = group_frames(Dataset(Path("."), frames), np.zeros(len(frames), int), np.zeros(1))
    assert [g.n for g in groups] == [10, 1, 3]
    assert groups[0].temperature_c == pytest.approx(float(readings.mean()))
    assert groups[1].temperature_c == -2.0
    assert groups[2].exposure_s == 0.0 and groups[2].temperature_c == pytest.approx(-5.1)


def test_without_a_set_point_the_reading_groups():
    frames = [_frame("a.png", 1.0, 25.0, None), _frame("b.png", 1.0, 25.0, None), _frame("c.png", 1.0, 30.0, None)]
    groups = group_frames(Dataset(Path("."), frames), np.zeros(3, int), np.zeros(1))
    assert [(g.n, g.temperature_c) for g in groups] == [(2, 25.0), (1, 30.0)]


def test_a_pattern_size_is_profiled_against_the_other_patterns():
    """A gain pattern k (σ 1 %) and an offset pattern o (σ 5 DN) in the same frames at three light levels: projected
    alone onto the gain's derivative, the split-half cross-product takes in the offset's share along it; regressed
    on both per pixel, it gives σ_k within 7 % (3 × the spread measured over seeds 0–7: ratios 0.976–1.055, mean
    1.010, sd 0.022); alone it comes out ≈ 25 % high."""
    from forensics.check.pixels import _profiled_projections

    rng = np.random.default_rng(3)
    h = w = 120
    levels = np.array([100.0, 400.0, 1600.0])[:, None, None] * np.ones((3, h, w))
    k = rng.normal(0.0, 0.01, (h, w))
    o = rng.normal(0.0, 5.0, (h, w))
    noise = np.sqrt(levels)  # shot-noise-like, independent in the two halves
    res_a = levels * k + o + rng.normal(0.0, 1.0, levels.shape) * noise
    res_b = levels * k + o + rng.normal(0.0, 1.0, levels.shape) * noise
    weight = 1.0 / noise**2
    ok = np.ones(levels.shape, bool)

    def sigma(others):
        ua, ub, a = _profiled_projections(levels, others, weight, ok, res_a, res_b)
        return float(np.sqrt(np.sum(ua * ub) / np.sum(a * a)))

    assert sigma([np.ones_like(levels)]) == pytest.approx(float(k.std()), rel=0.07)
    assert sigma([]) > 1.1 * float(k.std())  # alone, the offsets' share inflates it


def test_a_16_bit_fits_dark_series_keeps_its_full_scale(tmp_path):
    """Darks of a 16-bit CCD (BITPIX 16, BZERO 32768) whose hottest pixel stays far below 16,383 ADU: the full
    scale is the container's 65,535, in the whole frame and in a region (it was inferred as 14-bit before)."""
    from forensics.check.measurements import load_measurements
    from forensics.fixtures.darkseries import DarkSeriesDesign, make_dark_series

    design = DarkSeriesDesign(shape=(40, 48), exposures=(10.0, 30.0), n_bias=3, n_repeat_dark=2, hot_max=5.0,
                              setpoints=(-10.0,))
    make_dark_series(tmp_path, 2, design)
    whole = load_measurements(tmp_path)
    assert float(whole.hi.max()) < 16383 and whole.full_scale == 65535.0
    assert load_measurements(tmp_path, region=(8, 8, 24, 24)).full_scale == 65535.0
