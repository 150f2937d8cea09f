"""EER intervals when comparisons share images: the class (subject) bootstrap.

All-against-all comparisons of a biometric set are not independent: every image takes part in hundreds of
comparisons, and a subject whose images are poor pulls all of its genuine scores one way.  Resampling the
scores one by one (the reference paper's bootstrap, :func:`~forensics.stats.scores.bootstrap_eer`) ignores
that and gives intervals that are too narrow.  Here the *classes* are resampled with replacement, and every
comparison keeps the classes it belongs to: a genuine comparison of class ``c`` weighs ``w_c`` (how often
``c`` was drawn) and an impostor comparison of classes ``c ≠ d`` weighs ``w_c · w_d``.

Speed: one replicate of the paper's set (224 classes, 5 million comparisons) would cost a pass over all
comparisons.  Instead the scores are binned once per pair of classes (``B`` bins over the observed range)
and a replicate's histograms are ``w · G`` and ``wᵀ H w`` — matrix products, 1,000 replicates of the
paper's set in about a second.  The binning's own error is removed by shifting every replicate by the
difference between the exact EER and the binned EER of the full sample (both on the same scores), so the
interval is centred where :func:`~forensics.stats.scores.eer` puts the estimate.

The same replicate weights can be reused for many score sets of the same images (several ages, sensors,
matchers): replicate ``r`` of each is then the same resample of subjects, which is what makes a paired
comparison (a trend against age, a difference between sensors) possible.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from forensics._shared.errors import InputError
from forensics._shared.rng import RngLike, as_generator
from forensics.stats.scores import as_scores, eer, percentile_ci

__all__ = ["ClassBootstrap", "PairedScores", "binned_eer", "class_bootstrap_eer", "class_weights"]

#: Bins per class pair; the binned EER of the full sample is within a bin of the exact one and the
#: difference is removed (module notes), so this only needs to resolve the shape of the ROC near the EER.
DEFAULT_BINS = 256
# Upper bound on the elements of one (replicates x classes x bins) block.
_BLOCK = 1 << 23


@dataclass(frozen=True)
class PairedScores:
    """Comparisons with the classes of the two images compared.

    Attributes
    ----------
    score : ndarray
        One score per comparison, oriented so that higher means "more likely the same class".
    class_a, class_b : ndarray of int
        Class index (``0 … n_classes − 1``) of each comparison's two images; equal for genuine comparisons.
    n_classes : int
        Number of classes (classes without comparisons are allowed).
    """

    score: NDArray[np.float64]
    class_a: NDArray[np.intp]
    class_b: NDArray[np.intp]
    n_classes: int

    @classmethod
    def of(cls, score: ArrayLike, class_a: ArrayLike, class_b: ArrayLike, n_classes: int | None = None,
           higher_is_similar: bool = True) -> PairedScores:
        s = as_scores(score, "score")
        a = np.asarray(class_a, dtype=np.intp).ravel()
        b = np.asarray(class_b, dtype=np.intp).ravel()
        if not (s.size == a.size == b.size):
            raise InputError(f"scores and class labels differ in length ({s.size}, {a.size}, {b.size})")
        n = int(max(a.max(initial=-1), b.max(initial=-1)) + 1) if n_classes is None else int(n_classes)
        if a.size and (min(a.min(), b.min()) < 0 or max(a.max(), b.max()) >= n):
            raise InputError(f"class labels must lie in 0 … {n - 1}")
        return cls(s if higher_is_similar else -s, a, b, n)

    @property
    def genuine(self) -> NDArray[np.bool_]:
        return self.class_a == self.class_b

    def split(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(genuine scores, impostor scores)."""
        g = self.genuine
        return self.score[g], self.score[~g]


@dataclass(frozen=True)
class ClassBootstrap:
    """An EER with its class-bootstrap interval.

    ``replicates`` are the (binning-corrected) EERs of the resamples, in the order of the weight rows, so
    replicates of different score sets made with the same weights can be paired.
    """

    estimate: float
    ci: tuple[float, float]
    level: float
    replicates: NDArray[np.float64]
    n_genuine: int
    n_impostor: int
    binning_error: float

    def to_dict(self, include_replicates: bool = False) -> dict[str, Any]:
        out: dict[str, Any] = {"eer": self.estimate, "ci": list(self.ci), "level": self.level,
                               "n_genuine": self.n_genuine, "n_impostor": self.n_impostor,
                               "n_boot": int(self.replicates.size), "resampled": "classes",
                               "binning_error": self.binning_error}
        if include_replicates:
            out["replicates"] = self.replicates.tolist()
        return out


def class_weights(n_classes: int, n_boot: int, rng: RngLike) -> NDArray[np.float64]:
    """``(n_boot, n_classes)`` multiplicities of the classes in ``n_boot`` resamples with replacement."""
    if n_classes < 2:
        raise InputError(f"a class bootstrap needs at least 2 classes, got {n_classes}")
    gen = as_generator(rng)
    return gen.multinomial(n_classes, np.full(n_classes, 1.0 / n_classes), size=int(n_boot)).astype(np.float64)


def _histograms(pairs: PairedScores, edges: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per-class genuine histograms ``(C, B)`` and per-class-pair impostor histograms ``(C, C, B)``.

    The impostor table is symmetric with a zero diagonal: a comparison of classes ``c`` and ``d`` is counted
    half in ``[c, d]`` and half in ``[d, c]``, so that ``wᵀ H w`` counts it once with weight ``w_c w_d``.
    """
    c, nb = pairs.n_classes, edges.size - 1
    bins = np.clip(np.searchsorted(edges, pairs.score, side="right") - 1, 0, nb - 1)
    g = pairs.genuine
    genuine = np.bincount(pairs.class_a[g] * nb + bins[g], minlength=c * nb).reshape(c, nb).astype(np.float64)
    a, b, k = pairs.class_a[~g], pairs.class_b[~g], bins[~g]
    imp = np.bincount((a * c + b) * nb + k, minlength=c * c * nb).reshape(c, c, nb).astype(np.float32)
    imp = 0.5 * (imp + imp.transpose(1, 0, 2))
    return genuine, imp


def binned_eer(genuine: NDArray[np.float64], impostor: NDArray[np.float64]) -> NDArray[np.float64]:
    """EER of histogram rows ``(R, B)`` over common bins (scores uniform within a bin; higher = genuine).

    Rows without genuine or without impostor mass give NaN.

    At bin edge ``k`` (threshold ``e_k``, accept ``score ≥ e_k``) the false-reject rate is the genuine mass
    below it and the false-accept rate the impostor mass above it; both are linear inside a bin, so the
    crossing is found exactly by linear interpolation between the bracketing edges.
    """
    gen = np.atleast_2d(genuine)
    imp = np.atleast_2d(impostor)
    g_tot = gen.sum(axis=1, keepdims=True)
    i_tot = imp.sum(axis=1, keepdims=True)
    empty = (g_tot[:, 0] <= 0) | (i_tot[:, 0] <= 0)
    g_tot = np.where(g_tot > 0, g_tot, 1.0)
    i_tot = np.where(i_tot > 0, i_tot, 1.0)
    zeros = np.zeros((gen.shape[0], 1))
    frr = np.concatenate([zeros, np.cumsum(gen, axis=1)], axis=1) / g_tot
    far = 1.0 - np.concatenate([zeros, np.cumsum(imp, axis=1)], axis=1) / i_tot
    d = frr - far  # -1 at the lowest edge, +1 at the highest, non-decreasing
    k = np.argmax(d > 0, axis=1)
    k = np.maximum(k, 1)
    rows = np.arange(gen.shape[0])
    d0, d1 = d[rows, k - 1], d[rows, k]
    frac = np.where(d1 > d0, -d0 / np.where(d1 > d0, d1 - d0, 1.0), 0.0)
    out = frr[rows, k - 1] + frac * (frr[rows, k] - frr[rows, k - 1])
    # A resample without genuine (or impostor) comparisons has no EER.
    return np.where(empty, np.nan, out)


def class_bootstrap_eer(pairs: PairedScores, weights: NDArray[np.float64], level: float = 0.95,
                        bins: int = DEFAULT_BINS) -> ClassBootstrap:
    """EER of ``pairs`` with a percentile interval over class resamples.

    Parameters
    ----------
    pairs
        The comparisons (all genuine and impostor pairs, or a sample of them).
    weights
        ``(n_boot, n_classes)`` class multiplicities from :func:`class_weights`; pass the same array for
        score sets whose replicates are to be paired.
    level
        Coverage of the interval.
    bins
        Score bins per class pair (memory is ``n_classes² · bins`` floats).

    Returns
    -------
    ClassBootstrap
        ``estimate`` is :func:`~forensics.stats.scores.eer` of all the scores; replicate ``r`` the EER of the
        comparisons re-weighted by resample ``r`` (a genuine comparison of class ``c`` counts ``w_c`` times,
        an impostor comparison of classes ``c, d`` counts ``w_c w_d`` times).
    """
    weights = np.asarray(weights, dtype=np.float64)
    if weights.ndim != 2 or weights.shape[1] != pairs.n_classes:
        raise InputError(f"weights must be (n_boot, {pairs.n_classes}), got {weights.shape}")
    genuine_scores, impostor_scores = pairs.split()
    if genuine_scores.size == 0 or impostor_scores.size == 0:
        raise InputError("the EER needs genuine and impostor comparisons: are there classes with two images?")
    exact = eer(genuine_scores, impostor_scores).eer
    lo, hi = float(pairs.score.min()), float(pairs.score.max())
    edges = np.linspace(lo, hi if hi > lo else lo + 1.0, int(bins) + 1)
    edges[-1] = np.nextafter(edges[-1], np.inf)
    gen_hist, imp_hist = _histograms(pairs, edges)
    full = float(binned_eer(gen_hist.sum(axis=0), imp_hist.sum(axis=(0, 1)))[0])
    reps = _replicate_eers(gen_hist, imp_hist, weights)
    correction = exact - full
    reps = np.clip(reps + correction, 0.0, 1.0)
    finite = reps[np.isfinite(reps)]
    if finite.size < 0.9 * reps.size:
        raise InputError(f"{reps.size - finite.size} of {reps.size} class resamples had no genuine comparison; "
                         "the set needs more classes with two or more images")
    return ClassBootstrap(float(exact), percentile_ci(finite, level), float(level), reps,
                          int(genuine_scores.size), int(impostor_scores.size),
                          float(abs(correction)))


def _replicate_eers(gen_hist: NDArray[np.float64], imp_hist: NDArray[np.float32],
                    weights: NDArray[np.float64]) -> NDArray[np.float64]:
    c, nb = gen_hist.shape
    flat = imp_hist.reshape(c, c * nb)
    w32 = weights.astype(np.float32)
    chunk = max(1, _BLOCK // (c * nb))
    out = np.empty(weights.shape[0])
    for start in range(0, weights.shape[0], chunk):
        w = w32[start:start + chunk]
        # Σ_c Σ_d w_c w_d H[c, d, :]: one matrix product, then a weighted sum over d.
        partial = (w @ flat).reshape(w.shape[0], c, nb)
        imp = np.einsum("rdb,rd->rb", partial, w, dtype=np.float64)
        gen = weights[start:start + chunk] @ gen_hist
        out[start:start + chunk] = binned_eer(gen, imp)
    return out
