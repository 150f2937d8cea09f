"""Tests of forensics.prnu.residual, against a plain float64 oracle kept here.

The oracle (:func:`oracle_residual`) is the same algorithm written as simply as
possible: float64, ``pywt.wavedec2``/``waverec2``, ``scipy.ndimage.uniform_filter``
for the local variances and a full complex ``fft2``.  The benchmark
``benchmarks/bench_residual.py`` imports it for its side-by-side timing.
"""
from __future__ import annotations

import numpy as np
import pytest
import pywt
from scipy import ndimage

from forensics._shared.arrays import grey_luma
from forensics._shared.errors import InputError, UsageError
from forensics.prnu.residual import (
    median_residual,
    wavelet_noise,
    wavelet_residual,
    wiener_dft,
    zero_mean_cfa,
)

# ----------------------------------------------------------------------------- the float64 oracle

LUMA = (0.299, 0.587, 0.114)


def oracle_grey(image: np.ndarray) -> np.ndarray:
    x = np.asarray(image, dtype=np.float64)
    if x.ndim == 3:
        x = LUMA[0] * x[..., 0] + LUMA[1] * x[..., 1] + LUMA[2] * x[..., 2]
    return x


def oracle_local_variance(e: np.ndarray, noise_var: float, mode: str) -> np.ndarray:
    """min over 3, 5, 7, 9 windows of max(0, local mean of e − σ²)."""
    variances = [np.maximum(ndimage.uniform_filter(e, w, mode=mode, cval=0.0) - noise_var, 0.0) for w in (3, 5, 7, 9)]
    return np.min(variances, axis=0)


def oracle_residual(image: np.ndarray, sigma: float = 3.0, white_level: float = 255.0,
                    zero_mean: bool = True, wiener: bool = True) -> np.ndarray:
    """The reference residual, float64, as plainly as possible."""
    x = oracle_grey(image)
    s = sigma * white_level / 255.0
    h, w = x.shape
    # pad by mirroring: at least 2 pixels, up to a multiple of 16, extra pixel on top/left
    ph = -(-(h + 2) // 16) * 16 - h
    pw = -(-(w + 2) // 16) * 16 - w
    top, left = (ph + 1) // 2, (pw + 1) // 2
    xp = np.pad(x, ((top, ph - top), (left, pw - left)), mode="symmetric")
    coeffs = pywt.wavedec2(xp, "db4", mode="periodization", level=4)
    noise = [np.zeros_like(coeffs[0])]
    for bands in coeffs[1:]:
        shrunk = []
        for c in bands:
            v = oracle_local_variance(c * c, s * s, mode="constant")
            shrunk.append(c * s * s / (v + s * s))
        noise.append(tuple(shrunk))
    res = pywt.waverec2(noise, "db4", mode="periodization")[top : top + h, left : left + w]
    if zero_mean:
        for i in (0, 1):
            for j in (0, 1):
                sub = res[i::2, j::2]
                sub -= sub.mean()
                sub -= sub.mean(axis=1, keepdims=True)
                sub -= sub.mean(axis=0, keepdims=True)
    if wiener:
        sd = res.std()
        spectrum = np.fft.fft2(res)
        magnitude = np.abs(spectrum) / np.sqrt(res.size)
        v = oracle_local_variance(magnitude**2, sd * sd, mode="wrap")
        res = np.real(np.fft.ifft2(spectrum * sd * sd / (v + sd * sd)))
    return res


# ----------------------------------------------------------------------------- synthetic data


def corr(a: np.ndarray, b: np.ndarray) -> float:
    a = np.asarray(a, np.float64).ravel() - np.mean(a)
    b = np.asarray(b, np.float64).ravel() - np.mean(b)
    return float(a @ b / np.sqrt((a @ a) * (b @ b)))


def textured_scene(rng: np.random.Generator, shape: tuple[int, int], channels: int = 3) -> np.ndarray:
    """A scene with smooth shading, sharp edges and fine texture, in 8-bit units (float64)."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    base = 110 + 50 * np.sin(xx / 37.0) * np.cos(yy / 23.0)
    base += 25 * ((xx // 40 + yy // 30) % 2)  # edges (a checkerboard of patches)
    base += ndimage.gaussian_filter(rng.normal(0, 25, shape), 1.5)  # fine texture
    if channels == 1:
        return base
    tint = np.array([0.9, 1.0, 0.8])
    return base[..., None] * tint


def camera_image(rng: np.random.Generator, scene: np.ndarray, k: np.ndarray, noise: float = 1.5) -> np.ndarray:
    """uint8 image of ``scene`` through a sensor with PRNU ``k`` and shot/read noise."""
    kk = k if scene.ndim == 2 else k[..., None]
    img = scene * (1 + kk) + rng.normal(0, noise, scene.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def synthetic() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(20240611)
    shape = (203, 317)  # deliberately not multiples of 16, odd
    k = rng.normal(0, 0.02, shape)
    scene = textured_scene(rng, shape)
    return {"k": k, "scene": scene, "image": camera_image(rng, scene, k)}


# ----------------------------------------------------------------------------- the fast estimator against the oracle


def test_matches_float64_oracle(synthetic):
    image = synthetic["image"]
    fast = wavelet_residual(image, sigma=3.0)
    slow = oracle_residual(image, sigma=3.0)
    assert fast.dtype == np.float32 and fast.shape == image.shape[:2]
    # Same algorithm in float32 vs float64: only rounding differs (measured ≈ 1 − 1e-10).
    assert corr(fast, slow) >= 0.999
    assert np.max(np.abs(fast - slow)) <= 1e-3 * np.max(np.abs(slow))


@pytest.mark.parametrize("zero_mean, wiener", [(False, False), (True, False), (True, True)])
def test_stages_match_oracle(synthetic, zero_mean, wiener):
    image = synthetic["image"]
    fast = wavelet_residual(image, sigma=2.0, zero_mean=zero_mean, wiener=wiener)
    slow = oracle_residual(image, sigma=2.0, zero_mean=zero_mean, wiener=wiener)
    assert corr(fast, slow) >= 0.999


def test_residual_carries_the_prnu(synthetic):
    """The residual correlates with the multiplicative PRNU term I·k far above chance.

    Under no correlation, corr ~ N(0, 1/√n) with n ≈ 64 000 pixels: 0.1 is 25σ.
    """
    image, k, scene = synthetic["image"], synthetic["k"], synthetic["scene"]
    prnu_term = oracle_grey(scene) * k
    assert corr(wavelet_residual(image), prnu_term) > 0.1


@pytest.mark.filterwarnings("ignore:Level value of 4 is too high")
def test_wavelet_noise_is_the_standard_transform():
    """The hand-written transposed transform equals pywt.wavedec2/waverec2 exactly."""
    rng = np.random.default_rng(3)
    x = rng.normal(100, 20, (96, 160)).astype(np.float32)
    ours = wavelet_noise(x, 3.0, workers=1)
    coeffs = pywt.wavedec2(x.astype(np.float64), "db4", mode="periodization", level=4)
    noise = [np.zeros_like(coeffs[0])]
    for bands in coeffs[1:]:
        noise.append(tuple(c * 9 / (oracle_local_variance(c * c, 9.0, "constant") + 9) for c in bands))
    ref = pywt.waverec2(noise, "db4", mode="periodization")
    np.testing.assert_allclose(ours, ref, atol=1e-4 * np.abs(ref).max())


def test_threads_do_not_change_the_result(synthetic):
    image = synthetic["image"]
    np.testing.assert_array_equal(wavelet_residual(image, workers=1), wavelet_residual(image, workers=2))


# ----------------------------------------------------------------------------- dtypes and shapes


def test_dtypes_give_the_same_residual_up_to_scale(synthetic):
    """uint8, uint16 (×257), float in [0, 1] and a 12-bit mosaic in uint16 agree after rescaling.

    The algorithm is scale-equivariant (σ follows the white level), so the
    residuals differ only by float32 rounding.
    """
    u8 = synthetic["image"]
    ref = wavelet_residual(u8)
    u16 = (u8.astype(np.uint16) * 257).astype(np.uint16)
    flt = u8.astype(np.float32) / 255.0
    flt64 = u8.astype(np.float64) / 255.0
    for img, scale in [(u16, 257.0), (flt, 1 / 255.0), (flt64, 1 / 255.0)]:
        out = wavelet_residual(img)
        assert out.dtype == np.float32
        np.testing.assert_allclose(out / scale, ref, atol=1e-4 * np.abs(ref).max())
    grey = np.rint(grey_luma(u8)).astype(np.uint16) * 16  # 12-bit data in uint16, white level 4095·16/16
    mosaic12 = (grey // 16).astype(np.uint16)
    a = wavelet_residual(mosaic12, white_level=4095)
    b = wavelet_residual(grey, white_level=4095 * 16)
    np.testing.assert_allclose(a * 16, b, atol=1e-4 * np.abs(b).max())


def test_raw_mosaic_is_accepted():
    rng = np.random.default_rng(5)
    mosaic = rng.integers(200, 3800, (130, 174), dtype=np.uint16)
    out = wavelet_residual(mosaic, white_level=4095)
    assert out.shape == mosaic.shape and out.dtype == np.float32 and np.all(np.isfinite(out))
    assert corr(out, oracle_residual(mosaic, white_level=4095)) >= 0.999


@pytest.mark.parametrize("shape", [(2, 2), (5, 7), (17, 33), (64, 64), (3, 200)])
def test_any_size(shape):
    rng = np.random.default_rng(sum(shape))
    x = rng.normal(128, 10, shape)
    out = wavelet_residual(x, white_level=255)
    assert out.shape == shape and np.all(np.isfinite(out))


def test_inputs_are_not_modified(synthetic):
    image = synthetic["image"].copy()
    image.flags.writeable = False  # any in-place write would raise
    wavelet_residual(image)
    median_residual(image)
    np.testing.assert_array_equal(image, synthetic["image"])
    x = np.random.default_rng(1).normal(size=(40, 40)).astype(np.float32)
    x.flags.writeable = False
    zero_mean_cfa(x)
    wiener_dft(x)


@pytest.mark.parametrize(
    "bad",
    [np.zeros(10), np.zeros((4, 4, 2)), np.full((8, 8), np.nan), np.zeros((1, 50)), np.zeros((8, 8), complex)],
)
def test_bad_input_raises_input_error(bad):
    with pytest.raises(InputError):
        wavelet_residual(bad)


def test_bad_sigma():
    """An option out of range is a usage error (exit 2), not bad input data (D21)."""
    for sigma in (0, -1, float("nan")):
        with pytest.raises(UsageError, match="sigma"):
            wavelet_residual(np.zeros((20, 20)), sigma=sigma)


# ----------------------------------------------------------------------------- post-processing steps


def test_zero_mean_cfa_kills_row_and_column_means():
    rng = np.random.default_rng(7)
    x = rng.normal(0, 1, (51, 64)) + np.arange(64)[None, :] * 0.1 + 3.0
    x[::2, ::2] += 5  # a CFA-periodic offset
    y = zero_mean_cfa(x)
    for i in (0, 1):
        for j in (0, 1):
            s = y[i::2, j::2].astype(np.float64)
            assert np.abs(s.mean(axis=0)).max() < 1e-5
            assert np.abs(s.mean(axis=1)).max() < 1e-5


def test_wiener_dft_removes_periodic_artefacts():
    """An 8-pixel periodic grid (JPEG-like) is suppressed; white noise is kept."""
    rng = np.random.default_rng(11)
    noise = rng.normal(0, 1, (256, 256))
    grid = np.zeros_like(noise)
    grid[:, ::8] = 4.0
    grid -= grid.mean()
    out = wiener_dft((noise + grid).astype(np.float32))
    assert corr(out, noise) > 0.95
    assert abs(corr(out, grid)) < 0.5 * abs(corr(noise + grid, grid))


# ----------------------------------------------------------------------------- median residual


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_median_residual_recovers_a_spike(dtype):
    img = np.full((32, 40), 100, dtype=dtype)
    img[10, 17] = 150
    res = median_residual(img)
    assert res.dtype == np.float32
    assert res[10, 17] == pytest.approx(50.0)
    res[10, 17] = 0
    assert np.all(res == 0)


def test_median_residual_rgb_spike():
    img = np.full((20, 20, 3), 60, np.uint8)
    img[5, 6] = (160, 160, 160)
    res = median_residual(img)
    assert res.shape == (20, 20)
    assert res[5, 6] == pytest.approx(100.0, abs=1e-3)
    assert np.count_nonzero(np.abs(res) > 1e-3) == 1
