"""Dark-frame series: every pixel's offset and dark rate from biases and darks, cosmic-ray hits excluded.

What astronomers and sensor engineers measure a cooled sensor with: bias frames (exposure 0) and dark frames
at several exposure times, at one or more sensor temperatures, usually one frame per exposure.  Within one
*temperature group* (the frames taken at one set point) every pixel p follows the line

    y_pf = a_p + r_p · t_f + ε_pf,        Var ε_pf = σ_r² + S_pf / g,

with ``a_p`` the offset (the bias plus the dark charge collected while the frame is read out — a hot pixel
shows in bias frames too), ``r_p`` the dark rate in ADU/s, ``t_f`` the exposure (0 for biases), ``σ_r`` the
read noise (ADU), ``g`` the conversion gain (e⁻/ADU) and ``S_pf = max(a_p − B, 0) + max(r_p, 0)·t_f`` the
dark charge in ADU above the median bias level ``B`` (its shot noise is S/g ADU²).

The fit streams over the frames, never holding more than one of them (plus a chunk being read ahead):

1. **Sums.**  One pass accumulates, per pixel, Σy, Σt·y, Σy² over the group and Σy, Σy² over its biases
   (float64; the design sums Σt, Σt², Σt³ are the group's, corrected per pixel for the few samples left out).
   Samples at or above the saturation level are recorded sparsely and left out (non-linear or clipped).
2. **Cosmic rays** (:mod:`forensics.defects.darkrounds`).  Each round streams the frames again and finds, per
   pixel, its most discrepant sample against the current line, in units of that residual's exact standard
   deviation under the read + shot noise model; above ``k`` it is a cosmic-ray hit (charge is only ever added,
   so the test is one-sided), and the hit's neighbours in the same frame go from ``k_grow`` (a track spreads
   charge).  Hits are left out (their sums subtracted) and every pixel's line is solved again.  One sample per
   pixel per round, because a hit pulls the whole line; a single frame per exposure is enough.
3. **Diagnostics.**  A last pass measures, per frame, its common-mode residual (the median over pixels of
   y − a − r·t: a frame whose median dark level is off the lines, or whose bias jumped), its noise against the
   model and its read noise (biases), and, per pixel, the residual sum of squares: pixels far beyond the noise
   model do not follow a line (*misfits*), and the others give the gain from the
   dark signal's shot noise (:mod:`forensics.defects.darkgain`).

Every pixel's rate has a standard error from the noise model (read noise, shot noise of its dark charge, and
the frame-to-frame offset jitter σ_o measured on the bias frames); the group's median rate has an interval
that includes the jitter's common-mode effect, which does not average out over pixels.  A group's rates refer
to its *effective* temperature, the exposure-weighted mean of the measured CCD-TEMP that the fitted slope
actually sees (Σ c_f·t_f·T_f with the slope's weights c_f), so the small wander of the measured temperature
around the set point needs no temperature law.

Frames are grouped by their set point (or, without one, by their measured temperature); a frame whose measured
temperature is more than :data:`forensics.io.fits.SETPOINT_TOLERANCE_C` from its set point never settled and
is left out, named.  Memory per pixel and temperature group: 40 bytes of sums (float64), 28 bytes of the lines
shipped to each worker and 10–12 bytes of per-pass partial results (float32 z, its frame and value; float64
residual squares); the result keeps about 40 bytes (offset, rate, its error, residual noise, samples used,
residual squares and dark charge for the gain).  ``rounds + 2`` passes over the frames in all (plus one over
the flat pairs).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from forensics._shared.errors import InputError
from forensics._shared.progress import Progress, no_progress

if TYPE_CHECKING:
    from forensics._shared.parallel import Executor

#: Frame types of a dark series; ``flat`` and ``light`` frames give the conversion gain only.
DARK_TYPES = ("bias", "dark")
LIGHT_TYPES = ("flat", "light")
#: Measured temperature this far (°C) from the set point: the sensor had not settled (as the FITS reader warns).
SETPOINT_TOLERANCE_C = 1.0
#: Deleted residuals above this many σ of the noise model are cosmic-ray hits (≈ 3·10⁻⁷ false marks per sample).
K_OUTLIER = 5.0
#: A hit's 8 neighbours in the same frame are marked from this many σ (a track spreads its charge).
K_GROW = 3.0
#: Robust rounds after the first fit (the second catches a pixel hit twice, whose first hit masked the other).
ROUNDS = 2
#: Samples within this fraction of the data type's full scale are left out as possibly non-linear or clipped.
SATURATION_FRACTION = 0.9
#: Frames per work item (fixed by the data, never by the number of workers: the float sums fold identically).
CHUNK_FRAMES = 8
#: A frame whose common-mode residual exceeds this many σ_o, or whose noise is off the model by more than
#: :data:`NOISE_TOLERANCE`, or with more than :data:`OUTLIER_SHARE` of its samples rejected, is named.
FRAME_Z = 5.0
NOISE_TOLERANCE = 0.1
OUTLIER_SHARE = 0.01


# =========================================================================== frames and groups
@dataclass(frozen=True)
class SeriesFrame:
    """One frame of a series and its conditions (from the FITS header or a manifest).

    ``frame_type`` is ``bias``, ``dark``, ``flat`` or ``light``; ``temperature_c`` the *measured* sensor
    temperature, ``set_temperature_c`` the set point; ``captured`` a decimal year.
    """

    path: str
    frame_type: str
    exposure_s: float
    temperature_c: float | None = None
    set_temperature_c: float | None = None
    captured: float | None = None
    #: on-chip binning (x, y); None where the header or manifest does not state it
    binning: tuple[int, int] | None = None

    @property
    def name(self) -> str:
        return self.path.rsplit("/", 1)[-1]


@dataclass(frozen=True)
class SeriesPlan:
    """How a series' frames are used: temperature groups of biases and darks, flats, and frames left out."""

    frames: tuple[SeriesFrame, ...]
    groups: tuple[tuple[int, ...], ...]
    setpoints: tuple[float | None, ...]
    flats: tuple[int, ...]
    excluded: dict[int, str] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()

    @property
    def binning(self) -> tuple[int, int] | None:
        """The frames' common binning (:func:`forensics.io.dataset.common_binning`; None where none states one)."""
        from forensics.io.dataset import common_binning

        return common_binning([(f.path, f.binning) for f in self.frames])

    def biases(self, group: int) -> np.ndarray:
        """Which of a group's frames are biases, by their frame type: a bias is a bias whatever exposure its header
        gives (some cameras record their shortest exposure, e.g. 0.12 s, for a closed-shutter read-out), and its
        exposure stays the one recorded in the pixels' lines."""
        return np.array([self.frames[i].frame_type == "bias" for i in self.groups[group]], bool)

    def label(self, group: int) -> str:
        sp = self.setpoints[group]
        if sp is not None:
            return f"set point {sp:+.1f} °C"
        temps = [self.frames[i].temperature_c for i in self.groups[group]]
        known = [t for t in temps if t is not None]
        return f"measured {np.median(known):+.1f} °C" if known else "temperature unknown"


def plan_series(frames: Sequence[SeriesFrame], tolerance: float = SETPOINT_TOLERANCE_C) -> SeriesPlan:
    """Group the biases and darks by temperature; set aside flats; leave out frames that cannot be used.

    A group is the frames of one set point (rounded to 0.1 °C), or, for frames without one, of one cluster of
    measured temperatures (a new cluster after a gap of more than ``tolerance``).  A frame measured more than
    ``tolerance`` from its set point is left out (the sensor had not settled); a group needs two distinct
    exposure times (biases count as 0 s) to separate offset and rate.

    Raises
    ------
    InputError
        A frame without an exposure time or frame type, frames of which only some give a temperature, or frames of
        different binnings.
    """
    frames = tuple(frames)
    SeriesPlan(frames, (), (), ()).binning  # frames of different binnings: refused, naming one of each
    excluded: dict[int, str] = {}
    notes: list[str] = []
    darks, flats = [], []
    for i, fr in enumerate(frames):
        if fr.frame_type not in DARK_TYPES + LIGHT_TYPES:
            raise InputError(f"{fr.path}: frame type unknown ({fr.frame_type!r}); give IMAGETYP in the header or a "
                             "manifest column 'frame_type' (bias, dark, flat or light)")
        if fr.exposure_s is None or not math.isfinite(fr.exposure_s) or fr.exposure_s < 0:
            raise InputError(f"{fr.path}: no exposure time; give EXPTIME in the header or a manifest 'exposure_s'")
        if fr.frame_type in LIGHT_TYPES:
            flats.append(i)
            continue
        if (fr.temperature_c is not None and fr.set_temperature_c is not None
                and abs(fr.temperature_c - fr.set_temperature_c) > tolerance):
            excluded[i] = (f"the sensor measured {fr.temperature_c:+.2f} °C against its set point "
                           f"{fr.set_temperature_c:+.2f} °C: it never reached it")
            continue
        darks.append(i)
    known = [i for i in darks if frames[i].temperature_c is not None]
    if known and len(known) != len(darks):
        missing = next(i for i in darks if frames[i].temperature_c is None)
        raise InputError(f"{frames[missing].path}: no sensor temperature (CCD-TEMP) while other frames have one; "
                         "give it in a manifest column 'temperature_c' or leave the frame out")
    keys = _group_keys(frames, darks, tolerance)
    groups: dict[Any, list[int]] = {}
    for i, key in zip(darks, keys):
        groups.setdefault(key, []).append(i)
    kept, setpoints = [], []
    for key, members in sorted(groups.items(), key=lambda kv: (kv[0][1] is None, kv[0][1] or 0.0)):
        exposures = {frames[i].exposure_s for i in members}
        if len(exposures) < 2:
            why = (f"only one exposure time ({next(iter(exposures)):g} s) at this temperature: offset and dark rate "
                   "cannot be separated; add biases or darks of another exposure")
            for i in members:
                excluded[i] = why
            continue
        kept.append(tuple(members))
        setpoints.append(key[1] if key[0] == "set" else None)
    if not kept:
        raise InputError("no temperature group with biases or darks at two exposure times: a dark series needs "
                         "frames of at least two exposure times (biases count as 0 s) at one temperature")
    return SeriesPlan(frames, tuple(kept), tuple(setpoints), tuple(flats), excluded, tuple(notes))


def _group_keys(frames: Sequence[SeriesFrame], members: list[int], tolerance: float) -> list[tuple[str, Any]]:
    """("set", set point) for frames with a set point, else ("measured", cluster centre) or ("unknown", None)
    (:func:`forensics.io.dataset.temperature_groups`, the rule ``forensics info`` lists them by too)."""
    from forensics.io.dataset import temperature_groups

    return temperature_groups([frames[i].set_temperature_c for i in members],
                              [frames[i].temperature_c for i in members], tolerance)


# =========================================================================== reading
def load_frame(path: str) -> np.ndarray:
    """A frame's pixels, 2-D (FITS through astropy, anything else through :func:`forensics.io.images.read_image`).

    Raises
    ------
    InputError
        The file cannot be read or is not a single-channel frame.
    """
    from forensics.io.fits import is_fits, read_fits
    from forensics.io.images import read_image

    data = read_fits(path).data if is_fits(path) else read_image(path)
    if data.ndim != 2:
        raise InputError(f"{path}: a {data.shape} image; a dark series needs single-channel frames (a raw mosaic, "
                         "a monochrome sensor)")
    return data


def _check_shape(data: np.ndarray, shape: tuple[int, int] | None, path: str) -> tuple[int, int]:
    if shape is not None and data.shape != shape:
        raise InputError(f"{path}: frame is {data.shape[1]}×{data.shape[0]}, the others are {shape[1]}×{shape[0]}; "
                         "a series' frames must all have one size")
    return data.shape  # type: ignore[return-value]


# =========================================================================== pass 1: sums
@dataclass
class GroupSums:
    """Per-pixel sums of one temperature group (flattened arrays) and the sparse list of samples left out."""

    shape: tuple[int, int]
    sy: np.ndarray
    sty: np.ndarray
    syy: np.ndarray
    sb: np.ndarray
    sbb: np.ndarray
    n_bias: int
    lo: np.ndarray
    hi: np.ndarray
    dtype: np.dtype
    drop_pixel: np.ndarray
    drop_frame: np.ndarray
    drop_value: np.ndarray

    def merge(self, other: "GroupSums") -> "GroupSums":
        """Add the next chunk's sums (in frame order; ``other`` is consumed)."""
        if other.shape != self.shape:
            raise InputError(f"frames of {other.shape[1]}×{other.shape[0]} among frames of "
                             f"{self.shape[1]}×{self.shape[0]}; a series' frames must all have one size")
        for name in ("sy", "sty", "syy", "sb", "sbb"):
            getattr(self, name).__iadd__(getattr(other, name))
        self.n_bias += other.n_bias
        np.minimum(self.lo, other.lo, out=self.lo)
        np.maximum(self.hi, other.hi, out=self.hi)
        self.drop_pixel = np.concatenate([self.drop_pixel, other.drop_pixel])
        self.drop_frame = np.concatenate([self.drop_frame, other.drop_frame])
        self.drop_value = np.concatenate([self.drop_value, other.drop_value])
        return self


def sums_item(item: tuple[int, tuple[tuple[int, str, float, bool], ...], float | None]) -> tuple[int, GroupSums]:
    """Work item of pass 1: ``(group, ((frame index in group, path, exposure, is bias), …), saturation)`` → partial
    sums.

    Module-level so the execution layer's workers import it; it reads its frames itself.
    """
    group, frames, saturation = item
    acc: GroupSums | None = None
    shape = None
    for local, path, t, bias in frames:
        data = load_frame(path)
        shape = _check_shape(data, shape, path)
        y = data.astype(np.float64).ravel()
        if acc is None:
            n = y.size
            acc = GroupSums(shape, *(np.zeros(n) for _ in range(5)), 0, data.ravel().copy(), data.ravel().copy(),
                            data.dtype, np.zeros(0, np.int64), np.zeros(0, np.int32), np.zeros(0))
        else:
            np.minimum(acc.lo, data.ravel(), out=acc.lo)
            np.maximum(acc.hi, data.ravel(), out=acc.hi)
        acc.sy += y
        acc.sty += t * y
        acc.syy += y * y
        if bias:
            acc.sb += y
            acc.sbb += y * y
            acc.n_bias += 1
        if saturation is not None:
            hit = np.flatnonzero(y >= saturation)
            if hit.size:
                acc.drop_pixel = np.concatenate([acc.drop_pixel, hit])
                acc.drop_frame = np.concatenate([acc.drop_frame, np.full(hit.size, local, np.int32)])
                acc.drop_value = np.concatenate([acc.drop_value, y[hit]])
    assert acc is not None
    return group, acc


# =========================================================================== the per-pixel line
@dataclass
class LineFit:
    """Every pixel's line in one group (flattened float64 arrays; NaN where fewer than two exposures remain)."""

    offset: np.ndarray
    rate: np.ndarray
    n: np.ndarray
    mean_t: np.ndarray
    sxx: np.ndarray
    t3: np.ndarray
    sx: np.ndarray


def solve_lines(sums: GroupSums, exposures: np.ndarray, extra_pixel: np.ndarray | None = None,
                extra_frame: np.ndarray | None = None, extra_value: np.ndarray | None = None) -> LineFit:
    """Least-squares line per pixel from the sums, without the samples left out (saturated and rejected).

    ``t3`` is Σ(t − t̄)²·t over the samples used (the shot-noise term of the rate's variance).
    """
    pix = sums.drop_pixel if extra_pixel is None else np.concatenate([sums.drop_pixel, extra_pixel])
    fr = sums.drop_frame if extra_frame is None else np.concatenate([sums.drop_frame, extra_frame])
    val = sums.drop_value if extra_value is None else np.concatenate([sums.drop_value, extra_value])
    size = sums.sy.size
    t = np.asarray(exposures, np.float64)
    tl = t[fr]

    def less(total: float, weights: np.ndarray | None) -> np.ndarray:
        out = np.full(size, total, np.float64)
        if pix.size:
            out -= np.bincount(pix, weights=weights, minlength=size)
        return out

    n = less(float(t.size), None)
    sx = less(float(t.sum()), tl)
    sxx = less(float((t * t).sum()), tl * tl)
    sxxx = less(float((t ** 3).sum()), tl ** 3)
    sy = sums.sy - (np.bincount(pix, weights=val, minlength=size) if pix.size else 0.0)
    sxy = sums.sty - (np.bincount(pix, weights=tl * val, minlength=size) if pix.size else 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean_t = sx / n
        centred = sxx - sx * mean_t
        scale = max(float((t * t).max()), 1.0)
        ok = (n >= 2) & (centred > 1e-9 * scale)
        rate = np.where(ok, (sxy - mean_t * sy) / centred, np.nan)
        offset = np.where(ok, (sy - rate * sx) / n, np.nan)
        t3 = sxxx - 2 * mean_t * sxx + mean_t * mean_t * sx
    return LineFit(offset, rate, n, mean_t, np.where(ok, centred, np.nan), t3, sx)


# =========================================================================== results
@dataclass
class FrameReport:
    """How one frame was used and how it fits the model."""

    path: str
    frame_type: str
    exposure_s: float
    temperature_c: float | None
    set_temperature_c: float | None
    group: int | None
    used: bool
    reason: str = ""
    common_residual: float | None = None
    level_deviation: float | None = None
    dark_level: float | None = None
    noise_ratio: float | None = None
    read_noise: float | None = None
    outliers: int = 0
    saturated: int = 0
    tested: int = 0
    problems: list[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        return self.path.rsplit("/", 1)[-1]

    def to_dict(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items()}


@dataclass
class GroupFit:
    """One temperature group's fit: maps (flattened to ``shape``; not serialised) and summary figures.

    ``rate`` is in ADU/s at ``temperature_c`` (the effective temperature, ± ``temperature_se``), ``offset`` in
    ADU; ``rate_se`` the standard error of each rate; ``noise_ratio`` each pixel's residual scatter against the
    noise model (1 when it follows it); ``misfit`` the pixels that do not follow a line; ``cosmic_pixels`` and
    ``cosmic_frames`` the samples left out as cosmic-ray hits (flat pixel index, frame index in the plan).
    """

    label: str
    set_temperature_c: float | None
    temperature_c: float | None
    temperature_se: float
    frames: list[int]
    exposures: list[float]
    n_bias: int
    bias_level: float
    bias_level_se: float
    read_noise: float
    read_noise_frames: list[float]
    offset_jitter: float
    median_rate: float
    median_rate_se: float
    median_rate_common_se: float
    outliers: int
    saturated: int
    shape: tuple[int, int]
    offset: np.ndarray = field(repr=False)
    rate: np.ndarray = field(repr=False)
    rate_se: np.ndarray = field(repr=False)
    noise_ratio: np.ndarray = field(repr=False)
    used: np.ndarray = field(repr=False)
    constant: np.ndarray = field(repr=False)
    misfit: np.ndarray = field(repr=False)
    exposure_weights: list[float] = field(default_factory=list)
    residual_sq: np.ndarray | None = field(default=None, repr=False)
    shot_charge: np.ndarray | None = field(default=None, repr=False)
    cosmic_pixels: np.ndarray | None = field(default=None, repr=False)
    cosmic_frames: np.ndarray | None = field(default=None, repr=False)

    def rate_map(self) -> np.ndarray:
        return self.rate.reshape(self.shape)

    def median_rate_ci(self, level: float = 0.95) -> tuple[float, float]:
        from scipy import stats

        z = float(stats.norm.ppf(0.5 + level / 2))
        return self.median_rate - z * self.median_rate_se, self.median_rate + z * self.median_rate_se

    def to_dict(self) -> dict[str, Any]:
        lo, hi = self.median_rate_ci()
        rn = self.read_noise_frames
        return {
            "label": self.label, "set_temperature_c": self.set_temperature_c, "temperature_c": self.temperature_c,
            "temperature_se": self.temperature_se, "frames": len(self.frames), "bias_frames": self.n_bias,
            "exposures_s": sorted(set(self.exposures)),
            "bias_level_adu": self.bias_level, "bias_level_se": self.bias_level_se,
            "read_noise_adu": self.read_noise,
            "read_noise_frames_adu": {"min": min(rn), "median": float(np.median(rn)), "max": max(rn)} if rn else None,
            "offset_jitter_adu": self.offset_jitter,
            "median_rate_adu_per_s": self.median_rate, "median_rate_ci": [lo, hi],
            "median_rate_se": self.median_rate_se, "median_rate_common_se": self.median_rate_common_se,
            "cosmic_ray_samples": self.outliers, "saturated_samples": self.saturated,
            "misfit_pixels": int(self.misfit.sum()),
            "pixels_fitted": int(np.isfinite(self.rate).sum()),
        }


@dataclass
class DarkSeriesFit:
    """A dark series fitted group by group (see the module notes)."""

    shape: tuple[int, int]
    groups: list[GroupFit]
    frames: list[FrameReport]
    gain_used: float
    gain_source: str
    gain: dict[str, Any] = field(default_factory=dict)
    saturation: float | None = None
    settings: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    #: the frames' on-chip binning (x, y); None where they do not state it
    binning: tuple[int, int] | None = None

    @property
    def n_frames(self) -> int:
        return sum(1 for f in self.frames if f.used and f.frame_type in DARK_TYPES)

    def named_frames(self) -> list[FrameReport]:
        """Frames left out or not following the model."""
        return [f for f in self.frames if (not f.used and f.frame_type in DARK_TYPES) or f.problems]

    def to_dict(self) -> dict[str, Any]:
        return {"shape": list(self.shape), "binning": list(self.binning) if self.binning else None,
                "groups": [g.to_dict() for g in self.groups],
                "gain_used_e_per_adu": self.gain_used, "gain_source": self.gain_source, "gain": self.gain,
                "saturation_adu": self.saturation, "settings": self.settings,
                "frames": [f.to_dict() for f in self.frames],
                "named_frames": [{"file": f.name, "why": f.reason or "; ".join(f.problems)}
                                 for f in self.named_frames()],
                "warnings": list(self.warnings)}


# =========================================================================== the fit
def fit_dark_series(plan: SeriesPlan, gain: float | None = None, saturation: float | None = None,
                    k: float = K_OUTLIER, k_grow: float = K_GROW, rounds: int = ROUNDS,
                    executor: Executor | None = None, progress: Progress = no_progress) -> DarkSeriesFit:
    """Fit every pixel's offset and dark rate in each temperature group, cosmic-ray hits excluded.

    Parameters
    ----------
    plan
        The series (:func:`plan_series`).
    gain
        Conversion gain (e⁻/ADU) of the noise model.  Default: from pairs of flat fields in the series
        (:func:`forensics.defects.darkgain.flat_pair_gain`), else the header's EGAIN, else 1 with a warning.
    saturation
        Samples at or above it (ADU) are left out.  Default: :data:`SATURATION_FRACTION` of the data type's
        full scale (none for floating-point data).
    k, k_grow, rounds
        The cosmic-ray test: deleted residuals above ``k`` σ, their neighbours above ``k_grow`` σ; ``rounds``
        robust rounds (each one more pass over the frames).
    executor, progress
        Chunks of :data:`CHUNK_FRAMES` frames are the work items of each pass.
    """
    from forensics._shared.parallel import resolve
    from forensics.defects import darkgain
    from forensics.defects.darkrounds import NoiseModel, robust_fit

    ex = resolve(executor)
    frames = plan.frames
    exposures = [np.array([frames[i].exposure_s for i in members], np.float64) for members in plan.groups]
    warnings = list(plan.warnings)
    if saturation is None:
        saturation = _default_saturation(_frame_dtype(frames[plan.groups[0][0]].path))
    sums = _pass_sums(plan, exposures, saturation, ex, progress)
    shape = sums[0].shape
    if any(s.shape != shape for s in sums):
        raise InputError("the temperature groups' frames differ in size; a series' frames must all have one size")
    lines = [solve_lines(s, t) for s, t in zip(sums, exposures)]
    bias_level = [_bias_level(s, line) for s, line in zip(sums, lines)]
    read_noise = _read_noises(sums, lines, plan, warnings)
    gain_info = {"header_e_per_adu": _header_gain(plan)}
    flat = darkgain.flat_pair_gain(plan, lines, exposures, read_noise, bias_level, ex, progress) if plan.flats else None
    if flat is not None:
        gain_info["flat_pairs"] = flat.to_dict()
    gain_used, source = _choose_gain(gain, flat, gain_info["header_e_per_adu"], warnings)
    noise = NoiseModel(bias_level, read_noise, gain_used, k, k_grow)
    robust = robust_fit(plan, sums, exposures, noise, max(0, rounds), ex, progress)
    groups, reports = _summarise(plan, sums, robust, exposures, noise, warnings)
    dark_ptc = darkgain.dark_shot_gain(groups, gain_used)
    if dark_ptc is not None:
        gain_info["dark_shot_noise"] = dark_ptc.to_dict()
    settings = {"k_outlier": k, "k_grow": k_grow, "rounds": rounds, "saturation_adu": saturation,
                "setpoint_tolerance_c": SETPOINT_TOLERANCE_C}
    return DarkSeriesFit(shape, groups, reports, gain_used, source, gain_info, saturation, settings, warnings,
                         plan.binning)


def chunk_items(plan: SeriesPlan, exposures: list[np.ndarray]
                ) -> list[tuple[int, tuple[tuple[int, str, float, bool], ...]]]:
    """Each group's frames cut into work items of :data:`CHUNK_FRAMES`: ``(group, ((frame in group, path, exposure,
    is bias), …))``."""
    out = []
    for g, members in enumerate(plan.groups):
        biases = plan.biases(g)
        entries = [(local, plan.frames[i].path, float(exposures[g][local]), bool(biases[local]))
                   for local, i in enumerate(members)]
        out += [(g, tuple(entries[s:s + CHUNK_FRAMES])) for s in range(0, len(entries), CHUNK_FRAMES)]
    return out


def _pass_sums(plan: SeriesPlan, exposures: list[np.ndarray], saturation: float | None, ex: Any,
               progress: Progress) -> list[GroupSums]:
    items = [(g, chunk, saturation) for g, chunk in chunk_items(plan, exposures)]
    sums: list[GroupSums | None] = [None] * len(plan.groups)
    for g, part in ex.map(sums_item, items, progress=progress, desc="dark series: sums"):
        sums[g] = part if sums[g] is None else sums[g].merge(part)  # type: ignore[union-attr]
    return sums  # type: ignore[return-value]


def _default_saturation(dtype: np.dtype) -> float | None:
    from forensics._shared.arrays import full_scale

    dtype = np.dtype(dtype)
    return SATURATION_FRACTION * full_scale(dtype) if dtype.kind in "ui" else None


def _frame_dtype(path: str) -> np.dtype:
    """The pixel type of a frame, from its header."""
    from forensics.io.fits import is_fits, read_fits_header
    from forensics.io.images import read_info

    return np.dtype(read_fits_header(path).dtype if is_fits(path) else read_info(path).dtype)


def _bias_level(sums: GroupSums, line: LineFit) -> float:
    """The median bias B (from the biases' mean when there are biases, else the fitted offsets)."""
    if sums.n_bias:
        return float(np.median(sums.sb / sums.n_bias))
    return float(np.nanmedian(line.offset))


def _read_noises(sums: list[GroupSums], lines: list[LineFit], plan: SeriesPlan, warnings: list[str]) -> list[float]:
    """Each group's read noise σ_r from its biases' per-pixel temporal variance (median, Gaussian-calibrated).

    The median of s² over pixels is σ²·median(χ²_ν)/ν for Gaussian noise, which the hot pixels' and random
    telegraph pixels' tails do not move.  Without two biases, from the line residuals of the group (whose bulk
    dark shot noise then inflates it slightly).
    """
    from scipy import stats

    out: list[float | None] = []
    for g, (s, line) in enumerate(zip(sums, lines)):
        if s.n_bias >= 2:
            nu = s.n_bias - 1
            var = (s.sbb - s.sb * s.sb / s.n_bias) / nu
        else:
            nu_arr = line.n - 2
            resid = s.syy - line.offset * s.sy - line.rate * s.sty
            with np.errstate(divide="ignore", invalid="ignore"):
                var = resid / nu_arr
            nu = int(np.nanmedian(nu_arr))
            if nu < 1:
                out.append(None)
                continue
            warnings.append(f"{plan.label(g)}: fewer than two bias frames: the read noise is taken from the dark "
                            "frames' scatter about each pixel's line (their dark shot noise included)")
        med = float(np.nanmedian(var))
        out.append(math.sqrt(max(med, 0.0) * nu / float(stats.chi2.median(nu))))
    known = [v for v in out if v is not None]
    if not known:
        raise InputError("no group has two biases or three exposures: the read noise cannot be measured; add bias frames")
    return [v if v is not None else float(np.median(known)) for v in out]


def _header_gain(plan: SeriesPlan) -> float | None:
    from forensics.io.fits import is_fits, read_fits_header

    for fr in plan.frames:
        if is_fits(fr.path):
            value = read_fits_header(fr.path).gain_e_per_adu
            if value is not None and value > 0:
                return float(value)
    return None


def _choose_gain(gain: float | None, flat: Any, header: float | None, warnings: list[str]) -> tuple[float, str]:
    if gain is not None:
        if not gain > 0:
            raise InputError(f"gain {gain}: give a positive conversion gain in e⁻/ADU")
        return float(gain), "given"
    if flat is not None and flat.gain > 0:
        return float(flat.gain), "flat pairs"
    if header is not None:
        return header, "header (EGAIN)"
    warnings.append("no conversion gain (no flat pairs, no EGAIN in the headers, none given): the noise model uses "
                    "1 e⁻/ADU, which overstates the dark charge's shot noise when the real gain is larger")
    return 1.0, "assumed 1"


def _summarise(plan: SeriesPlan, sums: list[GroupSums], robust: Any, exposures: list[np.ndarray], noise: Any,
               warnings: list[str]) -> tuple[list[GroupFit], list[FrameReport]]:
    frames = plan.frames
    reports: list[FrameReport] = []
    index_of: dict[int, FrameReport] = {}
    for i, fr in enumerate(frames):
        rep = FrameReport(fr.path, fr.frame_type, fr.exposure_s, fr.temperature_c, fr.set_temperature_c, None,
                          used=False, reason=plan.excluded.get(i, ""))
        if fr.frame_type in LIGHT_TYPES:
            rep.reason = "light frame: used for the conversion gain only"
        reports.append(rep)
        index_of[i] = rep
    groups = []
    for g, members in enumerate(plan.groups):
        s, t, jitter = sums[g], exposures[g], robust.jitter[g]
        if jitter == 0.0:
            warnings.append(f"{plan.label(g)}: fewer than three bias frames, so the frame-to-frame offset jitter is "
                            "unknown: the median rate's interval holds its pixel-sampling error only, and no frame "
                            "can be named as off the fitted lines")
        readings = {plan.frames[i].temperature_c for i in members if plan.frames[i].exposure_s > 0}
        if len(readings) == 1 and None not in readings:
            warnings.append(f"{plan.label(g)}: every dark frame reads the same temperature, so the thermometer's "
                            "resolution is unknown and its step is not part of the temperature's uncertainty")
        sat_count = np.bincount(s.drop_frame, minlength=len(members))
        out_count = np.bincount(robust.drops[g][1], minlength=len(members))
        stats = [robust.stats.get((g, local)) for local in range(len(members))]
        residuals = np.array([np.nan if fs is None else fs.common_residual for fs in stats])
        # a median over N pixels of residuals of spread σ_e has sampling error 1.2533·σ_e/√N
        sampling = np.array([np.nan if fs is None or not fs.tested else 1.2533 * fs.residual_sigma / math.sqrt(fs.tested)
                             for fs in stats])
        deviation, deviation_se = frame_deviations(residuals, t, jitter, sampling)
        for local, i in enumerate(members):
            rep = index_of[i]
            fs = robust.stats.get((g, local))
            rep.group, rep.used = g, True
            rep.saturated, rep.outliers = int(sat_count[local]), int(out_count[local])
            if fs is not None:
                rep.common_residual, rep.noise_ratio = fs.common_residual, fs.noise_ratio
                rep.dark_level = fs.dark_level
                rep.read_noise, rep.tested = fs.frame_read_noise, fs.tested
            rep.level_deviation = None if not math.isfinite(deviation[local]) else float(deviation[local])
            rep.problems = _frame_problems(rep, float(deviation_se[local]), jitter > 0, s.n_bias >= 2)
        groups.append(_group_fit(plan, g, s, robust, t, noise, [index_of[i] for i in members]))
    return groups, reports


def frame_deviations(residuals: np.ndarray, t: np.ndarray, jitter: float, sampling: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's common-mode residual against the line through the other good frames', and its SE.

    A frame whose offset jumped pulls every pixel's line, and so every other frame's residual; against the line of
    the others it stands out by the whole jump.  Frames are tested one at a time, the worst first, and a frame
    beyond :data:`FRAME_Z` SEs leaves the set the others are compared with (so one bad frame does not make its
    neighbours look bad).  The SE combines the offset jitter σ_o (leverage included) with each frame's median
    sampling error.
    """
    n = residuals.size
    good = np.isfinite(residuals) & np.isfinite(sampling)
    while True:
        out, se = _deviations(residuals, t, jitter, sampling, good)
        z = np.where(good & (se > 0), np.abs(out) / np.where(se > 0, se, 1.0), 0.0)
        worst = int(np.argmax(z)) if n else 0
        if n == 0 or z[worst] <= FRAME_Z or good.sum() <= 4:
            return out, se
        good[worst] = False


def _deviations(residuals: np.ndarray, t: np.ndarray, jitter: float, sampling: np.ndarray, good: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    n = residuals.size
    out, se = np.full(n, np.nan), np.full(n, np.nan)
    for f in range(n):
        others = good.copy()
        others[f] = False
        if not np.isfinite(residuals[f]) or others.sum() < 3:
            continue
        x, y, w = t[others], residuals[others], sampling[others]
        mean_x = x.mean()
        sxx = float(((x - mean_x) ** 2).sum())
        slope = float(((x - mean_x) * (y - y.mean())).sum() / sxx) if sxx > 0 else 0.0
        leverage = 1 / others.sum() + ((t[f] - mean_x) ** 2 / sxx if sxx > 0 else 0.0)
        out[f] = residuals[f] - (y.mean() + slope * (t[f] - mean_x))
        se[f] = math.sqrt((jitter ** 2 + float(np.mean(w ** 2))) * leverage + jitter ** 2 + sampling[f] ** 2)
    return out, se


def _frame_problems(rep: FrameReport, deviation_se: float, jitter_known: bool = True,
                    read_noise_measured: bool = True) -> list[str]:
    """What is wrong with a frame.  Without the offset jitter (fewer than three biases) a frame's level is not
    tested: its standard error would hold the pixel sampling only, and every frame's ordinary jitter (a few tenths
    of an ADU) would name it.  Without two biases the read noise comes from the darks' scatter, their dark shot
    noise included, so the model's noise is an upper bound: only frames noisier than it are named."""
    problems = []
    dev = rep.level_deviation
    if jitter_known and dev is not None and deviation_se > 0 and abs(dev) > FRAME_Z * deviation_se:
        per_s = f" ({dev / rep.exposure_s:+.3g} ADU/s)" if rep.exposure_s > 0 else ""
        problems.append(f"median level {dev:+.2f} ADU{per_s} off the line of the other frames, "
                        f"{abs(dev) / deviation_se:.1f}× its standard error (offset jitter σ_o from the biases)")
    ratio = rep.noise_ratio
    if ratio is not None and math.isfinite(ratio) and (ratio - 1 > NOISE_TOLERANCE
                                                        or (read_noise_measured and 1 - ratio > NOISE_TOLERANCE)):
        problems.append(f"noise {rep.noise_ratio:.2f}× the read + shot noise model")
    if rep.tested and rep.outliers > OUTLIER_SHARE * rep.tested:
        problems.append(f"{rep.outliers} samples ({rep.outliers / rep.tested:.1%}) rejected as outliers: a light "
                        "leak, a bad readout or an unusually heavy cosmic-ray exposure")
    return problems


def _group_fit(plan: SeriesPlan, g: int, s: GroupSums, robust: Any, t: np.ndarray, noise: Any,
               reports: list[FrameReport]) -> GroupFit:
    from forensics.defects.darkrounds import expected_residual_sq

    line, jitter, esq = robust.lines[g], robust.jitter[g], robust.residual_sq[g]
    bias, read_noise, gain = noise.bias_level[g], noise.read_noise[g], noise.gain
    members = plan.groups[g]
    temps = [plan.frames[i].temperature_c for i in members]
    centred = t - t.mean()
    sxx = float((centred * centred).sum())
    weights = centred * t / sxx  # c_f·t_f: the slope's sensitivity to each frame's rate; sums to 1
    if all(v is not None for v in temps):
        temp = np.asarray(temps, float)
        t_eff = float((weights * temp).sum())
        spread = float(np.std(temp[t > 0], ddof=1)) if (t > 0).sum() >= 2 else 0.0
        t_se = spread * float(np.sqrt((weights ** 2).sum()))

    else:
        t_eff, t_se = None, 0.0
    a, r = line.offset, line.rate
    base = read_noise ** 2 + jitter ** 2 + np.maximum(a - bias, 0) / gain
    expected, shot = expected_residual_sq(line, bias, read_noise, jitter, gain)
    with np.errstate(divide="ignore", invalid="ignore"):
        var_r = base / line.sxx + np.maximum(r, 0) / gain * line.t3 / line.sxx ** 2
        ratio = np.sqrt(esq / expected)
    finite = np.isfinite(r)
    med = float(np.median(r[finite])) if finite.any() else float("nan")
    spread_r = 1.4826 * float(np.median(np.abs(r[finite] - med))) if finite.any() else float("nan")
    stat_se = 1.2533 * spread_r / math.sqrt(max(int(finite.sum()), 1))  # the median's sampling error
    common_se = jitter / math.sqrt(sxx)  # the offset jitter moves every pixel's slope alike
    rn_frames = [rep.read_noise for rep in reports if rep.read_noise is not None]
    return GroupFit(
        label=plan.label(g), set_temperature_c=plan.setpoints[g], temperature_c=t_eff, temperature_se=t_se,
        frames=list(members), exposures=t.tolist(), n_bias=s.n_bias, bias_level=bias,
        bias_level_se=jitter / math.sqrt(s.n_bias) if s.n_bias else float("nan"),
        read_noise=read_noise, read_noise_frames=rn_frames, offset_jitter=jitter, median_rate=med,
        median_rate_se=math.hypot(stat_se, common_se), median_rate_common_se=common_se,
        outliers=int(robust.drops[g][0].size), saturated=int(s.drop_pixel.size), shape=s.shape,
        offset=a.astype(np.float32), rate=r.astype(np.float32), rate_se=np.sqrt(var_r).astype(np.float32),
        noise_ratio=ratio.astype(np.float32), used=np.nan_to_num(line.n).astype(np.uint16), constant=(s.lo == s.hi),
        misfit=robust.misfit[g], exposure_weights=weights.tolist(), residual_sq=esq,
        shot_charge=np.where(np.isfinite(shot), shot, np.nan), cosmic_pixels=robust.drops[g][0],
        cosmic_frames=np.asarray(members)[robust.drops[g][1]] if robust.drops[g][1].size else np.zeros(0, int),
    )
