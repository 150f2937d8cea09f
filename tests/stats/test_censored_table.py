"""The truncated readout mean from a checked table (forensics.stats.censored.tabulated_truncated_mean).

The table replaces the exact sum over levels in the model check's predictions of dark frames near 0 DN; it must
agree with the sum to far below what any fit resolves (10⁻⁶ DN: a pixel's mean over two frames has a noise of
≈ 0.3 DN), and refuse where a spline cannot follow the mean (σ below 0.1 DN, where the mean is a staircase in μ)
or where the values are too few to pay; and that the whole truncated mean (closed form, table, sums) agrees with
the sum, including means deep below 0 DN at a wide noise, where the closed form does not reach."""
import numpy as np

from forensics.check.prediction import distinct_readout_means
from forensics.stats.censored import (TABLE_TOLERANCE, readout_moments, tabulated_truncated_mean,
                                      truncated_readout_mean)


def _dark_values(rng: np.random.Generator, n: int, sigma_lo: float, sigma_width: float, mu_lo: float, mu_hi: float):
    return rng.uniform(mu_lo, mu_hi, n), sigma_lo + sigma_width * rng.uniform(0.0, 1.0, n)


def test_table_matches_the_sum_on_dark_frames():
    # the EMVA 1288 standard series' dark frames: black level ≈ 1 DN, σ ≈ 0.45–0.55 DN (dark current's shot
    # noise spreads σ), DSNU and dark rates spread μ; every value is compared, not only the check sample
    rng = np.random.default_rng(3)
    for sigma_lo, width in ((0.45, 0.1), (0.2, 0.0), (0.8, 1.0)):
        mu, sigma = _dark_values(rng, 60_000, sigma_lo, width, -0.5, 3.0)
        table = tabulated_truncated_mean(mu, sigma, 0, 4095)
        assert table is not None
        exact = readout_moments(mu, sigma, 0, 4095, truncate=True)[0]
        assert np.max(np.abs(table - exact)) < 0.1 * TABLE_TOLERANCE


def test_table_refused_where_it_cannot_hold():
    rng = np.random.default_rng(4)
    mu, sigma = _dark_values(rng, 60_000, 0.02, 0.01, 0.0, 3.0)  # a staircase in μ
    assert tabulated_truncated_mean(mu, sigma, 0, 4095) is None
    mu, sigma = _dark_values(rng, 60_000, 0.5, 20.0, -100.0, 10.0)  # σ over 40×: a grid bigger than it saves
    assert tabulated_truncated_mean(mu, sigma, 0, 4095) is None
    mu, sigma = _dark_values(rng, 100, 0.5, 0.0, 0.0, 3.0)  # too few values to pay
    assert tabulated_truncated_mean(mu, sigma, 0, 4095) is None


def test_both_bounds_in_one_call():
    # values near 0 and near the full scale together: one table per bound, each within the tolerance
    rng = np.random.default_rng(5)
    low = _dark_values(rng, 30_000, 0.4, 0.2, -0.5, 3.0)
    high = _dark_values(rng, 30_000, 0.4, 0.2, 252.0, 256.0)
    mu, sigma = np.concatenate([low[0], high[0]]), np.concatenate([low[1], high[1]])
    exact = readout_moments(mu, sigma, 0, 255, truncate=True)[0]
    assert np.max(np.abs(distinct_readout_means(mu, sigma, 255) - exact)) < TABLE_TOLERANCE


def test_single_level_values_as_the_sum_gives_them():
    # values whose nearest level holds all but Φ(−10) of their mass are filled without summing (a fitted shot-noise
    # law leaves dark pixels at σ ≪ 0.1 DN): the same moments as the sum, truncated or not, near both bounds
    from forensics.stats.censored import _summed_readout

    rng = np.random.default_rng(6)
    mu = rng.uniform(-3.0, 6.0, 50_000)
    sigma = np.exp(rng.uniform(np.log(1e-3), np.log(0.4), mu.size))
    for truncate in (True, False):
        for hi, shift in ((4095, 0.0), (255, 250.0)):
            fast = readout_moments(mu + shift, sigma, 0, hi, truncate=truncate)
            summed = _summed_readout(mu + shift, sigma, 0, hi, truncate, 10.0)
            np.testing.assert_allclose(fast[0], summed[0], rtol=0, atol=1e-12)
            np.testing.assert_allclose(fast[1], summed[1], rtol=0, atol=1e-12)


def test_truncated_mean_deep_below_zero_at_a_wide_noise():
    # 16-bit dark frames with a 48 DN black level, 20 DN of read noise and a DSNU of 48 DN: a fifth of the pixels'
    # means lie 5-10 σ below 0 DN, beyond the closed form's reach; with the rest (near 0, inside its reach) they
    # must agree with the sum everywhere (closed form: within 2·10⁻⁴ DN, its documented bound; the table: within
    # its tolerance), and the deep values must be tabulated, not summed one by one
    rng = np.random.default_rng(7)
    sigma = np.full(80_000, 19.9)
    mu = np.concatenate([rng.uniform(-200.0, -100.0, 20_000), rng.uniform(-60.0, 150.0, 60_000)])
    exact = readout_moments(mu, sigma, 0, 65535, truncate=True, closed_form=False)[0]
    got = truncated_readout_mean(mu, sigma, 0, 65535)
    assert np.max(np.abs(got - exact)) < 2e-4
    deep = (0.5 - mu) / sigma > 5.0
    assert np.max(np.abs(got[deep] - exact[deep])) < TABLE_TOLERANCE
    assert tabulated_truncated_mean(mu[deep], sigma[deep], 0, 65535) is not None


def test_a_frame_whose_pixels_share_their_mean_gets_the_exact_sum():
    # a model without pixel patterns predicts one mean per condition: the near-bound mean is computed once (a
    # shortcut for speed, measured in benchmarks/RESULTS_check.md) and must be the exact sum at every pixel; a frame
    # whose pixels differ still matches the sum within the table's tolerance
    from forensics.check.prediction import censored_mean
    from forensics.sensor.effects import Offset, ReadNoise
    from forensics.sensor.model import SensorModel

    device = SensorModel(shape=(200, 300), bit_depth=12, effects=[Offset(), ReadNoise(sigma=0.45)],
                         t0=0.0).realize(np.random.default_rng(0), [1.0])
    ctx = device.context(1.0)
    sigma = 0.45  # the read noise alone: σ of every pixel
    flat = np.full((200, 300), 1.3)
    exact = readout_moments(np.array([1.3]), np.array([sigma]), 0, 4095, truncate=True, closed_form=False)[0][0]
    got = censored_mean(flat, ctx, 4095.0)
    assert np.all(got == exact)
    varied = flat + np.random.default_rng(1).uniform(-0.5, 0.5, flat.shape)
    want = readout_moments(varied, np.full(varied.shape, sigma), 0, 4095, truncate=True, closed_form=False)[0]
    assert np.max(np.abs(censored_mean(varied, ctx, 4095.0) - want)) < TABLE_TOLERANCE


def test_uniform_cubic_is_exact_for_cubics_and_fourth_order_otherwise():
    from forensics.stats.censored import uniform_cubic

    grid = np.arange(-1.0, 3.0 + 1e-9, 0.1)
    x = np.random.default_rng(7).uniform(-0.85, 2.85, 1000)
    cubic = lambda v: 2.0 - v + 0.5 * v**2 - 0.3 * v**3  # noqa: E731
    np.testing.assert_allclose(uniform_cubic(-1.0, 0.1, cubic(grid), x), cubic(x), rtol=0, atol=1e-12)
    # exp: |f⁗| ≤ e³ on the grid, so the error is at most (3/128)·0.1⁴·e³ ≈ 4.7e-5
    err = np.max(np.abs(uniform_cubic(-1.0, 0.1, np.exp(grid), x) - np.exp(x)))
    assert 1e-7 < err <= 3 / 128 * 0.1**4 * np.exp(3.0)


def test_uniform_bicubic_is_exact_for_bicubics():
    from forensics.stats.censored import uniform_bicubic

    gx, gy = np.arange(-1.0, 3.0 + 1e-9, 0.1), np.arange(0.4, 0.9 + 1e-9, 0.05)
    f = lambda x, y: (1 + x - 0.2 * x**3) * (2 - y + 0.7 * y**2 + 0.1 * y**3)  # noqa: E731
    rng = np.random.default_rng(8)
    x, y = rng.uniform(-0.9, 2.9, 1000), rng.uniform(0.45, 0.85, 1000)
    got = uniform_bicubic((-1.0, 0.4), (0.1, 0.05), f(gx[:, None], gy[None, :]), x, y)
    np.testing.assert_allclose(got, f(x, y), rtol=0, atol=1e-11)


def test_a_table_along_mu_where_sigma_is_a_function_of_it():
    # shot noise at one electronic offset: σ² = r² + g·max(μ − o, 0) — the table runs along μ with its nodes at their
    # own σ; every value within the tolerance of the sum, also across the law's kink at μ = o (where a cubic misses by
    # 7·10⁻⁵ DN: those values are summed), and a σ that is not the function's is caught by the check (refused)
    rng = np.random.default_rng(6)
    mu = rng.uniform(-0.5, 4.0, 60_000)

    def sigma_of(level):
        return np.sqrt(0.33**2 + 0.1 * np.maximum(level - 1.0, 0.0))

    sigma = sigma_of(mu)
    exact = readout_moments(mu, sigma, 0, 4095, truncate=True, dither=1.0)[0]
    table = tabulated_truncated_mean(mu, sigma, 0, 4095, dither=1.0, sigma_of=sigma_of)
    assert table is not None
    assert np.max(np.abs(table - exact)) < TABLE_TOLERANCE
    # the plain cubic through the same nodes misses at the kink: what the midpoint check is there for
    from forensics.stats.censored import TABLE_STEP, uniform_cubic
    h = TABLE_STEP * sigma.min()
    grid = np.arange(mu.min() - 2 * h, mu.max() + 3 * h, h)
    nodes = readout_moments(grid, sigma_of(grid), 0, 4095, truncate=True, dither=1.0)[0]
    assert np.max(np.abs(uniform_cubic(grid[0], grid[1] - grid[0], nodes, mu) - exact)) > 10 * TABLE_TOLERANCE
    wrong = sigma * (1.0 + 0.2 * rng.uniform(0.0, 1.0, mu.size))
    assert tabulated_truncated_mean(mu, wrong, 0, 4095, dither=1.0, sigma_of=sigma_of) is None
