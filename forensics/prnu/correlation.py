"""Correlation helpers shared by matching, identification and clustering: one implementation of each.

* arrays made zero-mean in float32 (:func:`_centred`) and their energy (:func:`_sum_sq`);
* the real FFT of an array kept to correlate it with many references (:class:`_Spectrum`) and the circular
  cross-correlation surface against one reference (:func:`surface`), as the PCE of
  :mod:`forensics.prnu.match` and the block-phase PCE of :mod:`forensics.prnu.blockpce` take it;
* the Gaussian tail statistics of a search: a peak's tail in a weighted search (:func:`_log_tail`), the
  corrected false-alarm probability over ``n`` positions (:func:`_false_alarm`), and its inverse, the
  Šidák threshold (:func:`sidak_z`, :func:`pce_threshold`), used by identification (positions, scales,
  orientations and fingerprints searched) and by clustering (comparisons made).
"""
from __future__ import annotations

import math

import numpy as np
import scipy.fft
from scipy import special

__all__ = ["pce_threshold", "sidak_z", "surface"]


def _sum_sq(a: np.ndarray) -> float:
    return float(np.square(a).sum(dtype=np.float64))


def _centred(a: np.ndarray) -> np.ndarray:
    """float32 copy of ``a`` minus its mean (the mean taken in float64)."""
    out = np.array(a, dtype=np.float32, copy=True)
    out -= np.float32(out.mean(dtype=np.float64))
    return out


def _shift_indices(r: int | None, n: int) -> np.ndarray:
    """Circular shift indices ``−r … r`` of an axis of length ``n`` (every index when ``r`` is None or covers it)."""
    if r is None or 2 * r + 1 >= n:
        return np.arange(n)
    return np.arange(-r, r + 1) % n


class _Spectrum:
    """Real FFT of a zero-mean array, kept to correlate it with many references."""

    def __init__(self, a: np.ndarray, workers: int) -> None:
        a0 = _centred(a)
        self.shape = a0.shape
        self.norm = math.sqrt(_sum_sq(a0))
        self.spec = scipy.fft.rfft2(a0, workers=workers)
        self.workers = workers


def surface(spectrum: _Spectrum, reference: np.ndarray) -> tuple[np.ndarray, float]:
    """Circular cross-correlation of the spectrum's array with the zero-mean ``reference``, and ``‖reference‖``.

    ``corr[dy, dx] = Σ a(y, x)·b(y − dy, x − dx)``: shift ``(dy, dx)`` means the spectrum's array ≈
    ``np.roll(reference, (dy, dx))`` (the shift convention of :func:`forensics.prnu.match.pce`).
    """
    b0 = _centred(reference)
    norm_b = math.sqrt(_sum_sq(b0))
    spec = scipy.fft.rfft2(b0, workers=spectrum.workers)
    del b0
    np.conjugate(spec, out=spec)
    spec *= spectrum.spec
    return scipy.fft.irfft2(spec, s=spectrum.shape, workers=spectrum.workers), norm_b


def _z(pce_value: float) -> float:
    """The normalised peak ``sign·√|PCE|`` of a signed PCE."""
    return math.copysign(math.sqrt(abs(pce_value)), pce_value)


def _log_tail(z: float, weight: float) -> float:
    """``log(Q(z)/weight)``: a peak's tail in a weighted search (smaller is stronger)."""
    return float(special.log_ndtr(-z)) - math.log(weight)


def _false_alarm(z: float, n: float, weight: float = 1.0) -> tuple[float, float]:
    """``1 − (1 − Q(z)/weight)^n`` and its log10, stable for tiny and for large tails.

    ``weight`` is the position's share of a weighted (Bonferroni–Šidák) search: ``n`` positions whose
    weights sum to ``n`` (one each when unweighted, see :mod:`forensics.prnu.identify`).
    """
    log_p = min(0.0, _log_tail(z, weight))
    p = math.exp(log_p)
    if p > 1e-12:
        log_keep = n * math.log1p(-p) if p < 1.0 else -math.inf
        p_fa = -math.expm1(log_keep)
        log10 = math.log10(p_fa) if p_fa > 0 else log_p / math.log(10) + math.log10(n)
    else:  # (1 − p)^n = 1 − n·p + O((n·p)²)
        log10 = (log_p + math.log(n)) / math.log(10)
        p_fa = min(1.0, 10.0**log10) if log10 > -320 else 0.0
    return float(min(1.0, p_fa)), float(min(0.0, log10))


def sidak_z(p_fa: float, n_tests: float) -> float:
    """The ``z`` with ``1 − (1 − Q(z))^n_tests = p_fa``: the Šidák threshold of ``n_tests`` standard normals.

    The inverse of :func:`_false_alarm` (weight 1); ``inf`` when nothing is tested.
    """
    if n_tests <= 0:
        return math.inf
    q = -math.expm1(math.log1p(-p_fa) / n_tests)  # per-test tail probability
    return -float(special.ndtri(q))


def pce_threshold(pfa: float, n_tests: float) -> float:
    """The PCE a best candidate needs for ``1 − (1 − Q(√PCE))^n_tests ≤ pfa`` (:func:`sidak_z` squared).

    For a position of a weighted search (``Candidate.search_weight`` ``w``) pass ``n_tests / w``.
    """
    z = sidak_z(pfa, n_tests)
    return z * z
