"""The geometry of an identification search: orientations, crops and scales (:mod:`forensics.prnu.identify`).

Which positions of which (rotated, resampled) fingerprint a query is compared with, and how many: each
(rotation, scale) of one fingerprint is one :class:`_Test` whose ``n_positions`` counts in the decision's
correction.

Geometry searched (per fingerprint; counted in the decision)
-------------------------------------------------------------
**Orientation** (``rotations``): ``'auto'`` tries the image as stored if it fits in the sensor's frame,
else both quarter turns (a portrait picture written rotated); ``'all'`` every quarter turn (0°, 90°,
180°, 270°) in which it fits; ``'none'`` the image as stored only.

**Aligned** images: an image of the frame's size at scale 1 is correlated as
:func:`forensics.prnu.match.score_query` does — its residual over the fingerprint's region with
``I·K`` — and scored at zero shift (one position) by the block-phase PCE (:mod:`forensics.prnu.blockpce`).

**Crops** (``crop_search``): an image smaller than the frame is taken as a crop at an unknown offset.
The query's ``W·I`` (residual times intensity, :func:`~forensics.prnu.match.prepare_query` on the whole
image) is correlated with ``K`` at every offset at which the crop lies inside the fingerprint's region,
or the region inside the crop (per axis), and inside the frame.  Both arrays are zero-padded to a
common canvas whose side is the longer of the two on each axis, so *every* circular shift pairs the same
number of real pixels: the correlation's null variance depends on the shift only through the JPEG
block phase, which the block-phase PCE accounts for.  Crops reaching outside a ``center:N``
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
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse

from forensics._shared.errors import InputError, UsageError
from forensics.prnu.fingerprint import Fingerprint, Region

__all__ = ["ScaleSearch", "parse_scales", "resample"]

#: A whole-frame resize may differ from the scaled frame's size by rounding, up to this many pixels.
_SIZE_SLACK = 2
_ROTATION_MODES = ("auto", "none", "all")


# ----------------------------------------------------------------------------- the scale grid


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


# ----------------------------------------------------------------------------- resampling


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



def _plan(shape: tuple[int, int], ref: _Reference, rotations: Any, search: ScaleSearch | None,
          crop_search: bool) -> list[_Test]:
    """Every (rotation, scale) test of a query of ``shape`` against ``ref``; empty if incompatible."""
    fp_frame = ref.frame
    max_scale = search.bounds()[1] if search is not None else 1.0
    tests: list[_Test] = []
    for rot in _rotations(rotations, shape, fp_frame, max_scale):
        rshape = _rotated(shape, rot)
        for scale, scale_yx in _scales_for(search, rshape, fp_frame):
            if scale_yx == (1.0, 1.0) and rshape == fp_frame:
                tests.append(_Test(rot, 1.0, (1.0, 1.0), True, 1))
            elif ref.origin is not None and (crop_search or scale_yx != (1.0, 1.0)):
                test = _crop_test(rot, scale, scale_yx, rshape, ref, crop_search)
                if test is not None:
                    tests.append(test)
    return tests
