"""Masek's 1-D Log-Gabor iris code (the reference paper's ``lg``).

L. Masek, *Recognition of Human Iris Patterns for Biometric Identification* (2003), and Masek & Kovesi's
MATLAB code as re-implemented in USIT (``lg``): each row of the rubber-sheet texture is filtered along the
angle with a 1-D Log-Gabor filter and the phase of each response is quantised to two bits; comparison by the
masked fractional Hamming distance minimised over circular shifts.
"""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from forensics.impact.iriscode import IrisCode, IrisCodeMatcher
from forensics.impact.segment import Segmentation, Segmenter
from forensics.impact.texture import fill_unusable


def log_gabor_1d(n: int, wavelength: float, sigma_on_f: float) -> np.ndarray:
    """Masek's 1-D Log-Gabor transfer function over ``n`` FFT bins (positive frequencies only).

    ``G(f) = exp(−(ln(f/f₀))² / (2 (ln σ/f)²))`` for ``0 < f ≤ 1/2`` with ``f₀ = 1/wavelength``, 0 at DC and at
    negative frequencies, so that the filtered signal is analytic and its phase is defined (as ``gaborconvolve``).
    """
    f = np.arange(n) / n
    g = np.zeros(n)
    pos = (f > 0) & (f <= 0.5)
    g[pos] = np.exp(-(np.log(f[pos] * wavelength)) ** 2 / (2 * np.log(sigma_on_f) ** 2))
    return g


class MasekMatcher(IrisCodeMatcher):
    """Masek's 1-D Log-Gabor iris code with the masked fractional Hamming distance.

    Parameters
    ----------
    segmenter
        Shared segmenter (cache); a new one if None.
    radial, angular
        Rubber-sheet size (Masek: 20×240).
    wavelength, sigma_on_f
        Log-Gabor centre wavelength in angular samples and bandwidth ratio (Masek: 18 and 0.5).
    max_shift
        Circular shifts tried: ``±max_shift`` angular samples (Masek: 8, i.e. ±12° at 240 samples).
    min_valid
        Fraction of the code's bits that must be valid in both masks for a shift to count; if no shift
        has that many, the distance is 1.0.
    min_magnitude
        Bits whose filter response magnitude is below this fraction of the template's median magnitude are
        masked as unreliable (Masek only masks exact zeros; 0 disables).

    Notes
    -----
    Encoding: masked samples of the texture are replaced by the mean of the usable ones (as Masek does, so
    that occlusions do not ring through the filter), every row is filtered at once with ``np.fft``, and each
    angular sample gives two bits (``Re > 0``, ``Im > 0``) sharing the sample's mask.  Layout: one
    :class:`IrisCode` column per angular sample holding ``2 × radial`` bits.
    """

    name: ClassVar[str] = "masek"
    higher_is_similar: ClassVar[bool] = False

    def __init__(self, segmenter: Segmenter | None = None, *, radial: int = 20, angular: int = 240,
                 wavelength: float = 18.0, sigma_on_f: float = 0.5, max_shift: int = 8,
                 min_valid: float = 0.1, min_magnitude: float = 0.0) -> None:
        self.segmenter = segmenter if segmenter is not None else Segmenter()
        self.radial, self.angular = int(radial), int(angular)
        self.wavelength, self.sigma_on_f = float(wavelength), float(sigma_on_f)
        self.max_shift, self.min_valid, self.min_magnitude = int(max_shift), float(min_valid), float(min_magnitude)
        self._filter = log_gabor_1d(self.angular, self.wavelength, self.sigma_on_f)

    def encode_texture(self, texture: np.ndarray, mask: np.ndarray,
                       segmentation: Segmentation | None = None) -> IrisCode:
        """The code of an already normalised ``(radial, angular)`` texture and its usability mask."""
        usable = np.asarray(mask, dtype=bool)
        t = fill_unusable(texture, usable).astype(np.float64)
        response = np.fft.ifft(np.fft.fft(t, axis=1) * self._filter[None, :], axis=1)
        magnitude = np.abs(response)
        valid = usable & (magnitude > 1e-12 * max(float(magnitude.max()), 1e-300))
        if self.min_magnitude > 0 and valid.any():
            valid &= magnitude >= self.min_magnitude * float(np.median(magnitude[valid]))
        # Column c: [row0 Re, row0 Im, row1 Re, …] — both bits of a sample share its mask.
        bits = np.stack([response.real > 0, response.imag > 0], axis=2).transpose(1, 0, 2)
        vmask = np.stack([valid, valid], axis=2).transpose(1, 0, 2)
        r, a = t.shape
        return IrisCode.from_bits(bits.reshape(a, 2 * r), vmask.reshape(a, 2 * r), segmentation)

    def mask_groups(self) -> np.ndarray:
        """A column's bits (Re and Im of each row's sample) share the mask of their sample."""
        return np.arange(2 * self.radial) // 2

    def encode(self, image: np.ndarray) -> IrisCode:
        """Segment (cached), normalise and encode an eye image."""
        texture, mask, seg = self.segmenter.unwrap(image, self.radial, self.angular)
        return self.encode_texture(texture, mask, seg)
