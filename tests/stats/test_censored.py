"""Moments of the clipped normal and of the quantised, clipped readout against Monte Carlo and the limits."""
import numpy as np
import pytest

from forensics.stats.censored import clipped_normal_moments, readout_moments

N = 400_000
CASES = [(0.3, 1.0, 0, 10), (5.0, 1.0, 0, 10), (1.0, 0.7, 0, 255), (254.0, 2.0, 0, 255), (-0.5, 2.0, 0, 3),
         (2.0, 0.4, 0, 255)]


def _check(mean, var, y):
    n = y.size
    se_m = np.sqrt(y.var() / n) + 1e-12
    se_v = np.sqrt(max(np.mean((y - y.mean()) ** 4) - y.var() ** 2, 0.0) / n) + 1e-12
    assert abs(mean - y.mean()) < 5 * se_m
    assert abs(var - y.var()) < 5 * se_v


@pytest.mark.parametrize("mu,sigma,lo,hi", CASES)
def test_clipped_normal_against_monte_carlo(mu, sigma, lo, hi):
    x = np.random.default_rng(1).normal(mu, sigma, N)
    m, v = clipped_normal_moments(mu, sigma, lo, hi)
    _check(float(m), float(v), np.clip(x, lo, hi))


@pytest.mark.parametrize("mu,sigma,lo,hi", CASES)
def test_readout_against_monte_carlo(mu, sigma, lo, hi):
    y = np.rint(np.clip(np.random.default_rng(2).normal(mu, sigma, N), lo, hi))
    m, v = readout_moments(mu, sigma, lo, hi)
    _check(float(m), float(v), y)
    inner = y[(y > lo) & (y < hi)]
    m, v = readout_moments(mu, sigma, lo, hi, truncate=True)
    _check(float(m), float(v), inner)


DITHER_CASES = [(2.0, 0.32, 0, 4095), (2.5, 0.32, 0, 4095), (0.3, 0.4, 0, 4095), (1.2, 0.05, 0, 255),
                (254.6, 0.5, 0, 255), (1.0, 2.5, 0, 4095), (-1.0, 3.0, 0, 4095)]


@pytest.mark.parametrize("mu,sigma,lo,hi", DITHER_CASES)
def test_dithered_readout_against_monte_carlo(mu, sigma, lo, hi):
    """EMVA 1288's simulator: rint(x + u) with u ~ U(−½, ½), clipped — exact sums and closed form alike, with and
    without the truncation (σ = 0.05: the box alone sets the levels' shares)."""
    rng = np.random.default_rng(3)
    y = np.clip(np.rint(rng.normal(mu, sigma, N) + rng.uniform(-0.5, 0.5, N)), lo, hi)
    for closed_form in (True, False):
        m, v = readout_moments(mu, sigma, lo, hi, dither=1.0, closed_form=closed_form)
        _check(float(m), float(v), y)
        m, v = readout_moments(mu, sigma, lo, hi, truncate=True, dither=1.0, closed_form=closed_form)
        _check(float(m), float(v), y[(y > lo) & (y < hi)])


def test_dither_of_width_zero_is_plain_rounding():
    mu, sigma = np.linspace(-2.0, 8.0, 41), np.linspace(0.05, 3.0, 41)
    plain, nearly = readout_moments(mu, sigma, 0, 255), readout_moments(mu, sigma, 0, 255, dither=1e-6)
    np.testing.assert_allclose(nearly[0], plain[0], atol=1e-6)
    np.testing.assert_allclose(nearly[1], plain[1], atol=1e-6)


def test_limits_and_vectorisation():
    mu = np.array([[100.0, -1e3, 1e3], [5.0, 50.0, 7.0]])
    m, v = clipped_normal_moments(mu, 1.5, 0.0, 200.0)
    assert m.shape == (2, 3)
    assert m[0, 0] == pytest.approx(100.0, abs=1e-12) and v[0, 0] == pytest.approx(2.25, rel=1e-12)
    assert (m[0, 1], v[0, 1]) == (0.0, 0.0) and (m[0, 2], v[0, 2]) == (200.0, 0.0)
    m, v = clipped_normal_moments(3.0, 2.0)  # no bounds
    assert (float(m), float(v)) == (3.0, 4.0)
    m, v = clipped_normal_moments([-1.0, 4.0], 0.0, 0.0, 3.0)  # σ = 0: the clipped value
    assert list(m) == [0.0, 3.0] and list(v) == [0.0, 0.0]
    # a large level far from the bounds: no cancellation
    m, v = clipped_normal_moments(6.0e4, 1.0, 0.0, 65535.0)
    assert float(m) == 6.0e4 and float(v) == pytest.approx(1.0, rel=1e-12)
    # the readout far from the bounds: μ and σ² + 1/12 (rounding); fully clipped: the bound and 0
    m, v = readout_moments(np.array([1000.0, 1000.25]), 3.0, 0, 65535)
    assert m == pytest.approx([1000.0, 1000.25], abs=1e-9) and v == pytest.approx(9 + 1 / 12, rel=1e-6)
    m, v = readout_moments(np.array([-40.0, 300.0]), 1.0, 0, 255)
    assert list(m) == [0.0, 255.0] and list(v) == [0.0, 0.0]


@pytest.mark.parametrize("truncate", [False, True])
def test_smooth_readout_equals_the_sum_over_levels(truncate):
    """For σ ≥ 2 DN the closed form (continuous moments + Euler–Maclaurin rounding terms) replaces the sum over
    integer levels.  The neglected O(g‴) terms scale as 1/σ²; measured worst cases over this grid are 1.6e-4 DN
    (mean) and 3e-3 DN² at σ = 2 (variance): 3e-4 DN and 1e-3·σ² bound them with a margin of two."""
    import forensics.stats.censored as censored

    rng = np.random.default_rng(5)
    sigma = rng.uniform(1.0, 25.0, 4000)
    # near both bounds, at them, beyond them (to 7σ: the closed form reaches max(1, σ/4) σ into a tail) and far inside
    mu = np.concatenate([rng.uniform(-7, 8, 1500) * sigma[:1500], 255 - rng.uniform(-7, 8, 1500) * sigma[1500:3000],
                         rng.uniform(0, 255, 1000)])
    fast = readout_moments(mu, sigma, 0, 255, truncate=truncate)
    exact = censored._summed_readout(mu, sigma, 0, 255, truncate, reach=12.0)
    assert np.max(np.abs(fast[0] - exact[0])) < 3e-4
    assert np.max(np.abs(fast[1] - exact[1]) / sigma**2) < 1e-3


def test_truncated_readout_of_a_mean_far_beyond_a_bound():
    """A hot pixel's wide noise (σ 400 DN) with its mean 50 σ beyond a bound: the closed form would reach that
    far into the tail (max(1, σ/4) σ) but the levels between the bounds hold no mass there (0/0 before, NaN
    means that reached the fit).  Such a readout is never observed; what is asked is a finite value between
    the bounds and no warning."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mean, var = readout_moments(np.array([-20000.0, 85600.0]), np.array([400.0, 400.0]), 0, 65535,
                                    truncate=True)
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(var))
    assert np.all((mean >= 1) & (mean <= 65534)) and np.all(var >= 0)


def test_truncated_readout_deep_beyond_a_bound_against_a_wide_sum():
    """A mean 5–13 σ below 0 DN at σ ≈ 20 DN (16-bit dark frames, a DSNU as wide as the black level): the
    readout conditional on 0 < y spreads over ≈ σ/z DN above the bound.  Against a brute sum over 600 levels
    (upper-tail probabilities: no cancellation) the sum holds to rounding, and with the closed form where it
    reaches (z ≤ σ/4) to its bound of the test above (3·10⁻⁴ DN; 10⁻³·σ² in the variance); before, the sum's window (10 σ less the distance beyond the bound) cut the conditional
    mass short from z ≈ 9 on, and a value 10 σ beyond was put on the level next to the bound (0.67–1.5 DN off)."""
    from scipy.special import ndtr

    rng = np.random.default_rng(9)
    sigma = rng.uniform(18.0, 22.0, 3000)
    mu = -rng.uniform(5.0, 13.0, 3000) * sigma
    k = np.arange(1.0, 601.0)
    p = ndtr(-(k - 0.5 - mu[:, None]) / sigma[:, None]) - ndtr(-(k + 0.5 - mu[:, None]) / sigma[:, None])
    want_mean = (p * k).sum(axis=1) / p.sum(axis=1)
    want_var = (p * k * k).sum(axis=1) / p.sum(axis=1) - want_mean**2
    mean, var = readout_moments(mu, sigma, 0, 65535, truncate=True, closed_form=False)
    np.testing.assert_allclose(mean, want_mean, rtol=0, atol=1e-9)
    np.testing.assert_allclose(var, want_var, rtol=0, atol=1e-8)
    mean, var = readout_moments(mu, sigma, 0, 65535, truncate=True)
    assert np.max(np.abs(mean - want_mean)) < 3e-4
    assert np.max(np.abs(var - want_var) / sigma**2) < 1e-3


@pytest.mark.parametrize("dither", [0.0, 0.5, 1.0, 2.0])
@pytest.mark.parametrize("sigma", [0.1, 0.3, 0.8])
def test_the_variance_harmonics_are_the_summed_variance_away_from_the_bounds(sigma, dither):
    # the closed form's cosine series at 64 fractions of a DN against the sum over levels (no bound within reach):
    # equal to rounding (10⁻¹³ DN²); a sign or factor wrong in any term moves it by ≥ 10⁻⁴
    from forensics.stats.censored import readout_variance_harmonics

    mu = 100.0 + np.arange(64) / 64
    exact = readout_moments(mu, sigma, 0, 4095, closed_form=False, dither=dither)[1]
    coef = readout_variance_harmonics(np.full(3, sigma), dither, n=40)        # vectorised over σ
    assert coef.shape == (3, 41)
    series = np.cos(2 * np.pi * np.outer(mu, np.arange(41))) @ coef[1]
    assert np.max(np.abs(series - exact)) < 1e-13
