"""The model check on photon-transfer series from an independent simulator (emva1288.camera): the effects
the simulator has are named, and the fitted conversion gain, read noise, dark current and doubling
temperature carry intervals that cover its truth (issue 9 item 5).

The full study — 100 cameras, every compared parameter's coverage in 0.92–0.98 — is
``benchmarks/coverage_emva.py`` (figures in benchmarks/RESULTS_check.md); here 12 small cameras (48 × 64).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

pytest.importorskip("emva1288", reason="emva1288 (a test dependency) is not installed")

from forensics.check import check  # noqa: E402
from forensics.fixtures.emva import EmvaDesign, make_emva_series, model_truth  # noqa: E402

EFFECTS = ["dark_current", "gain", "shot_noise", "input_noise", "dsnu", "prnu"]
REQUIRED = ["shot_noise.g", "input_noise.sigma_in", "dark_current.rate", "dark_current.t_double"]
OTHERS = ["gain.exponent", "black_level.level"]
#: the dark offset before the gain (EMVA μ_d0) has two names in a model with both effects: the dark signal at
#: zero exposure and the mean of the per-pixel offsets — one quantity, so neither is reported on its own
SAME_QUANTITY = ("dark_current.offset", "dsnu.offset")
DESIGN = replace(EmvaDesign(), shape=(48, 64))
CAMERAS = 12


@pytest.fixture(scope="module")
def cameras(tmp_path_factory):
    out = []
    for seed in range(CAMERAS):
        data = make_emva_series(tmp_path_factory.mktemp("emva") / "series", rng=100 + seed, design=DESIGN)
        out.append((data, check(data, add=EFFECTS, rng=seed, baseline=False)))
    return out


@pytest.fixture(scope="module")
def fits(cameras):
    return [r for _, r in cameras]


def test_the_simulators_effects_explain_its_frames(fits):
    for r in fits:
        assert r.flagged == [], r.flagged
        assert all(p.converged for p in r.params)
        assert r.error["pixel"] < 1.1


def test_intervals_cover_the_simulators_truth(fits):
    """Each camera's 95 % interval (± 1.96 SE) holds the truth with probability 0.95 if the SE is right: at
    least 9 of 12 then fails with probability 0.002 per parameter (binomial); an SE half its true size would
    cover ~68 % and fail this most of the time."""
    truth = model_truth(DESIGN)
    for name in REQUIRED + OTHERS:
        z = []
        for r in fits:
            p = next(p for p in r.params if p.label == name)
            assert p.se is not None and p.se > 0, p
            z.append((p.value - truth[name]) / p.se)
        covered = int(np.sum(np.abs(z) <= 1.96))
        assert covered >= 9, (name, np.round(z, 2))


def test_one_quantity_under_two_names_is_reported_not_separable(fits):
    for r in fits:
        a, b = (next(p for p in r.params if p.label == name) for name in SAME_QUANTITY)
        assert not a.identifiable and not b.identifiable and a.se is None and b.se is None
        assert SAME_QUANTITY[1] in a.note and SAME_QUANTITY[0] in b.note


def test_base_check_names_the_dark_signal_first(tmp_path):
    data = make_emva_series(tmp_path / "series", rng=7, design=DESIGN)
    r = check(data, rng=0, baseline=False)
    assert r.candidates[0].effect == "dark_current" and r.candidates[0].flagged
    assert {"shot_noise", "dsnu"} <= set(r.flagged)


def test_a_dark_signal_the_model_lacks_fails_the_pixel_gof(tmp_path):
    """Dark frames are predicted as zero light, so no scene estimate absorbs their misfit: with the dark signal's
    mean but not ISO's gain on it the held-out error is far above 1, and the in-sample gof must say so too."""
    data = make_emva_series(tmp_path / "series", rng=7, design=DESIGN)
    r = check(data, add=["dark_current"], rng=0, baseline=False)
    assert r.error["pixel"] > 1.3
    assert r.gof["pixel"] < 1e-3


def test_auto_adds_every_effect_the_simulator_has(tmp_path):
    """Forward selection from the base model ends with the simulator's effects (PRNU included: its fall of the
    held-out error is small next to the noise floor, but far beyond the error's sampling noise) and nothing
    flagged — within the default cap on additions (five stopped the simulator's 216-frame series one short)."""
    from forensics.check import check_auto

    data = make_emva_series(tmp_path / "series", rng=3, design=DESIGN)
    sel = check_auto(data, rng=0)
    assert sel.stopped == "nothing flagged", [(s.label, s.flagged) for s in sel.steps]
    assert {"dark_current", "gain", "shot_noise", "dsnu", "prnu"} <= set(sel.added), sel.added
    assert sel.result.error["pixel"] < 1.05


def emva1288_results(folder, iso: float, temperature: float):
    """emva1288's own analysis (``Results1288``) of the frames at one ISO and temperature: the standard's
    photon-transfer series — per exposure time a dark pair and one bright pair (the brighter flat), the spatial
    data at the longest exposure."""
    import logging
    from pathlib import Path

    from emva1288.process.data import Data1288
    from emva1288.process.loader import LoadImageData
    from emva1288.process.results import Results1288

    from forensics.io.dataset import open_dataset
    from forensics.io.images import read_image

    frames = [f for f in open_dataset(folder).frames if f.iso == iso and f.temperature_c == temperature]
    t_max = max(f.exposure_s for f in frames)
    top = max(float(f.extra.get("light", "0").split()[0]) for f in frames)
    images: dict = {"temporal": {}, "spatial": {}}
    for f in frames:
        light = f.extra.get("light", "0")
        photons = 0.0 if light == "0" else float(light.split()[0]) * f.exposure_s / t_max
        if light != "0" and float(light.split()[0]) != top:
            continue
        images["temporal"].setdefault(f.exposure_s * 1e9, {}).setdefault(photons, []).append(str(f.path))
        if f.exposure_s == t_max:
            images["spatial"].setdefault(f.exposure_s * 1e9, {}).setdefault(photons, []).append(str(f.path))
    data = LoadImageData(images, fload=lambda p: np.asarray(read_image(Path(p)), float),
                         loglevel=logging.ERROR).data
    return Results1288(Data1288(data, loglevel=logging.ERROR).data, loglevel=logging.ERROR)


def test_conversion_gain_agrees_with_emva1288s_own_analysis(cameras, monkeypatch):
    """Our conversion gain (all 36 conditions) and emva1288's K (its photon-transfer fit at ISO 100, 20 °C)
    estimate the same quantity from the same cameras: their paired difference has mean 0 within 3 standard
    errors of that mean (the spread of the differences over the 12 cameras, which includes emva1288's own
    scatter — it reports no standard error)."""
    if not hasattr(np, "asfarray"):  # emva1288.process still calls np.asfarray, removed in NumPy 2
        monkeypatch.setattr(np, "asfarray", lambda a, dtype=float: np.asarray(a, dtype), raising=False)
    ours, theirs = [], []
    for data, r in cameras:
        ours.append(next(p.value for p in r.params if p.label == "shot_noise.g"))
        theirs.append(float(emva1288_results(data, 100, 20.0).K))
    diff = np.array(ours) - np.array(theirs)
    assert abs(diff.mean()) <= 3 * diff.std(ddof=1) / np.sqrt(len(diff)), (np.round(ours, 4), np.round(theirs, 4))
    # and both are near the simulator's K: emva1288's scatter is the larger one (3 points at one temperature)
    assert np.std(ours) < np.std(theirs)
