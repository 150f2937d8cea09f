"""Dark calibration of raw CCD frames before their noise residuals: ``frame − offset − rate·exposure``.

An astronomer calibrates a raw CCD frame by subtracting a master bias and a master dark scaled to the frame's
exposure (ccdproc's ``subtract_bias`` and ``subtract_dark(..., scale=True)``).  Without it, a flat field's noise
residual keeps the sensor's *additive* fixed pattern — the bias structure, the dark-signal non-uniformity (DSNU)
and the hot pixels, each grown by the exposure — and a "PRNU" fingerprint of raw flats is partly a fingerprint of
the dark pattern: it matches dark frames, and its PRNU part is diluted by the hot pixels' spikes.  A scalar black
level cannot help; it only changes the intensity weight.

The master frames come from the project's dark-series fit (:func:`forensics.defects.darkseries.fit_dark_series`),
not from a second implementation: per temperature group, every pixel's line ``y = a_p + r_p·t`` through the biases
and darks (streamed per-pixel sums, one frame in memory at a time), cosmic-ray hits rejected against the pixel's own
line (one-sided 5σ, neighbours from 3σ: the robust rounds of :mod:`forensics.defects.darkrounds`).  That line is
ccdproc's master bias (``a_p``; it includes the dark charge collected during read-out) and its exposure-scaled
master dark (``r_p``, ADU/s) at once, fitted over every exposure instead of a median of repeats; with one frame per
exposure — the common case — a per-pixel median would not reject cosmic rays at all.

**Temperature.**  A frame is calibrated with the group of its set point (else the group whose temperature lies within
:data:`~forensics.defects.darkseries.SETPOINT_TOLERANCE_C` of its measured one).  When no group is that close the
calibration is refused — dark current doubles every 5–9 °C (≈ 5 °C for the bulk of the STL-1001E of the README, 6–9
°C for its hot pixels), so darks 5 °C off leave half the pattern or add it back — unless a doubling temperature
``doubling_c`` is given, which scales the rates by 2^((T_frame − T_group)/T_d) (:meth:`TemperatureLaw.constant
<forensics.defects.darklaw.TemperatureLaw.constant>`), also inside a group from its effective temperature to the
frame's measured one.  One T_d for every pixel is an approximation (hot pixels double more slowly than the bulk):
the matching group is always preferred.  The offset is not scaled (its read-out charge is a few ADU).

**Frames reduced already.**  Capture software often subtracts a dark itself (CCDSoft's auto-dark; the 2017 STL-1001E
flats of the README are such frames: their hottest pixels, which add up to 37,600 ADU to a raw 23 s frame, show
nothing).  Calibrating those again puts the pattern back in, negated.  So every frame's *share* of the predicted
pattern is measured first (:func:`dark_pattern_share`, at the 256 hottest isolated pixels: 1 for a raw frame, 0 for
a reduced one), one streamed read per frame before the build.  With ``scale='exposure'`` (ccdproc's
``subtract_dark(scale=True)``, the default) a frame clearly below half is refused, named; with ``scale='fit'`` each
frame's pattern is scaled by its share — the "dark frame optimisation" of astronomical software — which calibrates
raw frames as the exposure does (share 1.00 ± 0.01) and also removes what an imperfect reduction left.

Saturated raw pixels (at the frame type's full scale) stay saturated after calibration, so the fingerprint's
saturation mask still excludes them; every calibrated frame is float32 in ADU with that full scale as its white
level.  Memory: two float32 maps per temperature group (8 MB per group at 1 MP), plus one frame at a time; the fit
of the master frames peaks at ≈ 0.75 GB for the 42 frames of 1 MP of the 2017 series (its per-pixel sums).
"""
from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from forensics._shared.arrays import full_scale
from forensics._shared.errors import InputError, UsageError
from forensics._shared.progress import Progress, no_progress
from forensics.prnu.imageset import ImageSet

if TYPE_CHECKING:
    from forensics._shared.parallel import Executor
    from forensics.io.dataset import Dataset, Frame

__all__ = ["DarkGroup", "DarkCalibration", "FrameCalibration", "CalibratedFrame", "dark_calibration"]


#: Pixels at which a frame's share of the predicted dark pattern is measured (the hottest isolated ones).
PROBES = 256
#: A frame showing less than this share of the predicted dark pattern, measured to better than
#: :data:`DECISIVE_SE`, was dark-subtracted already (raw frames show 1, dark-subtracted ones 0: the midpoint).
SHARE_REFUSED = 0.5
DECISIVE_SE = 0.1
#: How the dark pattern is scaled to a frame (:class:`DarkCalibration`).
SCALES = ("exposure", "fit")


@dataclass(frozen=True)
class DarkGroup:
    """One temperature group's master frames: ``offset`` (ADU; bias plus read-out charge) and ``rate`` (ADU/s at
    ``temperature_c``, the group's effective temperature), float32 of the frame's shape."""

    label: str
    set_temperature_c: float | None
    temperature_c: float | None
    offset: np.ndarray = field(repr=False)
    rate: np.ndarray = field(repr=False)
    filled: int = 0
    probes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)

    def to_dict(self) -> dict[str, Any]:
        return {"label": self.label, "set_temperature_c": self.set_temperature_c,
                "temperature_c": self.temperature_c, "median_offset_adu": float(np.median(self.offset)),
                "median_rate_adu_per_s": float(np.median(self.rate)), "pixels_filled": self.filled}


@dataclass(frozen=True)
class FrameCalibration:
    """How one frame is calibrated: its exposure, the group used, the temperature factor of its rates, the scale of
    the whole dark pattern (1, or the frame's own share with ``scale='fit'``) and the share measured
    (:func:`dark_pattern_share`, with its standard error; NaN and inf before it is measured)."""

    exposure_s: float
    group: int
    factor: float
    scale: float = 1.0
    share: float = math.nan
    share_se: float = math.inf

    def to_dict(self) -> dict[str, Any]:
        return {"exposure_s": self.exposure_s, "group": self.group, "temperature_factor": self.factor,
                "scale": self.scale, "dark_share": None if math.isnan(self.share) else self.share,
                "dark_share_se": None if math.isinf(self.share_se) else self.share_se}


@dataclass(frozen=True)
class DarkCalibration:
    """Master offset and dark rate per temperature group, for ``frame − offset − factor·rate·exposure``.

    ``white_level`` is the full scale of the dark frames' type (the calibrated frames' saturation level);
    ``doubling_c`` the doubling temperature used across temperatures (None: refuse a frame no group matches);
    ``scale`` how the pattern is scaled to a frame: ``'exposure'`` (ccdproc's ``subtract_dark(scale=True)``; a frame
    showing less than half the predicted pattern is refused) or ``'fit'`` (each frame's own measured share of it, the
    "dark frame optimisation" of astronomical software: right also for frames the capture software reduced).
    """

    groups: tuple[DarkGroup, ...]
    source: str
    white_level: float
    doubling_c: float | None = None
    tolerance_c: float = 1.0
    warnings: tuple[str, ...] = ()
    scale: str = "exposure"

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.groups[0].offset.shape)  # type: ignore[return-value]

    def to_dict(self) -> dict[str, Any]:
        return {"source": self.source, "shape": list(self.shape), "white_level": self.white_level,
                "doubling_c": self.doubling_c, "tolerance_c": self.tolerance_c, "scale": self.scale,
                "groups": [g.to_dict() for g in self.groups], "warnings": list(self.warnings),
                "method": "frame - offset - rate * exposure (per-pixel lines of the dark-series fit, cosmic rays "
                          "rejected)"}

    # ------------------------------------------------------------------ which group, which factor
    def plan(self, name: str, exposure_s: float | None, temperature_c: float | None,
             set_temperature_c: float | None) -> FrameCalibration:
        """The group and rate factor for a frame of these conditions.

        Raises
        ------
        InputError
            No exposure time; or no group at the frame's temperature and no ``doubling_c``; or several groups and
            no temperature to choose between them.
        """
        if exposure_s is None or not math.isfinite(exposure_s) or exposure_s < 0:
            raise InputError(f"{name}: no exposure time, so the dark rate cannot be scaled to it; give EXPTIME in "
                             "the header or a manifest column 'exposure_s'")
        g = self._group_for(name, temperature_c, set_temperature_c)
        group = self.groups[g]
        factor = 1.0
        if self.doubling_c is not None and temperature_c is not None and group.temperature_c is not None:
            from forensics.defects.darklaw import TemperatureLaw

            law = TemperatureLaw.constant(self.doubling_c)
            factor = float(law.factor(1.0, group.temperature_c, temperature_c))
        return FrameCalibration(float(exposure_s), g, factor)

    def _group_for(self, name: str, temperature_c: float | None, set_temperature_c: float | None) -> int:
        if set_temperature_c is not None:
            for g, group in enumerate(self.groups):
                if group.set_temperature_c is not None and abs(group.set_temperature_c - set_temperature_c) < 0.05:
                    return g
        if temperature_c is None and set_temperature_c is None:
            if len(self.groups) == 1:
                return 0
            raise InputError(f"{name}: no sensor temperature (CCD-TEMP or a manifest 'temperature_c') to choose "
                             f"between the dark set's {len(self.groups)} temperature groups; give the frame's "
                             "temperature or a dark set taken at one temperature")
        t = temperature_c if temperature_c is not None else set_temperature_c
        known = [(abs(self._temperature(grp) - t), g) for g, grp in enumerate(self.groups)
                 if self._temperature(grp) is not None]
        if not known:
            if len(self.groups) == 1:
                return 0
            raise InputError(f"{name}: the dark set's groups have no temperature to match the frame's {t:+.2f} °C")
        gap, g = min(known)
        if gap <= self.tolerance_c or self.doubling_c is not None:
            return g
        raise InputError(f"{name}: taken at {t:+.2f} °C but the nearest dark group is at "
                         f"{self._temperature(self.groups[g]):+.2f} °C ({gap:.1f} °C off); dark current doubles "
                         "every 5-9 °C, so darks at another temperature leave much of the pattern: give darks at "
                         "the frame's temperature, or a doubling temperature (--dark-doubling) to scale them")

    @staticmethod
    def _temperature(group: DarkGroup) -> float | None:
        return group.temperature_c if group.temperature_c is not None else group.set_temperature_c

    # ------------------------------------------------------------------ applying it
    def apply(self, raw: np.ndarray, how: FrameCalibration, name: str = "frame") -> np.ndarray:
        """``raw − offset − factor·rate·exposure`` as float32; raw pixels at full scale stay at ``white_level``.

        Raises
        ------
        InputError
            The frame's size or pixel type differs from the dark set's.
        """
        raw = np.asarray(raw)
        if raw.ndim != 2 or raw.shape != self.shape:
            h, w = self.shape
            raise InputError(f"{name}: frame is {'×'.join(map(str, raw.shape[1::-1]))} but the dark set "
                             f"{self.source}'s frames are {w}×{h}; give darks of this camera at the same size and "
                             "binning")
        if raw.dtype.kind in "ui" and full_scale(raw.dtype) != self.white_level:
            raise InputError(f"{name}: {raw.dtype} pixels but the dark set {self.source} has a full scale of "
                             f"{self.white_level:g}; give darks written like the frames")
        group = self.groups[how.group]
        out = raw.astype(np.float32)
        # float32 throughout: one temporary per term, the scales folded into scalars
        out -= group.offset * np.float32(how.scale) if how.scale != 1.0 else group.offset
        out -= group.rate * np.float32(how.scale * how.factor * how.exposure_s)
        if raw.dtype.kind in "ui":
            # keep saturated pixels saturated (the fingerprint's mask finds them) and everything else below it
            np.minimum(out, np.float32(np.nextafter(np.float32(self.white_level), np.float32(0))), out=out)
            out[raw >= self.white_level] = self.white_level
        return out

    def measure(self, raw: np.ndarray, how: FrameCalibration, name: str = "frame") -> FrameCalibration:
        """``how`` with the frame's share of the predicted dark pattern and the scale it gets.

        With ``scale='exposure'`` a frame showing clearly less than half the pattern (share below
        :data:`SHARE_REFUSED`, measured to better than :data:`DECISIVE_SE`) is refused: it was dark-subtracted
        already, and calibrating it again would put the pattern back in, negated.  With ``scale='fit'`` the frame's
        share is its scale when it is measured that well, else 1.

        Raises
        ------
        InputError
            Naming the frame, the share measured and what to do.
        """
        share, se, n = dark_pattern_share(raw, self.groups[how.group], how, self.white_level)
        decisive = bool(n) and se < DECISIVE_SE
        if self.scale == "exposure" and decisive and share < SHARE_REFUSED:
            group = self.groups[how.group]
            hot = group.rate.ravel()[group.probes]
            rates = f"{float(hot.min()):.3g}-{float(hot.max()):.3g} ADU/s"
            raise InputError(f"{name}: shows {100 * share:.1f} ± {100 * se:.1f} % of the dark pattern the dark set "
                             f"predicts at its {n} hottest pixels ({rates}), "
                             "where a raw frame shows 100 %: it was dark-subtracted already (e.g. by the capture "
                             "software's auto-dark); leave out --dark, or scale the darks to what the frames show "
                             "(--dark-scale fit)")
        scale = share if self.scale == "fit" and decisive else 1.0
        return replace(how, scale=float(scale), share=float(share), share_se=float(se))

    def calibrated_frames(self, images: Any) -> list["CalibratedFrame"]:
        """The frames of a dataset (folder or :class:`~forensics.io.dataset.Dataset`), each loading calibrated.

        Each frame's exposure and temperature are read now, and its pixels once (its share of the dark pattern,
        :meth:`measure`), so a frame that cannot be calibrated is named before any work; the frames are picklable
        (workers calibrate the frames they read).

        Raises
        ------
        InputError
            A frame without exposure time, at a temperature no group matches, or of another size than the darks.
        UsageError
            ``images`` is not a dataset (arrays carry no exposure time).
        """
        from forensics.io.dataset import Dataset, open_dataset, set_point

        if isinstance(images, (str, os.PathLike)):
            images = open_dataset(images)
        if not isinstance(images, Dataset):
            raise UsageError("a dark calibration needs each frame's exposure time: give a dataset folder or Dataset, "
                             "not arrays")
        frames = list(images.frames)
        if frames:
            info = frames[0].info()
            if (info.height, info.width) != self.shape:
                h, w = self.shape
                raise InputError(f"{frames[0].path}: frame is {info.width}×{info.height} but the dark set "
                                 f"{self.source}'s frames are {w}×{h}; give darks of this camera at the same size "
                                 "and binning")
        plans = [self.plan(str(f.path), f.exposure_s, f.get("temperature_c"), set_point(f)) for f in frames]
        # one read of each frame now (streamed) for its share of the pattern: a refusal comes before any work
        return [CalibratedFrame(self, f, self.measure(f.load(), how, str(f.path))) for f, how in zip(frames, plans)]

    def calibrated_set(self, images: Any, name: str | None = None) -> ImageSet:
        """:meth:`calibrated_frames` as an :class:`ImageSet` (named ``name``, default the folder's name)."""
        from forensics.io.dataset import open_dataset

        if isinstance(images, (str, os.PathLike)):
            images = open_dataset(images)
        frames = self.calibrated_frames(images)
        return ImageSet([f.load for f in frames], [str(f.path) for f in frames],
                        name or images.root.name or str(images.root))


@dataclass(frozen=True)
class CalibratedFrame:
    """A dataset frame that loads dark-calibrated (module level and plain data, so worker processes receive it)."""

    calibration: DarkCalibration = field(repr=False)
    frame: "Frame"
    how: FrameCalibration

    @property
    def path(self) -> Any:
        return self.frame.path

    @property
    def file(self) -> str:
        return self.frame.file

    def load(self) -> np.ndarray:
        """The calibrated frame (:meth:`DarkCalibration.apply`)."""
        return self.calibration.apply(self.frame.load(), self.how, str(self.frame.path))

    def to_dict(self) -> dict[str, Any]:
        return {"file": str(self.frame.path), **self.how.to_dict()}


def _neighbour_median(image: np.ndarray, flat_index: np.ndarray) -> np.ndarray:
    """The median of the 8 neighbours of each pixel ``flat_index`` (not on the border), float64."""
    w = image.shape[1]
    flat = image.reshape(-1)
    offsets = np.array([-w - 1, -w, -w + 1, -1, 1, w - 1, w, w + 1])
    return np.median(flat[flat_index[:, None] + offsets[None, :]].astype(np.float64), axis=1)


def dark_pattern_share(raw: np.ndarray, group: DarkGroup, how: FrameCalibration, white_level: float
                       ) -> tuple[float, float, int]:
    """How much of the predicted dark pattern a raw frame carries: slope, its standard error, pixels used.

    At the group's hottest isolated pixels (``group.probes``), the frame's excess over the median of its 8 neighbours
    is regressed through the origin on the excess predicted by ``offset + factor·rate·exposure`` (the scene and the
    flat field are smooth at that scale; the PRNU and the noise scatter about the line).  A raw frame gives 1, a
    frame already dark-subtracted 0.  The error is the robust scatter (1.4826·MAD) over √Σ predicted²; pixels at
    or above :data:`~forensics.defects.darkseries.SATURATION_FRACTION` of full scale (non-linear, clipped) are
    left out.  Returns ``(nan, inf, 0)`` when no pixel is usable.
    """
    from forensics.defects.darkseries import SATURATION_FRACTION
    from forensics.stats.robust import origin_slope

    idx = group.probes
    if idx.size == 0:
        return math.nan, math.inf, 0
    rate = group.rate.reshape(-1)
    offset = group.offset.reshape(-1)
    scale = how.factor * how.exposure_s
    predicted = (offset[idx] + scale * rate[idx]) - (_neighbour_median(group.offset, idx)
                                                     + scale * _neighbour_median(group.rate, idx))
    values = np.asarray(raw).reshape(-1)[idx].astype(np.float64)
    observed = values - _neighbour_median(np.asarray(raw), idx)
    ok = (values < SATURATION_FRACTION * white_level) & (predicted > 0)
    if not ok.any():
        return math.nan, math.inf, 0
    share, se = origin_slope(predicted[ok], observed[ok])
    return share, se, int(ok.sum())


def dark_calibration(darks: "Dataset | str | os.PathLike", *, doubling_c: float | None = None, scale: str = "exposure",
                     executor: "Executor | None" = None, progress: Progress = no_progress) -> DarkCalibration:
    """Master offset and dark rate per temperature group from a folder of biases and darks (streamed).

    The frames need a frame type (FITS IMAGETYP, a manifest ``frame_type`` or ``subject``) and an exposure time
    (EXPTIME, ``exposure_s``); biases count as 0 s, and each temperature group needs two exposure times.  Flat
    fields in the folder only give the fit's conversion gain.  Pixels whose line could not be fitted (saturated in
    every dark) get the group's median offset and rate, counted in ``DarkGroup.filled``.

    ``scale`` is ``'exposure'`` or ``'fit'`` (:class:`DarkCalibration`).

    Raises
    ------
    InputError
        Frames without exposure time or type, of different sizes, or no group with two exposure times.
    UsageError
        A doubling temperature that is not positive, or an unknown ``scale``.
    """
    from forensics.defects.darkdetect import series_frames
    from forensics.defects.darkseries import SETPOINT_TOLERANCE_C, _frame_dtype, fit_dark_series, plan_series
    from forensics.io.dataset import open_dataset

    if scale not in SCALES:
        raise UsageError(f"scale={scale!r}: choose one of {', '.join(SCALES)}")
    if doubling_c is not None and not doubling_c > 0:
        raise UsageError(f"doubling temperature {doubling_c}: give a positive number of °C (5-9 is typical of CCDs)")
    ds = open_dataset(darks) if isinstance(darks, (str, os.PathLike)) else darks
    try:
        plan = plan_series(series_frames(ds))
    except InputError as exc:  # name the dark set where the message names no file of it
        message = str(exc)
        raise InputError(message if os.sep in message.split(": ", 1)[0] else f"dark set {ds.root}: {message}") from None
    white = full_scale(_frame_dtype(plan.frames[plan.groups[0][0]].path))
    fit = fit_dark_series(plan, executor=executor, progress=progress)
    groups = tuple(_group(g, fit.shape) for g in fit.groups)
    return DarkCalibration(groups, str(ds.root), white, doubling_c, SETPOINT_TOLERANCE_C, tuple(fit.warnings), scale)


def _group(g: Any, shape: Sequence[int]) -> DarkGroup:
    """A fitted group's maps as float32 frames, unfitted pixels filled with the group's medians."""
    offset = np.asarray(g.offset, np.float64).reshape(shape)
    rate = np.asarray(g.rate, np.float64).reshape(shape)
    bad = ~(np.isfinite(offset) & np.isfinite(rate))
    if bad.any():
        offset = np.where(bad, np.nanmedian(offset), offset)
        rate = np.where(bad, np.nanmedian(rate), rate)
    rate32 = rate.astype(np.float32)
    return DarkGroup(g.label, g.set_temperature_c, g.temperature_c, offset.astype(np.float32), rate32,
                     int(bad.sum()), _probes(rate32))


def _probes(rate: np.ndarray, count: int | None = None) -> np.ndarray:
    """The :data:`PROBES` pixels whose rate stands highest above their 8 neighbours' median (border excluded):
    where a frame's dark pattern is measured (:func:`dark_pattern_share`)."""
    count = PROBES if count is None else count
    h, w = rate.shape
    inner = (np.arange(1, h - 1)[:, None] * w + np.arange(1, w - 1)[None, :]).ravel()
    if inner.size == 0:
        return np.zeros(0, np.int64)
    # candidates first by rate (cheap), then by contrast over the neighbours: a hot cluster is not a spike
    candidates = inner[np.argsort(rate.reshape(-1)[inner])[-4 * count:]]
    contrast = rate.reshape(-1)[candidates] - _neighbour_median(rate, candidates)
    return candidates[np.argsort(contrast)[::-1][:count]].astype(np.int64)
