"""The compressed pre-screen of identification (:mod:`forensics.prnu.identify`) for large databases.

Pre-screen (:class:`Prescreen`)
-------------------------------
For large databases, candidates are first ranked by a compressed correlation: a fixed, seeded sparse
±1 random projection (CountSketch: every pixel goes to one of ``d`` buckets with a random sign) of each
fingerprint and of each aligned query's ``W·I``.  Inner products are preserved in expectation, with a
null standard deviation ``1/√d`` of the normalised correlation, so a match of PCE ``p`` over ``n``
pixels has a sketch z-score of about ``√(p·d/n)`` (``√(p/4)`` at the default ``d = n/4``).  The top
``keep`` candidates get the full PCE.  Only aligned images (zero shift, scale 1) are pre-screened;
crop and scale searches score every candidate.  Dropped candidates still count in ``n`` above, so the
false-alarm bound holds; a dropped true device can only turn an attribution into *unknown*.  How often
that happens is measured by :func:`prescreen_miss_rate` on data with known truth, never assumed.
``prescreen='auto'`` enables it for more than :data:`PRESCREEN_AUTO_MIN` fingerprints.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Any, Protocol

import numpy as np

from forensics._shared.errors import UsageError
from forensics.prnu.geometry import _Reference, _Test

__all__ = ["PRESCREEN_AUTO_MIN", "SKETCH_SEED", "Prescreen", "PrescreenMissRate", "sketch"]

#: ``prescreen='auto'`` is on above this many fingerprints (below it, full PCE on all is cheap enough).
PRESCREEN_AUTO_MIN = 50
#: Seed of the pre-screen's projection (fixed: a fingerprint's sketch must not change between runs).
SKETCH_SEED = 0x1D_2012


@dataclass(frozen=True)
class Prescreen:
    """The compressed pre-screen (module notes).

    Attributes
    ----------
    compression : int
        Sketch length ``d = n / compression`` for ``n`` pixels (at least ``min_dim``, at most ``n``).
    min_dim : int
    keep : int, optional
        Candidates kept for the full PCE; default ``max(min_keep, ⌈keep_fraction·N⌉)``.
    min_keep : int
    keep_fraction : float
    seed : int
        Seed of the projection (fixed, so that sketches are comparable across runs).
    """

    compression: int = 4
    min_dim: int = 1024
    keep: int | None = None
    min_keep: int = 10
    keep_fraction: float = 0.1
    seed: int = SKETCH_SEED

    def __post_init__(self) -> None:
        if self.compression < 1 or self.min_dim < 16:
            raise UsageError("prescreen: compression must be ≥ 1 and min_dim ≥ 16")
        if self.keep is not None and self.keep < 1:
            raise UsageError(f"prescreen keep={self.keep}: keep at least one candidate")
        if not (0 < self.keep_fraction <= 1) or self.min_keep < 1:
            raise UsageError("prescreen: keep_fraction must be in (0, 1] and min_keep ≥ 1")

    def dim(self, n_pixels: int) -> int:
        """Sketch length for arrays of ``n_pixels``."""
        return int(min(n_pixels, max(self.min_dim, n_pixels // self.compression)))

    def keep_for(self, n_fingerprints: int) -> int:
        """Candidates kept out of ``n_fingerprints``."""
        if self.keep is not None:
            return self.keep
        return max(self.min_keep, math.ceil(self.keep_fraction * n_fingerprints))

    def to_dict(self) -> dict[str, Any]:
        return {"compression": self.compression, "min_dim": self.min_dim, "keep": self.keep,
                "min_keep": self.min_keep, "keep_fraction": self.keep_fraction, "seed": self.seed}



@dataclass(frozen=True)
class PrescreenMissRate:
    """How often the pre-screen dropped the true device (:func:`prescreen_miss_rate`).

    ``ranks`` is the true device's rank by sketch score (0 = first) for each aligned query whose device
    is in the set; ``missed`` counts ranks ≥ ``keep``; ``ci`` is the 95 % Clopper–Pearson interval of
    the miss rate; ``scores`` the true devices' sketch z-scores.
    """

    n: int
    missed: int
    rate: float
    ci: tuple[float, float]
    keep: int
    dim: int
    n_fingerprints: int
    ranks: tuple[int, ...]
    scores: tuple[float, ...]
    n_skipped: int

    def to_dict(self) -> dict[str, Any]:
        return {"n": self.n, "missed": self.missed, "rate": self.rate, "ci95": list(self.ci), "keep": self.keep,
                "dim": self.dim, "n_fingerprints": self.n_fingerprints, "ranks": list(self.ranks),
                "scores": list(self.scores), "n_skipped": self.n_skipped}



@lru_cache(maxsize=8)
def _sketch_operator(n: int, dim: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Bucket and sign of every pixel (a ±1 matrix with one non-zero per column), fixed by the seed."""
    rng = np.random.default_rng([seed, n, dim])
    buckets = rng.integers(0, dim, n, dtype=np.int64)
    signs = (rng.integers(0, 2, n, dtype=np.int8) * 2 - 1).astype(np.float64)
    return buckets, signs


def sketch(array: np.ndarray, dim: int, seed: int = SKETCH_SEED) -> np.ndarray:
    """Unit-norm CountSketch of the zero-mean ``array`` (length ``dim``)."""
    x = np.asarray(array, np.float64).ravel()
    buckets, signs = _sketch_operator(x.size, int(dim), int(seed))
    y = np.bincount(buckets, weights=(x - x.mean()) * signs, minlength=int(dim))
    norm = float(np.linalg.norm(y))
    return y / norm if norm > 0 else y



def _with_sketches(refs: tuple[_Reference, ...], pre: Prescreen | None) -> tuple[_Reference, ...]:
    """The references with their fingerprints' sketches (computed once, here, in the driver)."""
    if pre is None:
        return refs
    return tuple(replace(r, sketch=sketch(r.fingerprint.K, pre.dim(r.fingerprint.K.size), pre.seed).astype(np.float32))
                 for r in refs)



def _prescreen_config(prescreen: Any, n: int) -> Prescreen | None:
    if prescreen is None or prescreen is False or prescreen == "off":
        return None
    if isinstance(prescreen, Prescreen):
        return prescreen
    if prescreen is True or prescreen == "on":
        return Prescreen()
    if prescreen == "auto":
        return Prescreen() if n > PRESCREEN_AUTO_MIN else None
    raise UsageError(f"prescreen={prescreen!r}: use None/'off', 'auto', 'on' or a Prescreen")



class _Sketched(Protocol):
    """What the pre-screen needs of a query: the sketch of its ``W·I`` over a region, in a rotation."""

    def sketch(self, region: str, rot: int, dim: int, seed: int) -> np.ndarray: ...


def _screen(query: _Sketched, refs: Sequence[_Reference], plans: list[list[_Test]], seed: int) -> dict[int, float]:
    """Sketch z-scores of the fingerprints whose every test is aligned (max over their rotations)."""
    scores: dict[int, float] = {}
    for j, (ref, tests) in enumerate(zip(refs, plans)):
        if not tests or ref.sketch is None or not all(t.aligned for t in tests):
            continue
        dim = ref.sketch.size
        values = [float(query.sketch(ref.region.spec, t.rotation, dim, seed) @ ref.sketch) for t in tests]
        scores[j] = math.sqrt(dim) * max(values)
    return scores


def _prescreen(query: _Sketched, refs: Sequence[_Reference], pre: Prescreen | None, plans: list[list[_Test]],
               compatible: list[int]) -> tuple[list[int], dict[int, float], dict[str, Any] | None]:
    """The fingerprints that get the full PCE, their sketch scores, and the pre-screen's figures."""
    if pre is None:
        return compatible, {}, None
    keep = pre.keep_for(len(refs))
    scores = _screen(query, refs, plans, pre.seed)
    if len(scores) <= keep:
        return compatible, {}, {"ran": False, "reason": f"{len(scores)} aligned candidates, keep {keep}"}
    ranked = sorted(scores, key=lambda j: (-scores[j], j))
    kept = set(ranked[:keep])
    chosen = [j for j in compatible if j in kept or j not in scores]
    dims = sorted({refs[j].sketch.size for j in scores})  # type: ignore[union-attr]
    info = {"ran": True, "screened": len(scores), "kept": len(kept), "dropped": len(scores) - len(kept),
            "dim": dims[0] if len(dims) == 1 else dims, "lowest_kept_score": scores[ranked[keep - 1]]}
    return chosen, scores, info
