"""Clustering an unlabelled collection by camera: which images share a sensor fingerprint?

No fingerprint is given and the number of devices is not known: images are grouped by the correlation of
their noise residuals, with a merging threshold derived from the null distribution of that correlation and
a stated false-alarm probability, never tuned per data set.  Images that match nothing stay unattributed.

**Comparison residuals** (:func:`comparison_residual`).  Each image gives one vector: its query residual
``W`` (σ = 2, zero mean per CFA sub-lattice, DFT Wiener: :func:`forensics.prnu.match.prepare_query`) times
its intensity weight ``I`` (saturated pixels 0) over a centred square crop, less its 8×8-periodic mean, of
unit norm.  The weight is the detector's: ``E[W_i W_j] ∝ I_i I_j K²``, so ``<W_i I_i, W_j I_j>`` weights
every pixel by how much fingerprint it can carry in both images, and the sum of a cluster's vectors is the
numerator ``Σ W·I`` of the maximum-likelihood fingerprint.  The 8×8-periodic mean (64 numbers) is the
pattern that JPEG's block grid and the 2×2 colour filter leave alike in every camera that processes alike:
small in one pair (0.5 σ on the Dresden Nikons), it adds up coherently in the sums of clusters and, left in,
merged their four cameras into one at 2000² crops; removed, different cameras' cluster sums correlate as
N(0, σ²).  The dot product of two vectors is their normalised cross-correlation (NCC).

**Geometry.**  Only images whose frame size agrees up to a 90° rotation are compared: each such *size
group* takes the orientation most of its images have (landscape on a tie); images stored the other way are
turned by a quarter turn.  Which quarter turn is not known (the camera was held either way), so both are
computed and each rotated image keeps the one that agrees best with the images already placed (those of the
majority orientation first, then rotated ones in order of evidence).  A group's crop is ``min(crop, short
side)`` rounded down to a multiple of 8 (square, so one crop serves both orientations; centred, with the CFA
phase kept).  Groups of other sizes are clustered on their own, with a warning.

**Memory.**  The vectors go to a store on disk in ``workdir`` (one ``.npy`` file per size group, written
and read by rows, never held whole): ``rows × crop² × 4`` bytes, ``rows`` = images + rotated images (4 GB
for 1,000 images at 1024²).  The similarity matrix is computed in blocks of :func:`block_images` rows: one
work item multiplies two blocks and holds about :data:`BLOCK_MEMORY` bytes, whatever the size of the
collection; the driver holds the ``rows²`` float64 Gram matrix (8 MB for 1,000 images) and at most a few
residuals in flight.  Residuals are computed on the execution layer, one image per item, read from its path
by the worker; so are the blocks (the store must then be on storage the workers see: the command line puts
it beside the output).

**Null distribution.**  For residuals of different cameras the NCC is about ``N(0, σ²)`` with ``σ² ≈
1/n_eff`` (``n_eff``: effective number of independent pixels, below ``crop²`` because residuals are
spatially correlated).  ``σ`` is measured, not assumed: pairs of images are also correlated with one of the
two residuals circularly shifted by half the crop (rounded down to a multiple of 8) along both axes, and
pairs within one diagonal block also along rows and along columns alone; every pair of images in blocks at
most :data:`NULL_BAND` blocks apart gives samples (all pairs in a collection of up to three blocks).  These
are non-matching by construction (the PRNU no longer lines up) and independent of which images match, yet
keep the 2×2 colour-filter and 8×8 JPEG grids aligned, so that artefacts shared by cameras of one model
stay in the null.  The null centre is the median and ``σ`` the median absolute deviation × 1.4826 of these
samples; its 95 % interval comes from a delete-a-group jackknife over images, and the thresholds use its
upper one-sided 95 % bound.

**Thresholds** (two stages, each with half the false-alarm budget ``p_fa``):

1. *Agglomeration.*  Clusters are merged, best first, while the NCC of their summed vectors,
   ``C_AB / √(C_AA·C_BB)`` with ``C`` the Gram matrix summed over members, is at least ``τ₁`` above the
   null centre in units of ``σ``.  For two single images this is their NCC; for larger clusters it is the
   NCC of their aggregated fingerprints, whose null is the same, so weak images gain the evidence of a whole
   cluster (average linkage of the pairwise z, cut at the same threshold, left 11 of the 54 Dresden images
   unattributed at 1024² crops, adjusted Rand index 0.71; this linkage leaves 2, 0.95).  Agglomeration of ``n`` images makes at most ``(n − 1)²`` comparisons (``n(n−1)/2`` pairs, then
   at most ``n − k − 1`` new ones after the ``k``-th merge), doubled in a group with rotated images (two
   orientations); ``τ₁`` is the Šidák threshold of ``p_fa/2`` over all of them.  A false merge needs at
   least one of these comparisons of two different cameras to pass, so the probability of any false merge
   is at most ``p_fa/2`` (given the Gaussian null).
2. *Attachment.*  Each image left alone is then tested against every cluster of two or more (one test per
   cluster and orientation), Šidák at ``p_fa/2`` over those tests (far fewer than the pairs), and joins the
   best cluster when it passes.

So the probability that any image is put with another camera's images is at most ``p_fa``.  A device with
only one image in the collection stays unattributed.

The clusters are written as a dataset by :func:`~forensics.prnu.clusterwrite.write_cluster_dataset`; their
agreement with known labels is measured by :mod:`forensics.prnu.agreement` (both importable from here too).
"""
from __future__ import annotations

import contextlib
import math
import os
import shutil
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import special

from forensics import __version__
from forensics._shared.errors import InputError, UsageError
from forensics._shared.parallel import Executor, chunks, resolve
from forensics._shared.progress import Progress, no_progress
from forensics.prnu.agreement import adjusted_rand_index, completeness, purity
from forensics.prnu.clusterwrite import write_cluster_dataset
from forensics.prnu.correlation import _false_alarm, sidak_z
from forensics.prnu.fingerprint import ImageSet, Region
from forensics.prnu.match import QUERY_SIGMA, prepare_query

__all__ = [
    "BLOCK_MEMORY",
    "DEFAULT_CROP",
    "DEFAULT_PFA",
    "MIN_CROP",
    "ClusterNull",
    "ClusterResult",
    "DeviceCluster",
    "ImageAssignment",
    "SizeGroup",
    "adjusted_rand_index",
    "block_images",
    "cluster_images",
    "comparison_residual",
    "completeness",
    "null_shifts",
    "purity",
    "write_cluster_dataset",
]

#: Default side of the centred square crop the residuals are compared over.
DEFAULT_CROP = 1024
#: Default probability that any image is put with another camera's images.
DEFAULT_PFA = 1e-3
#: Period of the pattern removed from every residual: the JPEG block (which also repeats the 2×2 CFA).
GRID = 8
#: Smallest crop worth comparing (a 64×64 residual still carries a usable fingerprint in simulation).
MIN_CROP = 64
#: Memory one similarity block may use (three blocks of vectors: two operands and one shifted copy).
BLOCK_MEMORY = 384 << 20
#: Null samples come from blocks at most this many blocks off the diagonal (all pairs of up to 3 blocks):
#: thousands of samples, at the cost of a few extra block products per row of blocks, however large the set.
NULL_BAND = 2
#: Fewest images of one frame size a collection needs (10 pairs, 30 null samples).
MIN_GROUP = 5
#: Fewest null samples a group needs to estimate σ itself; smaller groups borrow the pooled σ·crop.
MIN_NULL_SAMPLES = 30
#: Groups of images in the delete-a-group jackknife of σ.
JACKKNIFE_GROUPS = 10
#: Level of the interval of σ shown to the user; the thresholds use the one-sided bound of the same level.
LEVEL = 0.95
UNATTRIBUTED = "unattributed"


# ----------------------------------------------------------------------------- residuals


def comparison_residual(image: np.ndarray, crop: int, rotation: int = 0, sigma: float = QUERY_SIGMA,
                        workers: int | None = None) -> np.ndarray:
    """The vector an image is compared with: ``W·I`` over a centred ``crop × crop`` square, less its
    8×8-periodic mean, unit norm.

    Parameters
    ----------
    image : ndarray, (H, W) or (H, W, 3)
        Not modified.
    crop : int
        Side of the centred square (a multiple of 8; must fit in the frame).
    rotation : int
        ``np.rot90`` quarter turns applied to the image first.
    sigma : float
        Residual noise level, 8-bit scale (2, the query residual of the reference design).
    workers : int, optional
        Threads of the residual.

    Returns
    -------
    ndarray, float32, (crop, crop)
        All zeros when the weighted residual is constant (a blank or fully saturated image).
    """
    if crop % GRID:
        raise UsageError(f"crop={crop}: the comparison crop must be a multiple of {GRID} (the JPEG block grid)")
    query = prepare_query(image, Region("center", (crop, crop)), sigma=sigma, rotation=rotation, workers=workers)
    vec = np.ascontiguousarray(query.residual, dtype=np.float32)  # (a new array already: no copy)
    vec *= query.intensity  # saturated pixels have I = 0 and drop out
    # Remove the 8×8-periodic mean (which includes the mean): the pattern JPEG blocks and the 2×2 CFA leave
    # in every camera that processes alike.  Small in one pair, it adds up coherently in cluster sums.
    tiles = vec.reshape(crop // GRID, GRID, crop // GRID, GRID)
    tiles -= tiles.mean(axis=(0, 2), dtype=np.float64, keepdims=True).astype(np.float32)
    norm = math.sqrt(float(np.square(vec).sum(dtype=np.float64)))
    if norm > 0:
        vec /= np.float32(norm)
    else:
        vec[...] = 0
    return vec


@dataclass(frozen=True)
class _ResidualJob:
    """What every residual item needs (shared once per worker): the images and each one's plan."""

    images: ImageSet
    frames: tuple[tuple[int, int], ...]  # expected (H, W) as stored
    crops: tuple[int, ...]  # 0: not compared
    turns: tuple[tuple[int, ...], ...]  # quarter turns of each version of the image
    sigma: float


def _residual_item(job: _ResidualJob, i: int) -> list[np.ndarray]:
    """Work item: the comparison residual(s) of image ``i`` (read here, on the worker), float32 vectors."""
    if job.crops[i] == 0:
        return []
    image = job.images.load(i)
    shape = tuple(int(s) for s in image.shape[:2])
    if shape != job.frames[i]:
        raise InputError(f"{job.images.sources[i]}: decoded frame is {shape[0]}×{shape[1]}, its header said "
                         f"{job.frames[i][0]}×{job.frames[i][1]}; check the file")
    return [comparison_residual(image, job.crops[i], turn, job.sigma).ravel() for turn in job.turns[i]]


def _frame_shape(images: ImageSet, i: int) -> tuple[int, int]:
    """(H, W) of image ``i`` as stored: from the file header when it is a file, else by loading it."""
    source = images.sources[i]
    if os.path.isfile(source):
        from forensics.io.images import read_info

        info = read_info(source)
        return int(info.height), int(info.width)
    shape = images.load(i).shape
    return int(shape[0]), int(shape[1])


# ----------------------------------------------------------------------------- geometry


@dataclass
class _Group:
    """Images of one frame size up to a rotation (the plan, before any residual)."""

    frame: tuple[int, int]  # majority orientation (H, W)
    crop: int
    members: list[int]  # image indices
    rotated: list[bool]

    @property
    def n_rows(self) -> int:
        return len(self.members) + sum(self.rotated)


def _plan_groups(shapes: Sequence[tuple[int, int]], crop: int) -> list[_Group]:
    """Size groups, the majority orientation of each, and the crop (first-seen order)."""
    by_size: dict[tuple[int, int], list[int]] = {}
    for i, (h, w) in enumerate(shapes):
        by_size.setdefault((max(h, w), min(h, w)), []).append(i)
    groups = []
    for (long, short), members in by_size.items():
        landscape = sum(1 for i in members if shapes[i][1] >= shapes[i][0])
        frame = (short, long) if 2 * landscape >= len(members) else (long, short)
        side = min(crop, short) // GRID * GRID
        rotated = [tuple(shapes[i]) != frame for i in members]
        groups.append(_Group(frame, side if side >= MIN_CROP else 0, members, rotated))
    return groups


def block_images(crop: int, memory: int = BLOCK_MEMORY) -> int:
    """Rows of one similarity block: three blocks of ``crop²`` float32 vectors fit in ``memory`` bytes.

    Depends only on the crop (never on the workers), so every backend computes the same blocks.
    """
    return max(1, memory // (3 * 4 * crop * crop))


def null_shifts(crop: int) -> tuple[tuple[int, int], ...]:
    """The circular shifts of the null samples: half the crop, rounded down to a multiple of 8, along rows,
    columns and both (keeping the 2×2 CFA and 8×8 JPEG grids aligned)."""
    h = max(8, (crop // 2) // 8 * 8)
    return ((h, h), (h, 0), (0, h))


# ----------------------------------------------------------------------------- similarity blocks


def _read_rows(path: str, offset: int, width: int, start: int, stop: int) -> np.ndarray:
    """Rows ``start:stop`` of a float32 store of rows of ``width`` values from byte ``offset`` on, read (not
    mapped: mapped pages would count in the process's resident memory while the file is open)."""
    with open(path, "rb") as handle:
        handle.seek(offset + start * width * 4)
        rows = np.fromfile(handle, dtype=np.float32, count=(stop - start) * width)
    if rows.size != (stop - start) * width:
        raise InputError(f"{path}: the residual store is shorter than expected; was it changed during the run?")
    return rows.reshape(stop - start, width)


@dataclass(frozen=True)
class _GramJob:
    """Shared data of the block items: the stores (one .npy per group) and what is in them."""

    stores: tuple[str, ...]
    offsets: tuple[int, ...]  # where the rows start (after the .npy header)
    crops: tuple[int, ...]
    n_primary: tuple[int, ...]


def _gram_item(job: _GramJob, item: tuple[int, int, int, int, int, bool]) -> tuple[np.ndarray, np.ndarray | None]:
    """Work item: one block of the Gram matrix ``V_rows · V_colsᵀ`` of group ``g`` and, when asked, the null
    samples ``<v_i, shift(v_j)>`` of its primary rows, shape (shifts, rows, cols): every shift of
    :func:`null_shifts` on a diagonal block, the first one elsewhere."""
    g, r0, r1, c0, c1, with_null = item
    width = job.crops[g] ** 2
    a = _read_rows(job.stores[g], job.offsets[g], width, r0, r1)
    diagonal = (r0, r1) == (c0, c1)
    b = a if diagonal else _read_rows(job.stores[g], job.offsets[g], width, c0, c1)
    gram = a @ b.T
    primary = job.n_primary[g]
    if not with_null or r0 >= primary or c0 >= primary:
        return gram, None
    crop = job.crops[g]
    p, q = a[: min(r1, primary) - r0], b[: min(c1, primary) - c0]
    shifts = null_shifts(crop) if diagonal else null_shifts(crop)[:1]
    null = np.empty((len(shifts), len(p), len(q)), np.float32)
    for k, shift in enumerate(shifts):
        moved = np.roll(q.reshape(len(q), crop, crop), shift, axis=(1, 2)).reshape(len(q), -1)
        null[k] = p @ moved.T
        del moved
    return gram, null


# ----------------------------------------------------------------------------- null distribution


@dataclass(frozen=True)
class ClusterNull:
    """The null distribution of the NCC of two different cameras' residuals in one size group.

    Attributes
    ----------
    centre : float
        Median of the null samples (non-zero when all residuals share a pattern).
    sigma : float
        Its scale: median absolute deviation × 1.4826.
    sigma_ci : (float, float)
        95 % interval of ``sigma`` (delete-a-group jackknife over images).
    sigma_upper : float
        One-sided upper 95 % bound of ``sigma``: what the thresholds use.
    n_samples : int
        Null samples (pairs × 3 shifts).
    crop : int
    pooled : bool
        True when the group had too few images and took ``σ·crop`` pooled over the other groups.
    tail_observed, tail_expected : int, float
        Null samples beyond 4 σ from the centre, and the number a Gaussian null predicts (a check of the
        Gaussian tail the thresholds rely on).
    """

    centre: float
    sigma: float
    sigma_ci: tuple[float, float]
    sigma_upper: float
    n_samples: int
    crop: int
    pooled: bool = False
    tail_observed: int = 0
    tail_expected: float = 0.0

    @property
    def n_eff(self) -> float:
        """Effective number of independent pixels, ``1/σ²``."""
        return 1.0 / self.sigma**2

    def to_dict(self) -> dict[str, Any]:
        lo, hi = self.sigma_ci
        return {"centre": self.centre, "sigma": self.sigma, "sigma_ci": [lo, hi], "sigma_upper": self.sigma_upper,
                "sigma_times_crop": self.sigma * self.crop, "n_eff": self.n_eff,
                "n_eff_ci": [1.0 / hi**2, 1.0 / lo**2] if lo > 0 else [1.0 / hi**2, None],
                "n_samples": self.n_samples, "level": LEVEL, "pooled": self.pooled,
                "shifts": [list(s) for s in null_shifts(self.crop)],
                "tail_beyond_4_sigma": {"observed": self.tail_observed, "expected": self.tail_expected}}


def _mad_scale(x: np.ndarray) -> tuple[float, float]:
    centre = float(np.median(x))
    return centre, 1.4826 * float(np.median(np.abs(x - centre)))


def _estimate_null(values: np.ndarray, left: np.ndarray, right: np.ndarray, crop: int) -> ClusterNull:
    """Centre, σ and its jackknife interval from null samples of image pairs (``left``, ``right``)."""
    centre, sigma = _mad_scale(values)
    groups = min(JACKKNIFE_GROUPS, int(max(left.max(initial=0), right.max(initial=0))) + 1)
    reps = []
    for g in range(groups):
        keep = (left % groups != g) & (right % groups != g)
        if keep.sum() >= 3:
            reps.append(_mad_scale(values[keep])[1])
    if len(reps) >= 2:
        r = np.asarray(reps)
        se = math.sqrt((len(r) - 1) / len(r) * float(np.sum((r - r.mean()) ** 2)))
    else:
        se = sigma  # too few images for an interval: a bound of twice the estimate
    z2, z1 = float(special.ndtri(0.5 + LEVEL / 2)), float(special.ndtri(LEVEL))
    beyond = int(np.count_nonzero(np.abs(values - centre) > 4 * sigma)) if sigma > 0 else 0
    return ClusterNull(centre, sigma, (max(0.0, sigma - z2 * se), sigma + z2 * se), sigma + z1 * se,
                       int(values.size), crop, False, beyond, float(values.size * 2 * special.ndtr(-4.0)))


# ----------------------------------------------------------------------------- results


@dataclass(frozen=True)
class ImageAssignment:
    """One image's outcome.

    Attributes
    ----------
    index : int
        Position in the input.
    file : str
        Its name (the dataset's ``file`` or the source).
    source : str
        Where it was read from.
    group : int or None
        Size group (None: too small to compare).
    rotation : int
        Quarter turns applied to it (``np.rot90``) before the crop.
    cluster : str or None
        Device label, None when unattributed.
    stage : str
        'merged' (agglomeration), 'attached' (second stage), 'unattributed' or 'not compared'.
    best_match : str or None
        The image it correlates with most.
    best_z : float
        That pair's NCC in null standard deviations above the null centre.
    best_p_fa : float
        Probability that some non-matching comparison of the agglomeration reaches ``best_z`` (Šidák over its
        comparisons, with the conservative σ).
    cluster_z : float
        z of the image against the rest of its cluster (summed vectors), or against the best cluster for an
        unattributed image (−inf when there is none).
    passed : bool
        Whether it was attributed (its merge or attachment reached the threshold).
    """

    index: int
    file: str
    source: str
    group: int | None
    rotation: int
    cluster: str | None
    stage: str
    best_match: str | None
    best_z: float
    best_p_fa: float
    cluster_z: float
    passed: bool

    def to_dict(self) -> dict[str, Any]:
        return {"index": self.index, "file": self.file, "source": self.source, "group": self.group,
                "rotation": self.rotation, "cluster": self.cluster, "stage": self.stage,
                "best_match": self.best_match, "best_z": _finite(self.best_z), "best_p_fa": self.best_p_fa,
                "cluster_z": _finite(self.cluster_z), "passed": self.passed}


@dataclass(frozen=True)
class DeviceCluster:
    """One cluster (a device found): its members and how tightly they agree.

    ``mean_z``/``min_z`` summarise the pairwise z of its members (NCC above the null centre in σ);
    ``weakest_z`` is the lowest z of a member against the sum of the others (single pairs of weak images can
    be low while each agrees clearly with the rest).  The cluster passed the threshold of its stage, whose
    false-alarm probability is stated in the result.
    """

    label: str
    group: int
    members: tuple[int, ...]
    files: tuple[str, ...]
    mean_z: float
    min_z: float
    weakest_z: float
    n_attached: int

    @property
    def size(self) -> int:
        return len(self.members)

    def to_dict(self) -> dict[str, Any]:
        return {"label": self.label, "group": self.group, "size": self.size, "mean_z": self.mean_z,
                "min_z": self.min_z, "weakest_z": _finite(self.weakest_z), "n_attached": self.n_attached, "members": list(self.members),
                "files": list(self.files)}


@dataclass(frozen=True)
class SizeGroup:
    """Images of one frame size (up to a rotation) and how they were compared.

    ``threshold_merge``/``threshold_attach`` are in units of the estimated σ (the z of the results);
    ``n_comparisons``/``n_attach_tests`` the counts their Šidák corrections cover.
    """

    index: int
    frame: tuple[int, int]
    crop: int
    members: tuple[int, ...]
    n_rotated: int
    null: ClusterNull | None
    threshold_merge: float
    threshold_attach: float
    n_comparisons: int
    n_attach_tests: int
    merges: tuple[tuple[int, int, float], ...] = ()

    def to_dict(self) -> dict[str, Any]:
        return {"index": self.index, "frame": {"height": self.frame[0], "width": self.frame[1]}, "crop": self.crop,
                "n_images": len(self.members), "n_rotated": self.n_rotated,
                "null": self.null.to_dict() if self.null is not None else None,
                "threshold_merge_z": _finite(self.threshold_merge),
                "threshold_attach_z": _finite(self.threshold_attach),
                "n_comparisons": self.n_comparisons, "n_attach_tests": self.n_attach_tests,
                "merges": [{"a": a, "b": b, "z": z} for a, b, z in self.merges]}


@dataclass
class ClusterResult:
    """The clustering of a collection (:func:`cluster_images`).

    ``similarity`` holds one matrix per size group: the pairwise z (NCC above the null centre in σ) of its
    members in group order (rotated images in their chosen orientation), for the report; it is not part of
    :meth:`to_dict` (``write_cluster_dataset`` saves it as ``similarity.npz``).
    """

    images: list[ImageAssignment]
    clusters: list[DeviceCluster]
    groups: list[SizeGroup]
    p_fa: float
    sigma: float
    crop: int
    warnings: list[str] = field(default_factory=list)
    similarity: list[np.ndarray] = field(default_factory=list, repr=False)
    parameters: dict[str, Any] = field(default_factory=dict)

    @property
    def labels(self) -> list[str | None]:
        """Each image's device label (None: unattributed), in input order."""
        return [a.cluster for a in self.images]

    @property
    def n_unattributed(self) -> int:
        return sum(1 for a in self.images if a.cluster is None)

    def to_dict(self) -> dict[str, Any]:
        return {"p_fa": self.p_fa, "p_fa_meaning": "probability that any image is put with another camera's "
                "images (half for merges, half for attachments; Gaussian null with σ at its upper bound)",
                "n_images": len(self.images), "n_clusters": len(self.clusters),
                "n_unattributed": self.n_unattributed, "crop": self.crop, "sigma": self.sigma,
                "groups": [g.to_dict() for g in self.groups], "clusters": [c.to_dict() for c in self.clusters],
                "images": [a.to_dict() for a in self.images], "warnings": list(self.warnings),
                "parameters": dict(self.parameters)}


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


# ----------------------------------------------------------------------------- clustering one group


def _pair_z(gram: np.ndarray, null: ClusterNull) -> np.ndarray:
    """z of every pair of unit vectors (NCC − centre)/σ; −inf on the diagonal and for blank vectors."""
    diag = np.diag(gram).copy()
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (gram / np.sqrt(np.outer(diag, diag)) - null.centre) / null.sigma
    bad = diag <= 1e-12
    z[bad, :] = -np.inf
    z[:, bad] = -np.inf
    np.fill_diagonal(z, -np.inf)
    return z


def _resolve_orientations(gram: np.ndarray, group: _Group) -> list[int]:
    """The version row of each member: majority images have one; each rotated image keeps the quarter turn
    that agrees best with the images placed so far (majority first, then rotated ones by evidence)."""
    n = len(group.members)
    rows = list(range(n))
    alt = {}
    extra = n
    for k, rot in enumerate(group.rotated):
        if rot:
            alt[k] = extra
            extra += 1
    pending = sorted(alt)
    if not pending:
        return rows
    fixed = [k for k in range(n) if not group.rotated[k]]
    best = np.full((len(pending), 2), -np.inf)
    for p, k in enumerate(pending):
        for v, row in enumerate((k, alt[k])):
            if fixed:
                best[p, v] = float(gram[row, fixed].max())
    todo = list(range(len(pending)))
    while todo:
        p = max(todo, key=lambda q: (float(best[q].max()), -q))
        k = pending[p]
        v = int(np.argmax(best[p])) if np.isfinite(best[p]).any() else 0
        rows[k] = (k, alt[k])[v]
        todo.remove(p)
        for q in todo:
            kq = pending[q]
            for w, row in enumerate((kq, alt[kq])):
                best[q, w] = max(best[q, w], float(gram[row, rows[k]]))
    return rows


def _agglomerate(gram: np.ndarray, null: ClusterNull, tau: float) -> tuple[list[list[int]], list[tuple[int, int, float]]]:
    """Merge clusters best-first while the NCC of their summed vectors is ≥ τ (in σ above the centre).

    Returns the clusters (lists of positions, each sorted) and the merges ``(first member of A, first member
    of B, z)`` in order.
    """
    n = len(gram)
    c = np.array(gram, dtype=np.float64, copy=True)
    z = _pair_z(c, null)
    active = np.ones(n, bool)
    members = [[i] for i in range(n)]
    merges = []
    while n > 1:
        flat = int(np.argmax(z))
        x, y = divmod(flat, n)
        if not z[x, y] >= tau:
            break
        x, y = min(x, y), max(x, y)
        merges.append((members[x][0], members[y][0], float(z[x, y])))
        c[x] += c[y]
        c[:, x] += c[:, y]
        members[x] = sorted(members[x] + members[y])
        members[y] = []
        active[y] = False
        z[y, :] = -np.inf
        z[:, y] = -np.inf
        d = np.diag(c)
        with np.errstate(divide="ignore", invalid="ignore"):
            row = (c[x] / np.sqrt(d[x] * d) - null.centre) / null.sigma
        row[~active] = -np.inf
        row[~np.isfinite(row)] = -np.inf
        row[x] = -np.inf
        z[x, :] = row
        z[:, x] = row
    return [m for m in members if m], merges


def _z_against(gram: np.ndarray, row: int, cols: Sequence[int], null: ClusterNull) -> float:
    """z of vector ``row`` against the sum of vectors ``cols`` (NCC of the sums, above the centre, in σ)."""
    cols = list(cols)
    if not cols:
        return -math.inf
    den = float(gram[row, row]) * float(gram[np.ix_(cols, cols)].sum())
    if den <= 0:
        return -math.inf
    return (float(gram[row, cols].sum()) / math.sqrt(den) - null.centre) / null.sigma


# ----------------------------------------------------------------------------- the whole run


@dataclass
class _GroupState:
    """A group while it is being clustered."""

    plan: _Group
    gram: np.ndarray | None = None
    null: ClusterNull | None = None
    null_parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list)
    rows: list[int] = field(default_factory=list)
    clusters: list[list[int]] = field(default_factory=list)
    merges: list[tuple[int, int, float]] = field(default_factory=list)
    tau_merge: float = math.inf
    tau_attach: float = math.inf
    n_comparisons: int = 0
    n_attach_tests: int = 0
    attached: dict[int, int] = field(default_factory=dict)  # position -> cluster position

    def alt_row(self, k: int) -> int | None:
        if not self.plan.rotated[k]:
            return None
        return len(self.plan.members) + sum(self.plan.rotated[:k])


def _check_arguments(p_fa: float, crop: int, sigma: float) -> None:
    if not 0 < p_fa < 1:
        raise UsageError(f"p_fa={p_fa:g}: the false-alarm probability must lie between 0 and 1 (e.g. 1e-3)")
    if crop < MIN_CROP:
        raise UsageError(f"crop={crop}: compare over at least {MIN_CROP}×{MIN_CROP} pixels (1024 is usual)")
    if not sigma > 0:
        raise UsageError(f"sigma={sigma:g}: the residual noise level must be positive (2 is the reference's)")


def cluster_images(
    images: Any,
    *,
    p_fa: float = DEFAULT_PFA,
    crop: int = DEFAULT_CROP,
    sigma: float = QUERY_SIGMA,
    names: Sequence[str] | None = None,
    executor: Executor | None = None,
    workdir: str | os.PathLike | None = None,
    block: int | None = None,
    progress: Progress = no_progress,
) -> ClusterResult:
    """Group images by the camera that took them (the number of cameras is found, not given).

    Parameters
    ----------
    images : dataset folder, Dataset, ImageSet or sequence
        Anything :meth:`forensics.prnu.fingerprint.ImageSet.of` takes (paths, dataset frames, arrays,
        callables).  On worker processes or a cluster the items must be readable there (paths, frames).
    p_fa : float
        Probability that any image is put with another camera's images (half for the agglomeration, half
        for the attachment of left-over images; see the module notes).
    crop : int
        Side of the centred square compared (at most the frame's short side is used).
    sigma : float
        Residual noise level, 8-bit scale.
    names : sequence of str, optional
        How images are named in the result (default: the set's sources).
    executor : Executor, optional
        Runs the residuals (one image per item) and the similarity blocks (default: this process).
    workdir : path, optional
        Where the residual store goes (``rows × crop² × 4`` bytes; default: a temporary
        folder, removed afterwards).  On a Dask cluster it must be storage every worker sees.
    block : int, optional
        Rows per similarity block (default :func:`block_images` of each group's crop).
    progress : callable
        Progress bars for the residuals and the blocks.

    Returns
    -------
    ClusterResult

    Raises
    ------
    UsageError
        Arguments out of range.
    InputError
        Fewer than 5 images of one size (no null distribution can be estimated), or unreadable images.
    """
    _check_arguments(p_fa, crop, sigma)
    image_set = ImageSet.of(images, "collection")
    n = len(image_set)
    if n == 0:
        raise InputError("no images to cluster; give a dataset folder with images")
    labels_of = [str(s) for s in (names if names is not None else image_set.sources)]
    if len(labels_of) != n:
        raise UsageError(f"{len(labels_of)} names for {n} images; give one name per image")
    ex = resolve(executor)
    # File headers are read here (cheap); images that must be decoded or rendered to know their size, there.
    local = all(os.path.isfile(source) for source in image_set.sources)
    shapes = [_frame_shape(image_set, i) for i in range(n)] if local else list(
        ex.map(_frame_shape, range(n), shared=image_set, progress=progress, desc="sizes"))
    plans = _plan_groups(shapes, crop)
    if max((len(p.members) for p in plans if p.crop), default=0) < MIN_GROUP:  # before any residual
        raise InputError(f"no {MIN_GROUP} comparable images of one frame size among {n}: clustering needs at least "
                         f"{MIN_GROUP} images of one frame size to measure the null distribution of the residual "
                         "correlation")
    warnings = _geometry_warnings(plans, shapes, crop)
    states = [_GroupState(p) for p in plans]
    own = workdir is None
    folder = Path(tempfile.mkdtemp(prefix="forensics-cluster-")) if own else Path(workdir)  # type: ignore[arg-type]
    folder.mkdir(parents=True, exist_ok=True)
    try:
        seconds = _compute_grams(image_set, shapes, states, sigma, ex, folder, block, progress)
    finally:
        if own:
            shutil.rmtree(folder, ignore_errors=True)
        else:
            for g in range(len(states)):
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(folder / f"residuals-{g}.npy")
    start = time.perf_counter()
    _estimate_nulls(states, warnings)
    _stage_merge(states, p_fa)
    _stage_attach(states, p_fa)
    result = _assemble(states, image_set, labels_of, n, p_fa, sigma, crop, warnings)
    seconds["clustering"] = time.perf_counter() - start
    result.parameters["seconds"] = seconds
    result.parameters["block_rows"] = {g.index: block or block_images(g.crop) for g in result.groups if g.crop}
    return result


def _geometry_warnings(plans: list[_Group], shapes: list[tuple[int, int]], crop: int) -> list[str]:
    out = []
    if len(plans) > 1:
        sizes = ", ".join(f"{p.frame[1]}×{p.frame[0]} ({len(p.members)})" for p in plans)
        out.append(f"images of {len(plans)} frame sizes (width×height, images): {sizes}; each size is clustered "
                   "on its own, and images of different sizes are never put together")
    for p in plans:
        if p.crop == 0:
            out.append(f"{len(p.members)} image(s) of {p.frame[1]}×{p.frame[0]} are smaller than {MIN_CROP} pixels "
                       "on a side and are not compared (left unattributed)")
        elif p.crop < crop:
            out.append(f"images of {p.frame[1]}×{p.frame[0]} are compared over a {p.crop}×{p.crop} crop (the "
                       f"largest that fits), not {crop}×{crop}")
    return out


def _compute_grams(image_set: ImageSet, shapes: list[tuple[int, int]], states: list[_GroupState], sigma: float,
                   ex: Executor, folder: Path, block: int | None, progress: Progress) -> dict[str, float]:
    """Residuals into one store per group (a .npy file written by rows), then each group's Gram matrix and null samples.

    Returns the wall time of the two phases (seconds).
    """
    start = time.perf_counter()
    n = len(image_set)
    crops, turns = [0] * n, [()] * n
    where: dict[int, tuple[int, int, int | None]] = {}  # image -> (group, primary row, alternative row)
    for g, st in enumerate(states):
        for k, i in enumerate(st.plan.members):
            crops[i] = st.plan.crop
            turns[i] = (1, 3) if st.plan.rotated[k] else (0,)
            where[i] = (g, k, st.alt_row(k))
    job = _ResidualJob(image_set, tuple(shapes), tuple(crops), tuple(turns), sigma)
    stores: list[str] = []
    offsets: list[int] = []
    for g, st in enumerate(states):
        path = folder / f"residuals-{g}.npy"
        stores.append(str(path) if st.plan.crop else "")
        if st.plan.crop:  # the header and the file's full size, then rows written in place
            store = np.lib.format.open_memmap(path, mode="w+", dtype=np.float32,
                                              shape=(st.plan.n_rows, st.plan.crop ** 2))
            offsets.append(int(store.offset))
            del store
        else:
            offsets.append(0)
    handles = {g: open(stores[g], "r+b") for g, st in enumerate(states) if st.plan.crop}
    try:
        for i, vectors in enumerate(ex.map(_residual_item, range(n), shared=job, progress=progress,
                                           desc="residuals")):
            if not vectors:
                continue
            g, row, alt = where[i]
            for r, vec in zip((row, alt), vectors):
                handles[g].seek(offsets[g] + int(r) * vec.size * 4)  # type: ignore[arg-type]
                handles[g].write(np.ascontiguousarray(vec, dtype=np.float32).tobytes())
    finally:
        for handle in handles.values():
            handle.close()
    residual_seconds = time.perf_counter() - start
    start = time.perf_counter()
    items = []
    for g, st in enumerate(states):
        if not st.plan.crop:
            continue
        size = block or block_images(st.plan.crop)
        parts = chunks(st.plan.n_rows, size)
        items += [(g, a.start, a.stop, b.start, b.stop, jb - ia <= NULL_BAND)
                  for ia, a in enumerate(parts) for jb, b in enumerate(parts) if jb >= ia]
        st.gram = np.zeros((st.plan.n_rows, st.plan.n_rows), np.float64)
    gram_job = _GramJob(tuple(stores), tuple(offsets), tuple(st.plan.crop for st in states),
                        tuple(len(st.plan.members) for st in states))
    for item, (gram, null) in zip(items, ex.map(_gram_item, items, shared=gram_job, progress=progress,
                                                desc="similarity blocks")):
        g, r0, r1, c0, c1, _ = item
        st = states[g]
        assert st.gram is not None
        st.gram[r0:r1, c0:c1] = gram
        st.gram[c0:c1, r0:r1] = gram.T
        if null is not None:
            if r0 == c0:  # a diagonal block: each pair once
                iu, ju = np.triu_indices(null.shape[1], 1)
            else:
                iu, ju = (x.ravel() for x in np.indices(null.shape[1:]))
            for k in range(null.shape[0]):
                st.null_parts.append((null[k][iu, ju].astype(np.float64), iu + r0, ju + c0))
    return {"residuals": residual_seconds, "similarity": time.perf_counter() - start}


def _estimate_nulls(states: list[_GroupState], warnings: list[str]) -> None:
    """σ per group; groups with too few null samples borrow the pooled ``σ·crop`` of the others."""
    own = []
    for st in states:
        if not st.null_parts:
            continue
        values = np.concatenate([p[0] for p in st.null_parts])
        if values.size >= MIN_NULL_SAMPLES:
            left = np.concatenate([p[1] for p in st.null_parts])
            right = np.concatenate([p[2] for p in st.null_parts])
            st.null = _estimate_null(values, left, right, st.plan.crop)
            own.append(st.null)
    small = [st for st in states if st.plan.crop and st.null is None]
    if not small:
        return
    if not own:
        total = sum(len(st.plan.members) for st in small)
        raise InputError(f"only {total} comparable image(s) of one size: clustering needs at least {MIN_GROUP} images "
                         "of one frame size to measure the null distribution of the residual correlation")
    weights = np.array([x.n_samples for x in own], float)
    scale = float(np.average([x.sigma * x.crop for x in own], weights=weights))
    upper = float(np.average([x.sigma_upper * x.crop for x in own], weights=weights))
    lo = float(np.average([x.sigma_ci[0] * x.crop for x in own], weights=weights))
    hi = float(np.average([x.sigma_ci[1] * x.crop for x in own], weights=weights))
    centre = float(np.average([x.centre for x in own], weights=weights))
    for st in small:
        c = st.plan.crop
        st.null = ClusterNull(centre, scale / c, (lo / c, hi / c), upper / c, 0, c, pooled=True)
        warnings.append(f"{len(st.plan.members)} image(s) of {st.plan.frame[1]}×{st.plan.frame[0]} are too few to "
                        "measure their own null distribution; σ·crop pooled over the other sizes is used")


def _stage_merge(states: list[_GroupState], p_fa: float) -> None:
    """Orientation of rotated images, then agglomeration at the Šidák threshold over every comparison."""
    for st in states:
        m = len(st.plan.members)
        st.n_comparisons = (m - 1) ** 2 * (2 if any(st.plan.rotated) else 1) if st.null is not None else 0
    total = sum(st.n_comparisons for st in states)
    z = sidak_z(p_fa / 2, total)
    for st in states:
        if st.null is None or st.gram is None:
            continue
        st.tau_merge = z * st.null.sigma_upper / st.null.sigma if st.null.sigma > 0 else math.inf
        st.rows = _resolve_orientations(st.gram, st.plan)
        fixed = st.gram[np.ix_(st.rows, st.rows)]
        st.clusters, st.merges = _agglomerate(fixed, st.null, st.tau_merge)


def _stage_attach(states: list[_GroupState], p_fa: float) -> None:
    """Each image left alone against every cluster of two or more, Šidák over those tests."""
    candidates: list[tuple[_GroupState, int, list[list[int]]]] = []
    for st in states:
        if st.null is None:
            continue
        big = [c for c in st.clusters if len(c) >= 2]
        alone = [c[0] for c in st.clusters if len(c) == 1]
        for k in alone:
            versions = 2 if st.plan.rotated[k] else 1
            st.n_attach_tests += versions * len(big)
            candidates.append((st, k, big))
    total = sum(st.n_attach_tests for st in states)
    z = sidak_z(p_fa / 2, total)
    for st in states:
        if st.null is not None and st.null.sigma > 0:
            st.tau_attach = z * st.null.sigma_upper / st.null.sigma
    for st, k, big in candidates:
        assert st.gram is not None and st.null is not None
        if st.gram[st.rows[k], st.rows[k]] <= 1e-12:
            continue
        best, best_c, best_row = -math.inf, None, st.rows[k]
        versions = [k] if not st.plan.rotated[k] else [k, st.alt_row(k)]
        for c, members in enumerate(big):
            cols = [st.rows[j] for j in members]
            for row in versions:
                value = _z_against(st.gram, row, cols, st.null)  # type: ignore[arg-type]
                if value > best:
                    best, best_c, best_row = value, c, row
        if best_c is not None and best >= st.tau_attach:
            st.attached[k] = best_c
            st.rows[k] = int(best_row)  # type: ignore[arg-type]


def _assemble(states: list[_GroupState], image_set: ImageSet, names: list[str], n: int, p_fa: float,
              sigma: float, crop: int, warnings: list[str]) -> ClusterResult:
    """Labels (largest cluster first), per-image scores, per-cluster and per-group summaries."""
    found = []  # (size, first image, group index, positions)
    for g, st in enumerate(states):
        big = [list(c) for c in st.clusters if len(c) >= 2]
        for k, c in st.attached.items():
            big[c].append(k)
        for members in big:
            found.append((len(members), min(st.plan.members[k] for k in members), g, sorted(members)))
    found.sort(key=lambda t: (-t[0], t[1]))
    width = max(2, len(str(len(found))))
    labelled = [(f"cluster-{number:0{width}d}", g, members) for number, (_, _, g, members) in enumerate(found, 1)]
    z_by_group: dict[int, np.ndarray] = {}
    similarity = []
    for g, st in enumerate(states):
        if st.gram is not None and st.null is not None:
            z_by_group[g] = _pair_z(st.gram[np.ix_(st.rows, st.rows)], st.null)
            similarity.append(np.where(np.isfinite(z_by_group[g]), z_by_group[g], np.nan))
        else:
            similarity.append(np.zeros((0, 0)))
    images: list[ImageAssignment | None] = [None] * n
    for g, st in enumerate(states):
        members_of = {label: members for label, group, members in labelled if group == g}
        label_at = {k: label for label, members in members_of.items() for k in members}
        for k, i in enumerate(st.plan.members):
            images[i] = _image_assignment(st, g, k, i, z_by_group.get(g), label_at.get(k), members_of, names,
                                          image_set.sources[i])
    done = [a for a in images if a is not None]
    clusters = []
    for label, g, members in labelled:
        st = states[g]
        index = [st.plan.members[k] for k in members]
        sub = z_by_group[g][np.ix_(members, members)][np.triu_indices(len(members), 1)]
        clusters.append(DeviceCluster(label, g, tuple(index), tuple(names[i] for i in index), float(np.mean(sub)),
                                      float(np.min(sub)), min(done[i].cluster_z for i in index),
                                      sum(1 for k in members if k in st.attached)))
    groups = [SizeGroup(g, st.plan.frame, st.plan.crop, tuple(st.plan.members), sum(st.plan.rotated), st.null,
                        st.tau_merge, st.tau_attach, st.n_comparisons, st.n_attach_tests,
                        tuple((st.plan.members[a], st.plan.members[b], z) for a, b, z in st.merges))
              for g, st in enumerate(states)]
    for st in states:
        if st.null is not None and st.null.tail_observed > st.null.tail_expected + 3 * math.sqrt(
                st.null.tail_expected) + 3:
            warnings.append(f"images of {st.plan.frame[1]}×{st.plan.frame[0]}: {st.null.tail_observed} null samples lie "
                            f"beyond 4σ where a Gaussian null predicts {st.null.tail_expected:.1f}; the stated "
                            "false-alarm probability may be optimistic for this collection")
    parameters = {"sigma_8bit": sigma, "crop": crop, "residual": "query residual (σ = 2, zero-mean CFA, DFT "
                  "Wiener) × intensity, less its 8×8-periodic mean, unit norm",
                  "linkage": "NCC of summed vectors", "forensics_version": __version__}
    return ClusterResult(done, clusters, groups, p_fa, sigma, crop, warnings, similarity, parameters)


def _image_assignment(st: _GroupState, g: int, k: int, i: int, zg: np.ndarray | None, label: str | None,
                      cluster_members: dict[str, list[int]], names: list[str], source: str) -> ImageAssignment:
    rotation = 0
    if st.plan.rotated[k]:
        rotation = 3 if st.rows and st.rows[k] != k else 1
    if zg is None or st.gram is None or st.null is None:
        return ImageAssignment(i, names[i], source, None if not st.plan.crop else g, rotation, None,
                               "not compared", None, -math.inf, 1.0, -math.inf, False)
    row = zg[k]
    j = int(np.argmax(row)) if len(row) > 1 else k
    best = float(row[j]) if j != k else -math.inf
    best_match = names[st.plan.members[j]] if math.isfinite(best) else None
    factor = st.null.sigma / st.null.sigma_upper if st.null.sigma_upper > 0 else 1.0
    p = _false_alarm(best * factor, max(1, st.n_comparisons))[0] if math.isfinite(best) else 1.0
    if label is not None:
        others = [st.rows[m] for m in cluster_members[label] if m != k]
        cz = _z_against(st.gram, st.rows[k], others, st.null)
        stage = "attached" if k in st.attached else "merged"
    else:
        versions = [k, st.alt_row(k)] if st.plan.rotated[k] else [k]
        cz = max((_z_against(st.gram, v, [st.rows[m] for m in ms], st.null)  # type: ignore[arg-type]
                  for ms in cluster_members.values() for v in versions), default=-math.inf)
        stage = UNATTRIBUTED
    return ImageAssignment(i, names[i], source, g, rotation, label, stage, best_match, best, p, cz, label is not None)
