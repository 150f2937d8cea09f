"""Noise residuals: the part of an image that carries the sensor's fingerprint.

The main estimator, :func:`wavelet_residual`, follows the reference design of the
Binghamton camera-fingerprint code (Lukáš, Fridrich & Goljan 2006; Goljan & Fridrich
2008), re-implemented for speed:

1. **Grey.**  A colour image ``(H, W, 3)`` is reduced to grey with the ITU-R BT.601
   luma weights 0.299, 0.587, 0.114 *before* denoising.  The reference denoises each
   colour channel and combines the three residuals with the same weights; because the
   whole chain is linear except the Wiener shrinkage, both give nearly the same
   residual, and in JPEG images (chroma subsampled, channels demosaiced from one
   mosaic) the sensor pattern sits almost entirely in the luma.  Grey first is three
   times cheaper; it is the choice here.  2-D input (grey images, raw CFA mosaics) is
   used as it is.
2. **Wavelet denoising.**  The image is padded by mirroring (at least 2 pixels, up to
   a multiple of 16, split between both sides as in the reference) and decomposed
   with a 4-level 8-tap Daubechies wavelet (``db4``) in *periodization* mode: the
   orthogonal, critically sampled periodic transform of the reference (WaveLab /
   Rice toolbox), which needs sizes that are multiples of 2**4 — hence the padding.
   Each detail coefficient ``c`` is split by Mihcak's local Wiener estimate into
   signal and noise: local signal variance ``v = min over w in (3, 5, 7, 9) of
   max(0, mean_{w×w}(c²) − σ²)`` (windows zero-padded at the band edges, as
   MATLAB's ``filter2`` in the reference), noise part ``c·σ²/(v + σ²)``.  The
   residual ``W = I − denoised(I)`` is the inverse transform of the noise parts with
   the low band zeroed (by linearity the same thing as subtracting the denoised
   image).
3. **Zero mean.**  On each of the four 2×2 colour-filter-array sub-lattices, the
   row and column means are removed (kills linear patterns shared by cameras of a
   model: row/column read-out artefacts, demosaicing periodicities).
4. **Wiener filter in the DFT domain.**  With ``s = std(W)``, the spectrum ``F`` of
   ``W`` is multiplied by ``s²/(v + s²)`` where ``v`` is the same min-of-four-windows
   local variance computed on the normalised magnitude ``|F|/√(HW)``: the magnitude
   is replaced by its "noise part", exactly as the wavelet coefficients were.  This
   flattens the spectral peaks of periodic artefacts (JPEG blocks, demosaicing)
   while keeping the flat, white-ish PRNU spectrum.  The local windows wrap around the spectrum's edges:
   the DFT is periodic, and wrapping keeps the gain Hermitian-symmetric, so the
   filter can be applied on the half spectrum of a real FFT.  (The reference pads
   with zeros and takes the real part of the inverse; the two differ only in the
   four rows/columns next to the zero-frequency lines, where the zero-mean step
   has already made the spectrum vanish.)

Units: ``sigma`` is the standard deviation of the noise **on an 8-bit scale**
(full scale = 255), as in the reference (σ = 3 for fingerprints, 2 for queries).
It is converted to the input's units with ``white_level`` (the value of full
scale: 255 for uint8, 65535 for uint16, 1.0 for floats; pass the camera's white
level for raw mosaics, e.g. 4095 for 12-bit data stored in uint16).  The residual
is returned in the input's units, as float32.

All arithmetic is float32; inputs are never modified.
"""
from __future__ import annotations

import math
import os
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numpy as np
import pywt
import scipy.fft
from scipy import ndimage

from forensics._shared.errors import InputError, UsageError
from forensics._shared.arrays import full_scale, grey_luma
from forensics._shared.parallel import thread_budget

__all__ = [
    "LEVELS",
    "WAVELET",
    "wavelet_noise",
    "zero_mean_cfa",
    "wiener_dft",
    "wavelet_residual",
    "residual_and_grey",
    "median_residual",
    "default_workers",
]

#: Wavelet and number of decomposition levels of the reference design.
WAVELET = "db4"
LEVELS = 4
#: Window sizes of Mihcak's local variance estimate.
WINDOWS: tuple[int, ...] = (3, 5, 7, 9)
_R = WINDOWS[-1] // 2  # half-width of the largest window
_MIN_PAD = 2  # the reference always mirrors at least 2 rows/columns
_STRIP = 128  # rows per strip in the local-variance passes (keeps temporaries in cache)

_POOLS: dict[tuple[int, int], ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()


def default_workers() -> int:
    """Number of threads used when ``workers`` is None: the CPUs this process may use, at most 4 — or a
    worker's share of them under the execution layer (:func:`forensics._shared.parallel.thread_budget`)."""
    return thread_budget(4)


def _pool(workers: int) -> ThreadPoolExecutor | None:
    """A shared thread pool (NumPy, SciPy and PyWavelets release the GIL in their loops).

    Keyed by process id as well: a child made by ``fork`` inherits the pool object
    but not its threads, so it must make its own.  Tasks submitted here never wait
    on other tasks, so callers in several threads can share a pool without deadlock.
    """
    if workers <= 1:
        return None
    key = (os.getpid(), workers)
    with _POOLS_LOCK:
        pool = _POOLS.get(key)
        if pool is None:
            pool = _POOLS[key] = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="forensics-residual")
    return pool


class _Done:
    """A finished 'future' for the serial path."""

    def __init__(self, value: Any) -> None:
        self._value = value

    def result(self) -> Any:
        return self._value


def _submit(pool: ThreadPoolExecutor | None, fn: Callable[..., Any], *args: Any) -> Future | _Done:
    return _Done(fn(*args)) if pool is None else pool.submit(fn, *args)


# ----------------------------------------------------------------------------- input handling


def _check_image(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (3, 4)):
        raise InputError(
            f"image of shape {image.shape}: expected (H, W) grey or raw mosaic, or (H, W, 3) colour"
        )
    if image.shape[0] < 2 or image.shape[1] < 2:
        raise InputError(f"image of shape {image.shape} is too small for a noise residual (need at least 2×2)")
    full_scale(image.dtype)  # raises for unsupported dtypes
    if image.dtype.kind == "f" and not np.all(np.isfinite(image)):
        raise InputError("image contains NaN or infinite values; clean or mask them first")
    return image


def _pad_sizes(n: int, multiple: int) -> tuple[int, int]:
    """(before, after) mirror padding: at least 2, total up to a multiple, the extra row on top."""
    total = -(-(n + _MIN_PAD) // multiple) * multiple - n
    return (total + 1) // 2, total // 2


def _mirror_edges(buf: np.ndarray, top: int, bottom: int, left: int, right: int) -> None:
    """Fill the margins of ``buf`` in place by 'symmetric' mirroring (edge pixel repeated) of its centre.

    Written by hand because the centre has already been written into ``buf`` by the
    grey conversion; :func:`numpy.pad` would need another full-size copy.
    """
    h = buf.shape[0] - top - bottom
    w = buf.shape[1] - left - right
    if top > h or bottom > h or left > w or right > w:  # tiny images: numpy handles repeated mirroring
        centre = buf[top : top + h, left : left + w].copy()
        buf[...] = np.pad(centre, ((top, bottom), (left, right)), mode="symmetric")
        return
    rows = slice(top, top + h)
    if left:
        buf[rows, :left] = buf[rows, left : 2 * left][:, ::-1]
    if right:
        buf[rows, left + w :] = buf[rows, left + w - right : left + w][:, ::-1]
    if top:
        buf[:top] = buf[top : 2 * top][::-1]
    if bottom:
        buf[top + h :] = buf[top + h - bottom : top + h][::-1]


# ----------------------------------------------------------------------------- local Wiener shrinkage


def _min_local_variance(padded: np.ndarray, noise_var: float) -> np.ndarray:
    """Mihcak's local signal variance of the interior of an already padded energy array.

    ``padded`` holds squared coefficients (or squared magnitudes) with ``_R`` = 4
    extra rows and columns on every side, filled by the caller according to the
    boundary rule (zeros, or periodic wrap).  Returns, for the interior,
    ``max(0, min_w mean_{w×w} − noise_var)`` for w in 3, 5, 7, 9 (the min of the
    thresholded means equals the threshold of the min).

    The w×w means are separable box sums.  The vertical sums are built
    incrementally (the 5-row sum is the 3-row sum plus two rows, and so on) from
    contiguous row slices, which is 4× faster than a filter along axis 0; the
    horizontal pass uses :func:`scipy.ndimage.uniform_filter1d` (a running sum,
    double-precision internally).
    """
    h = padded.shape[0] - 2 * _R
    wp = padded.shape[1]
    vsum = padded[_R - 1 : _R - 1 + h] + padded[_R : _R + h]
    vsum += padded[_R + 1 : _R + 1 + h]
    buf = np.empty((h, wp), np.float32)
    best: np.ndarray | None = None
    for w in WINDOWS:
        r = w // 2
        if r > 1:
            vsum += padded[_R - r : _R - r + h]
            vsum += padded[_R + r : _R + r + h]
        ndimage.uniform_filter1d(vsum, w, axis=1, mode="constant", output=buf)
        mean = buf[:, _R : wp - _R]
        mean *= np.float32(1.0 / w)
        if best is None:
            best = mean.copy()
        else:
            np.minimum(best, mean, out=best)
    assert best is not None
    best -= np.float32(noise_var)
    np.maximum(best, 0, out=best)
    return best


def _band_noise(coef: np.ndarray, noise_var: float) -> np.ndarray:
    """Noise part ``c·σ²/(v + σ²)`` of one wavelet detail band (zero-padded windows).

    Processed in strips of ``_STRIP`` rows (with 4 rows of context on each side):
    the temporaries stay in the CPU cache and memory does not scale with the band.
    """
    h, w = coef.shape
    out = np.empty((h, w), np.float32)
    nv = np.float32(noise_var)
    padded = np.empty((min(_STRIP, h) + 2 * _R, w + 2 * _R), np.float32)
    for a in range(0, h, _STRIP):
        b = min(a + _STRIP, h)
        lo, hi = max(a - _R, 0), min(b + _R, h)
        p = padded[: b - a + 2 * _R]
        p.fill(0)
        top = _R - (a - lo)
        np.multiply(coef[lo:hi], coef[lo:hi], out=p[top : top + hi - lo, _R : _R + w])
        v = _min_local_variance(p, noise_var)
        v += nv
        np.divide(nv, v, out=v)
        np.multiply(v, coef[a:b], out=out[a:b])
    return out


# ----------------------------------------------------------------------------- wavelet transform


def _transpose(a: np.ndarray, block: int = 64) -> np.ndarray:
    """Contiguous transpose, blocked by hand: about 3× faster than ``ascontiguousarray(a.T)``."""
    out = np.empty(a.shape[::-1], a.dtype)
    for i in range(0, a.shape[0], block):
        out[:, i : i + block] = a[i : i + block].T
    return out


def _dwt_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return pywt.dwt(a, WAVELET, mode="periodization", axis=-1)


def _idwt_rows(lo: np.ndarray | None, hi: np.ndarray) -> np.ndarray:
    return pywt.idwt(lo, hi, WAVELET, mode="periodization", axis=-1)


def _transposed_dwt(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """1-D transform along the *first* axis, results left transposed."""
    return _dwt_rows(_transpose(x))


def _idwt_transposed(lo: np.ndarray | None, hi: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_transposed_dwt`."""
    return _transpose(_idwt_rows(lo, hi))


def wavelet_noise(
    grey: np.ndarray,
    noise_sigma: float,
    levels: int = LEVELS,
    workers: int | None = None,
) -> np.ndarray:
    """Wavelet-domain noise residual of a 2-D array (step 2 of the module's pipeline only).

    Parameters
    ----------
    grey : ndarray, (H, W)
        Grey image or mosaic, any real dtype; H and W must be multiples of
        ``2**levels`` (see :func:`wavelet_residual` for the padding).
    noise_sigma : float
        Noise standard deviation **in the units of** ``grey``.
    levels : int
        Decomposition levels (4 in the reference).
    workers : int, optional
        Threads (default :func:`default_workers`).

    Returns
    -------
    ndarray, float32, (H, W)
        The inverse transform of the detail-band noise parts, low band zeroed:
        identical (to float32 rounding) to ``pywt.waverec2`` of the shrunk
        ``pywt.wavedec2(grey, 'db4', mode='periodization', level=levels)``.

    Notes
    -----
    The 2-D transform is written here as 1-D transforms along the last axis with
    blocked transposes in between, instead of calling ``pywt.wavedec2``: PyWavelets'
    pass along axis 0 walks memory with a large stride and is 5× slower than the
    pass along axis 1.  The transform is separable, so the order of the two passes
    does not change the result; each level leaves its bands transposed, which the
    square Wiener windows do not mind, and the inverse undoes it.
    """
    m = 2**levels
    a = np.asarray(grey)
    if a.ndim != 2 or a.shape[0] % m or a.shape[1] % m:
        raise InputError(f"array of shape {a.shape}: wavelet_noise needs a 2-D array with sides multiple of {m}")
    a = a.astype(np.float32, copy=False)
    noise_var = float(noise_sigma) ** 2
    pool = _pool(default_workers() if workers is None else workers)

    # Forward transform; the Wiener shrinkage of each detail band runs in the pool
    # while the main thread decomposes the next level.  References are dropped as
    # soon as an array has been consumed, to keep the peak memory low.
    pending: list[tuple[Any, Any, Any]] = []
    for _ in range(levels):
        lo, hi = _dwt_rows(a)
        del a
        f_lo = _submit(pool, _transposed_dwt, lo)
        del lo
        hl, hh = _transposed_dwt(hi)
        del hi
        a, lh = f_lo.result()
        del f_lo
        pending.append(tuple(_submit(pool, _band_noise, band, noise_var) for band in (lh, hl, hh)))
        del lh, hl, hh
    del a

    # Inverse transform from the coarsest level, low band zero.
    rec: np.ndarray | None = None
    while pending:
        f_lh, f_hl, f_hh = pending.pop()
        f_lo = _submit(pool, _idwt_transposed, rec, f_lh.result())
        del rec, f_lh
        hi = _idwt_transposed(f_hl.result(), f_hh.result())
        del f_hl, f_hh
        rec = _idwt_rows(f_lo.result(), hi)
        del f_lo, hi
    assert rec is not None
    return rec.astype(np.float32, copy=False)


# ----------------------------------------------------------------------------- post-processing


def zero_mean_cfa(x: np.ndarray, inplace: bool = False) -> np.ndarray:
    """Remove row and column means on each of the four 2×2 CFA sub-lattices.

    On each sub-lattice ``s = x[i::2, j::2]``: ``s − rowmean − colmean + mean``,
    after which every row and every column of every sub-lattice sums to zero.

    Parameters
    ----------
    x : ndarray, (H, W)
    inplace : bool
        Modify ``x`` (must be a float32 array) instead of returning a new array.

    Returns
    -------
    ndarray, float32, (H, W)
    """
    if x.ndim != 2:
        raise InputError(f"array of shape {x.shape}: zero_mean_cfa needs a 2-D array")
    y = x if inplace else np.array(x, dtype=np.float32, copy=True)
    if y.dtype != np.float32:
        raise InputError("zero_mean_cfa(inplace=True) needs a float32 array")
    for i in (0, 1):
        for j in (0, 1):
            s = y[i::2, j::2]
            if s.size == 0:
                continue
            rows = s.mean(axis=1, dtype=np.float64)
            cols = s.mean(axis=0, dtype=np.float64)
            total = rows.mean()
            s -= (rows - total).astype(np.float32)[:, None]
            s -= cols.astype(np.float32)[None, :]
    return y


def _column_of_full_spectrum(mag: np.ndarray, col: int, width: int, flip: np.ndarray) -> np.ndarray:
    """Column ``col`` (any integer, periodic) of the full |DFT| from the half spectrum of a real input."""
    c = col % width
    if c < mag.shape[1]:
        return mag[:, c]
    return mag[flip, width - c]  # |F(u, c)| = |F(-u, W - c)| for real input


def wiener_dft(x: np.ndarray, sigma: float | None = None, workers: int | None = None) -> np.ndarray:
    """Wiener filter of the spectrum magnitude (step 4 of the module's pipeline).

    Parameters
    ----------
    x : ndarray, (H, W)
        A residual (any real dtype).
    sigma : float, optional
        Noise standard deviation in ``x``'s units; default ``x.std()``.
    workers : int, optional
        Threads for the FFTs (default :func:`default_workers`).

    Returns
    -------
    ndarray, float32, (H, W)
        ``irfft2(F · σ²/(v + σ²))`` with ``F = rfft2(x)`` and ``v`` Mihcak's local
        variance of ``|F|/√(HW)`` over 3…9 windows that wrap around the spectrum
        (spectral peaks, i.e. periodic patterns, are damped; a flat spectrum passes).
    """
    x = np.asarray(x)
    if x.ndim != 2:
        raise InputError(f"array of shape {x.shape}: wiener_dft needs a 2-D array")
    x = x.astype(np.float32, copy=False)
    h, w = x.shape
    workers = default_workers() if workers is None else workers
    if sigma is None:
        sigma = _std(x)
    noise_var = float(sigma) ** 2
    if noise_var == 0.0:
        return np.zeros_like(x)
    spec = scipy.fft.rfft2(x, workers=workers)
    mag = np.abs(spec)
    mag *= np.float32(1.0 / np.sqrt(h * w))
    wc = spec.shape[1]
    flip = (-np.arange(h)) % h
    # Periodic extension by 4 rows/columns on each side, built from the half spectrum.
    ext = np.empty((h, wc + 2 * _R), np.float32)
    ext[:, _R : _R + wc] = mag
    for j in range(1, _R + 1):
        ext[:, _R - j] = _column_of_full_spectrum(mag, -j, w, flip)
        ext[:, _R + wc - 1 + j] = _column_of_full_spectrum(mag, wc - 1 + j, w, flip)
    del mag
    rows = np.arange(-_R, h + _R) % h
    ext = np.take(ext, rows, axis=0)
    np.multiply(ext, ext, out=ext)
    _apply_wiener_gain(spec, ext, noise_var, _pool(workers))
    del ext
    return scipy.fft.irfft2(spec, s=(h, w), workers=workers).astype(np.float32, copy=False)


def _std(x: np.ndarray) -> float:
    """Standard deviation from float32 BLAS sums (relative error ~1e-5: plenty for a noise level)."""
    v = np.ascontiguousarray(x).ravel()
    n = v.size
    mean = float(v.sum(dtype=np.float64)) / n
    return math.sqrt(max(float(np.dot(v, v)) / n - mean * mean, 0.0))


def _apply_wiener_gain(spec: np.ndarray, padded: np.ndarray, noise_var: float,
                       pool: ThreadPoolExecutor | None) -> None:
    """Multiply ``spec`` in place by the 'noise part' gain σ²/(v + σ²) of the padded energy.

    The gain keeps the flat (noise-like) spectrum and damps local peaks.  Strips of
    rows are independent, so they run in the pool.
    """
    h = spec.shape[0]
    nv = np.float32(noise_var)

    def strip(a: int) -> None:
        b = min(a + _STRIP, h)
        v = _min_local_variance(padded[a : b + 2 * _R], noise_var)
        v += nv
        np.divide(nv, v, out=v)
        spec[a:b] *= v

    starts = range(0, h, _STRIP)
    if pool is None:
        for a in starts:
            strip(a)
    else:
        list(pool.map(strip, starts))


# ----------------------------------------------------------------------------- public estimators


def _scaled_sigma(sigma: float, white_level: float) -> float:
    if not np.isfinite(sigma) or sigma <= 0:
        # an option, not data: a usage error (exit 2)
        raise UsageError(f"sigma={sigma}: the noise level must be a positive number (8-bit scale, e.g. 3)")
    if not np.isfinite(white_level) or white_level <= 0:
        raise InputError(f"white_level={white_level}: must be a positive number (the pixel value of full scale)")
    return float(sigma) * float(white_level) / 255.0


def wavelet_residual(
    image: np.ndarray,
    sigma: float = 3.0,
    *,
    white_level: float | None = None,
    levels: int = LEVELS,
    zero_mean: bool = True,
    wiener: bool = True,
    workers: int | None = None,
) -> np.ndarray:
    """Noise residual ``W = I − F(I)`` of the reference PRNU design (see the module notes).

    Parameters
    ----------
    image : ndarray, (H, W) or (H, W, 3)
        uint8, uint16 (or other integer) or float pixels; RGB is reduced to grey
        with :data:`GREY_WEIGHTS`; a 2-D array (grey or raw CFA mosaic) is used as is.
        Any size of at least 2×2: it is mirror-padded to a multiple of ``2**levels``
        and the result is cropped back.
    sigma : float
        Noise standard deviation on an 8-bit scale (3 for fingerprints, 2 for queries).
    white_level : float, optional
        Pixel value of full scale; default from the dtype (255, 65535, 1.0 for float).
    levels : int
        Wavelet decomposition levels.
    zero_mean : bool
        Apply :func:`zero_mean_cfa` (step 3).
    wiener : bool
        Apply :func:`wiener_dft` with σ = std of the residual (step 4).
    workers : int, optional
        Threads (default :func:`default_workers`).

    Returns
    -------
    ndarray, float32, (H, W)
        The residual, in the input's units.

    Raises
    ------
    InputError
        For arrays that are not images (wrong shape, non-finite values, too small).
    """
    workers = default_workers() if workers is None else workers
    res, _ = residual_and_grey(image, sigma, white_level=white_level, levels=levels, workers=workers)
    if zero_mean or wiener:
        res = np.ascontiguousarray(res)
    else:
        res = res.copy()  # a compact array, not a view of the padded one
    if zero_mean:
        zero_mean_cfa(res, inplace=True)
    if wiener:
        res = wiener_dft(res, workers=workers)
    return res


def residual_and_grey(
    image: np.ndarray,
    sigma: float = 3.0,
    *,
    white_level: float | None = None,
    levels: int = LEVELS,
    workers: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Wavelet-stage residual (step 2 only) and the grey image, without extra copies.

    For callers that need both (the fingerprint accumulator): the grey image is
    computed once, straight into the padded buffer of the transform.

    Returns
    -------
    residual, grey : float32 arrays (H, W)
        Views into larger private arrays (not contiguous); both are the caller's
        to modify.
    """
    image = _check_image(image)
    if white_level is None:
        white_level = full_scale(image.dtype)
    noise_sigma = _scaled_sigma(sigma, white_level)
    h, w = image.shape[:2]
    m = 2**levels
    top, bottom = _pad_sizes(h, m)
    left, right = _pad_sizes(w, m)
    buf = np.empty((h + top + bottom, w + left + right), np.float32)
    grey = buf[top : top + h, left : left + w]
    grey_luma(image, out=grey)
    _mirror_edges(buf, top, bottom, left, right)
    noise = wavelet_noise(buf, noise_sigma, levels=levels, workers=workers)
    return noise[top : top + h, left : left + w], grey


def median_residual(image: np.ndarray, size: int = 3) -> np.ndarray:
    """Spiky-defect residual ``y − median_{size×size}(y)`` (Fridrich; the paper's defect residual).

    Parameters
    ----------
    image : ndarray, (H, W) or (H, W, 3)
        RGB is reduced to grey first (:func:`~forensics._shared.arrays.grey_luma`).
    size : int
        Odd median window (3 in the paper).

    Returns
    -------
    ndarray, float32, (H, W)
        In the input's units.  Borders repeat the edge (scipy's ``mode='reflect'``).
    """
    if size < 3 or size % 2 == 0:
        raise InputError(f"size={size}: the median window must be odd and at least 3")
    from forensics._shared.filters import median_filter

    y = grey_luma(image)
    y -= median_filter(y, size)
    return y
