"""Growth rates: the paper's eq. 16–19 as written, capture–recapture, exact intervals, regression, the model file."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import ndimage, stats

from forensics.defects.detection import MaskSpec, detect
from forensics.sensor.effects import ReadNoise
from forensics._shared.errors import InputError
from forensics.defects.growth import (
    Epoch,
    GrowthModel,
    chapman,
    epochs_from_datasets,
    estimate_growth,
    paper_gamma,
    paper_rate,
)
from forensics.stats.counts import clopper_pearson, garwood, midp_binomial, poisson_glm, trend_test
from forensics.sensor.presets import preset
from forensics.sensor.scenes import scene
from forensics.io.stack import stack_stats


# --------------------------------------------------------------------------- the paper
def test_paper_eq17_as_written_and_the_discrepancy():
    """n₁ = 27, n₂ = 28, n_match = 5, four years, 640×480 (paper section 4).

    Eq. 16 gives γ = 5/27 = 0.185 (the paper prints 0.185), and eq. 17 as written,
    γ·(n₂ − n₁)/((T₂ − T₁)·w·h) with w·h = 0.3072 MP, gives 0.1507 defects/MP/year.
    The paper reports λ = 0.66594, 4.419 times more.  No reading of the stated
    figures reproduces it: without γ eq. 17 gives 0.814 (ratio 0.818); dividing
    by γ instead gives 4.39; counting the n₂ − n_match = 23 new candidates gives
    3.47.  λ/γ = 3.596 would need (n₂ − n₁)/((T₂ − T₁)·w·h) with w·h ≈ 0.0695 MP,
    which is none of the sizes given (four 128×128 patches are 0.0655 MP).  The
    paper's value is therefore not derivable from its own figures; we implement
    eq. 17 as written and keep 0.6659 only as preset A's rate.
    """
    gamma = paper_gamma(27, 5)
    assert gamma == pytest.approx(0.185, abs=5e-4)
    lam = paper_rate(27, 28, 5, 2009.0, 2013.0, 640, 480)
    assert lam == pytest.approx(5 / 27 / (4 * 0.3072), rel=1e-12)
    assert lam == pytest.approx(0.150704, abs=1e-6)
    factor = 0.66594 / lam
    assert factor == pytest.approx(4.4188, abs=1e-3)
    assert not np.isclose(lam, 0.66594, rtol=0.05)
    assert 1 / (4 * 0.3072) == pytest.approx(0.8138, abs=1e-4)  # eq. 17 without γ: still not 0.66594


# --------------------------------------------------------------------------- exact intervals
def test_garwood_known_values_and_coverage():
    assert garwood(0) == pytest.approx((0.0, 3.6889), abs=1e-4)
    assert garwood(10) == pytest.approx((4.7954, 18.3904), abs=1e-4)
    # exact: coverage ≥ 95 % at every mean
    for mu in (0.5, 3.0, 20.0, 80.0):
        k = np.arange(0, int(mu * 5 + 30))
        pk = stats.poisson.pmf(k, mu)
        cover = sum(p for kk, p in zip(k, pk) if garwood(int(kk))[0] <= mu <= garwood(int(kk))[1])
        assert 0.95 <= cover <= 0.995


def test_clopper_pearson():
    assert clopper_pearson(0, 10) == pytest.approx((0.0, 0.30850), abs=1e-5)
    assert clopper_pearson(5, 10) == pytest.approx((0.18709, 0.81291), abs=1e-5)
    assert clopper_pearson(10, 10)[1] == 1.0


def test_midp_binomial_is_inside_clopper_pearson():

    for x, n in ((0, 10), (3, 10), (10, 10), (17, 60)):
        lo, hi = midp_binomial(x, n)
        clo, chi = clopper_pearson(x, n)
        assert clo <= lo <= x / n <= hi <= chi
    assert midp_binomial(0, 0) == (0.0, 1.0)


def test_chapman_formulae():
    c = chapman(27, 28, 5)
    assert c.n_hat == pytest.approx(28 * 29 / 6 - 1)
    assert c.variance == pytest.approx(28 * 29 * 22 * 23 / (36 * 7))
    assert c.lincoln_petersen == pytest.approx(27 * 28 / 5)
    assert c.ci[0] >= 27 + 28 - 5
    with pytest.raises(ValueError):
        chapman(3, 4, 5)


def test_chapman_is_nearly_unbiased_for_a_closed_population():
    rng = np.random.default_rng(0)
    n_true, p = 200, 0.4
    est = []
    for _ in range(2000):
        a = rng.random(n_true) < p
        b = rng.random(n_true) < p
        est.append(chapman(int(a.sum()), int(b.sum()), int((a & b).sum())).n_hat)
    assert np.mean(est) == pytest.approx(n_true, rel=0.02)


# --------------------------------------------------------------------------- regression
def test_poisson_glm_recovers_rate_and_slope():
    rng = np.random.default_rng(1)
    t = np.linspace(0, 10, 40)
    expo = np.full(40, 50.0)
    y = rng.poisson(expo * np.exp(-1 + 0.1 * (t - 5)))
    fit = poisson_glm(y, expo, np.column_stack([np.ones(40), t - 5]))
    assert fit.beta[0] == pytest.approx(-1, abs=0.1) and fit.beta[1] == pytest.approx(0.1, abs=0.03)


def test_trend_test_size_and_power():
    rng = np.random.default_rng(2)
    times = np.arange(2000.0, 2012.0, 2.0)
    p_null = [trend_test(rng.poisson(30, 5), times, 1.0).p_value for _ in range(400)]
    assert 0.02 <= np.mean(np.array(p_null) < 0.05) <= 0.09  # nominal 5 % size
    accel = [trend_test(rng.poisson(np.array([10, 20, 40, 80, 160])), times, 1.0) for _ in range(50)]
    assert all(not a.linear for a in accel)
    assert trend_test([3], [0.0, 1.0], 1.0) is None


# --------------------------------------------------------------------------- from detections
def simulated_epochs(dates=(2004.0, 2008.0, 2012.0), seed=0, k=40, shape=(96, 128), scale=400):
    rng = np.random.default_rng(seed)
    model = preset("G", shape, bit_depth=16, t0=2000.0, rate_scale=scale).with_effects(ReadNoise(30.0))
    device = model.realize(rng, list(dates))
    epochs = []
    for t in dates:
        frames = [device.expose(np.float32(65535) * ndimage.gaussian_filter(scene(shape, rng, 1, "texture"), 4),
                                device.context(t), rng) for _ in range(k)]
        epochs.append(Epoch(t, detect(stack_stats(frames), mask=MaskSpec("all")), f"{t:g}", "sim"))
    return device, epochs


def test_estimate_growth_against_truth(tmp_path):
    device, epochs = simulated_epochs()
    res = estimate_growth(epochs)
    truth = device.catalogue
    inside = epochs[0].detection.mask[truth.y, truth.x]
    # true new partially stuck defects after the first epoch, above the threshold used
    thr = epochs[0].detection.tau - epochs[0].detection.fits[0].center
    new_true = np.sum(inside & (truth.onset > 2004.0) & (truth.onset <= 2012.0) & (truth.amplitude > thr))
    assert abs(res.partial.rate.count - new_true) <= 3
    assert res.partial.rate.ci[0] <= res.partial.rate.rate <= res.partial.rate.ci[1]
    assert res.partial.rate.exposure == pytest.approx(epochs[0].detection.megapixels * 8.0)
    assert res.partial.trend is not None and 0 <= res.partial.trend.p_value <= 1
    d = res.to_dict()
    for key in ("rate_partial", "rate_partial_ci", "rate_stuck", "rate_stuck_ci", "threshold", "paper"):
        assert key in d
    assert d["threshold"]["sigma"] == 5.0 and len(d["threshold"]["tau_per_epoch"]) == 3
    assert d["paper"]["gamma"] == pytest.approx(d["paper"]["n_match"] / d["paper"]["n1"])
    # catalogue: onsets bracket the truth
    onset = {(int(x), int(y)): o for x, y, o in zip(truth.x, truth.y, truth.onset)}
    ok = [((c.onset_lo or -np.inf) < onset[(c.x, c.y)] <= c.onset_hi) for c in res.catalogue if (c.x, c.y) in onset]
    assert np.mean(ok) > 0.95 and len(ok) >= len(res.catalogue) - 1
    # the model round-trips through JSON
    path = res.model().save(tmp_path / "m.json")
    again = GrowthModel.load(path)
    assert again.to_dict() == json.loads(path.read_text())
    assert again.catalogue[0] == res.catalogue[0] and again.dates == res.dates
    (tmp_path / "bad.json").write_text('{"format": "other"}')
    with pytest.raises(InputError, match="not a growth model"):
        GrowthModel.load(tmp_path / "bad.json")


def test_epochs_must_match():
    _, epochs = simulated_epochs(dates=(2004.0, 2008.0), k=12)
    other = Epoch(2010.0, epochs[1].detection, "other", "another-device")
    with pytest.raises(InputError, match="device"):
        estimate_growth([epochs[0], other])
    with pytest.raises(InputError, match="same capture date"):
        estimate_growth([epochs[0], Epoch(2004.0, epochs[1].detection, "x", "sim")])
    with pytest.raises(InputError, match="at least two"):
        estimate_growth(epochs[:1])
    small = stack_stats([np.zeros((50, 60), np.uint16) + i for i in range(12)])
    with pytest.raises(InputError, match="same size"):
        estimate_growth([epochs[0], Epoch(2009.0, detect(small, mask=MaskSpec("all")), "small", "sim")])


def test_datasets_without_dates_or_of_other_sizes(tmp_path):
    from forensics.sensor.simulate import make_scenes

    a = make_scenes(tmp_path / "a", 3, (40, 48), 0, start_year=2001.0, device="cam")
    b = make_scenes(tmp_path / "b", 3, (40, 48), 1)  # no 'captured'
    c = make_scenes(tmp_path / "c", 3, (40, 56), 2, start_year=2005.0, device="cam")
    d = make_scenes(tmp_path / "d", 3, (40, 48), 3, start_year=2005.0, device="other")
    with pytest.raises(InputError, match="'captured'"):
        epochs_from_datasets([a, b])
    with pytest.raises(InputError, match="same size"):
        epochs_from_datasets([a, c])
    with pytest.raises(InputError, match="device"):
        epochs_from_datasets([a, d])
