"""1:N identification: which fingerprint of a database, if any, left its pattern in each query image?

For every query image and every candidate fingerprint ``K`` the PCE of :mod:`forensics.prnu.match` is
computed over every geometry searched, and the best device is the one with the highest PCE.

Geometry searched (per fingerprint; counted in the decision, see below)
------------------------------------------------------------------------
**Orientation** (``rotations``): ``'auto'`` tries the image as stored if it fits in the sensor's frame,
else both quarter turns (a portrait picture written rotated); ``'all'`` every quarter turn (0°, 90°,
180°, 270°) in which it fits; ``'none'`` the image as stored only.

**Aligned** images: an image of the frame's size at scale 1 is correlated as
:func:`forensics.prnu.match.score_query` does — its residual over the fingerprint's region with
``I·K`` — and scored at zero shift (one position) by the block-phase PCE below.

**Crops** (``crop_search``): an image smaller than the frame is taken as a crop at an unknown offset.
The query's ``W·I`` (residual times intensity, :func:`~forensics.prnu.match.prepare_query` on the whole
image) is correlated with ``K`` at every offset at which the crop lies inside the fingerprint's region,
or the region inside the crop (per axis), and inside the frame.  Both arrays are zero-padded to a
common canvas whose side is the longer of the two on each axis, so *every* circular shift pairs the same
number of real pixels: the correlation's null variance depends on the shift only through the JPEG
block phase, which the statistic below accounts for.  Crops reaching outside a ``center:N``
fingerprint's region are therefore not searched (build full-frame fingerprints to identify crops);
``corners`` fingerprints take aligned images only.

**Scales** (``scales``, resized or digitally zoomed images): for each scale ``s`` of the grid the
*fingerprint* is resampled by ``s`` (:func:`resample`, an antialiased triangle kernel) and searched as
for a crop of the resampled frame.  The fingerprint is resampled rather than the query (by ``1/s``)
because the query's residual then stays on its own pixel grid, with the noise statistics the PCE's null
assumes, instead of an interpolated (correlated) residual; the FFTs are ``s²`` smaller; and the camera
or editor did exactly this to the pattern.  The grid (:class:`ScaleSearch`) is geometric,
``s_k = hi·(1 + ρ)^(−k)`` down to ``lo``, with ``ρ = 4·e/L`` for a query whose longer side is ``L``
pixels: a true scale lies within a factor ``(1 + ρ)^½`` of a grid point, so the query's pixels are at
most ``L·ρ/4 = e`` pixels off the fingerprint's grid at its edges when aligned at its centre
(``e = 0.5`` pixel by default: 357 scales over 0.5–1.0 for ``L = 1024``; scales at which the image
does not fit in the resampled frame are left out, so a full frame is searched at scale 1 only).  A linear step can be given
instead (its grid error is reported).  The scales implied by the image's size (a whole frame resized
with its aspect ratio) are tried too.  The search is bounded: more than ``max_scales`` scales for one
image is refused before any work.

The statistic: block-phase PCE
------------------------------
The PCE of :mod:`forensics.prnu.match` divides the squared peak by one energy, the mean squared
correlation over all shifts.  JPEG's 8×8 blocks break that: residuals and fingerprints of JPEG images
are noisier on block boundaries, so the correlation's null variance is periodic in the shift, and at
the shifts that align the query's block grid with the fingerprint's — zero shift for a full frame, the
true offset for a crop — it is 1.6–1.85 times the mean (Dresden Nikons).  The plain PCE then exceeds its
χ²₁ null there: non-matching Dresden pairs reached PCE 21 at zero shift (p ≈ 4·10⁻⁶) and 48 in crop
searches whose Šidák bound was 40.  Here each shift's energy is the mean over the shifts of its own
phase ``(dy mod 8, dx mod 8)`` (the 11×11 window around the peak left out; shrunk towards the
all-shift energy by :data:`PHASE_PRIOR` shifts for small canvases), so ``z = peak/√energy`` is standard
normal under the null at every shift.  On images without blocks (simulations, PNG, resized images) all
phases agree and the value is the plain PCE; on JPEG frames and crops it is about half the plain PCE
(reported beside it as ``pce_global``, for comparison with ``forensics fingerprint match``).

The grid first: a weighted search
---------------------------------
The same energies show where the query's JPEG grid meets the fingerprint's: the aligning phase is the
one with the largest null energy (:func:`_grid_phase`; found only when clearly above the others, so not
on images without blocks).  A crop cut from a decoded JPEG lies on the camera's grid, so its true offset
is one of the ``n_A = n/64`` offsets of that phase.  Those offsets share half of the false-alarm budget
and the others the other half: position weights ``w_A = n/(2·n_A)`` and ``w_R = n/(2·(n − n_A))``, which
sum to ``n`` (weighted Bonferroni), and a peak's tail is ``Q(z)/w``.  On the Dresden 1024² crops the
threshold falls from PCE 40 to 33 on the grid (to 41.5 off it): 83 % of crops attributed instead of
76 %, with no false attribution.  A crop written again as JPEG after cropping carries its own grid and is
found off the camera's, at ``w_R``.  The choice of phase uses the energies only, never the normalised
peaks, so the bound holds.

Decision (Šidák over everything searched)
-----------------------------------------
Under the null hypothesis (no candidate took the image) the normalised peak ``z = sign·√|PCE|`` at
each position searched is about standard normal (:mod:`forensics.prnu.match`).  With ``n_j``
positions searched for fingerprint ``j`` (offsets × scales × orientations) and ``n = Σ_j n_j`` over
the ``N`` fingerprints the image is compatible with, the best device's corrected false-alarm
probability is

    p_FA = 1 − (1 − Q(z_best)/w_best)^n,     n = Σ_j positions_j · scales_j · rotations_j   (Šidák)

(``w = 1`` except on JPEG crops, above; candidates are ranked by ``Q(z)/w``)

and the image is *attributed* when ``p_FA ≤ pfa``, else *unknown*.  Neighbouring positions and scales
are positively correlated, which makes Šidák conservative for Gaussian ``z``, so searching more never
inflates false alarms; measured on simulated devices outside the set the corrected ``p_FA`` is close to
uniform (crop searches over ~10⁴ offsets: 5, 13 and 36 of 60 at 0.05, 0.2 and 0.5; aligned images: 9
and 39 of 200 at 0.05 and 0.2).
The equivalent PCE threshold, ``Q⁻¹(1 − (1 − pfa)^(w/n))²`` for the best peak's weight, is reported with each image.

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

Execution: one work item per query (a path or a dataset frame, read by the worker), the fingerprints
(and their sketches) shipped once per worker (``shared``); results in query order on every backend.
"""
from __future__ import annotations

import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from functools import lru_cache
from typing import Any

import numpy as np
import scipy.fft
import scipy.sparse
from scipy import special

from forensics._shared.errors import InputError, UsageError
from forensics._shared.parallel import Executor, resolve
from forensics._shared.progress import Progress, no_progress
from forensics.prnu.fingerprint import Fingerprint, Region, parse_region
from forensics.prnu.match import (
    QUERY_SIGMA,
    _centred,
    _false_alarm,
    _is_reference,
    _PreparedImage,
    _shift_indices,
    _Spectrum,
    _sum_sq,
)
from forensics.prnu.residual import default_workers

__all__ = [
    "CORRECTION",
    "DEFAULT_PFA",
    "PRESCREEN_AUTO_MIN",
    "Candidate",
    "IdentificationResult",
    "Prescreen",
    "PrescreenMissRate",
    "QueryIdentification",
    "ScaleSearch",
    "identify",
    "parse_scales",
    "pce_threshold",
    "prescreen_miss_rate",
    "resample",
]

#: Default false-alarm probability of an attribution, over all fingerprints and positions searched.
DEFAULT_PFA = 1e-3
#: ``prescreen='auto'`` is on above this many fingerprints (below it, full PCE on all is cheap enough).
PRESCREEN_AUTO_MIN = 50
#: The decision rule, as reported.
CORRECTION = ("weighted Šidák: p_FA = 1 − (1 − Q(z_best)/w_best)^n, n = Σ over compatible fingerprints of "
              "positions × scales × rotations searched; z = √PCE; w = 1 except on a JPEG crop (offsets on its "
              "detected block grid share half the budget: w > 1 there, < 1 elsewhere); attributed when p_FA ≤ pfa")
#: Seed of the pre-screen's projection (fixed: a fingerprint's sketch must not change between runs).
SKETCH_SEED = 0x1D_2012
#: Period of the block grid whose phase the correlation's null variance depends on (JPEG's 8×8 blocks).
BLOCK = 8
#: Weight, in shifts, of the all-shift energy in each phase's energy (shrinks small canvases' noisy estimates).
PHASE_PRIOR = 256
#: Share of a search's false-alarm budget given to the offsets on the query's detected JPEG grid.
GRID_SHARE = 0.5
#: A block phase is the grid when its null energy exceeds the mean by this fraction (Dresden: 0.6–0.85) …
GRID_MIN_EXCESS = 0.1
#: … and by this many standard errors of its estimate.
GRID_SIGMAS = 8.0
#: A whole-frame resize may differ from the scaled frame's size by rounding, up to this many pixels.
_SIZE_SLACK = 2
_ROTATION_MODES = ("auto", "none", "all")


# ----------------------------------------------------------------------------- settings objects


@dataclass(frozen=True)
class ScaleSearch:
    """The scales searched for resized or digitally zoomed images.

    A scale ``s`` is query pixels per sensor pixel: 0.5 is a picture shrunk to half its width, 1.5 a
    digital zoom of 1.5× (a centre crop enlarged).

    Attributes
    ----------
    lo, hi : float
        The range searched (default 0.5–1.0).
    step : float, optional
        A linear step; default: the geometric step ``ρ = 4·max_error/L`` for a query whose longer side is
        ``L`` pixels (see the module notes).
    max_error : float
        Largest misregistration, in query pixels at the image's edges, of the automatic step.
    from_size : bool
        Also try the scales implied by the query's size (a whole frame resized, aspect ratio kept).
    values : tuple of float, optional
        Explicit scales instead of a range.
    max_scales : int
        Refuse a grid of more scales than this for one image (bounds the time: each scale costs about
        one FFT-based correlation per fingerprint at ``s²`` the frame's size).
    """

    lo: float = 0.5
    hi: float = 1.0
    step: float | None = None
    max_error: float = 0.5
    from_size: bool = True
    values: tuple[float, ...] | None = None
    max_scales: int = 400

    def __post_init__(self) -> None:
        if self.values is not None:
            if not self.values or any(not (0.05 <= v <= 8.0) for v in self.values):
                raise UsageError(f"scales {self.values}: give scales between 0.05 and 8")
            return
        if not (0.05 <= self.lo <= self.hi <= 8.0):
            raise UsageError(f"scale range {self.lo}:{self.hi}: need 0.05 ≤ lo ≤ hi ≤ 8")
        if self.step is not None and self.step <= 0:
            raise UsageError(f"scale step {self.step}: must be positive")
        if self.max_error <= 0:
            raise UsageError(f"max_error {self.max_error}: must be positive (pixels)")

    def grid(self, side: int, floor: float = 0.0, check: bool = True) -> tuple[float, ...]:
        """The scales for a query whose longer side is ``side`` pixels, largest first.

        Parameters
        ----------
        side : int
        floor : float
            Smallest scale at which the query still fits in the resampled frame: scales below it are
            left out (a full frame, for instance, is searched at scale 1 only).
        check : bool
            Refuse more than ``max_scales`` scales.

        Raises
        ------
        UsageError
            More than ``max_scales`` scales.
        """
        lo = max(self.lo, floor)
        if self.values is not None:
            scales = sorted({float(v) for v in self.values if v >= floor}, reverse=True)
        elif lo > self.hi:
            scales = []
        elif lo == self.hi:
            scales = [self.hi]
        elif self.step is not None:
            n = math.floor((self.hi - lo) / self.step + 1e-9)
            scales = [self.hi - k * self.step for k in range(n + 1)]
        else:
            rho = self.ratio(side)
            n = math.ceil(math.log(self.hi / lo) / math.log1p(rho) - 1e-9)
            scales = [self.hi / (1 + rho) ** k for k in range(n + 1)]
        if check and len(scales) > self.max_scales:
            raise UsageError(
                f"the scale search {self.describe()} needs {len(scales)} scales for a {side}-pixel image (more than "
                f"max_scales={self.max_scales}); narrow the range, coarsen the step or raise the limit")
        return tuple(scales)

    def ratio(self, side: int) -> float:
        """The automatic geometric step ``ρ = 4·max_error/L``."""
        return 4.0 * self.max_error / max(1, int(side))

    def grid_error(self, side: int) -> float:
        """Largest misregistration (query pixels, at the image's edges) between a true scale and the grid."""
        if self.values is not None:
            return math.nan  # explicit scales: no statement about scales between them
        if self.step is None:
            return side * self.ratio(side) / 4.0
        return side * self.step / (4.0 * self.lo)

    def bounds(self) -> tuple[float, float]:
        """The smallest and largest scale searched."""
        if self.values is not None:
            return min(self.values), max(self.values)
        return self.lo, self.hi

    def describe(self) -> str:
        if self.values is not None:
            return ",".join(f"{v:g}" for v in self.values)
        step = f"step {self.step:g}" if self.step is not None else f"grid error ≤ {self.max_error:g} px"
        return f"{self.lo:g}–{self.hi:g} ({step})"

    def to_dict(self) -> dict[str, Any]:
        return {"lo": self.lo, "hi": self.hi, "step": self.step, "max_error_px": self.max_error,
                "from_size": self.from_size, "values": list(self.values) if self.values is not None else None,
                "max_scales": self.max_scales}


def parse_scales(text: str) -> ScaleSearch:
    """``'LO:HI'`` (automatic step), ``'LO:HI:STEP'``, or a comma list ``'0.5,0.7'``.

    Raises
    ------
    UsageError
        Anything else.
    """
    t = str(text).strip()
    try:
        if ":" in t:
            parts = [float(p) for p in t.split(":")]
            if len(parts) == 2:
                return ScaleSearch(parts[0], parts[1])
            if len(parts) == 3:
                return ScaleSearch(parts[0], parts[1], step=parts[2])
        else:
            return ScaleSearch(values=tuple(float(p) for p in t.split(",") if p.strip()))
    except ValueError:
        pass
    raise UsageError(f"scales {text!r}: give LO:HI (e.g. 0.5:1.0), LO:HI:STEP (0.5:1.0:0.05) or a list (0.5,0.75)")


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


# ----------------------------------------------------------------------------- results


@dataclass(frozen=True)
class Candidate:
    """One fingerprint's best score against one query.

    Attributes
    ----------
    device_id : str
    pce : float
        Signed PCE at the best position (``z = sign·√|PCE|``).
    p_fa : float
        False-alarm probability of this fingerprint alone over its own search
        (``1 − (1 − Q(z))^n_positions``); the decision uses the query's corrected value instead.
    log10_p_fa : float
    ncc : float
        Normalised correlation at the peak.
    rotation : int
        Quarter turns (``np.rot90``) applied to the query.
    scale : float
        Query pixels per sensor pixel (1 for no resize).
    offset : (int, int)
        Top-left corner of the (rotated) query in the frame resampled by ``scale``, (row, column).
    n_positions : int
        Positions searched for this fingerprint (offsets × scales × rotations).
    method : str
        ``'aligned'`` (zero shift), ``'crop'`` (offset search) or ``'scale'`` (scale and offset search).
    sketch_score : float, optional
        The pre-screen's z-score ``√d·corr`` (None when not pre-screened).
    pce_global : float
        The plain PCE at the same peak (one energy over all shifts, as ``forensics fingerprint match``
        reports), for comparison; the decision uses ``pce`` (block-phase energy, module notes).
    search_weight : float
        The peak's share of the weighted search (module notes): above 1 on the query's detected JPEG
        grid, below 1 off it, 1 without a grid.  Its tail is ``Q(z)/search_weight``.
    """

    device_id: str
    pce: float
    p_fa: float
    log10_p_fa: float
    ncc: float
    rotation: int
    scale: float
    offset: tuple[int, int]
    n_positions: int
    method: str
    sketch_score: float | None = None
    pce_global: float | None = None
    search_weight: float = 1.0

    @property
    def z(self) -> float:
        """The normalised peak ``sign·√|PCE|``."""
        return math.copysign(math.sqrt(abs(self.pce)), self.pce)

    @property
    def log_tail(self) -> float:
        """``log(Q(z)/search_weight)``: candidates rank by it, smallest (strongest) first."""
        return _log_tail(self.z, self.search_weight)

    def geometry(self) -> str:
        """Where the query matched, for tables: ``'aligned'`` or e.g. ``'rot 90°, scale 0.7, at (12, 40)'``."""
        parts = []
        if self.rotation:
            parts.append(f"rot {90 * self.rotation}°")
        if self.method == "scale":
            parts.append(f"scale {self.scale:.4g}")
        if self.method != "aligned":
            parts.append(f"at ({self.offset[0]}, {self.offset[1]})")
        if self.search_weight > 1.0:
            parts.append("on the JPEG grid")
        return ", ".join(parts) or "aligned"

    def to_dict(self) -> dict[str, Any]:
        return {"device_id": self.device_id, "pce": self.pce, "p_fa": self.p_fa, "log10_p_fa": self.log10_p_fa,
                "ncc": self.ncc, "rotation": self.rotation, "scale": self.scale, "offset": list(self.offset),
                "n_positions": self.n_positions, "method": self.method, "sketch_score": self.sketch_score,
                "pce_global": self.pce_global, "search_weight": self.search_weight}


@dataclass(frozen=True)
class QueryIdentification:
    """The identification of one image.

    Attributes
    ----------
    source : str
    shape : (int, int)
        Image height and width as stored.
    decision : str
        ``'attributed'`` or ``'unknown'``.
    device_id : str or None
        The attributed device.
    best, runner_up : Candidate or None
        Highest and second-highest PCE.
    top : tuple of Candidate
        The ``top_k`` highest, best first.
    p_fa, log10_p_fa : float
        The best device's false-alarm probability corrected for everything searched (module notes).
    pce_threshold : float
        The PCE the best device needed for an attribution at the run's ``pfa``.
    n_tests : int
        ``n`` of the correction: positions × scales × rotations summed over compatible fingerprints.
    n_fingerprints : int
        Fingerprints the image is compatible with (size, orientation, scale).
    n_scored : int
        Fingerprints that got the full PCE (fewer than ``n_fingerprints`` after a pre-screen).
    prescreen : dict or None
        The pre-screen's figures (sketch length, kept, dropped), None when it did not run.
    scales : dict or None
        The scale grid used (number, range, grid error in pixels), None without a scale search.
    note : str or None
        Why an image could not be scored, if so.
    """

    source: str
    shape: tuple[int, int]
    decision: str
    device_id: str | None
    best: Candidate | None
    runner_up: Candidate | None
    top: tuple[Candidate, ...]
    p_fa: float
    log10_p_fa: float
    pce_threshold: float
    n_tests: int
    n_fingerprints: int
    n_scored: int
    prescreen: dict[str, Any] | None = None
    scales: dict[str, Any] | None = None
    note: str | None = None

    @property
    def attributed(self) -> bool:
        return self.decision == "attributed"

    def to_dict(self) -> dict[str, Any]:
        return {"source": self.source, "shape": list(self.shape), "decision": self.decision,
                "device_id": self.device_id, "best": self.best.to_dict() if self.best else None,
                "runner_up": self.runner_up.to_dict() if self.runner_up else None,
                "top": [c.to_dict() for c in self.top], "p_fa": self.p_fa, "log10_p_fa": self.log10_p_fa,
                "pce_threshold": self.pce_threshold, "n_tests": self.n_tests,
                "n_fingerprints": self.n_fingerprints, "n_scored": self.n_scored, "prescreen": self.prescreen,
                "scales": self.scales, "note": self.note}


@dataclass
class IdentificationResult:
    """Every query's identification against one set of fingerprints (:func:`identify`)."""

    queries: list[QueryIdentification]
    devices: list[dict[str, Any]]
    pfa: float
    settings: dict[str, Any]
    correction: str = CORRECTION
    name: str | None = None

    @property
    def n_attributed(self) -> int:
        return sum(1 for q in self.queries if q.attributed)

    def counts(self) -> dict[str, int]:
        """Images attributed to each device (devices with none omitted)."""
        out: dict[str, int] = {}
        for q in self.queries:
            if q.attributed and q.device_id is not None:
                out[q.device_id] = out.get(q.device_id, 0) + 1
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"set": self.name, "n_images": len(self.queries), "n_fingerprints": len(self.devices),
                "n_attributed": self.n_attributed, "n_unknown": len(self.queries) - self.n_attributed,
                "pfa": self.pfa, "correction": self.correction, "settings": self.settings,
                "counts": self.counts(), "devices": self.devices, "queries": [q.to_dict() for q in self.queries]}


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


# ----------------------------------------------------------------------------- small public helpers


def pce_threshold(pfa: float, n_tests: float) -> float:
    """The PCE a best candidate needs for ``1 − (1 − Q(√PCE))^n_tests ≤ pfa``.

    For a position of a weighted search (``Candidate.search_weight`` ``w``) pass ``n_tests / w``.
    """
    if n_tests <= 0:
        return math.inf
    q = -math.expm1(math.log1p(-pfa) / n_tests)  # per-position tail probability
    z = -float(special.ndtri(q))
    return z * z


def _resample_matrix(n_in: int, n_out: int, scale: float, out_origin: int = 0, in_origin: float = 0.0
                     ) -> scipy.sparse.csr_matrix:
    """Sparse (n_out × n_in) antialiased linear interpolation: output ``o`` ↔ input ``(o + out_origin + ½)/s − ½ − in_origin``.

    The triangle kernel is stretched to ``1/s`` input pixels when shrinking (area-like averaging, as image
    editors' "bilinear" resizers do) and is plain linear interpolation when enlarging.
    """
    support = max(1.0, 1.0 / scale)
    centres = (np.arange(n_out) + out_origin + 0.5) / scale - 0.5 - in_origin
    first = np.floor(centres - support).astype(np.int64) + 1
    width = math.ceil(2 * support) + 1
    idx = first[:, None] + np.arange(width)[None, :]
    weights = np.maximum(0.0, 1.0 - np.abs(idx - centres[:, None]) / support)
    weights[(idx < 0) | (idx >= n_in)] = 0.0
    total = weights.sum(axis=1, keepdims=True)
    weights = np.divide(weights, total, out=np.zeros_like(weights), where=total > 0)
    rows = np.repeat(np.arange(n_out), width)
    matrix = scipy.sparse.csr_matrix((weights.ravel().astype(np.float32), (rows, np.clip(idx, 0, n_in - 1).ravel())),
                                     shape=(n_out, n_in))
    matrix.eliminate_zeros()
    return matrix


def resample(array: np.ndarray, scale: float | tuple[float, float], shape: tuple[int, int] | None = None, *,
             out_origin: tuple[int, int] = (0, 0), in_origin: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """Resample a 2-D array by ``scale`` (output pixels per input pixel) with an antialiased triangle kernel.

    Parameters
    ----------
    array : ndarray, (H, W)
    scale : float or (float, float)
        Per axis if a pair.
    shape : (int, int), optional
        Output shape (default ``round(scale·(H, W))``).
    out_origin, in_origin
        Where the two grids start in a common frame (output pixels of the resampled frame, input pixels
        of the original): a region cut from a frame at ``t`` maps to the resampled frame's pixel grid
        exactly when ``in_origin = t`` and ``out_origin = ⌈t·s⌉``.

    Returns
    -------
    ndarray, float32
    """
    a = np.asarray(array, np.float32)
    if a.ndim != 2:
        raise InputError(f"resample: need a 2-D array, got shape {a.shape}")
    sy, sx = (float(scale), float(scale)) if np.ndim(scale) == 0 else (float(scale[0]), float(scale[1]))  # type: ignore[index]
    if sy <= 0 or sx <= 0:
        raise UsageError(f"resample: scale {scale} must be positive")
    if shape is None:
        shape = (max(1, round(a.shape[0] * sy)), max(1, round(a.shape[1] * sx)))
    ay = _resample_matrix(a.shape[0], int(shape[0]), sy, out_origin[0], in_origin[0])
    ax = _resample_matrix(a.shape[1], int(shape[1]), sx, out_origin[1], in_origin[1])
    rows = ay @ a                       # (h_out, W)
    out = (ax @ rows.T).T               # (h_out, w_out)
    return np.ascontiguousarray(out, dtype=np.float32)


# ----------------------------------------------------------------------------- references and geometry


@dataclass(frozen=True)
class _Reference:
    """A candidate fingerprint with what every query needs of it."""

    device_id: str
    fingerprint: Fingerprint
    region: Region
    origin: tuple[int, int] | None      # top-left of the region in the frame; None for 'corners'
    sketch: np.ndarray | None = None    # unit-norm sketch of K (pre-screen)

    @property
    def frame(self) -> tuple[int, int]:
        return int(self.fingerprint.frame_shape[0]), int(self.fingerprint.frame_shape[1])


@dataclass(frozen=True)
class _Test:
    """One (rotation, scale) of one fingerprint for one query, with its search geometry."""

    rotation: int
    scale: float
    scale_yx: tuple[float, float]
    aligned: bool
    n_positions: int
    k_shape: tuple[int, int] = (0, 0)          # the (resampled) fingerprint's shape
    k_origin: tuple[int, int] = (0, 0)         # its top-left in the resampled frame
    canvas: tuple[int, int] = (0, 0)
    centre: tuple[int, int] = (0, 0)           # query origin in K's coordinates at zero shift
    radius: tuple[int, int] = (0, 0)


def _axis_range(q: int, k: int, f: int, t: int, crop_search: bool) -> tuple[int, int] | None:
    """Offsets δ (query origin in the fingerprint region's coordinates) searched along one axis, or None.

    The query (length ``q``) lies inside the region (length ``k``, at ``t`` in a frame of length ``f``)
    or the region inside the query, and the query inside the frame.  Without a crop search only a whole
    frame (up to the rounding of a resize) is accepted.
    """
    if q > f or (not crop_search and q < f - _SIZE_SLACK):
        return None
    lo = max(min(0, k - q), -t)
    hi = min(max(0, k - q), f - q - t)
    return (lo, hi) if lo <= hi else None


def _crop_test(rot: int, scale: float, scale_yx: tuple[float, float], shape: tuple[int, int], ref: _Reference,
               crop_search: bool) -> _Test | None:
    """The geometry of searching a (rotated) query of ``shape`` in ``ref`` resampled by ``scale_yx``."""
    fh, fw = ref.frame
    assert ref.origin is not None
    sy, sx = scale_yx
    frame_s = (max(1, round(fh * sy)), max(1, round(fw * sx)))
    kh, kw = ref.fingerprint.K.shape
    if scale_yx == (1.0, 1.0):
        k_shape, k_origin = (kh, kw), ref.origin
    else:
        k_origin = (math.ceil(ref.origin[0] * sy - 1e-9), math.ceil(ref.origin[1] * sx - 1e-9))
        k_shape = (max(1, min(round(kh * sy), frame_s[0] - k_origin[0])),
                   max(1, min(round(kw * sx), frame_s[1] - k_origin[1])))
    ranges = [_axis_range(q, k, f, t, crop_search) for q, k, f, t in zip(shape, k_shape, frame_s, k_origin)]
    if ranges[0] is None or ranges[1] is None:
        return None
    canvas = (max(shape[0], k_shape[0]), max(shape[1], k_shape[1]))
    if min(canvas) < 22:  # the PCE's 11×11 exclusion window needs room
        return None
    centre, radius, count = [], [], 1
    for (lo, hi), size in zip(ranges, canvas):
        c = (lo + hi) // 2
        r = max(hi - c, c - lo)
        centre.append(c)
        radius.append(r)
        count *= min(2 * r + 1, size)  # as forensics.prnu.match._shift_indices searches
    return _Test(rot, scale, scale_yx, False, count, k_shape, k_origin, canvas, (centre[0], centre[1]),
                 (radius[0], radius[1]))


def _rotated(shape: tuple[int, int], rot: int) -> tuple[int, int]:
    return (shape[1], shape[0]) if rot % 2 else (shape[0], shape[1])


def _rotations(spec: Any, shape: tuple[int, int], frame: tuple[int, int], max_scale: float) -> tuple[int, ...]:
    """Quarter turns to try for an image of ``shape`` against a frame (module notes)."""
    limit = (round(frame[0] * max_scale) + _SIZE_SLACK, round(frame[1] * max_scale) + _SIZE_SLACK)

    def fits(rot: int) -> bool:
        h, w = _rotated(shape, rot)
        return h <= limit[0] and w <= limit[1]

    if isinstance(spec, str):
        if spec == "none":
            return (0,) if fits(0) else ()
        if spec == "auto":
            if fits(0):
                return (0,)
            return (1, 3) if fits(1) else ()
        if spec == "all":
            return tuple(r for r in range(4) if fits(r))
        raise UsageError(f"rotations={spec!r}: choose one of {', '.join(_ROTATION_MODES)}, or give quarter turns")
    turns = (int(spec),) if np.ndim(spec) == 0 else tuple(int(r) for r in spec)
    return tuple(sorted({r % 4 for r in turns if fits(r % 4)}))


def _scales_for(search: ScaleSearch | None, shape: tuple[int, int], frame: tuple[int, int]
                ) -> list[tuple[float, tuple[float, float]]]:
    """(nominal scale, per-axis scales) to try for a (rotated) query of ``shape``: the grid, and the scale its
    size implies if it is a whole frame resized with its aspect ratio."""
    if search is None:
        return [(1.0, (1.0, 1.0))]
    # the query must fit in the resampled frame (up to the rounding of a resize)
    floor = max((shape[0] - _SIZE_SLACK) / frame[0], (shape[1] - _SIZE_SLACK) / frame[1])
    out = [(s, (s, s)) for s in search.grid(max(shape), floor)]
    if search.from_size:
        h, w = shape
        sy, sx = h / frame[0], w / frame[1]
        lo, hi = search.bounds()
        # both axes agree up to the rounding of the size; a scale already on the grid is not tried twice
        if abs(round(frame[0] * sx) - h) <= 1 and lo <= sx <= hi and all(abs(s - sx) > 1e-9 for s, _ in out):
            out.append((sx, (sy, sx)))
    return out


def _scale_info(search: ScaleSearch | None, shape: tuple[int, int]) -> dict[str, Any] | None:
    """The scale grid of a query, as reported."""
    if search is None:
        return None
    side = max(shape)
    grid = search.grid(side, check=False)
    error = search.grid_error(side)
    return {"n_grid": len(grid), "lo": min(grid), "hi": max(grid),
            "grid_error_px": None if math.isnan(error) else error, "from_size": search.from_size,
            "note": "scales at which the image does not fit in a fingerprint's frame are not searched"}


def _plan(shape: tuple[int, int], ref: _Reference, settings: _Settings) -> list[_Test]:
    """Every (rotation, scale) test of a query of ``shape`` against ``ref``; empty if incompatible."""
    fp_frame = ref.frame
    search = settings.scales
    max_scale = search.bounds()[1] if search is not None else 1.0
    tests: list[_Test] = []
    for rot in _rotations(settings.rotations, shape, fp_frame, max_scale):
        rshape = _rotated(shape, rot)
        for scale, scale_yx in _scales_for(search, rshape, fp_frame):
            if scale_yx == (1.0, 1.0) and rshape == fp_frame:
                tests.append(_Test(rot, 1.0, (1.0, 1.0), True, 1))
            elif ref.origin is not None and (settings.crop_search or scale_yx != (1.0, 1.0)):
                test = _crop_test(rot, scale, scale_yx, rshape, ref, settings.crop_search)
                if test is not None:
                    tests.append(test)
    return tests


# ----------------------------------------------------------------------------- the pre-screen's sketch


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


# ----------------------------------------------------------------------------- work items


@dataclass(frozen=True)
class _Settings:
    """What every query is identified with (the work items' shared data)."""

    refs: tuple[_Reference, ...]
    top_k: int
    pfa: float
    rotations: Any
    scales: ScaleSearch | None
    crop_search: bool
    prescreen: Prescreen | None
    sigma: float
    exclusion: int
    workers: int | None
    query_options: dict[str, Any] = field(default_factory=dict)


class _QueryImage:
    """One query: its residuals and spectra, each computed once and reused for every fingerprint."""

    def __init__(self, image: np.ndarray, source: str, settings: _Settings) -> None:
        if image.ndim not in (2, 3):
            raise InputError(f"{source}: array of shape {image.shape} is not an image")
        self.shape = (int(image.shape[0]), int(image.shape[1]))
        self.source = source
        self.workers = default_workers() if settings.workers is None else settings.workers
        self.prepared = _PreparedImage(image, source, settings.sigma, self.workers, settings.query_options)
        self._products: dict[tuple[str, int], np.ndarray] = {}
        self._spectra: dict[tuple[Any, ...], _Spectrum] = {}
        self._sketches: dict[tuple[str, int, int, int], np.ndarray] = {}

    def product(self, region: str, rot: int) -> np.ndarray:
        """Zero-mean ``W·I`` (residual times intensity), float32.

        ``region='full'`` with a rotation: the whole image's residual turned (one residual per image
        for the crop and scale searches); another region: the residual of that region of the turned image.
        """
        key = (region, rot)
        if key not in self._products:
            if region == "full":
                q, _ = self.prepared.get("full", 0, False)
                p = np.rot90(q.residual * q.intensity, rot)
            else:
                q, _ = self.prepared.get(region, rot, False)
                p = q.residual * q.intensity
            self._products[key] = _centred(np.ascontiguousarray(p))
        return self._products[key]

    def canvas_spectrum(self, test: _Test) -> _Spectrum:
        """Spectrum of the query's ``W·I`` zero-padded to the test's canvas, its origin at the canvas' centre offset."""
        key = (test.rotation, test.canvas, test.centre)
        if key not in self._spectra:
            p = self.product("full", test.rotation)
            canvas = np.zeros(test.canvas, np.float32)
            canvas[: p.shape[0], : p.shape[1]] = p
            canvas = np.roll(canvas, test.centre, axis=(0, 1))
            self._spectra[key] = _Spectrum(canvas, self.workers)
        return self._spectra[key]

    def sketch(self, region: str, rot: int, dim: int, seed: int) -> np.ndarray:
        key = (region, rot, dim, seed)
        if key not in self._sketches:
            self._sketches[key] = sketch(self.product(region, rot), dim, seed)
        return self._sketches[key]


def _log_tail(z: float, weight: float) -> float:
    """``log(Q(z)/weight)``: a peak's tail in a weighted search (smaller is stronger)."""
    return float(special.log_ndtr(-z)) - math.log(weight)


def _z(pce_value: float) -> float:
    return math.copysign(math.sqrt(abs(pce_value)), pce_value)


@dataclass(frozen=True)
class _Peak:
    """The block-phase PCE of one correlation surface (see :func:`_block_pce`)."""

    pce: float
    pce_global: float
    shift: tuple[int, int]
    sign: int
    ncc: float
    weight: float = 1.0          # the peak's share of the weighted search (see _grid_phase)


def _surface(spectrum: _Spectrum, reference: np.ndarray) -> tuple[np.ndarray, float]:
    """Circular cross-correlation of the spectrum's array with ``reference`` (as :func:`forensics.prnu.match.pce`)."""
    b0 = _centred(reference)
    norm_b = math.sqrt(_sum_sq(b0))
    spec = scipy.fft.rfft2(b0, workers=spectrum.workers)
    del b0
    np.conjugate(spec, out=spec)
    spec *= spectrum.spec
    return scipy.fft.irfft2(spec, s=spectrum.shape, workers=spectrum.workers), norm_b


def _phases(n: int) -> np.ndarray:
    """Block phase ``shift mod BLOCK`` of every circular shift index, shifts taken in ``(−n/2, n/2]``."""
    idx = np.arange(n)
    return np.where(idx > n // 2, idx - n, idx) % BLOCK


def _block_pce(corr: np.ndarray, rows: np.ndarray, cols: np.ndarray, exclusion: int, norms: float) -> _Peak:
    """Peak of ``corr`` over ``rows × cols`` normalised by the energy of the shifts in its block phase.

    JPEG's 8×8 blocks make the null variance of the correlation periodic in the shift: on the Dresden
    JPEGs, the shifts that align the query's block grid with the fingerprint's have 1.6–1.85 times the
    mean energy (others 0.8), and the plain PCE, with one energy for all shifts, then exceeds its χ²₁
    tail there (non-matching Dresden pairs: PCE 21 at zero shift, many crop searches above the Šidák
    bound).  Each shift's ``z`` is therefore the correlation over the root-mean-square of the shifts with
    the same phase ``(dy mod 8, dx mod 8)`` (the ``exclusion`` window around the peak left out, as in the
    PCE), shrunk towards the all-shift energy by :data:`PHASE_PRIOR` shifts so that a small canvas's noisy
    phase energies do not themselves inflate ``z``.  On images without blocks all phases agree and the
    statistic is the PCE.
    """
    h, w = corr.shape
    half = exclusion // 2
    if h < 2 * exclusion or w < 2 * exclusion:
        raise InputError(f"a correlation of shape {corr.shape} is too small for PCE with a {exclusion}×{exclusion} "
                         "exclusion window")
    ry, rx = _phases(h), _phases(w)
    one_y = (ry[None, :] == np.arange(BLOCK)[:, None]).astype(np.float64)   # (BLOCK, h)
    one_x = (rx[:, None] == np.arange(BLOCK)[None, :]).astype(np.float64)   # (w, BLOCK)
    sq = np.square(corr, dtype=np.float64)
    sums = one_y @ sq @ one_x
    del sq
    counts = np.outer(one_y.sum(axis=1), one_x.sum(axis=0))

    def energies(s: np.ndarray, c: np.ndarray) -> np.ndarray:
        overall = s.sum() / c.sum()
        return (s + PHASE_PRIOR * overall) / (c + PHASE_PRIOR)

    energy = energies(sums, counts)
    sub = corr[np.ix_(rows, cols)] / np.sqrt(energy[np.ix_(ry[rows], rx[cols])])
    (iy, ix), weight = _weighted_argmax(sub, ry[rows], rx[cols], _grid_phase(sums, counts))
    py, px = int(rows[iy]), int(cols[ix])
    # leave the window around the peak out of the energies
    wr = np.unique((py + np.arange(-half, half + 1)) % h)
    wc = np.unique((px + np.arange(-half, half + 1)) % w)
    window = np.square(corr[np.ix_(wr, wc)], dtype=np.float64)
    win_y = (ry[wr][None, :] == np.arange(BLOCK)[:, None]).astype(np.float64)
    win_x = (rx[wc][:, None] == np.arange(BLOCK)[None, :]).astype(np.float64)
    sums -= win_y @ window @ win_x
    counts -= np.outer(win_y.sum(axis=1), win_x.sum(axis=0))
    np.maximum(sums, 0.0, out=sums)
    energy = energies(sums, counts)
    peak = float(corr[py, px])
    dy = py - h if py > h // 2 else py
    dx = px - w if px > w // 2 else px
    e_phase = float(energy[ry[py], rx[px]])
    e_all = float(sums.sum() / counts.sum())
    if e_phase <= 0.0 or e_all <= 0.0 or norms == 0.0:
        return _Peak(0.0, 0.0, (dy, dx), 0, 0.0)
    sign = 1 if peak > 0 else (-1 if peak < 0 else 0)
    return _Peak(sign * peak * peak / e_phase, sign * peak * peak / e_all, (int(dy), int(dx)), sign,
                 float(np.clip(peak / norms, -1.0, 1.0)), weight)


def _grid_phase(sums: np.ndarray, counts: np.ndarray) -> tuple[int, int] | None:
    """The block phase of the shifts that align the query's JPEG grid with the fingerprint's, if any.

    Under the null the correlation's variance at shift ``s`` is ``Σ_p v_q(p)·v_K(p + s)`` over the
    block phases ``p`` of the two arrays' variances; when both are periodic alike (JPEG: noisier
    block boundaries) it is largest at the aligning phase (rearrangement inequality).  A phase counts
    as the grid when its energy exceeds the mean by :data:`GRID_MIN_EXCESS` and by :data:`GRID_SIGMAS`
    standard errors of an energy estimated from that many shifts (``√(2/m)`` for a white surface), so
    images without blocks (PNG, simulations, resampled fingerprints) have none.  The choice depends
    on the energies only, not on the normalised peaks, so it leaves the null of ``z`` unchanged.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_phase = sums / counts
    overall = float(sums.sum() / counts.sum())
    if not overall > 0.0:
        return None
    a = np.unravel_index(int(np.nanargmax(mean_phase)), mean_phase.shape)
    excess = float(mean_phase[a]) / overall - 1.0
    if excess < max(GRID_MIN_EXCESS, GRID_SIGMAS * math.sqrt(2.0 / float(counts[a]))):
        return None
    return int(a[0]), int(a[1])


def _weighted_argmax(z: np.ndarray, phase_rows: np.ndarray, phase_cols: np.ndarray,
                     grid: tuple[int, int] | None) -> tuple[tuple[int, int], float]:
    """The position of ``z`` with the smallest weighted tail ``Q(z)/w``, and its weight ``w``.

    Weighted Bonferroni over one test's ``n`` positions: the grid-aligned ones (``n_A``, the phase
    :func:`_grid_phase` found) share :data:`GRID_SHARE` of the false-alarm budget (``w_A = share·n/n_A``),
    the others the rest (``w_R = (1 − share)·n/n_R``); the weights sum to ``n``, so the Šidák count is
    unchanged and the bound holds whichever class the true offset is in.  A crop cut from a decoded
    JPEG sits on the grid (threshold of ``n/w_A`` positions: PCE 33 instead of 40 for 1024² crops of a
    3008×2000 frame at p_FA 10⁻³); one re-encoded after cropping has its own grid and is searched at
    ``n/w_R`` (PCE 41.5).  Without a grid every weight is 1 and this is the plain argmax.
    """
    flat = int(np.argmax(z))
    best = np.unravel_index(flat, z.shape)
    if grid is None:
        return (int(best[0]), int(best[1])), 1.0
    on_rows, on_cols = phase_rows == grid[0], phase_cols == grid[1]
    n = z.size
    n_a = int(on_rows.sum()) * int(on_cols.sum())
    if n_a == 0 or n_a == n:
        return (int(best[0]), int(best[1])), 1.0
    w_a, w_r = GRID_SHARE * n / n_a, (1.0 - GRID_SHARE) * n / (n - n_a)
    ra, ca = np.flatnonzero(on_rows), np.flatnonzero(on_cols)
    za = z[np.ix_(ra, ca)]
    ia = np.unravel_index(int(np.argmax(za)), za.shape)
    pos_a = (int(ra[ia[0]]), int(ca[ia[1]]))
    masked = z.copy()
    masked[np.ix_(ra, ca)] = -np.inf
    ib = np.unravel_index(int(np.argmax(masked)), masked.shape)
    pos_r = (int(ib[0]), int(ib[1]))
    return (pos_a, w_a) if _log_tail(z[pos_a], w_a) <= _log_tail(z[pos_r], w_r) else (pos_r, w_r)


def _run_test(query: _QueryImage, ref: _Reference, test: _Test, exclusion: int) -> tuple[_Peak, tuple[int, int]]:
    """Block-phase PCE of one test, and the query's top-left in the (resampled) frame at the peak."""
    k = ref.fingerprint.K
    if test.aligned:
        q, spectrum = query.prepared.get(ref.region.spec, test.rotation, True)
        assert spectrum is not None
        corr, norm_b = _surface(spectrum, q.intensity * k)
        zero = np.zeros(1, np.int64)
        return _block_pce(corr, zero, zero, exclusion, spectrum.norm * norm_b), (0, 0)
    if test.scale_yx != (1.0, 1.0):
        assert ref.origin is not None
        k = resample(k, test.scale_yx, test.k_shape, out_origin=test.k_origin, in_origin=ref.origin)
    reference = np.zeros(test.canvas, np.float32)
    reference[: test.k_shape[0], : test.k_shape[1]] = _centred(k)
    spectrum = query.canvas_spectrum(test)
    corr, norm_b = _surface(spectrum, reference)
    del reference
    rows = _shift_indices(test.radius[0], test.canvas[0])
    cols = _shift_indices(test.radius[1], test.canvas[1])
    peak = _block_pce(corr, rows, cols, exclusion, spectrum.norm * norm_b)
    # the query sits at δ = centre − shift in K's coordinates (shift convention of forensics.prnu.match.pce)
    dy, dx = peak.shift
    offset = (test.k_origin[0] + test.centre[0] - dy, test.k_origin[1] + test.centre[1] - dx)
    return peak, offset


def _score_reference(query: _QueryImage, ref: _Reference, tests: list[_Test], exclusion: int,
                     sketch_score: float | None) -> Candidate:
    """The best of a fingerprint's tests, with its own search-corrected p_FA."""
    best: tuple[float, _Peak, _Test, tuple[int, int]] | None = None
    for test in tests:
        peak, offset = _run_test(query, ref, test, exclusion)
        tail = _log_tail(_z(peak.pce), peak.weight)
        if best is None or tail < best[0]:
            best = (tail, peak, test, offset)
    assert best is not None
    _, peak, test, offset = best
    n = sum(t.n_positions for t in tests)
    p_fa, log10 = _false_alarm(_z(peak.pce), n, peak.weight) if peak.sign != 0 else (1.0, 0.0)
    method = "aligned" if test.aligned else ("crop" if test.scale_yx == (1.0, 1.0) else "scale")
    return Candidate(ref.device_id, float(peak.pce), p_fa, log10, peak.ncc, test.rotation, float(test.scale),
                     (int(offset[0]), int(offset[1])), int(n), method, sketch_score, float(peak.pce_global),
                     float(peak.weight))


def _screen(query: _QueryImage, settings: _Settings, plans: list[list[_Test]]) -> dict[int, float]:
    """Sketch z-scores of the fingerprints whose every test is aligned (max over their rotations)."""
    pre = settings.prescreen
    assert pre is not None
    scores: dict[int, float] = {}
    for j, (ref, tests) in enumerate(zip(settings.refs, plans)):
        if not tests or ref.sketch is None or not all(t.aligned for t in tests):
            continue
        dim = ref.sketch.size
        values = [float(query.sketch(ref.region.spec, t.rotation, dim, pre.seed) @ ref.sketch) for t in tests]
        scores[j] = math.sqrt(dim) * max(values)
    return scores


def _load_query(payload: Any, index: int) -> tuple[np.ndarray, str]:
    if isinstance(payload, (str, os.PathLike)):
        from forensics.io.images import read_image

        return read_image(payload), str(payload)
    if hasattr(payload, "load") and not isinstance(payload, np.ndarray):
        name = getattr(payload, "file", None) or str(getattr(payload, "path", "")) or f"query[{index}]"
        return np.asarray(payload.load()), str(name)
    return np.asarray(payload), f"query[{index}]"


def _identify_item(settings: _Settings, item: tuple[int, Any]) -> QueryIdentification:
    """Work item: one query against every compatible fingerprint."""
    index, payload = item
    image, source = _load_query(payload, index)
    query = _QueryImage(image, source, settings)
    del image
    plans = [_plan(query.shape, ref, settings) for ref in settings.refs]
    compatible = [j for j, tests in enumerate(plans) if tests]
    n_tests = sum(t.n_positions for tests in plans for t in tests)
    scale_info = _scale_info(settings.scales, query.shape)
    if not compatible:
        note = (f"no fingerprint is compatible with this {query.shape[1]}×{query.shape[0]} image (size, orientation"
                + (", scales searched" if settings.scales is not None else "; a resized image needs a scale search")
                + ")")
        return QueryIdentification(source, query.shape, "unknown", None, None, None, (), 1.0, 0.0, math.inf, 0, 0, 0,
                                   None, scale_info, note)
    chosen, sketch_scores, pre_info = _prescreen(query, settings, plans, compatible)
    candidates = [_score_reference(query, settings.refs[j], plans[j], settings.exclusion, sketch_scores.get(j))
                  for j in chosen]
    candidates.sort(key=lambda c: (c.log_tail, c.device_id))
    best = candidates[0]
    p_fa, log10 = _false_alarm(best.z, n_tests, best.search_weight) if best.pce != 0 else (1.0, 0.0)
    attributed = best.z > 0 and p_fa <= settings.pfa
    return QueryIdentification(
        source, query.shape, "attributed" if attributed else "unknown", best.device_id if attributed else None,
        best, candidates[1] if len(candidates) > 1 else None, tuple(candidates[: settings.top_k]), p_fa, log10,
        pce_threshold(settings.pfa, n_tests / best.search_weight), int(n_tests), len(compatible), len(candidates),
        pre_info, scale_info)


def _prescreen(query: _QueryImage, settings: _Settings, plans: list[list[_Test]], compatible: list[int]
               ) -> tuple[list[int], dict[int, float], dict[str, Any] | None]:
    """The fingerprints that get the full PCE, their sketch scores, and the pre-screen's figures."""
    pre = settings.prescreen
    if pre is None:
        return compatible, {}, None
    keep = pre.keep_for(len(settings.refs))
    scores = _screen(query, settings, plans)
    if len(scores) <= keep:
        return compatible, {}, {"ran": False, "reason": f"{len(scores)} aligned candidates, keep {keep}"}
    ranked = sorted(scores, key=lambda j: (-scores[j], j))
    kept = set(ranked[:keep])
    chosen = [j for j in compatible if j in kept or j not in scores]
    dims = sorted({settings.refs[j].sketch.size for j in scores})  # type: ignore[union-attr]
    info = {"ran": True, "screened": len(scores), "kept": len(kept), "dropped": len(scores) - len(kept),
            "dim": dims[0] if len(dims) == 1 else dims, "lowest_kept_score": scores[ranked[keep - 1]]}
    return chosen, scores, info


# ----------------------------------------------------------------------------- the drivers


def _references(fingerprints: Any) -> tuple[tuple[_Reference, ...], list[dict[str, Any]]]:
    """The candidates (loaded once, here) from a database or from ``(id, Fingerprint)`` pairs."""
    pairs: list[tuple[Any, Fingerprint]]
    if hasattr(fingerprints, "entries") and hasattr(fingerprints, "load"):
        pairs = [(entry, fingerprints.load(entry.device_id)) for entry in fingerprints.entries()]
    else:
        pairs = []
        for item in fingerprints:
            try:
                ident, fp = item
            except (TypeError, ValueError):
                raise UsageError("fingerprints: give a FingerprintDatabase or (device id, Fingerprint) pairs") from None
            pairs.append((ident, fp))
    if not pairs:
        raise UsageError("no fingerprints to identify against; add some to the database first")
    refs, devices, seen = [], [], set()
    for ident, fp in pairs:
        device_id = str(getattr(ident, "device_id", ident))
        if device_id in seen:
            raise UsageError(f"device id {device_id!r} appears twice among the fingerprints")
        seen.add(device_id)
        if not isinstance(fp, Fingerprint):
            raise UsageError(f"{device_id}: {type(fp).__name__} is not a Fingerprint")
        region = parse_region(fp.region)
        origin = None
        if region.kind != "corners":
            rows, cols = region.pieces(fp.frame_shape)[0]
            origin = (int(rows.start), int(cols.start))
        refs.append(_Reference(device_id, fp, region, origin))
        info = ident.to_dict() if hasattr(ident, "to_dict") else {"device_id": device_id}
        info = {k: v for k, v in info.items() if k != "provenance"}
        devices.append(info)
    return tuple(refs), devices


def _with_sketches(refs: tuple[_Reference, ...], pre: Prescreen | None) -> tuple[_Reference, ...]:
    """The references with their fingerprints' sketches (computed once, here, in the driver)."""
    if pre is None:
        return refs
    return tuple(replace(r, sketch=sketch(r.fingerprint.K, pre.dim(r.fingerprint.K.size), pre.seed).astype(np.float32))
                 for r in refs)


def _scale_search(scales: Any) -> ScaleSearch | None:
    if scales is None:
        return None
    if isinstance(scales, ScaleSearch):
        return scales
    if isinstance(scales, str):
        return ScaleSearch() if scales == "auto" else parse_scales(scales)
    if np.ndim(scales) == 0:
        return ScaleSearch(values=(float(scales),))
    return ScaleSearch(values=tuple(float(s) for s in scales))


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


def _query_items(queries: Any, executor: Executor) -> tuple[list[tuple[int, Any]], str | None]:
    name = None
    if hasattr(queries, "frames") and hasattr(queries, "root"):  # a Dataset
        name = str(queries.root)
        queries = queries.frames
    if isinstance(queries, (np.ndarray, str, os.PathLike)):
        raise UsageError("queries: give a sequence of images, paths or frames (or a Dataset), not a single one")
    items = list(enumerate(queries))
    if executor.backend != "in-process" and not all(_is_reference(p) for _, p in items):
        raise UsageError("identification on worker processes or a cluster reads every query from its file: give "
                         "image paths or dataset frames, not arrays (or use the in-process executor)")
    return items, name


def _check_options(top_k: int, pfa: float, rotations: Any) -> None:
    if top_k < 1:
        raise UsageError(f"top_k={top_k}: list at least one candidate")
    if not (0.0 < pfa < 1.0):
        raise UsageError(f"pfa={pfa}: the false-alarm probability must be in (0, 1)")
    if isinstance(rotations, str) and rotations not in _ROTATION_MODES:
        raise UsageError(f"rotations={rotations!r}: choose one of {', '.join(_ROTATION_MODES)}, or give quarter turns")


def identify(
    queries: Iterable[Any],
    fingerprints: Any,
    *,
    top_k: int = 3,
    pfa: float = DEFAULT_PFA,
    rotations: str | int | Sequence[int] = "auto",
    scales: ScaleSearch | str | float | Sequence[float] | None = None,
    crop_search: bool = True,
    prescreen: Prescreen | str | bool | None = None,
    sigma: float = QUERY_SIGMA,
    exclusion: int = 11,
    workers: int | None = None,
    executor: Executor | None = None,
    progress: Progress = no_progress,
    **query_options: Any,
) -> IdentificationResult:
    """Identify the device of each query image among a set of fingerprints (module notes).

    Parameters
    ----------
    queries : sequence or Dataset
        Image arrays, image paths or dataset frames (objects with ``load()``); on worker processes or a
        cluster, paths or frames (each worker reads its query).
    fingerprints : FingerprintDatabase or sequence of (id, Fingerprint)
        ``id`` a device id or a :class:`~forensics.prnu.database.DeviceEntry`; all are loaded once here.
    top_k : int
        Candidates listed per image.
    pfa : float
        False-alarm probability of an attribution, corrected for every fingerprint, position, scale and
        rotation searched (Šidák, module notes).
    rotations : {'auto', 'none', 'all'} or quarter turns
    scales : None, 'auto', 'LO:HI[:STEP]', ScaleSearch or scales
        None: scale 1 only; 'auto': :class:`ScaleSearch` over 0.5–1.0 with a grid error ≤ 0.5 pixel.
    crop_search : bool
        Search the offset of images smaller than the (resampled) frame.
    prescreen : None/'off', 'auto', 'on' or Prescreen
        'auto': on for more than :data:`PRESCREEN_AUTO_MIN` fingerprints.
    sigma, exclusion
        Query residual noise level (8-bit scale) and the PCE's exclusion window.
    workers : int, optional
        FFT and wavelet threads per query.
    executor : Executor, optional
        One work item per query; default in this process.
    progress : callable
        Counts queries.
    **query_options
        Passed to :func:`forensics.prnu.match.prepare_query` (white_level, black_level, ...).

    Returns
    -------
    IdentificationResult
    """
    _check_options(top_k, pfa, rotations)
    search = _scale_search(scales)
    ex = resolve(executor)
    refs, devices = _references(fingerprints)
    pre = _prescreen_config(prescreen, len(refs))
    refs = _with_sketches(refs, pre)
    settings = _Settings(refs, int(top_k), float(pfa), rotations, search, bool(crop_search), pre, float(sigma),
                         int(exclusion), workers, dict(query_options))
    name = str(queries.root) if hasattr(queries, "frames") and hasattr(queries, "root") else None
    if ex.backend == "in-process" and not hasattr(queries, "__len__") and not hasattr(queries, "frames"):
        # an iterator of images: identified as it is consumed, never held as a list
        results = [_identify_item(settings, item) for item in progress(enumerate(queries), desc="identifying")]
    else:
        items, name = _query_items(queries, ex)
        results = list(ex.map(_identify_item, items, shared=settings, progress=progress, desc="identifying"))
    return IdentificationResult(results, devices, float(pfa), _settings_dict(settings, prescreen), CORRECTION, name)


def _settings_dict(settings: _Settings, requested: Any) -> dict[str, Any]:
    return {"top_k": settings.top_k, "rotations": settings.rotations if isinstance(settings.rotations, str)
            else list(np.atleast_1d(settings.rotations).tolist()),
            "scales": settings.scales.to_dict() if settings.scales is not None else None,
            "crop_search": settings.crop_search,
            "prescreen": settings.prescreen.to_dict() if settings.prescreen is not None else None,
            "prescreen_requested": requested if isinstance(requested, (str, bool)) or requested is None else "custom",
            "prescreen_auto_min": PRESCREEN_AUTO_MIN, "sigma": settings.sigma, "exclusion": settings.exclusion}


# ----------------------------------------------------------------------------- measuring the pre-screen


def _rank_item(settings: _Settings, item: tuple[int, Any]) -> tuple[dict[str, float], bool]:
    """Work item of :func:`prescreen_miss_rate`: every aligned fingerprint's sketch score for one query."""
    index, payload = item
    image, source = _load_query(payload, index)
    query = _QueryImage(image, source, settings)
    plans = [_plan(query.shape, ref, settings) for ref in settings.refs]
    scores = _screen(query, settings, plans)
    return {settings.refs[j].device_id: s for j, s in scores.items()}, bool(scores)


def prescreen_miss_rate(
    queries: Iterable[Any],
    truth: Sequence[str | None],
    fingerprints: Any,
    prescreen: Prescreen | None = None,
    *,
    rotations: str | int | Sequence[int] = "auto",
    sigma: float = QUERY_SIGMA,
    executor: Executor | None = None,
    progress: Progress = no_progress,
    **query_options: Any,
) -> PrescreenMissRate:
    """How often the pre-screen drops the true device, on queries of known devices.

    Only the sketch stage runs (no full PCE).  Queries whose device is not among the fingerprints
    (``truth`` None or unknown) or that are not aligned (crops, other sizes) are skipped and counted.

    Parameters
    ----------
    queries : sequence or Dataset
        As :func:`identify`.
    truth : sequence of str or None
        The true device id of each query.
    fingerprints : FingerprintDatabase or sequence of (id, Fingerprint)
    prescreen : Prescreen, optional
        Default :class:`Prescreen` ``()``.

    Returns
    -------
    PrescreenMissRate
    """
    from forensics.stats.counts import clopper_pearson

    pre = prescreen or Prescreen()
    ex = resolve(executor)
    items, _ = _query_items(queries, ex)
    if len(truth) != len(items):
        raise UsageError(f"{len(truth)} true devices for {len(items)} queries; give one per query")
    refs, _ = _references(fingerprints)
    refs = _with_sketches(refs, pre)
    settings = _Settings(refs, 1, DEFAULT_PFA, rotations, None, False, pre, float(sigma), 11, None,
                         dict(query_options))
    keep = pre.keep_for(len(refs))
    ranks, scores, skipped = [], [], 0
    for (scored, aligned), device in zip(ex.map(_rank_item, items, shared=settings, progress=progress,
                                                desc="pre-screen"), truth):
        if not aligned or device is None or str(device) not in scored:
            skipped += 1
            continue
        own = scored[str(device)]
        ranks.append(sum(1 for v in scored.values() if v > own))
        scores.append(own)
    n = len(ranks)
    missed = sum(1 for r in ranks if r >= keep)
    ci = clopper_pearson(missed, n) if n else (0.0, 1.0)
    dims = {r.sketch.size for r in refs if r.sketch is not None}
    return PrescreenMissRate(n, missed, missed / n if n else math.nan, (float(ci[0]), float(ci[1])), keep,
                             min(dims) if dims else 0, len(refs), tuple(ranks), tuple(float(s) for s in scores),
                             skipped)
