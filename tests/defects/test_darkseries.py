"""Dark-frame series on synthetic FITS frames of known truth (fixtures.darkseries): every step of the estimate.

The frames are 16-bit FITS with BZERO 32768, written by astropy: a bias with a column pattern and an offset
jitter, a dark rate per pixel (a lognormal bulk doubling every 5 °C and a hot tail doubling every 8 °C), dark
charge during the read-out, shot noise at 2 e⁻/ADU, read noise 6.5 ADU, cosmic-ray tracks, a frame whose sensor
never reached its set point and one whose offset jumped, and flat-field pairs.  Tolerances come from the
estimates' own standard errors (checked to be calibrated first) or from the sampling theory named at each test.
"""
from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from forensics._shared.errors import InputError
from forensics.defects.darkdetect import DarkSettings, compare_counts, dark_epochs, detect_dark, series_frames
from forensics.defects.darklaw import TemperatureLaw, fit_temperature_law
from forensics.defects.darkseries import fit_dark_series, plan_series
from forensics.fixtures.darkseries import DarkSeriesDesign, make_dark_series
from forensics.io.dataset import open_dataset
from forensics.sensor.catalogue import PARTIAL

DESIGN = DarkSeriesDesign(n_flats=10, unsettled=True, offset_jump=15.0, hot_fraction=0.05)


def dataset(folder: Path):
    """The folder's FITS frames as a dataset (no manifest: the headers say everything)."""
    return open_dataset(folder)


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    folder = tmp_path_factory.mktemp("darks")
    truth = make_dark_series(folder, 2024, DESIGN)
    plan = plan_series(series_frames(dataset(folder)))
    return folder, truth, plan, fit_dark_series(plan)


def expected_slopes(truth, plan, group) -> np.ndarray:
    """What each pixel's least-squares slope estimates: Σ c_f·t_f·rate(T_f) over the group's frames (c_f the slope's
    weights), with each frame's true temperature — the rate the fit sees, temperature wander included."""
    true_t = {f["file"]: f["temperature_c"] for f in truth.files}
    frames = [plan.frames[i] for i in group.frames]
    t = np.array([f.exposure_s for f in frames])
    c = (t - t.mean()) / ((t - t.mean()) ** 2).sum()
    return sum(ci * ti * truth.rate_at(true_t[Path(f.path).name]) for ci, ti, f in zip(c, t, frames)).ravel()


def test_frames_read_with_bzero_and_grouped_by_set_point(series):
    from astropy.io import fits

    folder, truth, plan, fit = series
    header = fits.getheader(next(folder.glob("bias*.fits")))
    assert header["BITPIX"] == 16 and header["BZERO"] == 32768  # unsigned data stored the cameras' way
    assert [g.set_temperature_c for g in fit.groups] == [-10.0, -5.0]
    # the bias level is read in ADU, BZERO applied: the bias map plus the read-out dark charge (0.17 ADU)
    expected = float(np.median(truth.bias_map)) + DESIGN.rate_bulk * DESIGN.readout_s
    for g in fit.groups:
        assert abs(g.bias_level - expected) < 4 * g.bias_level_se + 0.5  # the median of a column pattern: ±0.5


def test_read_noise(series):
    _, _, _, fit = series
    # the median of per-pixel variances over N pixels with ν = 9: SE(σ)/σ = ½·√(π/(νN)) ≈ 0.4 %; quantisation
    # (1/12 ADU²) and the read-out dark's shot noise (0.09 ADU²) add 0.1 %
    for g in fit.groups:
        assert g.read_noise == pytest.approx(DESIGN.read_noise, rel=0.02)
        assert all(abs(v / DESIGN.read_noise - 1) < 0.05 for v in g.read_noise_frames)


def test_rates_agree_with_truth_within_their_standard_errors(series):
    _, truth, plan, fit = series
    for g in fit.groups:
        z = (g.rate - expected_slopes(truth, plan, g)) / g.rate_se
        z = z[~g.misfit]
        # calibrated errors: z has unit spread (N ≈ 6,000: the spread's SE is ≈ 1 %) and no bias beyond the
        # offset jitter, which moves every pixel's slope alike (its share of a pixel's error: common / per-pixel SE)
        common = g.median_rate_common_se / float(np.median(g.rate_se))
        assert abs(float(np.mean(z))) < 4 * common + 4 / math.sqrt(z.size)
        assert 0.93 < float(np.std(z)) < 1.07
        assert np.mean(np.abs(z) > 5) < 1e-3


def test_median_rate_interval_covers_truth(series):
    _, truth, plan, fit = series
    for g in fit.groups:
        lo, hi = g.median_rate_ci()
        true = float(np.median(expected_slopes(truth, plan, g)))
        half = (hi - lo) / 2
        assert abs(g.median_rate - true) < 2 * half  # a 95 % interval (≈ 2 SE), allowed to 4 SE


def test_cosmic_rays_left_out(series):
    folder, truth, plan, fit = series
    names = [Path(f.path).name for f in plan.frames]
    shape = fit.shape
    for g in fit.groups:
        members = {names[i]: i for i in g.frames}
        hit_pixels = {y * shape[1] + x for name, y, x, _ in truth.cosmic_hits if name in members}
        found = {(int(p), int(f)) for p, f in zip(g.cosmic_pixels, g.cosmic_frames)}
        big = [(y * shape[1] + x, members[name]) for name, y, x, e in truth.cosmic_hits
               if name in members and e / DESIGN.gain > 10 * 10.0]  # deposits above 10× the largest noise σ
        assert big, "the series must have cosmic-ray hits to test"
        assert sum(hit in found for hit in big) >= 0.95 * len(big)
        z = (g.rate - expected_slopes(truth, plan, g)) / g.rate_se
        hit = np.array(sorted(hit_pixels))
        assert np.max(np.abs(z[hit])) < 6  # hit pixels' rates are as good as any other's


def test_without_rejection_cosmic_rays_bias_the_rates(series):
    _, truth, plan, _ = series
    naive = fit_dark_series(plan, rounds=0)
    g = naive.groups[0]
    z = (g.rate - expected_slopes(truth, plan, g)) / g.rate_se
    assert np.max(np.abs(z)) > 10  # what the robust rounds prevent (previous test)


def test_frames_that_do_not_follow_the_model_are_named(series):
    _, _, _, fit = series
    named = {f.name: f for f in fit.named_frames()}
    unsettled = [f for f in named.values() if "never reached" in f.reason]
    assert len(unsettled) == 1 and not unsettled[0].used
    jumped = [f for f in named.values() if any("off the line of the other frames" in p for p in f.problems)]
    assert len(jumped) == 1 and jumped[0].level_deviation == pytest.approx(DESIGN.offset_jump, abs=2.0)
    assert len(named) == 2  # and nothing else


def test_gain_from_flat_pairs_and_dark_shot_noise(series):
    _, _, _, fit = series
    flat = fit.gain["flat_pairs"]
    se = (flat["ci"][1] - flat["ci"][0]) / (2 * 2.776)  # t interval of 5 pairs
    assert abs(flat["gain_e_per_adu"] - DESIGN.gain) < 4 * se
    assert fit.gain_source == "flat pairs"
    dark = fit.gain["dark_shot_noise"]
    se = (dark["ci"][1] - dark["ci"][0]) / (2 * 2.262)  # t interval of 10 subsets
    assert abs(dark["gain_e_per_adu"] - DESIGN.gain) < 4 * se


def test_temperature_law_by_rate_class(series):
    _, truth, _, fit = series
    law = fit_temperature_law(fit.groups)
    assert abs(law.bulk.beta - 1 / DESIGN.doubling_bulk) < 4 * law.bulk.beta_se
    temps = [g.temperature_c for g in fit.groups]
    carried = np.mean([g.rate * np.exp2(-law.bulk.beta * (t - law.t_class)) for g, t in zip(fit.groups, temps)], axis=0)
    hot_classes = [c for c in law.classes if c.lo > 10 * law.bulk.rate]
    assert hot_classes, "the hot tail must reach ten times the bulk"
    for c in hot_classes:  # the truth's mean rates over the same pixels, at the groups' temperatures
        members = (carried >= c.lo) & (carried < c.hi)
        means = [truth.rate_at(t).ravel()[members].mean() for t in temps]
        true_beta = math.log2(means[1] / means[0]) / (temps[1] - temps[0])
        assert abs(c.beta - true_beta) < 4 * c.beta_se
        assert c.doubling > law.bulk.doubling  # hot pixels double more slowly


def test_law_round_trip(tmp_path, series):
    _, _, _, fit = series
    law = fit_temperature_law(fit.groups)
    law.save(tmp_path / "law.json")
    again = TemperatureLaw.load(tmp_path / "law.json")
    rates = np.array([0.1, 1.0, 30.0])
    assert np.allclose(again.to_reference(rates, -5.0, -10.0), law.to_reference(rates, -5.0, -10.0))
    # carrying there and back is the identity (the class is found by a fixed point)
    assert np.allclose(law.to_reference(law.to_reference(rates, -5.0, -10.0), -10.0, -5.0), rates, rtol=1e-6)
    with pytest.raises(InputError, match="not a temperature law"):
        (tmp_path / "other.json").write_text('{"format": "x"}')
        TemperatureLaw.load(tmp_path / "other.json")


def test_hot_pixels_at_a_threshold_in_adu_per_second(series):
    _, truth, _, fit = series
    result = detect_dark(fit, DarkSettings(threshold=1.0, t_ref=-10.0))
    true = truth.rate_at(-10.0)
    hot = np.zeros(fit.shape, bool)
    sel = result.kind == PARTIAL
    hot[result.y[sel], result.x[sel]] = True
    # misclassified pixels lie within 5 standard errors of the threshold (plus 2 % for the law's carrying)
    margin = 5 * result.rate_se + 0.02
    assert not (hot & (true < 1.0 - margin)).any()
    assert not (~hot & (true > 1.0 + margin)).any()
    assert result.count(PARTIAL) == pytest.approx(int((true > 1.0).sum()), abs=10)
    assert result.count_ci[0] <= result.count(PARTIAL) <= result.count_ci[1]
    assert result.t_ref == -10.0 and result.threshold_dict()["units"] == "ADU/s"


def test_counts_from_each_temperature_alone_agree(series):
    _, _, _, fit = series
    law = fit_temperature_law(fit.groups)
    settings = DarkSettings(threshold=1.0, t_ref=-10.0, law=law)
    cold = detect_dark(replace(fit, groups=[fit.groups[0]]), settings)
    warm = detect_dark(replace(fit, groups=[fit.groups[1]]), settings)
    comparison = compare_counts(cold, warm, ("-10 °C", "-5 °C"))
    assert comparison.overlap
    assert comparison.paired_p > 1e-3  # the synthetic sensor's pixels share their class's law exactly


def test_single_temperature_needs_a_law(series):
    _, _, _, fit = series
    warm = replace(fit, groups=[fit.groups[1]])
    with pytest.raises(InputError, match="temperature law"):
        detect_dark(warm, DarkSettings(threshold=1.0, t_ref=-10.0))
    own = detect_dark(warm, DarkSettings(threshold=1.0))  # at its own temperature: nothing to carry
    assert own.t_ref == pytest.approx(fit.groups[1].temperature_c)


def test_growth_and_dating_of_dark_series(tmp_path):
    from forensics.defects.dating import date_dataset
    from forensics.defects.growth import estimate_growth

    design = replace(DarkSeriesDesign(), setpoints=(-10.0,), hot_fraction=0.02, n_bias=6)
    folders, truths = [], []
    base = None
    for epoch, (start, new) in enumerate([("2017-09-08T20:00:00", 0), ("2019-09-08T20:00:00", 120),
                                          ("2021-09-08T20:00:00", 120)]):
        folder = tmp_path / f"epoch{epoch}"
        base = make_dark_series(folder, 100 + epoch, replace(design, start=start), sensor=base, new_hot=new)
        folders.append(folder)
        truths.append(base)
    settings = DarkSettings(threshold=1.0, t_ref=-10.0, law=TemperatureLaw.constant(5.0))
    epochs = dark_epochs([dataset(f) for f in folders[:2]], settings)
    growth = estimate_growth(epochs)
    new_true = int(((truths[1].rate_at(-10.0) > 1.0) & ~(truths[0].rate_at(-10.0) > 1.0)).sum())
    assert abs(growth.partial.new[0] - new_true) <= 3  # pixels near the threshold may go either way
    lo, hi = growth.partial.rate.ci
    area_years = growth.area_mp * (growth.dates[1] - growth.dates[0])
    assert lo <= new_true / area_years <= hi
    assert growth.threshold["units"] == "ADU/s" and growth.threshold["t_ref_c"] == -10.0
    model = growth.model()
    assert model.detection["method"] == "dark_series"
    dated = date_dataset(model, dataset(folders[2]))
    truth_date = 2021 + (31 + 28 + 31 + 30 + 31 + 30 + 31 + 31 + 7) / 365
    assert dated.interval[0] <= truth_date <= (dated.interval[1] or math.inf)
