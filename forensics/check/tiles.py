"""The model check of whole frames, tile by tile: memory bounded by a tile, time linear in the pixels.

A whole-frame fit holds (conditions × frame) arrays — ≈ 0.66 KB per pixel and fitted condition since the
seventeenth session (2.2 KB before, when the cached inverses of the chain kept frame-sized tables), 12 GB for a 1 MP
series of 18 conditions (:func:`whole_frame_advice`).  Here the frame is cut into tiles of about ``size × size``
pixels; each tile is read (its region of every frame, with a halo of its neighbours' pixels) and checked on its own
— the whole check, memory of one tile per worker — and the tiles' results are combined:

* **Global parameters** (black level, conversion gain, dark rate, read noise …): each tile's estimate with its
  covariance is a quadratic approximation of that tile's log-likelihood; the tiles' pixels are disjoint
  (each pixel is scored in one tile only: the halo is the tiles' unscored border), so the whole frame's
  log-likelihood is their sum, and its maximum is the information-weighted combination
  ``θ̂ = (Σ Pₜ)⁻¹ Σ Pₜ θₜ`` with ``Pₜ = Cov(θₜ)⁻¹`` and covariance ``(Σ Pₜ)⁻¹`` — the normal equations summed
  over the tiles (the "aggregated estimating equation" estimator of Lin & Xi, Statistics and Its Interface 4,
  2011; asymptotically as efficient as the joint fit when every tile holds many pixels).
* **Are the parameters the same everywhere?**  ``Q = Σ (θₜ − θ̂)ᵀ Pₜ (θₜ − θ̂) / φₜ`` is χ² with
  ``Σ kₜ − k`` degrees of freedom if they are (Cochran's heterogeneity test, per parameter and jointly; φₜ ≥ 1
  the tile's own misfit, :func:`tile_dispersion`, so that a model that misfits everywhere alike is not read as a
  parameter that differs).  A
  dark rate or a gain that changes across the sensor — amplifier glow in a corner, a gain gradient — fails it:
  a spatial effect the model lacks, which one small region cannot show.
* **Tiles whose covariance is not a sampling variance** are left out of the combination of the parameter
  concerned (:func:`untrusted_estimates`): equal tiles under one design carry about the same information per
  pixel, so a tile that claims a hundred times the tiles' median (its standard error a tenth) has settled on a
  cusp or a degenerate optimum, not measured better; and a tile whose held-out error is ten times the tiles'
  median is not described by the model, so its curvature says nothing of its estimates' spread.  Without it,
  one such tile of the STL-1001E's whole frame (β ± 9·10⁻⁸ against the others' ± 5·10⁻³) set the combined β.
* **Parameters that are not combined** — held or not separable from another, on a bound, the largest of several
  values (a defect amplitude, whose tile estimates are skewed) — are listed with the reason and the tiles'
  values (:func:`uncombined_params`), so that the tiled check states every parameter one check would.
* **Errors** pool the tiles' squared held-out errors by their numbers of held-out means; **goodness of fit**
  combines the tiles' independent p-values (Fisher's method); **candidates** sum their score (LM) statistics
  over the tiles, each χ² with its degrees of freedom under the model (Holm-adjusted across candidates, flagged
  by the same rule as one check), and say in how many tiles each was flagged on its own.

What tiles give up: the pixel-local patterns of a pixel in a halo are fitted in each tile that reads it (only
its own tile scores it); random-effect patterns are centred per tile (their common mode is the tile's global
parameter, which the combination pools); defect arrival and placement are tested per tile.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from forensics.stats.tails import chi2_sf

from forensics._shared.errors import InputError, UsageError
from forensics._shared.progress import Progress, no_progress
from forensics._shared.rng import RngLike
from forensics.check.diagnosis import flag_rule
from forensics.check.measurements import Region
from forensics.check.result import ParamEstimate, PatternEstimate
from forensics.io.dataset import Dataset, open_dataset
from forensics.stats.multiple import holm_adjusted

if TYPE_CHECKING:
    from forensics._shared.parallel import Executor
    from forensics.check.result import CheckResult

#: Pixels of the neighbours read around each tile: the check's unscored border
#: (:func:`~forensics.check.measurements.load_measurements`' default, half the scene window), so that every
#: pixel of the frame's interior is scored in exactly one tile and its scene estimate sees all its neighbours.
HALO = 3


#: The smallest tile side: the check of a region needs a 7 × 7 scene window inside its 3-pixel border.
MIN_TILE = 16

#: Peak memory of a whole-frame ``--auto`` check per pixel and frame read (bytes): the EMVA 1288 simulator's
#: 216-frame series (320 × 240, 210 frames with content) peaked at 5.2–5.3 GB (benchmarks/RESULTS_check.md,
#: seventeenth session).  An estimate for advice, not a bound: it grows with the effects fitted.
WHOLE_FRAME_BYTES = 330
#: A whole-frame check estimated above this (bytes) is pointed to ``--tiles``.
TILES_ADVICE_BYTES = 2 * 2**30

#: A tile's estimate is left out of the combination when its standard error per pixel (× √ of its core's pixels)
#: is below the tiles' median by more than this factor, i.e. it claims 100 × the typical information.  Under the
#: model, tiles of one frame and design differ in information per pixel only by their content (vignetting, the
#: share of defects): on the STL-1001E's whole frame 0.74–1.14 of the median for the settled parameters, the
#: degenerate tiles 10⁻⁵; on the EMVA simulator's 1 MP series (64 tiles of 125²) 0.98–1.03.
PRECISION_LIMIT = 10.0
#: A tile whose misfit φ (:func:`tile_dispersion`, the square of its held-out error) exceeds the tiles' median
#: by more than this factor (ten times the typical held-out error) has every estimate left out: where the model
#: does not describe a tile, its curvature is not its estimates' variance (the STL-1001E tiles' φ: 3.3–37, median 4.9;
#: a tile that settled on a degenerate fit: 17,956).
MISFIT_LIMIT = 100.0


def whole_frame_advice(n_pixels: int, n_frames: int, limit: float = TILES_ADVICE_BYTES) -> str | None:
    """Advice to check tile by tile when one fit of ``n_frames`` frames of ``n_pixels`` pixels is estimated to
    hold more than ``limit`` bytes (:data:`WHOLE_FRAME_BYTES`); None below it.

    Examples
    --------
    >>> whole_frame_advice(64 * 64, 108) is None
    True
    >>> whole_frame_advice(4000 * 3000, 36)[:54]
    'checking the whole frame as one fit needs about 133 GB'
    """
    estimate = float(n_pixels) * n_frames * WHOLE_FRAME_BYTES
    if estimate <= limit:
        return None
    return (f"checking the whole frame as one fit needs about {estimate / 2**30:.0f} GB ({n_frames} frames of "
            f"{n_pixels:,} pixels) and minutes per step; --tiles 128 checks it tile by tile in the memory of one "
            "tile per worker (with --workers N in parallel)")


@dataclass(frozen=True)
class Tile:
    """One tile: the part it scores (``core``) and the part it reads (``region``: the core and its halo,
    clipped at the frame's edges); both ``(top, left, height, width)``."""

    core: Region
    region: Region


def tile_grid(shape: Sequence[int], size: int, halo: int = HALO) -> list[Tile]:
    """Tiles of about ``size × size`` pixels covering a frame of ``shape`` (rows, columns), row by row.

    The cores split each side into ``ceil(side / size)`` near-equal parts (no sliver at the end); each is read
    with ``halo`` pixels of its neighbours around it.

    Examples
    --------
    >>> [t.core for t in tile_grid((40, 20), 20)]
    [(0, 0, 20, 20), (20, 0, 20, 20)]
    >>> tile_grid((40, 20), 20)[1].region
    (17, 0, 23, 20)
    """
    h, w = int(shape[0]), int(shape[1])
    if size < MIN_TILE:
        raise ValueError(f"tile size {size}: at least {MIN_TILE} pixels (a tile's check scores its interior, "
                         "3 pixels in from its edges, with a 7 × 7 scene window)")
    rows = np.linspace(0, h, math.ceil(h / size) + 1).round().astype(int)
    cols = np.linspace(0, w, math.ceil(w / size) + 1).round().astype(int)
    out = []
    for top, bottom in zip(rows[:-1], rows[1:]):
        for left, right in zip(cols[:-1], cols[1:]):
            r0, r1 = max(top - halo, 0), min(bottom + halo, h)
            c0, c1 = max(left - halo, 0), min(right + halo, w)
            out.append(Tile((int(top), int(left), int(bottom - top), int(right - left)),
                            (int(r0), int(c0), int(r1 - r0), int(c1 - c0))))
    return out


@dataclass(frozen=True)
class TileCandidate:
    """One candidate's evidence in one tile (from :class:`~forensics.check.result.Candidate`)."""

    effect: str
    lm: float
    df: int
    delta_bic: float
    flagged: bool
    delta_bic_confirmed: float | None = None  #: as :attr:`~forensics.check.result.Candidate.delta_bic_confirmed`


@dataclass(frozen=True)
class TileResult:
    """What the combination needs of one tile's check (small: it travels back from a worker)."""

    tile: Tile
    effects: list[str]
    params: list[ParamEstimate]
    classes: dict[str, float | None]  #: held-out error per pixel class
    held_out: dict[str, int]  #: held-out means per pixel class
    variance_error: float | None
    gof: dict[str, float | None]
    candidates: list[TileCandidate]
    not_converged: list[str]
    warnings: list[str]
    #: the pixel-local random-effect patterns' sizes as the frames show them (those with a size)
    patterns: list[PatternEstimate] = field(default_factory=list)
    #: why the tile could not be checked at all (its one-line input error), else empty
    unchecked: str = ""

    @property
    def excluded(self) -> bool:
        """Left out of every combination: not checked, or its fit did not settle."""
        return bool(self.unchecked or self.not_converged)

    @classmethod
    def of(cls, tile: Tile, result: "CheckResult") -> "TileResult":
        """The parts of a tile's :class:`~forensics.check.result.CheckResult` the combination uses."""
        unsettled = [p.label for p in result.params if not p.converged]
        cands = [TileCandidate(c.effect, float(c.lm), int(c.df), float(c.delta_bic), bool(c.flagged),
                               c.delta_bic_confirmed)
                 for c in result.candidates if c.lm is not None and np.isfinite(c.lm) and c.df > 0]
        return cls(tile, list(result.effects), list(result.params), dict(result.error["classes"]),
                   dict(result.data["held_out_means"]), result.error["variance"], dict(result.gof), cands,
                   unsettled, list(result.warnings),
                   [p for p in result.patterns if p.size is not None and p.size_se is not None and p.size_se > 0])


@dataclass(frozen=True)
class TiledParam:
    """A global parameter combined over the tiles, and whether the tiles agree on it."""

    estimate: ParamEstimate  #: the combined value, its standard error and covariances
    tiles: int  #: tiles whose estimate entered (identifiable, settled, not on a bound)
    q: float | None  #: Cochran's Q of this parameter alone (Σ (θₜ − θ̂)² / (φₜ·seₜ²), φₜ: :func:`tile_dispersion`)
    df: int
    p_same: float | None  #: P(Q this large | the parameter is the same in every tile)
    spread: float | None  #: the tiles' values' standard deviation beyond their own errors (DerSimonian–Laird τ)

    def to_dict(self) -> dict[str, Any]:
        return {**self.estimate.to_dict(), "tiles": self.tiles, "q": self.q, "df": self.df, "p_same": self.p_same,
                "spread": self.spread}


@dataclass(frozen=True)
class UncombinedParam:
    """A global parameter the tiles report but that is not combined by information, why, and the tiles' values —
    so that a tiled check states every parameter a whole-frame check would."""

    effect: str
    name: str
    unit: str
    reason: str  #: why it is not pooled (the most common reason over the tiles), e.g. held with the effect's note
    tiles: int  #: tiles that report it
    median: float | None  #: the tiles' settled, finite values: median, smallest and largest (None: no such value)
    low: float | None
    high: float | None

    @property
    def label(self) -> str:
        return f"{self.effect}.{self.name}"

    def to_dict(self) -> dict[str, Any]:
        return {**self.__dict__, "label": self.label}


@dataclass(frozen=True)
class TiledPattern:
    """A random-effect pattern's size (its standard deviation as the frames show it, e.g. PRNU's or the DSNU's)
    combined over the tiles by inverse variance — every tile measures the same sensor-wide spread — with the
    tiles' agreement on it."""

    effect: str
    name: str
    size: float
    size_se: float
    tiles: int
    q: float | None
    df: int
    p_same: float | None
    spread: float | None

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class CombinedCandidate:
    """A candidate's evidence summed over the tiles."""

    effect: str
    lm: float
    df: int
    delta_bic: float
    p_raw: float
    p: float  #: Holm-adjusted over the candidates
    flagged: bool
    flagged_tiles: int
    tested_tiles: int
    delta_bic_confirmed: float | None = None  #: summed over the tiles (a tile without a fixed pattern: its ΔBIC)

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class UntrustedEstimate:
    """A tile's estimate left out of the combination (:func:`untrusted_estimates`), and why."""

    tile: int  #: its index in the tiles given
    core: tuple[int, int, int, int]  #: the tile's core (top, left, rows, columns)
    label: str  #: ``effect.name``
    reason: str

    def to_dict(self) -> dict[str, Any]:
        return {"tile": self.tile, "core": list(self.core), "label": self.label, "reason": self.reason}


@dataclass
class TiledCheck:
    """The whole frame's check from its tiles (:func:`check_tiles`).  ``to_dict()`` gives the JSON."""

    shape: tuple[int, int]
    size: int
    effects: list[str]
    tiles: list[TileResult]
    params: list[TiledParam]
    joint_q: float | None
    joint_df: int
    joint_p_same: float | None
    error: dict[str, Any]
    gof: dict[str, float | None]
    candidates: list[CombinedCandidate]
    warnings: list[str] = field(default_factory=list)
    patterns: list[TiledPattern] = field(default_factory=list)
    #: the parameters the tiles report that are not combined (held, on a bound, the largest of several values…)
    uncombined: list[UncombinedParam] = field(default_factory=list)
    #: tiles' estimates left out of the combination: their covariance is not a sampling variance
    untrusted: list[UntrustedEstimate] = field(default_factory=list)

    @property
    def flagged(self) -> list[str]:
        return [c.effect for c in self.candidates if c.flagged]

    @property
    def failed(self) -> list[TileResult]:
        """Tiles left out of every combination (not checked, or their fit did not settle)."""
        return [t for t in self.tiles if t.excluded]

    def to_dict(self) -> dict[str, Any]:
        return {"shape": list(self.shape), "tile_size": self.size, "effects": self.effects,
                "params": [p.to_dict() for p in self.params],
                "uncombined": [p.to_dict() for p in self.uncombined],
                "untrusted": [u.to_dict() for u in self.untrusted],
                "patterns": [p.to_dict() for p in self.patterns],
                "heterogeneity": {"q": self.joint_q, "df": self.joint_df, "p_same": self.joint_p_same},
                "error": self.error, "gof": self.gof, "candidates": [c.to_dict() for c in self.candidates],
                "tiles": [{"core": list(t.tile.core), "region": list(t.tile.region),
                           "error": t.classes, "held_out": t.held_out, "gof": t.gof,
                           "params": {p.label: {"value": p.value, "se": p.se} for p in t.params},
                           "flagged": [c.effect for c in t.candidates if c.flagged],
                           "not_converged": t.not_converged, "unchecked": t.unchecked or None}
                          for t in self.tiles],
                "warnings": self.warnings}


# ------------------------------------------------------------------------------------------------ combination
def _not_pooled(p: ParamEstimate) -> str | None:
    """Why a tile's estimate does not enter :func:`combine_params` (:func:`_tile_covariance`), or None if it does."""
    if not p.converged:
        return "did not converge"
    if not p.identifiable:
        return f"not identifiable ({p.note})" if p.note else "not identifiable"
    if p.bound:
        return f"at its {p.bound} bound"
    if not p.quadratic:
        return "the largest of several values (skewed: reported per tile, not pooled)"
    if p.se is None or not p.se > 0 or not np.isfinite(p.value):
        return "no standard error"
    return None


def _area(t: TileResult) -> int:
    return int(t.tile.core[2] * t.tile.core[3])


def untrusted_estimates(tiles: Sequence[TileResult], precision_limit: float = PRECISION_LIMIT,
                        misfit_limit: float = MISFIT_LIMIT) -> list[UntrustedEstimate]:
    """The tiles' estimates whose covariance the combination cannot take as their sampling variance.

    * Every pooled estimate of a tile whose misfit φ (:func:`tile_dispersion`) is above ``misfit_limit`` times the
      tiles' median: the model does not describe that tile.
    * A parameter's estimate whose standard error per pixel (× √ of the core's pixels) is below the median over
      the tiles that pool it by more than ``precision_limit``: equal tiles under one design carry about the same
      information per pixel, so a hundredfold claim is a cusp or a degenerate optimum of that tile's fit.

    Both medians are taken over at least three tiles (fewer say nothing of what is typical).

    Examples
    --------
    Five tiles measure a parameter to ± 1; a sixth claims ± 10⁻⁷ (a fit settled on a cusp):

    >>> from forensics.check.result import ParamEstimate
    >>> t = [TileResult(Tile((8 * i, 0, 8, 8), (8 * i, 0, 8, 8)), [], [ParamEstimate("x", "a", 1.0, se)],
    ...                 {}, {}, None, {}, [], [], []) for i, se in enumerate([1.0, 1.1, 0.9, 1.0, 1.2, 1e-7])]
    >>> [(u.tile, u.core[0], u.label) for u in untrusted_estimates(t)]
    [(5, 40, 'x.a')]
    """
    out: list[UntrustedEstimate] = []
    misfit = _misfits(tiles, misfit_limit)
    for i, why in misfit.items():
        out += [UntrustedEstimate(i, tiles[i].tile.core, p.label, why) for p in tiles[i].params
                if _not_pooled(p) is None]
    per_label: dict[str, list[tuple[int, float]]] = {}
    for i, t in enumerate(tiles):
        if t.excluded or i in misfit:
            continue
        for p in t.params:
            if _not_pooled(p) is None:
                per_label.setdefault(p.label, []).append((i, float(p.se) * math.sqrt(_area(t))))
    for label, pairs in per_label.items():
        out += [UntrustedEstimate(i, tiles[i].tile.core, label, why)
                for i, why in _overprecise(pairs, precision_limit).items()]
    return out


def _misfits(tiles: Sequence[TileResult], limit: float) -> dict[int, str]:
    """The tiles (index → why) whose misfit φ is above ``limit`` times the median over the tiles with a held-out
    error (at least three)."""
    held = [(i, tile_dispersion(t)) for i, t in enumerate(tiles)
            if not t.excluded and any(v is not None for v in t.classes.values())]
    if len(held) < 3:
        return {}
    typical = float(np.median([phi for _, phi in held]))
    return {i: (f"held-out error {math.sqrt(phi):.3g}, more than {math.sqrt(limit):.0f} × the tiles' median "
                f"{math.sqrt(typical):.3g}: the model does not describe the tile")
            for i, phi in held if phi > limit * typical}


def _overprecise(pairs: Sequence[tuple[int, float]], limit: float) -> dict[int, str]:
    """The tiles (index → why) whose standard error per pixel, of ``pairs`` (index, SE × √pixels), is below the
    median over at least three tiles by more than ``limit``."""
    if len(pairs) < 3:
        return {}
    typical = float(np.median([se for _, se in pairs]))
    return {i: (f"standard error {se / typical:.2g} × the tiles' median per pixel: the fit settled on a cusp or "
                "a degenerate optimum") for i, se in pairs if se < typical / limit}


def _tile_covariance(params: Sequence[ParamEstimate], leave_out: Sequence[str] = ()
                     ) -> tuple[list[str], np.ndarray, np.ndarray]:
    """(labels, values, covariance) of a tile's usable estimates: identifiable, settled, with a standard
    error, off their bounds (at a bound the likelihood is not quadratic about the value), quadratic (not the
    largest of several values, whose tile estimates are skewed: their heterogeneity Q would read the skew as a
    parameter that differs across the sensor); less ``leave_out`` (:func:`untrusted_estimates`: the others'
    covariance is then their marginal one, the submatrix)."""
    use = [p for p in params if _not_pooled(p) is None and p.label not in leave_out]
    labels = [p.label for p in use]
    cov = np.diag([float(p.se) ** 2 for p in use])
    for i, p in enumerate(use):
        for j, q in enumerate(use):
            if i != j and q.label in p.cov:
                cov[i, j] = p.cov[q.label]
    cov = 0.5 * (cov + cov.T)
    return labels, np.array([p.value for p in use], float), cov


def uncombined_params(tiles: Sequence[TileResult], combined: Sequence[str]) -> list[UncombinedParam]:
    """The global parameters of ``tiles`` whose labels are not in ``combined``, each with the most common reason
    over the tiles and the spread of the tiles' settled values.

    Examples
    --------
    >>> from forensics.check.result import ParamEstimate
    >>> t = [TileResult(Tile((0, 0, 8, 8), (0, 0, 8, 8)), [],
    ...                 [ParamEstimate("clusters", "amplitude", v, 9.0, "DN", quadratic=False)],
    ...                 {}, {}, None, {}, [], [], []) for v in (280.0, 300.0, 310.0)]
    >>> u = uncombined_params(t, [])[0]
    >>> u.label, u.tiles, u.median, u.low, u.high, u.reason.split(" (")[0]
    ('clusters.amplitude', 3, 300.0, 280.0, 310.0, 'the largest of several values')
    """
    seen: dict[str, list[ParamEstimate]] = {}
    for t in tiles:
        if t.excluded:
            continue
        for p in t.params:
            if p.label not in combined:
                seen.setdefault(p.label, []).append(p)
    out = []
    for ests in seen.values():
        reasons = [_not_pooled(p) for p in ests]  # (never None: a label pooled in any tile is combined)
        reason = max(dict.fromkeys(reasons), key=reasons.count)  # the most common; ties: the first seen
        vals = np.array([p.value for p in ests if p.converged and np.isfinite(p.value)], float)
        stats_ = (float(np.median(vals)), float(vals.min()), float(vals.max())) if vals.size else (None, None, None)
        out.append(UncombinedParam(ests[0].effect, ests[0].name, ests[0].unit, reason, len(ests), *stats_))
    return out


def _precision(cov: np.ndarray) -> np.ndarray:
    """The inverse of a covariance, on its unit-diagonal scaling (the parameters' units differ by orders of
    magnitude); a pseudo-inverse where the tile's estimates are (nearly) collinear."""
    d = np.sqrt(np.diag(cov))
    corr = cov / np.outer(d, d)
    return np.linalg.pinv(corr, rcond=1e-10, hermitian=True) / np.outer(d, d)


def combine_params(tiles: Sequence[TileResult], untrusted: Sequence[UntrustedEstimate] | None = None
                   ) -> tuple[list[TiledParam], float | None, int, float | None]:
    """The global parameters combined over ``tiles`` by their information (module docstring), each with its
    heterogeneity test, and the joint heterogeneity test (Q, df, p); the estimates of
    :func:`untrusted_estimates` left out (``untrusted``: those of ``tiles``, when already found).

    Examples
    --------
    Two tiles that measured one parameter, 10 ± 1 and 12 ± 1: the combination is 11 ± 0.71, and Q = 2 on 1 df.

    >>> from forensics.check.result import ParamEstimate, PatternEstimate
    >>> t = [TileResult(Tile((0, 0, 8, 8), (0, 0, 8, 8)), [], [ParamEstimate("offset", "level", v, 1.0)],
    ...                 {}, {}, None, {}, [], [], []) for v in (10.0, 12.0)]
    >>> p, q, df, _ = combine_params(t)
    >>> round(p[0].estimate.value, 3), round(p[0].estimate.se, 3), round(q, 3), df
    (11.0, 0.707, 2.0, 1)
    """
    order: list[str] = []
    meta: dict[str, ParamEstimate] = {}
    parts = []
    left_out: dict[int, set[str]] = {}
    for u in untrusted_estimates(tiles) if untrusted is None else untrusted:
        left_out.setdefault(u.tile, set()).add(u.label)
    for i, t in enumerate(tiles):
        if t.excluded:
            continue
        labels, values, cov = _tile_covariance(t.params, left_out.get(i, set()))
        if not labels:
            continue
        parts.append((labels, values, cov, _precision(cov), tile_dispersion(t)))
        for p in t.params:
            if p.label in labels and p.label not in meta:
                meta[p.label] = p
                order.append(p.label)
    k = len(order)
    if k == 0:
        return [], None, 0, None
    index = {label: i for i, label in enumerate(order)}
    info = np.zeros((k, k))
    rhs = np.zeros(k)
    for labels, values, _, prec, _ in parts:
        idx = [index[label] for label in labels]
        info[np.ix_(idx, idx)] += prec
        rhs[idx] += prec @ values
    cov = _precision(info)  # the inverse of the summed information (same scaled pseudo-inverse)
    theta = cov @ rhs
    q_joint, n_joint = 0.0, 0
    per_vals: list[list[tuple[float, float]]] = [[] for _ in range(k)]
    for labels, values, tcov, prec, phi in parts:
        idx = [index[label] for label in labels]
        d = values - theta[idx]
        q_joint += float(d @ prec @ d) / phi
        n_joint += len(idx)
        for j, i in enumerate(idx):
            per_vals[i].append((float(values[j]), float(tcov[j, j]) * phi))
    joint_df = n_joint - k
    out = []
    for i, label in enumerate(order):
        p0 = meta[label]
        se = float(np.sqrt(max(cov[i, i], 0.0)))
        covs = {order[j]: float(cov[i, j]) for j in range(k) if j != i}
        estimate = ParamEstimate(p0.effect, p0.name, float(theta[i]), se, p0.unit, cov=covs)
        q, df, p_same, spread = scalar_heterogeneity(per_vals[i], float(theta[i]))
        out.append(TiledParam(estimate, len(per_vals[i]), q, df, p_same, spread))
    p_joint = float(chi2_sf(q_joint, joint_df)) if joint_df >= 1 else None
    return out, (q_joint if joint_df >= 1 else None), max(joint_df, 0), p_joint


def tile_dispersion(t: TileResult) -> float:
    """A tile's dispersion φ = max(1, e²), e its held-out error pooled over the pixel classes (the root mean
    square over its held-out means, in noise floors).

    The heterogeneity tests scale each tile's covariance by it (quasi-likelihood; McCullagh & Nelder, Generalized
    Linear Models, 1989, §9.2): a standard error from the information alone assumes the model holds, and where it
    misfits (the SBIG tiles' errors 1.4–2.3) the tiles' values scatter by more than those errors although nothing
    spatial may be missing.  The combined values and their standard errors are a whole-frame check's (unscaled).

    Examples
    --------
    >>> t = TileResult(Tile((0, 0, 8, 8), (0, 0, 8, 8)), [], [], {"normal": 2.0, "partial": 1.0},
    ...                {"normal": 3, "partial": 1}, None, {}, [], [], [])
    >>> tile_dispersion(t)
    3.25
    """
    pairs = [(e, t.held_out.get(name, 0)) for name, e in t.classes.items() if e is not None]
    n = sum(m for _, m in pairs)
    return max(1.0, sum(e * e * m for e, m in pairs) / n) if n else 1.0


def scalar_heterogeneity(values: Sequence[tuple[float, float]], centre: float
                         ) -> tuple[float | None, int, float | None, float | None]:
    """(Cochran's Q, df, p, spread) of the tiles' values of one quantity, ``values`` as (value, variance) pairs
    (variances already scaled by each tile's :func:`tile_dispersion`), about ``centre``.  The spread is the
    tiles' standard deviation beyond their own errors: DerSimonian & Laird's moment estimate τ (Controlled
    Clinical Trials 7, 1986), 0 when the tiles agree within their errors.

    Examples
    --------
    >>> q, df, p, tau = scalar_heterogeneity([(10.0, 1.0), (12.0, 1.0)], 11.0)
    >>> q, df, round(p, 3), round(tau, 3)
    (2.0, 1, 0.157, 1.0)
    """
    df = len(values) - 1
    if df < 1:
        return None, max(df, 0), None, None
    v = np.array([a for a, _ in values])
    w = 1.0 / np.array([b for _, b in values])
    q = float(np.sum(w * (v - centre) ** 2))
    # τ from Q about the inverse-variance mean (the moment estimator's own centre)
    mean = float(np.sum(w * v) / np.sum(w))
    q_mean = float(np.sum(w * (v - mean) ** 2))
    c = float(np.sum(w) - np.sum(w * w) / np.sum(w))
    tau = float(np.sqrt(max((q_mean - df) / c, 0.0))) if c > 0 else None
    return q, df, float(chi2_sf(q, df)), tau


def combine_pattern_sizes(tiles: Sequence[TileResult]) -> list[TiledPattern]:
    """Every random-effect pattern's size combined over the tiles that measured it (inverse-variance weighted
    mean; Cochran's Q and the DerSimonian–Laird spread as for a parameter; tiles left out as a parameter's are by
    :func:`untrusted_estimates`).

    Examples
    --------
    >>> from forensics.check.result import PatternEstimate
    >>> t = [TileResult(Tile((0, 0, 8, 8), (0, 0, 8, 8)), [], [], {}, {}, None, {}, [], [], [],
    ...                 [PatternEstimate("prnu", "k", 64, 0.01, 0.03, size=v, size_se=0.001)]) for v in (0.010, 0.012)]
    >>> p = combine_pattern_sizes(t)[0]
    >>> round(p.size, 4), round(p.size_se, 5), round(p.q, 1)
    (0.011, 0.00071, 2.0)
    """
    found: dict[tuple[str, str], list[tuple[int, float, float, float]]] = {}
    misfit = _misfits(tiles, MISFIT_LIMIT)  # as for a parameter (:func:`untrusted_estimates`)
    for i, t in enumerate(tiles):
        if t.excluded or i in misfit:
            continue
        phi = tile_dispersion(t)
        for p in t.patterns:
            found.setdefault((p.effect, p.name), []).append((i, float(p.size), float(p.size_se) ** 2, phi))
    out = []
    for (effect, name), found_values in found.items():
        overprecise = _overprecise([(i, math.sqrt(b * _area(tiles[i]))) for i, _, b, _ in found_values],
                                   PRECISION_LIMIT)
        values = [(a, b, phi) for i, a, b, phi in found_values if i not in overprecise]
        w = 1.0 / np.array([b for _, b, _ in values])
        mean = float(np.sum(w * np.array([a for a, _, _ in values])) / np.sum(w))
        # the size and its SE as the tiles measured them; the agreement test with each tile's misfit, as a parameter's
        q, df, p_same, spread = scalar_heterogeneity([(a, b * phi) for a, b, phi in values], mean)
        out.append(TiledPattern(effect, name, mean, float(np.sqrt(1.0 / np.sum(w))), len(values), q, df, p_same,
                                spread))
    return out


def combine_errors(tiles: Sequence[TileResult]) -> dict[str, Any]:
    """The held-out error per pixel class pooled over the tiles (root of the mean squared error, each tile
    weighted by its held-out means), the pixel error as one check's (the worst class), and the variance
    channel's error pooled as a root mean square over the tiles."""
    names: list[str] = []
    for t in tiles:
        names += [n for n in t.classes if n not in names]
    classes: dict[str, float | None] = {}
    for name in names:
        pairs = [(t.classes[name], t.held_out.get(name, 0)) for t in tiles
                 if not t.excluded and t.classes.get(name) is not None and t.held_out.get(name, 0) > 0]
        n = sum(m for _, m in pairs)
        classes[name] = float(np.sqrt(sum(e * e * m for e, m in pairs) / n)) if n else None
    values = [v for v in classes.values() if v is not None]
    var = [t.variance_error for t in tiles if not t.excluded and t.variance_error is not None]
    return {"pixel": max(values) if values else None, "classes": classes,
            "variance": float(np.sqrt(np.mean(np.square(var)))) if var else None}


#: p-values below this are taken at it in Fisher's sum (a tile's "< 1e-300" is 0.0 in its result)
P_FLOOR = 1e-300


def combine_gof(tiles: Sequence[TileResult]) -> dict[str, float | None]:
    """Each channel's goodness-of-fit p-value over the tiles by Fisher's method (−2 Σ ln p ~ χ²₂ₜ for
    independent tests under the model)."""
    keys: list[str] = []
    for t in tiles:
        keys += [k for k in t.gof if k not in keys]
    out: dict[str, float | None] = {}
    for key in keys:
        ps = [max(float(t.gof[key]), P_FLOOR) for t in tiles if not t.excluded and t.gof.get(key) is not None]
        out[key] = float(chi2_sf(-2.0 * float(np.sum(np.log(ps))), 2 * len(ps))) if ps else None
    return out


def combine_candidates(tiles: Sequence[TileResult]) -> list[CombinedCandidate]:
    """Every candidate's score statistics summed over the tiles that tested it (each χ² with its df under the
    model, the tiles independent), ΔBIC summed likewise, Holm-adjusted across candidates and flagged by the
    rule of one check (:func:`~forensics.check.diagnosis.flag_rule`); ranked by ΔBIC."""
    sums: dict[str, list[float]] = {}
    patterns: set[str] = set()
    for t in tiles:
        if t.excluded:
            continue
        for c in t.candidates:
            s = sums.setdefault(c.effect, [0.0, 0, 0.0, 0, 0, 0.0])
            s[0] += c.lm
            s[1] += c.df
            s[2] += c.delta_bic
            s[3] += int(c.flagged)
            s[4] += 1
            s[5] += c.delta_bic if c.delta_bic_confirmed is None else c.delta_bic_confirmed
            if c.delta_bic_confirmed is not None:
                patterns.add(c.effect)
    names = list(sums)
    p_raw = [float(chi2_sf(sums[n][0], sums[n][1])) for n in names]
    p_adj = holm_adjusted(p_raw) if names else np.array([])
    confirmed = {n: float(sums[n][5]) if n in patterns else None for n in names}
    out = [CombinedCandidate(n, float(sums[n][0]), int(sums[n][1]), float(sums[n][2]), p_raw[i], float(p_adj[i]),
                             flag_rule(float(sums[n][2]), confirmed[n], float(p_adj[i])), int(sums[n][3]),
                             int(sums[n][4]), confirmed[n])
           for i, n in enumerate(names)]
    return sorted(out, key=lambda c: -c.delta_bic)


def combine(shape: tuple[int, int], size: int, tiles: Sequence[TileResult]) -> TiledCheck:
    """The whole frame's :class:`TiledCheck` from its tiles' results."""
    tiles = list(tiles)
    untrusted = untrusted_estimates(tiles)
    params, q, df, p = combine_params(tiles, untrusted)
    warnings = []
    failed = [t for t in tiles if t.excluded]
    if failed:
        where = "; ".join(_where(t) for t in failed[:5])
        skipped = [t.unchecked for t in failed if t.unchecked]
        warnings.append(f"{len(failed)} of {len(tiles)} tiles did not converge or could not be checked and are left "
                        f"out of every combined figure ({where}{' …' if len(failed) > 5 else ''})"
                        + (f"; the first not checked: {skipped[0]}" if skipped else ""))
    if tiles and all(t.unchecked for t in tiles):
        raise InputError(f"no tile of the frames could be checked: {tiles[0].unchecked}")
    empty = [t for t in tiles if not t.excluded and not any(v is not None for v in t.classes.values())]
    if empty:
        warnings.append(f"{len(empty)} tile(s) gave no held-out error (no usable pixel means there, e.g. a dead or "
                        "saturated part of the sensor): " + "; ".join(_where(t) for t in empty[:5]))
    if untrusted:
        by_tile: dict[int, list[UntrustedEstimate]] = {}
        for u in untrusted:
            by_tile.setdefault(u.tile, []).append(u)
        named = [f"{_where(tiles[i])}: {', '.join(u.label for u in us)} ({us[0].reason})"
                 for i, us in list(by_tile.items())[:5]]
        warnings.append(f"{len(untrusted)} estimate(s) of {len(by_tile)} tile(s) left out of the combined parameters, "
                        f"their standard errors not a sampling spread — {'; '.join(named)}"
                        f"{' …' if len(by_tile) > 5 else ''}")
    usable = [t for t in tiles if not t.excluded and t not in empty]
    if usable:  # what every tile says about the data (the design, the fields missing): the best-measured tile's
        best = max(usable, key=lambda t: sum(t.held_out.values()))
        warnings += [w for w in best.warnings if not w.startswith("only a region of the")]
    effects = next((t.effects for t in tiles if t.effects), [])
    return TiledCheck((int(shape[0]), int(shape[1])), int(size), list(effects), tiles, params, q, df, p,
                      combine_errors(tiles), combine_gof(tiles), combine_candidates(tiles), warnings,
                      combine_pattern_sizes(tiles), uncombined_params(tiles, [x.estimate.label for x in params]),
                      untrusted)


def _where(t: TileResult) -> str:
    top, left, h, w = t.tile.core
    return f"rows {top}–{top + h - 1}, columns {left}–{left + w - 1}"


# ------------------------------------------------------------------------------------------------ running
def check_tile(data: Dataset, item: tuple[Tile, list[Any], np.random.SeedSequence, int, dict[str, float] | None]
               ) -> TileResult:
    """One tile's check (a work item of :func:`check_tiles`: module-level, the dataset shared)."""
    from forensics.check.pipeline import base_model, prepare, run_check

    tile, add, seeds, n_sim, start = item
    try:
        ev, extra = prepare(data, add, np.random.default_rng(seeds), n_sim, region=tile.region)
        result = run_check(ev, [*base_model(ev.black_level), *extra], start=start)
    except InputError as exc:
        # a part of the frame the check cannot use (e.g. content-free or saturated there): the tile is named and
        # left out, the others still count
        return TileResult(tile, [], [], {}, {}, None, {}, [], [], [], unchecked=str(exc))
    return TileResult.of(tile, result)


def check_tiles(data: Dataset | str | Path, add: Sequence[Any] = (), size: int = 256, rng: RngLike = 0,
                n_sim: int = 199, progress: Progress = no_progress,
                executor: Executor | None = None, start: dict[str, float] | None = None,
                scratch: str | Path | None = None) -> TiledCheck:
    """Check the base model plus ``add`` on every tile of the frames and combine the tiles (module docstring).

    Parameters
    ----------
    data
        Dataset (or its folder).
    add
        Effects to add to the base model, as :func:`~forensics.check.pipeline.check` takes them.
    size
        The tiles' side in pixels (each is read with a 3-pixel halo); a tile's check needs ≈ 2.2 KB per pixel and
        fitted condition (:data:`~forensics.check.pipeline.FIT_BYTES_PER_PIXEL_CONDITION`), per worker.
    rng
        Seed (or SeedSequence) of the tiles' Monte-Carlo streams: tile ``i`` draws from child ``i`` of
        ``SeedSequence(rng).spawn``, whatever the order the tiles run in.
    executor
        The execution layer: one tile per work item, the dataset shipped once per worker.
    start
        Global pixel parameters every tile's fit starts from (``effect.name`` → value, e.g. a fit of the central
        region: ``{p.label: p.value for p in result.params}``); default: the central tile is checked first and the
        others start from its values.  Each tile still fits to convergence.
    scratch
        Where the frames are decoded once for the tiles (:func:`~forensics.io.framecache.frame_cache`; default the
        system's temporary directory, removed afterwards).  With a Dask scheduler given by address (workers that
        may be on other machines) the frames are decoded once only where ``scratch`` is given (it must be storage
        every worker sees).  Without room there, or without ``scratch`` on such a cluster, every tile decodes the
        files itself, said in the warnings.

    Returns
    -------
    TiledCheck

    Examples
    --------
    >>> from forensics.check.tiles import check_tiles                         # doctest: +SKIP
    >>> whole = check_tiles("darks/", add=["shot_noise", "dark_current"], size=256)  # doctest: +SKIP
    >>> [(p.estimate.label, p.estimate.value, p.p_same) for p in whole.params]      # doctest: +SKIP
    """
    from forensics.check.pipeline import resolve_effects
    from forensics.io.framecache import frame_cache

    if size < MIN_TILE:
        raise UsageError(f"--tiles {size}: a tile needs at least {MIN_TILE} × {MIN_TILE} pixels (its 3-pixel border is "
                         "not scored); tiles of 128–512 pixels keep the per-tile cost small")
    ds = data if isinstance(data, Dataset) else open_dataset(data)
    shape = ds.shape()
    resolve_effects(add)  # an unknown effect is named before any tile is read
    tiles = tile_grid(shape, size)
    root = rng if isinstance(rng, np.random.SeedSequence) else np.random.SeedSequence(
        rng if isinstance(rng, (int, np.integer)) else np.random.default_rng(rng).integers(2**63))
    seeds = root.spawn(len(tiles))
    if len(tiles) == 1:
        return combine(shape[:2], size, [check_tile(ds, (tiles[0], list(add), seeds[0], n_sim, start))])
    if scratch is None and executor is not None and not executor.local_disk:
        # the workers of a scheduler given by address may not see this machine's temporary directory
        results = _run_tiles(ds, shape, tiles, list(add), seeds, n_sim, start, progress, executor)
        why = ("every tile decodes the frames itself (the cluster's workers may not see this machine's temporary "
               "directory): give scratch space every worker sees (--scratch) to decode them once")
    else:
        # every tile reads every frame: decoded once, a tile costs its own pixels instead of whole frames
        with frame_cache(ds, scratch, progress, executor) as (cached, why):
            results = _run_tiles(cached, shape, tiles, list(add), seeds, n_sim, start, progress, executor)
    whole = combine(shape[:2], size, results)
    return whole if why is None else replace(whole, warnings=[*whole.warnings, why])


def _run_tiles(ds: Dataset, shape: Sequence[int], tiles: Sequence[Tile], add: list[Any], seeds: Sequence[np.random.SeedSequence],
               n_sim: int, start: dict[str, float] | None, progress: Progress,
               executor: Executor | None) -> list[TileResult]:
    """Every tile's result in tile order: the central tile first in this process, where no ``start`` is given."""
    from forensics._shared.parallel import resolve

    first: TileResult | None = None
    centre = central_tile(tiles, shape)
    if start is None:
        # the central tile first, in this process: every other tile's fit starts from its values (a tile from the
        # nulls spends most of its cycles finding what every tile shares; each still fits to convergence)
        first = check_tile(ds, (tiles[centre], add, seeds[centre], n_sim, None))
        start = None if first.excluded else start_values(first.params)
    items = [(t, add, s, n_sim, start) for i, (t, s) in enumerate(zip(tiles, seeds))
             if not (first is not None and i == centre)]
    results = list(resolve(executor).map(check_tile, items, shared=ds, progress=progress, desc="tiles"))
    if first is not None:
        results.insert(centre, first)
    return results


def start_values(params: Sequence[ParamEstimate]) -> dict[str, float]:
    """The settled parameters of a check as ``effect.name`` → value: what :func:`check_tiles`' ``start`` takes."""
    return {p.label: p.value for p in params if p.converged}


def central_tile(tiles: Sequence[Tile], shape: Sequence[int]) -> int:
    """The index of the tile whose core holds the frame's centre.

    Examples
    --------
    >>> central_tile(tile_grid((60, 60), 20), (60, 60))
    4
    """
    cy, cx = shape[0] / 2.0, shape[1] / 2.0
    for i, t in enumerate(tiles):
        top, left, h, w = t.core
        if top <= cy < top + h and left <= cx < left + w:
            return i
    return len(tiles) // 2
