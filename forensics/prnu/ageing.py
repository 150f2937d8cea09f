"""Fingerprint ageing: the reference paper's table 2, and the median-residual fingerprints it is made of.

Up to 16 fingerprints per set, each from 50 disjoint random images, from the 3×3 **median** residual
``y − median(y)`` (spiky defects survive it; the wavelet denoiser would partly smooth them away).  The
mean NCC over the ``n² − n`` ordered intra-set pairs of each set and the ``n²`` inter-set pairs, with
bootstrap intervals over *fingerprints* (pairs sharing a fingerprint are not independent, so pairs are
not resampled), and the consistency ``inter / √(intra_A · intra_B)``: 1 when both sets carry the same
pattern, whatever their noise, below 1 when the pattern changed (see :class:`AgeingTable`).

Why ageing lowers the inter-set NCC (and why the median residual shows it): a partially stuck pixel adds
a light-independent offset ``d``; in a median residual it is a spike of height ≈ ``d``, and the ML
estimate ``Σ W·I / Σ I²`` turns it into a spike ``≈ d / Ī`` in ``K`` — for ``d`` of tens of DN, tens of
times the PRNU's ``σ_k``.  Fingerprints of one epoch share every spike present then; an old set has
spikes the young one lacks.  The shared spikes add to the numerator of the inter-set NCC only what both
sets have, while the new ones add energy to the old fingerprints' norm: inter-set NCC falls below both
intra-set values.

The same-device protocol (:mod:`forensics.prnu.samedevice`) draws the groups of images and calls
:func:`build_ageing_fingerprints` and :func:`ageing_table`; both work on their own too.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from forensics._shared.arrays import grey_luma
from forensics._shared.errors import InputError
from forensics._shared.parallel import Executor
from forensics._shared.progress import Progress, no_progress
from forensics._shared.rng import RngLike, as_generator
from forensics.prnu.fingerprint import (
    Fingerprint,
    FingerprintBuilder,
    FingerprintJob,
    Region,
    build_fingerprints,
    intensity,
    saturation_mask,
)
from forensics.prnu.residual import median_residual, zero_mean_cfa

__all__ = [
    "AGEING_FINGERPRINTS",
    "AGEING_IMAGES",
    "MIN_AGEING_FINGERPRINTS",
    "AGEING_RESIDUALS",
    "MedianFingerprintBuilder",
    "build_ageing_fingerprints",
    "PairStatistic",
    "AgeingTable",
    "ageing_table",
]

#: Table 2: 16 fingerprints of 50 disjoint images per set.
AGEING_FINGERPRINTS = 16
AGEING_IMAGES = 50
#: A small set still gets at least this many ageing fingerprints (with fewer images each).
MIN_AGEING_FINGERPRINTS = 4
AGEING_RESIDUALS = ("median", "wavelet")


# ----------------------------------------------------------------------------- median-residual fingerprints


class MedianFingerprintBuilder(FingerprintBuilder):
    """``K = Σ W·I / Σ I²`` with the median residual ``W = y − median_{q×q}(y)``, streamed.

    The paper's estimator for the ageing table (it keeps spiky defects).  Intensity
    ``I``, the saturation rule and the accumulation are those of
    :class:`forensics.prnu.fingerprint.FingerprintBuilder`; only the residual differs, and
    the result is made zero-mean on each CFA sub-lattice without the DFT Wiener step
    (not part of the median variant; it would only rescale a flat spectrum).

    Parameters
    ----------
    region : str or Region
    size : int
        Median window (3).
    **options
        ``white_level``, ``black_level``, ``saturation_level``, ``saturation_dilate``,
        ``rolloff`` as :class:`forensics.prnu.fingerprint.FingerprintBuilder`.
    """

    def __init__(self, region: str | Region = "full", size: int = 3, **options: Any) -> None:
        super().__init__(region, sigma=0.0, **options)
        self.size = int(size)

    def _residual_and_intensity(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        assert self.frame_shape is not None and self.white_level is not None
        shape = self.region.shape(self.frame_shape)
        w_all, i_all = np.zeros(shape, np.float32), np.zeros(shape, np.float32)
        level = self.white_level if self.saturation_level is None else self.saturation_level
        for src, dst in zip(self.region.pieces(self.frame_shape), self.region.mosaic_slices(self.frame_shape)):
            piece = image[src]
            grey = grey_luma(piece)
            sat = saturation_mask(piece, level, self.saturation_dilate)
            w_all[dst] = median_residual(grey, self.size)
            i_all[dst] = intensity(grey, self.white_level, self.black_level, sat, self.rolloff)
        return w_all, i_all

    def _postprocess(self, raw: np.ndarray) -> np.ndarray:
        assert self.frame_shape is not None
        for dst in self.region.mosaic_slices(self.frame_shape):
            raw[dst] = zero_mean_cfa(np.ascontiguousarray(raw[dst]))
        return raw

    def _estimator(self) -> dict[str, Any]:
        return {"estimator": f"K = sum(W*I) / sum(I^2), W = y - median{self.size}x{self.size}(y), "
                             "then zero-mean per CFA sub-lattice"}


def build_ageing_fingerprints(images: Any, groups: Sequence[Sequence[int]], region: Region, residual: str = "median",
                              sigma: float = 3.0, median_size: int = 3, progress: Progress = no_progress,
                              desc: str = "ageing fingerprints", options: dict[str, Any] | None = None, *,
                              executor: Executor | None = None) -> list[np.ndarray]:
    """One fingerprint per group of images, all built on the execution layer (items: group × chunk of images).

    Parameters
    ----------
    images : forensics.prnu.fingerprint.ImageSet
        Anything with ``load(i)`` and ``sources`` (picklable for worker processes or a cluster).
    groups : sequence of sequences of int
        Disjoint image indices, one group per fingerprint (e.g. ``SetPlan.ageing_groups``).
    region : Region
    residual : {'median', 'wavelet'}
        :class:`MedianFingerprintBuilder` (the paper) or the wavelet
        :class:`~forensics.prnu.fingerprint.FingerprintBuilder` with noise level ``sigma``.
    median_size : int
    progress, desc
        One bar counting the work items.
    options : dict
        As :class:`~forensics.prnu.fingerprint.FingerprintBuilder` (``workers`` is ignored by the median one).
    executor : Executor, optional
        Default: in this process.  Groups are finished in order and their sums dropped as soon as
        each fingerprint is complete (:func:`~forensics.prnu.fingerprint.build_fingerprints`).
    """
    options = dict(options or {})
    median_options = {k: v for k, v in options.items() if k != "workers"}
    template: FingerprintBuilder = (MedianFingerprintBuilder(region, median_size, **median_options)
                                    if residual == "median" else FingerprintBuilder(region, sigma, **options))
    jobs = [FingerprintJob(template, images, tuple(int(i) for i in group)) for group in groups]
    return [fp.K for fp in build_fingerprints(jobs, executor=executor, progress=progress, desc=desc)]


# ----------------------------------------------------------------------------- ageing table


@dataclass(frozen=True)
class PairStatistic:
    """A statistic of fingerprint pairs with a bootstrap interval over fingerprints.

    ``ci`` is None when there are too few fingerprints for a bootstrap (fewer than 3
    in a set) or the statistic is undefined.
    """

    label: str
    mean: float
    ci: tuple[float, float] | None
    n_pairs: int
    sd: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {"label": self.label, "mean": _finite(self.mean),
                "ci": [_finite(self.ci[0]), _finite(self.ci[1])] if self.ci is not None else None,
                "n_pairs": self.n_pairs, "sd": _finite(self.sd)}


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


@dataclass(frozen=True)
class AgeingTable:
    """The paper's table 2: mean NCC between fingerprints within and across the two sets.

    Attributes
    ----------
    residual : str
        'median' (the paper) or 'wavelet'.
    names : (str, str)
        The sets.
    n_fingerprints : (int, int)
    images_per_fingerprint : (int, int)
    intra_a, intra_b, inter : PairStatistic
        Mean NCC over the ``n² − n`` ordered intra-set pairs of each set and the
        ``n_a·n_b`` inter-set pairs (the paper's three numbers).
    consistency : PairStatistic
        ``inter / √(intra_a · intra_b)``.  If both sets carry one fixed pattern
        ``k`` and each fingerprint is ``k`` plus independent estimation noise, the
        expected intra-set NCC is ``P/(P + N_set)`` and the inter-set NCC
        ``P/√((P + N_a)(P + N_b))`` — the geometric mean of the two intra-set
        values, whatever the noise of each set.  So the ratio is 1 when the
        pattern did not change (even if one set's images are noisier, which
        alone would put the inter-set mean below the larger intra-set value),
        and below 1 when it did: it is the correlation of the two sets'
        underlying patterns (Spearman's correction for attenuation).  New defects
        ``D`` give ``√((P + D_a)/(P + D_b))`` for the older set b.
    inter_below_intra : bool
        The paper's reading: the inter-set mean is below both intra-set means.
    matrix : ndarray
        NCC of every pair of fingerprints, A's first (for plots).
    level, n_boot : float, int
    verdict : str
    """

    residual: str
    names: tuple[str, str]
    n_fingerprints: tuple[int, int]
    images_per_fingerprint: tuple[int, int]
    intra_a: PairStatistic
    intra_b: PairStatistic
    inter: PairStatistic
    consistency: PairStatistic
    inter_below_intra: bool
    matrix: np.ndarray
    level: float
    n_boot: int
    verdict: str

    @property
    def statistics(self) -> tuple[PairStatistic, PairStatistic, PairStatistic, PairStatistic]:
        """intra_a, intra_b, inter, consistency."""
        return self.intra_a, self.intra_b, self.inter, self.consistency

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (the matrix included)."""
        return {
            "residual": self.residual,
            "names": list(self.names),
            "n_fingerprints": list(self.n_fingerprints),
            "images_per_fingerprint": list(self.images_per_fingerprint),
            "intra_a": self.intra_a.to_dict(),
            "intra_b": self.intra_b.to_dict(),
            "inter": self.inter.to_dict(),
            "consistency": self.consistency.to_dict(),
            "inter_below_intra": self.inter_below_intra,
            "level": self.level,
            "n_boot": self.n_boot,
            "verdict": self.verdict,
            "matrix": self.matrix.tolist(),
        }


def _ncc_matrix(rows: np.ndarray) -> np.ndarray:
    """NCC of every pair of rows (each row one flattened fingerprint), float64 sums in column chunks."""
    n, p = rows.shape
    means = rows.mean(axis=1, dtype=np.float64)
    gram = np.zeros((n, n))
    chunk = max(1, (1 << 23) // max(n, 1))
    for s in range(0, p, chunk):
        block = rows[:, s:s + chunk].astype(np.float64)
        block -= means[:, None]
        gram += block @ block.T
    norm = np.sqrt(np.maximum(np.diag(gram), 0.0))
    den = np.outer(norm, norm)
    out = np.zeros_like(gram)
    np.divide(gram, den, out=out, where=den > 0)
    np.fill_diagonal(out, np.where(norm > 0, 1.0, 0.0))
    return np.clip(out, -1.0, 1.0)


def _pair_means(m: np.ndarray, ia: np.ndarray, ib: np.ndarray, na: int) -> np.ndarray:
    """Intra-A, intra-B, inter means and consistency for rows of resampled indices.

    ``ia`` (R, na) and ``ib`` (R, nb) hold indices into A's and B's blocks of ``m``;
    pairs of a fingerprint with a copy of itself (same original index) are left
    out of the intra means.  Returns an (R, 4) array (NaN where undefined).
    """
    def intra(idx: np.ndarray, off: int) -> np.ndarray:
        g = m[(idx + off)[:, :, None], (idx + off)[:, None, :]]
        valid = idx[:, :, None] != idx[:, None, :]
        count = valid.sum(axis=(1, 2))
        total = np.where(valid, g, 0.0).sum(axis=(1, 2))
        out = np.full(idx.shape[0], np.nan)
        np.divide(total, count, out=out, where=count > 0)
        return out

    a, b = intra(ia, 0), intra(ib, na)
    inter = m[ia[:, :, None], (ib + na)[:, None, :]].mean(axis=(1, 2))
    prod = a * b
    cons = np.full(inter.shape, np.nan)
    ok = np.isfinite(prod) & (a > 0) & (b > 0)
    cons[ok] = inter[ok] / np.sqrt(prod[ok])
    return np.column_stack([a, b, inter, cons])


def ageing_table(
    fingerprints_a: Sequence[np.ndarray | Fingerprint],
    fingerprints_b: Sequence[np.ndarray | Fingerprint],
    rng: RngLike,
    *,
    names: tuple[str, str] = ("A", "B"),
    residual: str = "median",
    images_per_fingerprint: tuple[int, int] = (0, 0),
    n_boot: int = 1000,
    level: float = 0.95,
) -> AgeingTable:
    """Table 2 from two lists of fingerprints: intra- and inter-set mean NCC with intervals.

    Parameters
    ----------
    fingerprints_a, fingerprints_b : sequences of arrays or Fingerprint
        All of one shape; at least 2 per set (3 for intervals).
    rng : numpy.random.Generator or int
        For the bootstrap over fingerprints.
    names : (str, str)
    residual : str
        Recorded: which residual the fingerprints were made from.
    images_per_fingerprint : (int, int)
        Recorded.
    n_boot, level : int, float
        Bootstrap replicates and coverage.

    Notes
    -----
    Pairs that share a fingerprint are correlated, so the intervals resample
    fingerprints (with replacement, each set separately) and recompute every
    statistic over the resampled pairs, leaving out pairs of a fingerprint with a
    copy of itself.  The consistency ratio is bootstrapped jointly with the means.
    """
    rng = as_generator(rng)
    arrays = [np.asarray(f.K if isinstance(f, Fingerprint) else f, np.float32)
              for f in (*fingerprints_a, *fingerprints_b)]
    na, nb = len(fingerprints_a), len(fingerprints_b)
    if na < 2 or nb < 2:
        raise InputError(f"the ageing table needs at least 2 fingerprints per set (got {na} and {nb})")
    shape = arrays[0].shape
    if any(a.shape != shape for a in arrays):
        raise InputError("ageing table: all fingerprints must have one shape (same region and frame size)")
    rows = np.empty((na + nb, int(np.prod(shape))), np.float32)
    for k, a in enumerate(arrays):
        rows[k] = a.ravel()
    del arrays
    m = _ncc_matrix(rows)
    del rows
    point = _pair_means(m, np.arange(na)[None], np.arange(nb)[None], na)[0]
    can_boot = na >= 3 and nb >= 3
    reps = _bootstrap_pair_means(m, na, nb, int(n_boot), rng) if can_boot else None
    tail = 100 * (1 - level) / 2

    def stat(label: str, k: int, n_pairs: int) -> PairStatistic:
        value = float(point[k])
        if reps is None or not math.isfinite(value):
            return PairStatistic(label, value, None, n_pairs, float("nan"))
        col = reps[:, k][np.isfinite(reps[:, k])]
        if col.size < 0.9 * reps.shape[0]:  # undefined in too many replicates (intra NCC near 0)
            return PairStatistic(label, value, None, n_pairs, float("nan"))
        lo, hi = np.percentile(col, [tail, 100 - tail])
        return PairStatistic(label, value, (float(lo), float(hi)), n_pairs, float(np.std(col, ddof=1)))

    a, b = names
    intra_a = stat(f"{a}–{a} (intra-set)", 0, na * na - na)
    intra_b = stat(f"{b}–{b} (intra-set)", 1, nb * nb - nb)
    inter = stat(f"{a}–{b} (inter-set)", 2, na * nb)
    consistency = stat("consistency inter/√(intra·intra)", 3, na * nb)
    below = bool(inter.mean < min(intra_a.mean, intra_b.mean))
    verdict = _table_verdict(names, intra_a, intra_b, inter, consistency)
    return AgeingTable(
        residual=residual, names=(a, b), n_fingerprints=(na, nb),
        images_per_fingerprint=(int(images_per_fingerprint[0]), int(images_per_fingerprint[1])),
        intra_a=intra_a, intra_b=intra_b, inter=inter, consistency=consistency, inter_below_intra=below,
        matrix=m, level=float(level), n_boot=int(n_boot) if can_boot else 0, verdict=verdict,
    )


def _bootstrap_pair_means(m: np.ndarray, na: int, nb: int, n_boot: int, rng: np.random.Generator) -> np.ndarray:
    """(n_boot, 4) replicates of :func:`_pair_means` over fingerprints resampled with replacement, each set
    separately (in chunks of replicates that keep the index arrays small)."""
    parts = []
    chunk = max(1, min(n_boot, (1 << 22) // (na * na + nb * nb + na * nb)))
    for s in range(0, n_boot, chunk):
        b = min(chunk, n_boot - s)
        parts.append(_pair_means(m, rng.integers(0, na, size=(b, na)), rng.integers(0, nb, size=(b, nb)), na))
    return np.concatenate(parts)


def _table_verdict(names: tuple[str, str], intra_a: PairStatistic, intra_b: PairStatistic, inter: PairStatistic,
                   consistency: PairStatistic) -> str:
    """The table's reading in words, from the consistency and its interval."""
    a, b = names
    means = (f"inter-set mean NCC {inter.mean:.4f}, intra-set {intra_a.mean:.4f} ({a}) and {intra_b.mean:.4f} ({b})")
    c = consistency
    if not math.isfinite(c.mean):
        verdict = f"{means}; an intra-set mean is not positive, so the sets carry no common pattern to compare"
    elif c.ci is None:
        verdict = (f"{means}; consistency {c.mean:.3f}; too few fingerprints for an interval (at least 3 per set "
                   "are needed)")
    elif c.ci[0] <= 0 <= c.ci[1]:
        verdict = (f"{means}; consistency {c.mean:.3f} [{c.ci[0]:.3f}, {c.ci[1]:.3f}] contains 0: the two sets share "
                   "no detectable pattern, as two different devices do (one sensor keeps its PRNU as it ages; only "
                   "defects so strong that they swamp it could do this)")
    elif c.ci[1] < 1:
        verdict = (f"{means}; consistency {c.mean:.3f} [{c.ci[0]:.3f}, {c.ci[1]:.3f}] is below 1: the fingerprints "
                   "of the two sets agree less than their own noise explains, so the pattern changed between the "
                   "sets — ageing defects if they come from one device (the paper's table 2), different devices "
                   "if the EER says so")
    elif c.ci[0] > 1:
        verdict = (f"{means}; consistency {c.mean:.3f} [{c.ci[0]:.3f}, {c.ci[1]:.3f}] is above 1: no sign of a "
                   "change (check for content shared across the sets)")
    else:
        verdict = (f"{means}; consistency {c.mean:.3f} [{c.ci[0]:.3f}, {c.ci[1]:.3f}] contains 1: no change of "
                   "the fingerprint between the sets is detected")
    return verdict
