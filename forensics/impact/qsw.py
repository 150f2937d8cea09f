"""Ma et al.'s key local variations: USIT's ``qsw`` (quadratic spline wavelet) iris code.

L. Ma, T. Tan, Y. Wang and D. Zhang, "Efficient iris recognition by characterizing key local variations",
*IEEE Transactions on Image Processing* 13(6), 2004, 739–750.  (USIT's ``qsw`` cites the same group's TPAMI
2003 paper in its usage text, but what it implements — local extrema of a dyadic quadratic-spline wavelet
transform of 1-D intensity signals, turned into a binary sequence and compared by XOR — is the TIP 2004
method.)

The published method, as implemented here:

1. The normalised iris (USIT: 512 angular × 64 radial samples, row 0 at the pupil) is cut into ``signals``
   = 10 bands of ``rows_per_signal`` = 5 rows from the pupil outwards (the region nearest the pupil, where
   eyelids rarely reach: 50 of the 64 rows); each band is averaged over its rows into a 1-D intensity
   signal along the angle (circular, 512 samples).
2. Each signal is decomposed with Mallat and Zhong's dyadic wavelet transform, whose wavelet is the
   quadratic spline (the derivative of a cubic-spline smoothing function): à trous filters
   ``h = (1, 3, 3, 1)/8`` and ``g = (2, −2)`` dilated by ``2^j`` at level ``j``, circular along the angle
   (computed exactly with the FFT).  Its local extrema are the points of sharpest intensity variation.
   USIT keeps two scales, ``W_{2^3}`` and ``W_{2^4}`` (``scales=(3, 4)``), as Ma et al. use two.
3. Ma et al. record the positions of the local minima and maxima and turn them into a binary sequence:
   ``1`` from a local minimum to the next local maximum, ``0`` from a maximum to the next minimum — i.e.
   bit ``i`` says whether the transform rises from sample ``i`` to ``i + 1``.  (USIT further drops
   extremum pairs of very small swing with an undocumented threshold; we keep every extremum, as the
   paper's description does not give one.)
4. Templates are compared by XOR — the masked fractional Hamming distance — minimised over circular
   shifts along the angle: ``max_shift`` = 17 samples (±12°, the range of this project's Masek matcher;
   Ma et al. compensate rotation the same way, by shifting the binary sequences).

Code: 10 signals × 2 scales × 512 samples = 10,240 bits, one :class:`~forensics.impact.iriscode.IrisCode`
column per angular sample (20 bits), so a rotation of the eye is an exact roll of the code.  A signal sample
is usable when at least 3 of its 5 texture samples are (eyelids, lashes and reflections masked by the
segmentation); unusable samples are filled with the texture mean before averaging (as Masek does), and the
mask marks their bits invalid.
"""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from forensics._shared.errors import UsageError
from forensics.impact.iriscode import IrisCode, IrisCodeMatcher
from forensics.impact.segment import Segmentation, Segmenter
from forensics.impact.texture import TEXTURE_SHAPE, cell_validity, fill_unusable

__all__ = ["QswMatcher", "dyadic_wavelet"]

# Mallat & Zhong's quadratic spline filters (taps at n = −1 … 2 and n = 0, 1).
_H_TAPS = ((-1, 0.125), (0, 0.375), (1, 0.375), (2, 0.125))
_G_TAPS = ((0, 2.0), (1, -2.0))


def _transfer(taps: tuple[tuple[int, float], ...], n: int, dilation: int) -> np.ndarray:
    """FFT of the circular filter with ``taps`` spread ``dilation`` samples apart (the à trous holes)."""
    kernel = np.zeros(n)
    for pos, value in taps:
        kernel[(pos * dilation) % n] += value
    return np.fft.fft(kernel)


def dyadic_wavelet(signals: np.ndarray, scales: tuple[int, ...]) -> np.ndarray:
    """Mallat–Zhong dyadic wavelet transform ``W_{2^s}`` of circular signals along the last axis.

    Returns an array of shape ``(len(scales), *signals.shape)``; scale ``s ≥ 1`` is the detail after
    ``s − 1`` smoothing steps (level ``j`` filters dilated by ``2^j``).  The filters as published are
    causal: their cascade delays the signal by ``2^(s−1) − ½`` samples; the delay is undone in the Fourier
    domain, so that an extremum of ``W`` lies on the sharp variation it marks (the kernel is then
    antisymmetric about 0 and ``W`` of a symmetric bump is antisymmetric about the bump).
    """
    x = np.asarray(signals, dtype=np.float64)
    n = x.shape[-1]
    spectrum = np.fft.fft(x, axis=-1)
    freq = np.fft.fftfreq(n)
    out = np.empty((len(scales), *x.shape))
    for k, s in enumerate(scales):
        if s < 1 or 2 ** (s - 1) * 3 >= n:
            raise UsageError(f"qsw: scale {s} does not fit a signal of {n} samples")
        response = _transfer(_G_TAPS, n, 2 ** (s - 1))
        for j in range(s - 1):
            response = response * _transfer(_H_TAPS, n, 2 ** j)
        delay = 2.0 ** (s - 1) - 0.5
        response = response * np.exp(2j * np.pi * freq * delay)
        if n % 2 == 0:
            response[n // 2] = response[n // 2].real  # the Nyquist bin of a real kernel stays real
        out[k] = np.fft.ifft(spectrum * response, axis=-1).real
    return out


class QswMatcher(IrisCodeMatcher):
    """Ma et al. (2004) through USIT's ``qsw``: rising/falling between wavelet extrema, Hamming distance.

    Parameters
    ----------
    segmenter
        Shared segmenter (cache); a new one if None.
    radial, angular
        Rubber-sheet size (USIT: 64 × 512).
    rows_per_signal, signals
        Rows averaged into one 1-D signal, and the number of signals taken from the pupil outwards (Ma et
        al. and USIT: 5 and 10).
    scales
        Dyadic scales ``s`` of ``W_{2^s}`` to code (USIT: 3 and 4).
    max_shift
        Circular shifts tried, ``±max_shift`` angular samples (17 = ±12°).
    min_valid
        Fraction of the code's bits that must be valid in both masks for a shift to count.
    """

    name: ClassVar[str] = "qsw"
    higher_is_similar: ClassVar[bool] = False

    def __init__(self, segmenter: Segmenter | None = None, *, radial: int = TEXTURE_SHAPE[0],
                 angular: int = TEXTURE_SHAPE[1], rows_per_signal: int = 5, signals: int = 10,
                 scales: tuple[int, ...] = (3, 4), max_shift: int = 17, min_valid: float = 0.1) -> None:
        self.segmenter = segmenter if segmenter is not None else Segmenter()
        self.radial, self.angular = int(radial), int(angular)
        self.rows_per_signal, self.signals = int(rows_per_signal), int(signals)
        self.scales = tuple(int(s) for s in scales)
        self.max_shift, self.min_valid = int(max_shift), float(min_valid)
        if self.rows_per_signal < 1 or self.signals < 1 or self.rows_per_signal * self.signals > self.radial:
            raise UsageError(f"qsw: {self.signals} signals of {self.rows_per_signal} rows do not fit a texture of "
                             f"{self.radial} rows")
        if not self.scales:
            raise UsageError("qsw: give at least one scale")
        dyadic_wavelet(np.zeros((1, self.angular)), self.scales)  # checks the scales against the width

    def signals_of(self, texture: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The 1-D intensity signals ``(signals, angular)`` and their usability (majority of the rows)."""
        rows = self.rows_per_signal * self.signals
        t = fill_unusable(texture, mask)[:rows].astype(np.float64)
        sig = t.reshape(self.signals, self.rows_per_signal, -1).mean(axis=1)
        valid = cell_validity(np.asarray(mask, dtype=bool)[:rows], (self.rows_per_signal, 1))
        return sig, valid

    def encode_texture(self, texture: np.ndarray, mask: np.ndarray,
                       segmentation: Segmentation | None = None) -> IrisCode:
        """The code of an already normalised ``(radial, angular)`` texture and its usability mask."""
        sig, valid = self.signals_of(texture, mask)
        w = dyadic_wavelet(sig, self.scales)                          # (scales, signals, angular)
        rising = np.roll(w, -1, axis=-1) > w
        # Angle-major: column x holds [scale 0: signals…, scale 1: signals…].
        bits = rising.transpose(2, 0, 1).reshape(sig.shape[1], -1)
        vmask = np.broadcast_to(valid[None], rising.shape).transpose(2, 0, 1).reshape(sig.shape[1], -1)
        return IrisCode.from_bits(bits, vmask, segmentation)

    def mask_groups(self) -> np.ndarray:
        """A column's bits (scales × signals) share the mask of their signal."""
        return np.tile(np.arange(self.signals), len(self.scales))

    def encode(self, image: np.ndarray) -> IrisCode:
        """Segment (cached), normalise and encode an eye image."""
        texture, mask, seg = self.segmenter.unwrap(image, self.radial, self.angular)
        return self.encode_texture(texture, mask, seg)
