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
2. **Robust rounds.**  Each round streams the frames again and tests every sample against the current fit:
   its *deleted* residual (the residual it would have if its own frame were left out of the pixel's line,
   z = e / (σ·√(1 − h)), h the sample's leverage) above ``k`` standard deviations of the read + shot noise
   model marks a cosmic-ray hit (charge is only ever added, so the test is one-sided); the hit's neighbours
   in the same frame are marked from ``k_grow`` σ, since a track spreads charge.  Marked samples are left
   out (their sums subtracted) and every pixel's line is solved again.  A single frame per exposure is
   enough: the deleted residual does not let the hit pull the line towards itself.
3. The last round also measures, per frame, its common-mode residual (the median over pixels of y − a − r·t:
   a frame whose median dark level is off the line, or whose bias drifted), its noise against the model and
   its share of rejected samples, and, per pixel, the residual sum of squares (for the per-pixel excess noise
   and the gain from the dark signal's shot noise, :mod:`forensics.defects.darkgain`).

Every pixel's rate has a standard error from the noise model (read noise, shot noise of its dark charge, and
the frame-to-frame offset jitter σ_o measured on the bias frames); the group's median rate has an interval
that includes the jitter's common-mode effect, which does not average out over pixels.  A group's rates refer
to its *effective* temperature, the exposure-weighted mean of the measured CCD-TEMP that the fitted slope
actually sees (Σ c_f·t_f·T_f with the slope's weights c_f), so the small wander of the measured temperature
around the set point needs no temperature law.

Frames are grouped by their set point (or, without one, by their measured temperature); a frame whose measured
temperature is more than :data:`forensics.io.fits.SETPOINT_TOLERANCE_C` from its set point never settled and
is left out, named.  Memory: about 40 bytes per pixel per temperature group for the sums, 20 more per group
during a robust round (the fit shipped to the workers) and 8 in the last round; the result keeps about
18 bytes per pixel per group (offset, rate, its error, residual noise, samples used).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import ndimage

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
        A frame without an exposure time or frame type, or frames of which only some give a temperature.
    """
    frames = tuple(frames)
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
    """("set", set point) for frames with a set point, else ("measured", cluster centre) or ("unknown", None)."""
    keys: dict[int, tuple[str, Any]] = {}
    loose = []
    for i in members:
        fr = frames[i]
        if fr.set_temperature_c is not None:
            keys[i] = ("set", round(float(fr.set_temperature_c), 1))
        elif fr.temperature_c is not None:
            loose.append(i)
        else:
            keys[i] = ("unknown", None)
    loose.sort(key=lambda i: frames[i].temperature_c)  # type: ignore[arg-type, return-value]
    cluster: list[int] = []
    for i in loose + [None]:  # type: ignore[list-item]
        if cluster and (i is None or frames[i].temperature_c - frames[cluster[-1]].temperature_c > tolerance):
            centre = round(float(np.median([frames[j].temperature_c for j in cluster])), 1)
            keys.update({j: ("measured", centre) for j in cluster})
            cluster = []
        if i is not None:
            cluster.append(i)
    return [keys[i] for i in members]


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


def sums_item(item: tuple[int, tuple[tuple[int, str, float], ...], float | None]) -> tuple[int, GroupSums]:
    """Work item of pass 1: ``(group, ((frame index in group, path, exposure), …), saturation)`` → partial sums.

    Module-level so the execution layer's workers import it; it reads its frames itself.
    """
    group, frames, saturation = item
    acc: GroupSums | None = None
    shape = None
    for local, path, t in frames:
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
        if t == 0:
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


# =========================================================================== robust rounds
@dataclass
class RoundState:
    """What every round's work item needs (shipped once per worker): each group's fit and the noise model."""

    shape: tuple[int, int]
    offset: list[np.ndarray]
    rate: list[np.ndarray]
    n: list[np.ndarray]
    mean_t: list[np.ndarray]
    sxx: list[np.ndarray]
    sx: list[np.ndarray]
    t3: list[np.ndarray]
    noise: "NoiseModel"
    dropped: list[dict[int, np.ndarray]]
    exempt: list[np.ndarray]


@dataclass
class FrameStats:
    """One frame's measurements in a round."""

    local: int
    flagged_pixel: np.ndarray
    flagged_value: np.ndarray
    common_residual: float
    noise_ratio: float
    frame_read_noise: float | None
    tested: int


def residual_variance(t: float, offset: np.ndarray, rate: np.ndarray, n: np.ndarray, mean_t: np.ndarray,
                      sxx: np.ndarray, sx: np.ndarray, t3: np.ndarray, bias: float, read_noise: float,
                      gain: float) -> np.ndarray:
    """Variance of the least-squares residual of the sample at exposure ``t`` under the noise model.

    With σ_f² = A + B·t_f (A = σ_r² + max(a − B₀, 0)/g, B = max(r, 0)/g), leverages h_fj = 1/n + u_f·u_j/Sxx
    (u = t − t̄): Var e_f = σ_f²(1 − 2h_ff) + Σ_j h_fj²σ_j² = A(1 − h_ff) + B·[t_f(1 − 2h_ff) + Σt/n² + 2u_f/n +
    u_f²·Σu²t/Sxx²].  Exact where the noise is heteroscedastic (shot noise), where the homoscedastic σ_f²(1 − h_ff)
    overstates a long exposure's residual variance and hides hits in it.
    """
    t32 = np.float32(t)
    inv_gain = np.float32(1.0 / gain)
    a_term = np.float32(read_noise ** 2) + np.maximum(offset - np.float32(bias), 0) * inv_gain
    b_term = np.maximum(rate, 0) * inv_gain
    u = t32 - mean_t
    h = 1 / n + u * u / sxx
    shot = t32 * (1 - 2 * h) + sx / (n * n) + 2 * u / n + u * u * t3 / (sxx * sxx)
    return a_term * (1 - h) + b_term * shot


def round_item(state: RoundState, item: tuple[int, tuple[tuple[int, str, float], ...], bool]
               ) -> tuple[int, list[FrameStats], np.ndarray | None]:
    """Work item of a robust round: test a chunk of frames against the group's fit (see the module notes).

    Returns the group, each frame's statistics and marked samples, and (last round) the chunk's per-pixel
    residual sum of squares over the samples kept.
    """
    group, frames, last = item
    shape = state.shape
    nm = state.noise
    a, r = state.offset[group], state.rate[group]
    fit = (state.n[group], state.mean_t[group], state.sxx[group], state.sx[group], state.t3[group])
    esq = np.zeros(a.size, np.float64) if last else None
    out = []
    for local, path, t in frames:
        data = load_frame(path)
        _check_shape(data, shape, path)
        y = data.astype(np.float32).ravel()
        e = y - a - r * np.float32(t)
        with np.errstate(divide="ignore", invalid="ignore"):
            var = residual_variance(t, a, r, *fit, nm.bias_level[group], nm.read_noise[group], nm.gain)
            z = e / np.sqrt(var)
        valid = np.isfinite(z) & (var > 0)
        gone = state.dropped[group].get(local)
        if gone is not None and gone.size:
            valid[gone] = False
        testable = valid.copy()
        testable[state.exempt[group]] = False
        flag = testable & (z > nm.k)
        if nm.k_grow < nm.k and flag.any():
            near = ndimage.binary_dilation(flag.reshape(shape), structure=np.ones((3, 3), bool)).ravel()
            flag |= near & testable & (z > nm.k_grow)
        kept = valid & ~flag
        idx = np.flatnonzero(flag)
        zk = z[kept]
        med_z = float(np.median(zk)) if zk.size else float("nan")
        ratio = float(1.4826 * np.median(np.abs(zk - med_z))) if zk.size else float("nan")
        frame_rn = None
        if t == 0 and kept.any():
            with np.errstate(divide="ignore", invalid="ignore"):
                scaled = e[kept] / np.sqrt(1 - 1 / fit[0][kept] - fit[1][kept] ** 2 / fit[2][kept])
            frame_rn = float(1.4826 * np.median(np.abs(scaled - np.median(scaled))))
        out.append(FrameStats(local, idx.astype(np.int64), y[idx].astype(np.float64),
                              float(np.median(e[kept])) if kept.any() else float("nan"), ratio, frame_rn,
                              int(valid.sum())))
        if esq is not None:
            ek = np.where(kept, e, 0).astype(np.float64)
            esq += ek * ek
    return group, out, esq


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
    noise model (1 when it follows it).
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

    @property
    def n_frames(self) -> int:
        return sum(1 for f in self.frames if f.used and f.frame_type in DARK_TYPES)

    def named_frames(self) -> list[FrameReport]:
        """Frames left out or not following the model."""
        return [f for f in self.frames if (not f.used and f.frame_type in DARK_TYPES) or f.problems]

    def to_dict(self) -> dict[str, Any]:
        return {"shape": list(self.shape), "groups": [g.to_dict() for g in self.groups],
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
    lines, extra, stats, esq, misfit = _robust_rounds(plan, sums, exposures, lines, noise, rounds, ex, progress)
    groups, reports = _summarise(plan, sums, lines, extra, exposures, stats, esq, misfit, noise, warnings)
    dark_ptc = darkgain.dark_shot_gain(groups, gain_used)
    if dark_ptc is not None:
        gain_info["dark_shot_noise"] = dark_ptc.to_dict()
    settings = {"k_outlier": k, "k_grow": k_grow, "rounds": rounds, "saturation_adu": saturation,
                "setpoint_tolerance_c": SETPOINT_TOLERANCE_C}
    return DarkSeriesFit(shape, groups, reports, gain_used, source, gain_info, saturation, settings, warnings)


@dataclass(frozen=True)
class NoiseModel:
    """Each group's median bias B and read noise σ_r, the gain g and the outlier test's thresholds."""

    bias_level: list[float]
    read_noise: list[float]
    gain: float
    k: float
    k_grow: float


Drops = tuple[np.ndarray, np.ndarray, np.ndarray]  # (pixel, frame within group, value) of samples left out


def _robust_rounds(plan: SeriesPlan, sums: list[GroupSums], exposures: list[np.ndarray], lines: list[LineFit],
                   noise: NoiseModel, rounds: int, ex: Any, progress: Progress
                   ) -> tuple[list[LineFit], list[Drops], dict[tuple[int, int], FrameStats], list[np.ndarray | None],
                              list[np.ndarray]]:
    """Mark cosmic-ray hits round by round and refit (see the module notes).

    A pixel with more marked samples than cosmic rays could plausibly give it (:func:`max_hits`, from the
    observed rate of hits) does not follow a line at all — a hot pixel whose dark signal is not linear in the
    exposure: its marks are withdrawn, it is exempt from later rounds and reported as a misfit.
    """
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int32), np.zeros(0))
    extra: list[Drops] = [empty for _ in sums]
    exempt = [np.zeros(s.sy.size, bool) for s in sums]
    stats: dict[tuple[int, int], FrameStats] = {}
    esq: list[np.ndarray | None] = [None] * len(sums)
    total = max(1, rounds)
    for round_index in range(total):
        last = round_index == total - 1
        state = _round_state(sums[0].shape, sums, lines, extra, exempt, noise)
        items = [(g, chunk, last) for g, chunk in _chunks(plan, exposures)]
        new: list[list[Drops]] = [[] for _ in sums]
        for g, frame_stats, part in ex.map(round_item, items, shared=state, progress=progress,
                                           desc=f"dark series: round {round_index + 1}"):
            for fs in frame_stats:
                stats[(g, fs.local)] = fs  # the last round's measurements are the ones reported
                new[g].append((fs.flagged_pixel, np.full(fs.flagged_pixel.size, fs.local, np.int32), fs.flagged_value))
            if part is not None:
                esq[g] = part if esq[g] is None else esq[g] + part
        for g in range(len(sums)):
            merged = tuple(np.concatenate([extra[g][j]] + [x[j] for x in new[g]]) for j in range(3))
            extra[g], misfits = _withdraw_misfits(merged, sums[g].sy.size)  # type: ignore[arg-type]
            exempt[g] |= misfits
        lines = [solve_lines(s, t, *x) for s, t, x in zip(sums, exposures, extra)]
    return lines, extra, stats, esq, exempt


def max_hits(rate: float, pixels: int) -> int:
    """The most cosmic-ray hits one pixel may plausibly take: the smallest m with pixels·P(Poisson(rate) > m) < ½."""
    from scipy import stats

    m = 1
    while pixels * float(stats.poisson.sf(m, rate)) >= 0.5:
        m += 1
    return m


def _withdraw_misfits(drops: Drops, size: int) -> tuple[Drops, np.ndarray]:
    """Withdraw the marks of pixels with more marked samples than cosmic rays explain; return them as misfits."""
    pix = drops[0]
    misfit = np.zeros(size, bool)
    if pix.size == 0:
        return drops, misfit
    counts = np.bincount(pix, minlength=size)
    limit = max_hits(pix.size / size, size)
    misfit = counts > limit
    keep = ~misfit[pix]
    return (pix[keep], drops[1][keep], drops[2][keep]), misfit


def _chunks(plan: SeriesPlan, exposures: list[np.ndarray]) -> list[tuple[int, tuple[tuple[int, str, float], ...]]]:
    out = []
    for g, members in enumerate(plan.groups):
        entries = [(local, plan.frames[i].path, float(exposures[g][local])) for local, i in enumerate(members)]
        out += [(g, tuple(entries[s:s + CHUNK_FRAMES])) for s in range(0, len(entries), CHUNK_FRAMES)]
    return out


def _pass_sums(plan: SeriesPlan, exposures: list[np.ndarray], saturation: float | None, ex: Any,
               progress: Progress) -> list[GroupSums]:
    items = [(g, chunk, saturation) for g, chunk in _chunks(plan, exposures)]
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


def _round_state(shape: tuple[int, int], sums: list[GroupSums], lines: list[LineFit], extra: list[Drops],
                 exempt: list[np.ndarray], noise: NoiseModel) -> RoundState:
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731  (the shipped fit: 28 bytes per pixel per group)
    dropped = []
    for s, x in zip(sums, extra):
        pix = np.concatenate([s.drop_pixel, x[0]])
        fr = np.concatenate([s.drop_frame, x[1]])
        order = np.argsort(fr, kind="stable")
        pix, fr = pix[order], fr[order]
        bounds = np.flatnonzero(np.diff(fr)) + 1
        dropped.append({int(fr[p[0]]): pix[p] for p in np.split(np.arange(fr.size), bounds) if p.size})
    return RoundState(shape, [f32(li.offset) for li in lines], [f32(li.rate) for li in lines],
                      [f32(li.n) for li in lines], [f32(li.mean_t) for li in lines], [f32(li.sxx) for li in lines],
                      [f32(li.sx) for li in lines], [f32(li.t3) for li in lines], noise, dropped,
                      [np.flatnonzero(e) for e in exempt])


def _summarise(plan: SeriesPlan, sums: list[GroupSums], lines: list[LineFit], extra: list[Drops],
               exposures: list[np.ndarray], stats: dict[tuple[int, int], FrameStats], esq: list[np.ndarray | None],
               misfit: list[np.ndarray], noise: NoiseModel, warnings: list[str]
               ) -> tuple[list[GroupFit], list[FrameReport]]:
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
        s, line, t = sums[g], lines[g], exposures[g]
        jitter = _offset_jitter(g, members, t, stats)
        if jitter == 0.0:
            warnings.append(f"{plan.label(g)}: fewer than three bias frames, so the frame-to-frame offset jitter is "
                            "unknown: the median rate's interval holds its pixel-sampling error only, and no frame "
                            "can be named as off the fitted lines")
        sat_count = np.bincount(s.drop_frame, minlength=len(members))
        out_count = np.bincount(extra[g][1], minlength=len(members))
        for local, i in enumerate(members):
            rep = index_of[i]
            fs = stats.get((g, local))
            rep.group, rep.used = g, True
            rep.saturated, rep.outliers = int(sat_count[local]), int(out_count[local])
            if fs is not None:
                rep.common_residual, rep.noise_ratio = fs.common_residual, fs.noise_ratio
                rep.read_noise, rep.tested = fs.frame_read_noise, fs.tested
            rep.problems = _frame_problems(rep, jitter)
        groups.append(_group_fit(plan, g, s, line, t, jitter, noise.bias_level[g], noise.read_noise[g], noise.gain,
                                 esq[g], [index_of[i] for i in members], int(extra[g][0].size),
                                 int(s.drop_pixel.size), misfit[g]))
    return groups, reports


def _offset_jitter(g: int, members: tuple[int, ...], t: np.ndarray, stats: dict[tuple[int, int], FrameStats]) -> float:
    """σ_o: the scatter of the biases' common-mode residuals (the frame-to-frame offset jitter), 0 if unknown."""
    values = [stats[(g, local)].common_residual for local in range(len(members))
              if t[local] == 0 and (g, local) in stats and math.isfinite(stats[(g, local)].common_residual)]
    return float(np.std(values, ddof=1)) if len(values) >= 3 else 0.0


def _frame_problems(rep: FrameReport, jitter: float) -> list[str]:
    problems = []
    if rep.common_residual is not None and jitter > 0 and abs(rep.common_residual) > FRAME_Z * jitter:
        per_s = f" ({rep.common_residual / rep.exposure_s:+.3g} ADU/s)" if rep.exposure_s > 0 else ""
        problems.append(f"median level {rep.common_residual:+.2f} ADU{per_s} off the fitted lines, "
                        f"{abs(rep.common_residual) / jitter:.1f}× the biases' offset jitter σ_o = {jitter:.2f} ADU")
    if rep.noise_ratio is not None and math.isfinite(rep.noise_ratio) and abs(rep.noise_ratio - 1) > NOISE_TOLERANCE:
        problems.append(f"noise {rep.noise_ratio:.2f}× the read + shot noise model")
    if rep.tested and rep.outliers > OUTLIER_SHARE * rep.tested:
        problems.append(f"{rep.outliers} samples ({rep.outliers / rep.tested:.1%}) rejected as outliers: a light "
                        "leak, a bad readout or an unusually heavy cosmic-ray exposure")
    return problems


def _group_fit(plan: SeriesPlan, g: int, s: GroupSums, line: LineFit, t: np.ndarray, jitter: float, bias: float,
               read_noise: float, gain: float, esq: np.ndarray | None, reports: list[FrameReport], outliers: int,
               saturated: int, misfit: np.ndarray) -> GroupFit:
    members = plan.groups[g]
    temps = np.array([plan.frames[i].temperature_c for i in members], dtype=object)
    centred = t - t.mean()
    sxx = float((centred * centred).sum())
    weights = centred * t / sxx  # c_f·t_f: the slope's sensitivity to each frame's rate; sums to 1
    if all(v is not None for v in temps):
        temps = temps.astype(float)
        t_eff = float((weights * temps).sum())
        spread = float(np.std(temps[t > 0], ddof=1)) if (t > 0).sum() >= 2 else 0.0
        t_se = spread * float(np.sqrt((weights ** 2).sum()))
    else:
        t_eff, t_se = None, 0.0
    a, r = line.offset, line.rate
    charge0 = np.maximum(a - bias, 0)
    base = read_noise ** 2 + jitter ** 2 + charge0 / gain
    with np.errstate(divide="ignore", invalid="ignore"):
        var_r = base / line.sxx + np.maximum(r, 0) / gain * line.t3 / line.sxx ** 2
        shot = charge0 * (line.n - 2) + np.maximum(r, 0) * (line.sx - line.sx / line.n - line.t3 / line.sxx)
        expected = (read_noise ** 2 + jitter ** 2) * (line.n - 2) + shot / gain
        ratio = np.sqrt(esq / expected) if esq is not None else np.full(a.size, np.nan)
    finite = np.isfinite(r)
    med = float(np.median(r[finite])) if finite.any() else float("nan")
    spread_r = 1.4826 * float(np.median(np.abs(r[finite] - med))) if finite.any() else float("nan")
    stat_se = 1.2533 * spread_r / math.sqrt(max(int(finite.sum()), 1))
    common_se = jitter / math.sqrt(sxx)
    bias_se = jitter / math.sqrt(s.n_bias) if s.n_bias else float("nan")
    const = (s.lo == s.hi)
    rn_frames = [rep.read_noise for rep in reports if rep.read_noise is not None]
    return GroupFit(
        label=plan.label(g), set_temperature_c=plan.setpoints[g], temperature_c=t_eff, temperature_se=t_se,
        frames=list(members), exposures=t.tolist(), n_bias=s.n_bias, bias_level=bias, bias_level_se=bias_se,
        read_noise=read_noise, read_noise_frames=rn_frames, offset_jitter=jitter, median_rate=med,
        median_rate_se=math.hypot(stat_se, common_se), median_rate_common_se=common_se, outliers=outliers,
        saturated=saturated, shape=s.shape, offset=a.astype(np.float32), rate=r.astype(np.float32),
        rate_se=np.sqrt(var_r).astype(np.float32), noise_ratio=ratio.astype(np.float32),
        used=np.nan_to_num(line.n).astype(np.uint16), constant=const, misfit=misfit,
        exposure_weights=weights.tolist(),
        residual_sq=esq, shot_charge=np.where(np.isfinite(shot), shot, np.nan),
    )
