"""The model check: fit, held-out error, goodness of fit, ranked candidates (fast subset of the sweep).

The full sweep (every candidate × 10 seeds, 20 null seeds, four conventions) is ``benchmarks/sweep_check.py``; here
one seed per candidate (seeds 1 and 2 in turn: two per candidate cost CI 80 s of a worker and repeated what the
sweep measures ten times), two null seeds, a user-defined effect and the separability warnings.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage

from forensics.sensor.model import make_effect
from forensics.fixtures.hidden import CANDIDATES, Design, make_hidden
from forensics.stats import spatial as sp
from forensics.check import KERNEL_VAR, check, loo_quadratic_kernel, scene_estimate
from forensics.check.scoretests import random_effect_lr as _random_effect_lr

PIXEL = ("prnu", "dark_current", "gain", "nonlinearity")


# ----------------------------------------------------------------------------------------- building blocks
def test_scene_kernel_is_exact_for_quadratics_and_ignores_the_centre():
    k = loo_quadratic_kernel(7)
    assert k[3, 3] == 0.0 and k.sum() == pytest.approx(1.0)
    yy, xx = np.mgrid[0:40, 0:40].astype(float)
    scene = 100 + 3 * xx - 2 * yy + 0.05 * xx**2 + 0.02 * yy**2 - 0.03 * xx * yy
    est = ndimage.correlate(scene, k)
    np.testing.assert_allclose(est[3:-3, 3:-3], scene[3:-3, 3:-3], atol=1e-9)
    assert KERNEL_VAR == pytest.approx(float(np.sum(k**2))) and 0.07 < KERNEL_VAR < 0.09


@pytest.mark.parametrize("shape", [(4, 5), (9, 7), (134, 134), (150, 97)])
@pytest.mark.parametrize("mode", ["reflect", "constant"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_kernel_by_axis_sums_equals_the_two_dimensional_correlation(shape, mode, dtype):
    # the radial form c0 + c2·(x² + y²) summed along each axis (a block of rows at a time: 150 rows cross the
    # blocks' seams) against scipy's 49-tap correlation, on values with a large mean: rounding only
    from forensics.check.scene import KERNEL, correlate_kernel

    rng = np.random.default_rng(3)
    img = (1000.0 + rng.normal(0.0, 30.0, shape)).astype(dtype)
    got = correlate_kernel(img, mode)
    want = ndimage.correlate(img.astype(np.float64), KERNEL, mode=mode)
    assert got.dtype == dtype and got.shape == shape
    # float64: a few ulps of the 1000-DN sums; float32: the output's own rounding (2⁻²⁴ of 1000 DN)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-10 if dtype == np.float64 else 2e-4)


def test_scene_estimate_is_unbiased_with_known_noise_and_masks_defects():
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:96, 0:96].astype(float)
    light = 1000 * (1 - 0.3 * ((xx - 48) ** 2 + (yy - 48) ** 2) / 48**2)
    noise = 2.0
    mask = np.zeros(light.shape, bool)
    mask[rng.integers(5, 90, 60), rng.integers(5, 90, 60)] = True
    errs = []
    for _ in range(40):
        img = light + noise * rng.standard_normal(light.shape)
        img[mask] += 300.0  # defects, known
        errs.append(scene_estimate(img, mask) - light)
    errs = np.array(errs)[:, 6:-6, 6:-6]
    assert abs(errs.mean()) < 0.01  # bias ≪ σ/√(40·84²·Σw²)-scale noise
    assert errs.var() == pytest.approx(noise**2 * KERNEL_VAR, rel=0.08)  # defects' neighbours use fill values


def test_ripley_and_clark_evans_under_complete_spatial_randomness():
    rng = np.random.default_rng(1)
    window = (0.0, 0.0, 200.0, 150.0)
    radii = np.array([2.0, 5.0, 10.0])
    ls, zs = [], []
    for _ in range(60):
        n = 250
        x, y = rng.integers(0, 200, n), rng.integers(0, 150, n)
        keep = np.unique(np.column_stack([x, y]), axis=0)
        ls.append(sp.ripley_l(keep[:, 0], keep[:, 1], window, radii))
        zs.append(sp.clark_evans(keep[:, 0], keep[:, 1], window).z)
    l_mean = np.mean(ls, axis=0)
    np.testing.assert_allclose(l_mean[1:], radii[1:], rtol=0.04)  # lattice effects only at r of a pixel or two
    assert abs(np.mean(zs)) < 0.6 and 0.6 < np.std(zs) < 1.5


def test_thomas_minimum_contrast_recovers_the_spread():
    rng = np.random.default_rng(2)
    parents = rng.uniform(0, 300, (60, 2))
    pts = np.concatenate([p + 2.5 * rng.standard_normal((5, 2)) for p in parents])
    pts = pts[(pts >= 0).all(1) & (pts < 300).all(1)]
    radii = np.array([1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 10.0, 12.0])
    k = sp.ripley_k(np.floor(pts[:, 0]), np.floor(pts[:, 1]), (0.0, 0.0, 300.0, 300.0), radii)
    a, sigma = sp.fit_thomas_excess(radii, k)
    assert sigma == pytest.approx(2.5, rel=0.3)
    assert a * len(pts) / 300**2 == pytest.approx(5.0, rel=0.4)  # f·m/λ·λ = mean cluster size for f = 1


def test_random_effect_likelihood_ratio():
    rng = np.random.default_rng(3)
    a = rng.uniform(5, 50, 4000)
    null = rng.standard_normal(4000)
    lr0, _ = _random_effect_lr(null, a)
    assert lr0 < 10  # ½χ²₀ + ½χ²₁ under the null
    alt = rng.standard_normal(4000) * np.sqrt(1 + 0.01 * a)
    lr1, t = _random_effect_lr(alt, a)
    assert lr1 > 100 and t == pytest.approx(0.01, rel=0.35)


# ----------------------------------------------------------------------------------------- hidden effects
@pytest.mark.parametrize("seed", [11, 12])
def test_null_case_flags_nothing(tmp_path, seed):
    data = make_hidden("none", tmp_path / "none", rng=seed)
    r = check(data.out, rng=seed)
    assert r.flagged == []
    assert r.error["pixel"] < 1.1 and r.error["variance"] < 0.05 and r.error["growth"] < 3
    assert all(p is None or p >= 0.001 for p in r.gof.values())
    assert set(CANDIDATES) <= {c.effect for c in r.candidates}


@pytest.mark.parametrize(("effect", "seed"), [(e, 1 + i % 2) for i, e in enumerate(CANDIDATES)])
def test_hidden_effect_is_named_and_adding_it_fits(tmp_path, effect, seed):
    data = make_hidden(effect, tmp_path / effect, rng=seed)
    after = check(data.out, add=[effect], rng=seed)
    before = after.baseline
    assert before.candidates[0].effect == effect, [(c.effect, c.delta_bic) for c in before.candidates]
    assert before.candidates[0].flagged
    assert after.flagged == [], [(c.effect, c.delta_bic, c.p) for c in after.candidates]
    assert all(p is None or p >= 0.001 for p in after.gof.values()), after.gof
    assert effect in after.effects and effect not in [c.effect for c in after.candidates]
    if effect in PIXEL:
        assert after.error["pixel"] <= 1.1
        assert before.error["pixel"] >= 1.5 * after.error["pixel"]
    elif effect == "shot_noise":
        assert after.error["variance"] <= 0.05 < before.error["variance"]
    elif effect == "accelerating_growth":
        assert after.error["growth"] <= 3 < before.error["growth"]
    elif effect == "clusters":
        assert after.gof["spatial"] >= 0.05 > before.gof["spatial"]


# ----------------------------------------------------------------------------------------- a user's effect
USER_EFFECT = '''
"""Column amplifiers: every column adds its own constant offset (a fixed pattern no built-in effect has)."""
from dataclasses import dataclass

import numpy as np

from forensics.sensor.model import Effect, Pattern, Stage, param


@dataclass
class ColumnOffset(Effect):
    name = "column_offset"
    description = "each column adds its own constant offset (column amplifiers)"
    stage = Stage.DARK

    sigma: float = param(3.0, "DN", "standard deviation of the column offsets", null=0.0)

    def realize(self, device, rng):
        device.state[self.key] = self.sigma * rng.standard_normal(device.model.shape[1])

    def apply(self, signal, ctx, rng):
        signal += ctx.device.state[self.key][None, :]
        return signal

    def patterns(self, device):
        h, w = device.model.shape
        return [Pattern("offset", device.state[self.key], np.broadcast_to(np.arange(w), (h, w)), hyper="sigma")]
'''


def test_user_defined_effect_shows_as_misfit_and_adding_it_fits(tmp_path):
    assert len(USER_EFFECT.strip().splitlines()) < 40
    path = tmp_path / "column.py"
    path.write_text(USER_EFFECT)
    spec = f"{path}:ColumnOffset"
    data = make_hidden(spec, tmp_path / "data", rng=5)
    after = check(data.out, add=[spec], rng=5)
    before = after.baseline
    # the base model fails, and the residual map shows the column structure
    assert before.gof["pixel"] < 1e-3
    assert before.error["pixel"] > 1.2
    res = before.plots.residual_map[3:-3, 3:-3]
    assert np.var(np.nanmean(res, axis=0)) > 10 * np.var(np.nanmean(res, axis=1))
    # adding the user's class fits
    assert after.error["pixel"] <= 1.1
    assert "column_offset" in after.effects
    pattern = next(p for p in after.patterns if p.effect == "column_offset")
    assert pattern.blocks == 128 and 1.5 < pattern.rms < 4.5  # relative to the neighbourhood (σ = 3 DN)


# ----------------------------------------------------------------------------------------- warnings
def test_warns_when_the_data_cannot_separate(tmp_path):
    """One exposure time and one temperature: the hot pixels' dark current looks like a constant offset.

    (Only the hot-pixel tail is hidden: a dark-current non-uniformity on every pixel would be a real fixed
    pattern the base model lacks, rightly flagged, though not separable from DSNU with this design.)"""
    design = Design(exposures=(1.0,), temperatures=(20.0,), ages=(0, 1, 2, 3, 4, 5))
    hot_only = make_effect("dark_current", rate_max=40.0, t_ref=25.0, t_double=7.0)
    data = make_hidden(hot_only, tmp_path / "dc", rng=3, design=design)
    r = check(data.out, rng=3)
    text = " ".join(r.warnings)
    assert "exposure_s" in text and "temperature_c" in text
    assert any("dark_current" in w and "add frames" in w for w in r.warnings), r.warnings
    dc = next(c for c in r.candidates if c.effect == "dark_current")
    assert not dc.flagged


def test_warns_about_too_few_light_levels(tmp_path):
    design = Design(subjects={"dark": 0.0, "flat": 1400.0}, reference_subjects=("dark", "flat"), exposures=(1.0,),
                    ages=(0, 1, 2, 3, 4))
    data = make_hidden("none", tmp_path / "two", rng=4, design=design)
    r = check(data.out, rng=4)
    assert r.data["light_levels"] == 2
    assert any("light level" in w and "third" in w for w in r.warnings), r.warnings


def test_json_has_the_documented_keys(tmp_path):
    data = make_hidden("none", tmp_path / "n", rng=21, design=Design(ages=(0, 1, 2, 3, 4)))
    d = check(data.out, rng=1).to_dict()
    assert {"effects", "error", "gof", "candidates"} <= set(d)
    assert set(d["error"]) == {"pixel", "classes", "variance", "growth"}
    assert set(d["error"]["classes"]) == {"normal", "partial", "stuck"}
    assert set(d["gof"]) == {"pixel", "variance", "growth", "spatial"}
    for c in d["candidates"]:
        assert {"effect", "delta_bic", "p", "flagged"} <= set(c)
        assert isinstance(c["flagged"], bool) and 0 <= c["p"] <= 1 and math.isfinite(c["delta_bic"])
