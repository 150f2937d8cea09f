"""The tails of ``forensics.stats.tails`` are ``scipy.stats``' own values, and the model check imports neither
``scipy.stats`` nor ``scipy.signal`` (0.3–0.45 s of every small check)."""
import subprocess
import sys

import numpy as np
from scipy import stats

from forensics.stats import tails


def test_the_tails_are_scipy_stats_bit_for_bit():
    x = np.array([0.0, 1e-3, 0.5, 1.0, 3.84, 10.0, 100.0, 1e3])
    for df in (1, 2, 7, 30, 400):
        assert np.array_equal(tails.chi2_sf(x, df), stats.chi2.sf(x, df))
        assert np.array_equal(tails.f_sf(x, df, 13), stats.f.sf(x, df, 13))
        assert np.array_equal(tails.t_sf(x - 2.0, df), stats.t.sf(x - 2.0, df))
    p = np.array([1e-12, 1e-6, 0.001, 0.025, 0.5, 0.9, 0.999])
    for df in (1, 3, 50):
        assert np.array_equal(tails.chi2_isf(p, df), stats.chi2.isf(p, df))
        assert np.array_equal(tails.chi2_ppf(p, df), stats.chi2.ppf(p, df))
    assert np.array_equal(tails.norm_isf(p), stats.norm.isf(p))
    assert np.array_equal(tails.norm_sf(x - 3.0), stats.norm.sf(x - 3.0))
    assert isinstance(tails.chi2_sf(3.0, 2), float)
    # a threshold per pixel: one inversion per distinct df, the same bits
    df = np.random.default_rng(0).integers(1, 9, (300, 400))
    assert np.array_equal(tails.chi2_isf(1e-6, df), stats.chi2.isf(1e-6, df))


def test_the_median_order_bounds_are_the_binomial_quantiles():
    for n in [*range(1, 300), 1_000, 76_800, 76_801, 300_000]:
        assert tails.median_order_bounds(n) == (int(stats.binom.ppf(0.025, n, 0.5)), int(stats.binom.isf(0.025, n, 0.5)))


def test_the_wide_scene_convolution_is_scipy_signal_s_bit_for_bit():
    from scipy import signal

    from forensics.check.pixels import _fft_convolve_valid, loo_quadratic_kernel

    rng = np.random.default_rng(1)
    for shape, size in (((3, 78, 94), 31), ((1, 40, 33), 5)):
        x, kernel = rng.normal(size=shape), loo_quadratic_kernel(size)
        assert np.array_equal(_fft_convolve_valid(x, kernel),
                              signal.fftconvolve(x, kernel[None], mode="valid", axes=(1, 2)))


def test_the_model_check_imports_neither_scipy_stats_nor_scipy_signal():
    code = ("import sys, forensics.check.pipeline, forensics.cli.main\n"
            "print(sorted(m for m in ('scipy.stats', 'scipy.signal') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
