"""The pixel channel's helpers: never-scored pixels (the dark frames' border) and the patterns' estimation noise."""
import numpy as np
from scipy import stats

from forensics.check.fit import estimation_variance
from forensics.check.pixelfit import UNSCORED_MISFIT_P, drop_unscored_misfits
from forensics.check.result import PatternEstimate
from forensics.sensor.model import Pattern


def _border_setup(rng, n_cond=20, shape=(16, 16), sigma=2.0):
    """Weights: the interior scored, the outer ring only pattern-weighted (as in dark frames); residuals pure
    noise of the stated σ."""
    w = np.zeros((n_cond, *shape))
    w[:, 2:-2, 2:-2] = 1.0 / sigma**2
    wp = np.full((n_cond, *shape), 1.0 / sigma**2)
    y = sigma * rng.standard_normal((n_cond, *shape))
    values = rng.standard_normal(shape[0] * shape[1])
    pat = Pattern("r", values, np.arange(shape[0] * shape[1]).reshape(shape))
    return w, wp, y, pat


def test_unscored_pixel_with_a_jump_is_dropped_and_zeroed():
    rng = np.random.default_rng(3)
    w, wp, y, pat = _border_setup(rng)
    y[10:, 0, 5] += 40.0  # a defect's onset at a border pixel: 20 σ in half the frames
    before = pat.values.copy()
    assert drop_unscored_misfits(wp, w, y, np.zeros_like(y), [(0, pat)])
    assert np.all(wp[:, 0, 5] == 0) and pat.values[5] == 0.0
    # noise-only border pixels: each fails with probability ≤ UNSCORED_MISFIT_P (the median scale is ≥ 1); 111
    # of them here (expected 0.11 false drops), so more than two would be a < 3e-4 event (Poisson)
    border = ~(w > 0).any(0)
    dropped = border & ~(wp > 0).any(0)
    assert dropped.sum() - 1 <= 2
    kept = (wp > 0).any(0)
    assert np.array_equal(pat.values[kept.ravel()], before[kept.ravel()])
    assert np.all(wp[:, 2:-2, 2:-2] > 0)  # scored pixels are never touched


def test_common_misfit_early_in_a_fit_drops_nothing():
    # global parameters still off: every pixel misfits alike (here by a factor 10 in χ²); only outliers go
    rng = np.random.default_rng(4)
    w, wp, y, pat = _border_setup(rng)
    y *= np.sqrt(10.0)
    assert not drop_unscored_misfits(wp, w, y, np.zeros_like(y), [(0, pat)])


def test_threshold_matches_the_chi2_tail():
    rng = np.random.default_rng(5)
    trials, drops = 40, 0
    for _ in range(trials):
        w, wp, y, pat = _border_setup(rng)
        drop_unscored_misfits(wp, w, y, np.zeros_like(y), [(0, pat)])
        drops += int((~(wp > 0).any(0)).sum())
    n = trials * int((~(w > 0).any(0)).sum())  # border pixels tested
    # χ²(19) tail at p = 1e-3 (median χ²/df scale ≈ 1): expected n·p = 2.4 drops; Poisson 99.9 % upper bound 9
    assert drops <= stats.poisson.ppf(0.999, n * UNSCORED_MISFIT_P)


def test_estimation_variance_is_x2_v_and_shrinks_for_random_effects():
    shape = (4, 5)
    x = np.full((3, *shape), 2.0)
    v = np.full((1, *shape), 0.5)
    fixed = Pattern("d", np.zeros(20), np.arange(20).reshape(shape))
    random = Pattern("k", np.zeros(20), np.arange(20).reshape(shape), hyper="sigma_k")

    class E:
        key = "e"

    out = estimation_variance([(0, fixed)], [x], v, [], [E()])
    assert np.allclose(out, 4.0 * 0.5)
    pe = PatternEstimate("e", "k", 20, 1.0, 1.0, "sigma_k", 1.0)  # τ² = 1: MSE v·τ²/(τ² + v) = 1/3
    out = estimation_variance([(0, random)], [x], v, [pe], [E()])
    assert np.allclose(out, 4.0 * 0.5 / 1.5)


def test_recentre_moves_random_effects_to_zero_mean_only():
    """A random-effect pattern's mean belongs to a global parameter: whatever moved it (values zeroed at dropped
    pixels) is shifted back; a fixed-effect pattern (a defect's offset) keeps its values."""
    from forensics.check.pixelfit import recentre

    rng = np.random.default_rng(6)
    random_pat = Pattern("o", (3.0 + rng.standard_normal(64)).astype(np.float32), np.arange(64).reshape(8, 8))
    fixed_pat = Pattern("d", np.array([5.0, 7.0]), np.full((8, 8), -1))
    fixed_pat.blocks[0, 0], fixed_pat.blocks[3, 3] = 0, 1
    spread = float(np.std(random_pat.values))
    fixed_before = fixed_pat.values.copy()
    assert recentre([(0, random_pat), (1, fixed_pat)], [True, False])
    assert abs(float(np.mean(random_pat.values, dtype=np.float64))) < 1e-6 * spread
    assert np.isclose(float(np.std(random_pat.values)), spread, rtol=1e-5)  # a shift, not a rescaling
    assert np.array_equal(fixed_pat.values, fixed_before)
    assert not recentre([(0, random_pat)], [True])  # already centred: nothing to do
