"""Loading a dataset into per-condition statistics: the first stage of the check.

Every frame is read once.  Frames are grouped by condition (epoch, exposure, ISO, temperature, subject);
each group's frames stream into :class:`~forensics.io.stack.StackAccumulator` s — all frames, and the even
and odd frames separately (the two halves the pixel channel fits and scores on) — and so does each frame's
residual from its own scene estimate, whose temporal variance is the pixel channel's noise floor: it is what
the noise of a residual actually is, whether the temporal noise is white or spatially correlated (demosaiced,
JPEG-compressed frames) and whether or not the frames' overall level drifts (a level change is part of every
frame's scene estimate, so it is not in the residual).  What the data limit is measured on the way: the
spatial correlation of the temporal noise and the spread of the frame means (:class:`NoiseTraits`).

Conditions are independent: each is one work item of the execution layer (:mod:`forensics._shared.parallel`),
read from its frames' paths by whichever worker runs it (:func:`condition_stats`), and the per-condition
results are assembled in condition order, so the measurements are bit-identical on every backend (and to
reading the frames in one loop).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import ndimage

from forensics.stats.tails import f_sf

import forensics.stats.spatial as sp
from forensics._shared.arrays import grey_mean, infer_full_scale
from forensics._shared.errors import InputError
from forensics._shared.progress import Progress, no_progress
from forensics.check.classes import QUANT_VAR
from forensics.check.scene import KERNEL, KERNEL_VAR, SCENE_SIZE, correlate_kernel, scene_estimate
from forensics.io.dataset import LIGHT_COLUMN, Dataset, open_dataset, split_epochs
from forensics.io.stack import StackAccumulator, StackStats, prefetch

if TYPE_CHECKING:  # the execution layer is imported where the frames are read
    from forensics._shared.parallel import Executor


@dataclass
class Group:
    """Frames sharing one condition at one epoch."""

    index: int
    epoch: int
    time: float
    exposure_s: float | None
    iso: float | None
    temperature_c: float | None
    subject: str | None
    frames: list[int]
    light: str | None = None  #: the manifest's ``light`` column (a light level), when it has one
    #: the frames are different scenes (ordinary photographs pooled per epoch, :func:`pool_scenes`), not repeats
    scenes: bool = False

    @property
    def n(self) -> int:
        return len(self.frames)

    @property
    def condition(self) -> tuple[Any, ...]:
        return (self.exposure_s, self.iso, self.temperature_c, self.subject, self.light)

    def label(self) -> str:
        parts = [f"epoch {self.epoch}"]
        if self.subject:
            parts.append(str(self.subject))
        if self.exposure_s is not None:
            parts.append(f"{self.exposure_s:g} s")
        if self.iso is not None:
            parts.append(f"ISO {self.iso:g}")
        if self.temperature_c is not None:
            parts.append(f"{self.temperature_c:g} °C")
        if self.light is not None:
            parts.append(f"light {self.light}")
        if self.scenes:
            parts.append(f"{self.n} photographs")
        return ", ".join(parts)


@dataclass
class NoiseTraits:
    """What the temporal noise looks like, beyond its variance (for the check's warnings on what data limit).

    ``lag1`` is the correlation of the temporal noise between horizontally and vertically adjacent pixels
    (≈ 0 for a raw sensor's noise; demosaicing and JPEG compression correlate it), from the differences of
    consecutive frames of a condition, high-passed so that the scene and level changes drop out.  ``blocks``
    holds, per repeated condition, the mean of every frame over square blocks ``(n_frames, n_blocks)``: the
    frames' level changes against the noise of a frame mean (:func:`forensics.check.frame_advice.level_drift`).
    """

    lag1: float | None
    blocks: list[np.ndarray]
    jpeg: bool


#: Side of the blocks over which frame means are taken (the noise is independent between blocks this large).
DRIFT_BLOCK = 32
#: Side of the box whose mean is removed from a frame difference before its lag-1 correlation is measured.
LAG_BOX = 15
JPEG_SUFFIXES = (".jpg", ".jpeg", ".jpe", ".jfif")


@dataclass
class Measurements:
    """Per-condition statistics of a dataset, ready for checking.

    Arrays indexed ``[g]`` run over :attr:`groups` (every condition); those
    indexed by the pixel channel run over :attr:`fitted` — the conditions with at
    least two frames (:attr:`repeated`), then the dark conditions of a single frame
    (:attr:`single`), in that order.  A single frame is fitted, never scored: its
    half *a* and half *b* are the frame itself.
    """

    root: Path
    shape: tuple[int, int]
    full_scale: float
    border: int
    epoch_times: np.ndarray
    has_time: bool
    groups: list[Group]
    mean_all: np.ndarray
    var_all: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    repeated: list[int]
    mean_a: np.ndarray
    mean_b: np.ndarray
    n_a: np.ndarray
    n_b: np.ndarray
    n_frames: int
    scene_all: np.ndarray = field(default=None)  # type: ignore[assignment]
    notes: list[str] = field(default_factory=list)
    #: per condition, the temporal variance of each frame's residual from its own scene estimate
    var_resid: np.ndarray = field(default=None)  # type: ignore[assignment]
    traits: NoiseTraits | None = None
    #: photographs (:func:`pool_scenes`): per repeated condition and half ``(R, 2, H, W)``, the mean over the
    #: half's frames of the squared residual from each frame's own scene estimate (None without photographs).
    #: Every photograph has its own texture, so the two halves' means have different noise floors.
    half_ms: np.ndarray | None = None
    #: the readout's upper clip level when the data saturate below the full scale (a sensor's full well reached
    #: before the converter's top: :func:`saturation_level`); None: the full scale
    saturation: float | None = None
    #: dark conditions of a single frame (a dark series' one frame per exposure): fitted by the pixel channel
    #: with the noise the repeats' variance law predicts, not scored (:mod:`forensics.check.singles`)
    single: list[int] = field(default_factory=list)

    @property
    def fitted(self) -> list[int]:
        """The conditions the pixel channel fits, in the order of its arrays: :attr:`repeated`, then
        :attr:`single`."""
        return self.repeated + self.single

    @property
    def clip_level(self) -> float:
        """The upper bound of the readout: a pixel that touched it is censored (:attr:`saturation` or the full
        scale)."""
        return self.full_scale if self.saturation is None else self.saturation

    def censored(self, g: int) -> np.ndarray:
        """(H, W): the pixels whose readout touched 0 or :attr:`clip_level` in some frame of condition ``g`` (their
        mean is not the pixel's mean)."""
        return (self.lo[g] <= 0) | (self.hi[g] >= self.clip_level)

    def drift(self, r: int) -> LevelDrift:
        """Frame-to-frame level changes of repeated condition ``r`` (index into :attr:`repeated`)."""
        if self.traits is None or r >= len(self.traits.blocks):
            return LevelDrift(0.0, 0.0, 1.0)
        return level_drift(self.traits.blocks[r])

    @property
    def interior(self) -> np.ndarray:
        h, w = self.shape
        m = np.zeros(self.shape, bool)
        b = self.border
        m[b:h - b, b:w - b] = True
        return m

    @property
    def window(self) -> sp.Window:
        h, w = self.shape
        b = self.border
        return (float(b), float(b), float(w - b), float(h - b))

    def field_values(self, name: str) -> list[Any]:
        """Distinct values of a condition field over all frames (None excluded)."""
        attr = {"exposure_s": "exposure_s", "iso": "iso", "temperature_c": "temperature_c"}.get(name)
        if attr is None:
            return []
        return sorted({getattr(g, attr) for g in self.groups if getattr(g, attr) is not None})


#: An explicit region of the frames: (top, left, height, width) in pixels.
Region = tuple[int, int, int, int]


def central_region(shape: Sequence[int], size: int) -> Region:
    """The central ``size × size`` region of frames of ``shape`` (the whole frame along a side shorter than
    ``size``), for :func:`load_measurements`'s ``region``."""
    h, w = int(shape[0]), int(shape[1])
    return max(0, (h - size) // 2), max(0, (w - size) // 2), min(h, size), min(w, size)


def _region_slices(h: int, w: int, region: Region | None) -> tuple[slice, slice]:
    if region is None:
        return slice(0, h), slice(0, w)
    top, left, height, width = (int(v) for v in region)
    if top < 0 or left < 0 or height < 1 or width < 1 or top + height > h or left + width > w:
        raise InputError(f"region (top {top}, left {left}, height {height}, width {width}) is not inside the "
                         f"{w}×{h} frames; give top, left ≥ 0 and top + height ≤ {h}, left + width ≤ {w}")
    return slice(top, top + height), slice(left, left + width)


def frame_residual(grey: np.ndarray) -> np.ndarray:
    """A frame less its neighbours' leave-one-out quadratic estimate (:data:`~forensics.check.scene.KERNEL`):
    the frame's noise and fixed pattern, without its scene or its level.

    The kernel is applied linearly (no outlier rejection, reflected edges): cheap for every frame, and its
    temporal variance is exactly that of the kernel's residual of the temporal noise, which is what the half
    means' residuals carry.  A defect is fixed in time, so it adds nothing to its neighbours' temporal variance
    beyond its own noise's small share (w² ≤ 0.006).  Within the kernel's reach of the edge (outside the
    check's border) the reflection makes the value differ from the pixel channel's.
    """
    return grey - correlate_kernel(grey)


def block_means(grey: np.ndarray, size: int = DRIFT_BLOCK) -> np.ndarray:
    """Means of a frame over its whole ``size × size`` blocks (row-major; a partial last row or column is
    dropped)."""
    h, w = (grey.shape[0] // size) * size, (grey.shape[1] // size) * size
    if h == 0 or w == 0:
        return np.array([float(grey.mean())])
    return grey[:h, :w].reshape(h // size, size, w // size, size).mean(axis=(1, 3)).ravel()


def lag1_terms(previous: np.ndarray, current: np.ndarray, box: int = LAG_BOX) -> tuple[float, float] | None:
    """One pair of consecutive frames' contribution to :class:`Lag1`: (lag-1 cross product, square), each a
    mean over the high-passed difference of the frames; None when the frames are too small for the box."""
    # the difference of two frames of one condition is noise plus a smooth level change; the box mean removes
    # the latter (it lowers a white noise's lag-1 correlation by ≈ 1/box², negligible)
    d = current - previous
    hp = (d - ndimage.uniform_filter(d, size=box, mode="reflect"))[box:-box, box:-box]
    if hp.size == 0:
        return None
    cross = 0.5 * (float(np.sum(hp[:, 1:] * hp[:, :-1])) / max(hp[:, 1:].size, 1)
                   + float(np.sum(hp[1:] * hp[:-1])) / max(hp[1:].size, 1))
    return cross, float(np.mean(hp * hp))


class Lag1:
    """Accumulates the lag-1 spatial correlation of the temporal noise from consecutive frames' differences."""

    def __init__(self, box: int = LAG_BOX):
        self.box = box
        self.cross = 0.0
        self.square = 0.0

    def add(self, previous: np.ndarray, current: np.ndarray) -> None:
        self.add_terms(lag1_terms(previous, current, self.box))

    def add_terms(self, terms: tuple[float, float] | None) -> None:
        """Add one pair's :func:`lag1_terms` (computed anywhere; added in frame order, the sums are those of
        :meth:`add` to the last bit)."""
        if terms is not None:
            self.cross += terms[0]
            self.square += terms[1]

    def result(self) -> float | None:
        return self.cross / self.square if self.square > 0 else None


def temperature_key(frame: Any) -> tuple[str, float | None]:
    """What a frame's temperature is grouped by: its set point where it has one and the measured temperature
    lies within :data:`forensics.io.fits.SETPOINT_TOLERANCE_C` of it, else the measured temperature.

    Why: a cooled camera's thermistor wanders and is quantised (the 2017 STL-1001E's −10 °C biases read −10.20 …
    −9.79 °C), and grouping by the reading split repeats of one condition into conditions of one or two frames
    (the 2017 series: 27 conditions instead of 15; a wander of 0.6 °C left 2 of 50 repeated).  A frame that never
    reached its set point keeps its reading (named by :func:`off_set_point`).

    Examples
    --------
    >>> from pathlib import Path
    >>> from forensics.io.dataset import Frame
    >>> temperature_key(Frame(Path("d.fit"), "d.fit", temperature_c=-9.79, extra={"set_temperature_c": "-10"}))
    ('set point', -10.0)
    >>> temperature_key(Frame(Path("d.fit"), "d.fit", temperature_c=-7.0, extra={"set_temperature_c": "-10"}))
    ('measured', -7.0)
    """
    from forensics.io.dataset import set_point
    from forensics.io.fits import SETPOINT_TOLERANCE_C

    target = set_point(frame)
    measured = frame.temperature_c
    if target is not None and (measured is None or abs(measured - target) <= SETPOINT_TOLERANCE_C):
        return ("set point", target)
    return ("measured", measured)


def group_frames(ds: Dataset, epoch: np.ndarray, epoch_times: np.ndarray) -> list[Group]:
    """Frames grouped by (epoch, exposure, ISO, temperature, subject, light), in order of epoch and first frame
    (``light``: the manifest's optional column of that name, e.g. the irradiance of a photon-transfer series).
    The temperature is the set point where the frame reached it (:func:`temperature_key`); a group's temperature
    is then its frames' mean measured temperature (the set point where none was measured)."""
    keys: dict[tuple[Any, ...], list[int]] = {}
    for i, f in enumerate(ds.frames):
        light = f.extra.get(LIGHT_COLUMN) or None
        keys.setdefault((int(epoch[i]), f.exposure_s, f.iso, temperature_key(f), f.subject, light), []).append(i)
    groups = []
    for j, (k, idx) in enumerate(sorted(keys.items(), key=lambda kv: (kv[0][0], kv[1][0]))):
        measured = [ds.frames[i].temperature_c for i in idx]
        temperature = float(np.mean(measured)) if None not in measured else k[3][1]
        groups.append(Group(j, k[0], float(epoch_times[k[0]]), k[1], k[2], temperature, k[4], idx, k[5]))
    return groups


PHOTOGRAPHS_NOTE = ("the frames are ordinary photographs (different scenes, not repeats of one), pooled per "
                     "epoch: the noise floor includes the scenes' fine texture, and the temporal variance and "
                     "exposure-, ISO- and temperature-dependent effects cannot be tested from them")
#: Two frames of one condition are different scenes when their block means differ, beyond an affine level
#: change, by this many times what the frames' residual noise gives a block mean (for repeats the ratio is
#: about 1–3 — more for spatially correlated noise —, for photographs of different scenes hundreds or more).
SCENE_RATIO = 100.0


def different_scenes(first_blocks: np.ndarray, second_blocks: np.ndarray, pixel_var: float,
                     size: int = DRIFT_BLOCK) -> bool:
    """Whether two frames show different scenes: the second's :func:`block_means` are not an affine function
    of the first's (a level change, e.g. flicker or auto-exposure) within :data:`SCENE_RATIO` times the
    variance their noise gives (``pixel_var``: the frames' residual variance per pixel, fixed pattern included,
    which only makes the test slower to call frames different)."""
    n = first_blocks.size
    if n < 4:
        return False
    design = np.stack([first_blocks, np.ones(n)], 1)
    coef, *_ = np.linalg.lstsq(design, second_blocks, rcond=None)
    resid = second_blocks - design @ coef
    ms = float(resid @ resid) / (n - 2)
    noise = (1.0 + coef[0] ** 2) * max(pixel_var, QUANT_VAR) / size**2
    return ms > SCENE_RATIO * noise


def _common(values: Sequence[Any]) -> Any:
    """The value all frames share, or None when they differ."""
    first = values[0]
    return first if all(v == first for v in values) else None


def pool_scenes(ds: Dataset, groups: list[Group]) -> list[Group]:
    """Ordinary photographs — no condition repeated — pooled into one group per epoch (``scenes`` True).

    Every frame has its own scene, so frames of one condition cannot be repeats; but everything the sensor adds
    that does not depend on the scene (a defect's offset, a stuck value, PRNU's gain on whatever light falls)
    is the same in every photograph of an epoch.  The pixel channel predicts each half's mean from that half's
    own scene estimate, so halves of different scenes are fitted and scored like repeats.  A field (exposure,
    ISO, temperature) is kept where every pooled frame shares it, otherwise unknown (None): effects acting
    through it cannot be tested and the check says so.
    """
    by_epoch: dict[int, list[int]] = {}
    for g in groups:
        by_epoch.setdefault(g.epoch, []).extend(g.frames)
    out = []
    for j, (epoch, frames) in enumerate(sorted(by_epoch.items())):
        frames = sorted(frames)
        first = next(g for g in groups if g.epoch == epoch)
        fr = [ds.frames[i] for i in frames]
        out.append(Group(j, epoch, first.time, _common([f.exposure_s for f in fr]), _common([f.iso for f in fr]),
                         _common([f.temperature_c for f in fr]), None, frames, None, scenes=True))
    return out


@dataclass(frozen=True)
class ConditionFrames:
    """One condition as a work item of :func:`load_measurements`: where its frames are and what to measure.

    Small and picklable (paths, not pixels): the worker that runs it reads the frames itself."""

    paths: tuple[str, ...]
    names: tuple[str, ...]  #: the frames' file names (for messages)
    crop: tuple[slice, slice]  #: the region analysed
    repeated: bool  #: two or more frames: the pixel channel's halves, residuals and noise traits are measured
    scenes: bool  #: already known to be different scenes (photographs pooled per epoch)
    frame_cache: str | None = None  #: the frames decoded once (:mod:`forensics.io.framecache`), or None


@dataclass
class ConditionStats:
    """What one condition's frames reduce to (:func:`condition_stats`); arrays of the region's shape."""

    whole: StackStats
    halves: tuple[StackStats, StackStats] | None  #: even and odd frames (repeated conditions)
    var_resid: np.ndarray | None  #: temporal variance of the frames' residuals (repeated conditions)
    scenes: bool  #: the frames are different scenes (given, or found from the first two frames' content)
    found_scenes: bool  #: found from the content here (not known from the grouping)
    half_ms: np.ndarray | None  #: photographs: ``(2, H, W)`` sums of squared residuals per half (not yet means)
    blocks: np.ndarray | None  #: repeats: every frame's :func:`block_means`, ``(n_frames, n_blocks)``
    lag: list[tuple[float, float] | None]  #: :func:`lag1_terms` of consecutive repeats, in frame order
    dtype: np.dtype  #: the first frame's pixel type
    scene: np.ndarray  #: :func:`~forensics.check.scene.scene_estimate` of the condition's mean
    #: content-free frames left out (:mod:`forensics.io.content`): (position in the condition, file, why)
    excluded: list[tuple[int, str, str]] = field(default_factory=list)


@dataclass
class EmptyCondition:
    """A condition that content-free frames left with too few frames to measure (:func:`condition_stats`)."""

    excluded: list[tuple[int, str, str]]
    n_frames: int


def condition_stats(item: ConditionFrames) -> ConditionStats | EmptyCondition:
    """Read one condition's frames (in order, decoding one ahead) and reduce them: the work item of
    :func:`load_measurements` (module-level, so that workers import it by reference).

    Content-free frames (constant, or clipped at the pixel type's floor or full scale: :func:`frame_problem`)
    are left out before they reach any statistic; a condition left with too few frames is an
    :class:`EmptyCondition`."""
    from forensics.io.framecache import open_cached
    from forensics.io.images import read_image

    crop = item.crop
    whole, halves, resid = StackAccumulator(), (StackAccumulator(), StackAccumulator()), StackAccumulator()
    scenes, found = item.scenes, False
    previous = None
    frame_blocks: list[np.ndarray] = []
    lag: list[tuple[float, float] | None] = []
    ms: np.ndarray | None = None
    stacked_dtype = None  # what this condition's stack accumulates (set by its first frame)
    first: tuple[np.ndarray, np.ndarray] | None = None  # the first frame's squared residual and block means
    dtype = None
    excluded: list[tuple[int, str, str]] = []
    j = -1  # position among the frames kept
    frames = ((open_cached(item.frame_cache, p) for p in item.paths) if item.frame_cache is not None
              else prefetch(read_image(p) for p in item.paths))
    for k, (name, whole_frame) in enumerate(zip(item.names, frames)):
        img = np.asarray(whole_frame[crop])  # a mapped frame: only the region's rows are read
        problem = frame_problem(img)
        if problem is not None:  # clipped or constant: it would be taken for stuck pixels or a gain pattern
            excluded.append((k, name, problem))
            continue
        j += 1
        dtype = img.dtype if dtype is None else dtype
        grey = grey_mean(img, np.float64)
        stacked = _stackable(img, grey, stacked_dtype)
        stacked_dtype = stacked.dtype
        whole.add(stacked, name=name)
        halves[j % 2].add(stacked, name=name)
        if not item.repeated:
            continue
        res = frame_residual(grey)
        resid.add(res, name=name)
        if j == 0:
            first = ((res * res).astype(np.float32), block_means(grey))
        elif j == 1 and not scenes and different_scenes(first[1], block_means(grey), float(np.mean(res**2))):
            scenes = found = True  # a condition without metadata to tell photographs apart: their content does
            frame_blocks.clear()  # neither the level-drift test nor the noise's correlation applies
        if scenes:
            if ms is None:
                ms = np.zeros((2, *grey.shape), np.float32)
            if j == 1 and found:  # found different at this frame: the first frame is not in its half yet
                ms[0] += first[0]
            ms[j % 2] += (res * res).astype(np.float32)
        else:  # repeats: the level-drift test's blocks and the noise's spatial correlation
            frame_blocks.append(block_means(grey))
            if previous is not None:
                lag.append(lag1_terms(previous, grey))
            previous = grey
    if j + 1 < (2 if item.repeated else 1):
        return EmptyCondition(excluded, len(item.paths))
    total = whole.result()
    scene = scene_estimate(total.mean.astype(np.float64))  # of the float64 mean, as the measurements hold it
    if not item.repeated:
        return ConditionStats(total, None, None, scenes, found, None, None, lag, np.dtype(dtype), scene, excluded)
    return ConditionStats(total, (halves[0].result(), halves[1].result()), resid.result().var, scenes, found, ms,
                          np.array(frame_blocks), lag, np.dtype(dtype), scene, excluded)


def frame_problem(frame: np.ndarray) -> str | None:
    """Why a frame holds nothing of the sensor for the check (:mod:`forensics.io.content`), or None.

    The check knows no black level: a pixel at the pixel type's floor (0 for unsigned integers) or full scale
    is clipped, and a frame with fewer than 1 % of its pixels strictly between them, or a constant one, is
    content-free — its zero variance would be read as stuck pixels and its clipped level as a gain pattern.
    """
    from forensics.io.content import content_problem

    dtype = np.asarray(frame).dtype
    floor = float(np.iinfo(dtype).min) if dtype.kind in "ui" else -np.inf
    return content_problem(frame, floor)


def load_measurements(data: Dataset | str | Path, border: int | None = None, epoch_gap: float = 0.25,
                      region: Region | None = None, progress: Progress = no_progress,
                      executor: Executor | None = None) -> Measurements:
    """Read every frame once and reduce the dataset to per-condition statistics.

    Parameters
    ----------
    data
        A dataset or its folder.
    border
        Pixels ignored at each edge (default: half the scene window, 3).
    epoch_gap
        Capture-time gap (years) that starts a new epoch.
    region
        ``(top, left, height, width)``: analyse only this part of every frame (said in the notes); default the
        whole frame, whatever its size (frames are read one at a time, so memory is a few per-condition
        arrays of the frame's size).  :func:`central_region` gives a centred one.
    progress
        Progress callable: one bar counting the conditions read.
    executor
        The execution layer (None: in this process).  Each condition is one work item
        (:func:`condition_stats`); a worker reads the condition's frames from their paths, so on a cluster
        the dataset must be on storage every worker sees.

    Raises
    ------
    InputError
        No condition has two or more frames (the noise floor cannot be measured).
    """
    from forensics._shared.parallel import resolve

    ds = data if isinstance(data, Dataset) else open_dataset(data)
    shape = ds.shape()
    notes = []
    h, w = shape[0], shape[1]
    crop = _region_slices(h, w, region)
    if region is not None:
        rh, rw = crop[0].stop - crop[0].start, crop[1].stop - crop[1].start
        notes.append(f"only a region of the {w}×{h} frames analysed, as asked: {rw}×{rh} pixels at rows "
                     f"{crop[0].start}–{crop[0].stop - 1}, columns {crop[1].start}–{crop[1].stop - 1}")
    if len(shape) == 3:
        notes.append("colour frames averaged to grey")
    try:
        times = ds.captured_times()
        has_time = True
    except InputError:
        times = np.zeros(len(ds))
        has_time = False
        notes.append("no 'captured' field: one epoch, defect arrival and placement not tested")
    epoch, epoch_times = split_epochs(times, epoch_gap)
    groups = group_frames(ds, epoch, epoch_times)
    repeated = [g.index for g in groups if g.n >= 2]
    if not repeated:
        no_repeated_darks(ds, groups)
        groups = pool_scenes(ds, groups)
        repeated = [g.index for g in groups if g.n >= 2]
        if not repeated:
            raise InputError(f"{ds.root}: no condition has two or more frames and no epoch two or more photographs; "
                             "the noise floor is measured from repeated frames of one condition (same exposure_s, "
                             "iso, temperature_c, subject, light and epoch): take at least 2 frames per condition")
        notes.append(PHOTOGRAPHS_NOTE)
    single = single_dark_conditions(groups)
    notes += off_set_point(ds)
    items = [ConditionFrames(tuple(str(ds.frames[i].path) for i in g.frames),
                             tuple(ds.frames[i].file for i in g.frames), crop, g.n >= 2, g.scenes, ds.frame_cache)
             for g in groups]
    parts = resolve(executor).map(condition_stats, items, progress=progress, desc="conditions")
    return _assemble(ds, groups, repeated, parts, (crop[0].stop - crop[0].start, crop[1].stop - crop[1].start),
                     notes, has_time, epoch_times, border, single)


def no_repeated_darks(ds: Dataset, groups: Sequence[Group]) -> None:
    """Refuse a dark series in which no condition repeats, saying why, instead of pooling its frames as
    photographs of different scenes.

    Why: dark frames are not scenes; pooled per epoch they lose their exposures and temperatures (which differ),
    and a check with a dark current then stopped with "'dark_current' needs the field 'exposure_s' for every
    frame" although every frame had one.  The usual cause is a sensor that never settled: frames measured more
    than :data:`forensics.io.fits.SETPOINT_TOLERANCE_C` from their set point keep their own reading, so each is
    a condition of its own.

    Raises
    ------
    InputError
        Some condition holds dark frames (``subject`` dark) and none has two or more frames.
    """
    from forensics.io.dataset import is_dark_subject
    from forensics.io.fits import SETPOINT_TOLERANCE_C

    if not any(is_dark_subject(g.subject) for g in groups):
        return
    off = unsettled_frames(ds)
    why = (f"{len(off)} of {len(ds)} frames were measured more than {SETPOINT_TOLERANCE_C:g} °C from their set "
           f"point (the sensor never settled; e.g. {off[0].file}), so each keeps its own temperature" if off else
           "every exposure and temperature has a single frame")
    raise InputError(f"{ds.root}: no condition of these dark frames has two or more frames: {why}; the noise floor "
                     "is measured from repeated frames of one condition (dark frames are not pooled as photographs): "
                     "take at least 2 frames of one exposure (e.g. biases) at a temperature the sensor holds")


def unsettled_frames(ds: Dataset, tolerance: float | None = None) -> list[Any]:
    """The frames whose measured temperature lies more than ``tolerance`` °C from their set point (the sensor
    never reached it); ``tolerance``: default the FITS reader's (:data:`forensics.io.fits.SETPOINT_TOLERANCE_C`)."""
    from forensics.io.dataset import set_point
    from forensics.io.fits import SETPOINT_TOLERANCE_C

    tolerance = SETPOINT_TOLERANCE_C if tolerance is None else tolerance
    return [f for f in ds.frames if (sp_c := set_point(f)) is not None and f.temperature_c is not None
            and abs(f.temperature_c - sp_c) > tolerance]


def off_set_point(ds: Dataset, tolerance: float | None = None) -> list[str]:
    """A warning naming the frames whose measured temperature lies more than ``tolerance`` °C from their set
    point (:func:`unsettled_frames`): their condition is at the temperature measured, and the dark current's
    law carries them there — if the measured temperature is right."""
    from forensics.io.dataset import set_point
    from forensics.io.fits import SETPOINT_TOLERANCE_C

    tolerance = SETPOINT_TOLERANCE_C if tolerance is None else tolerance
    off = [f"{f.file} ({f.temperature_c:.2f} °C, set point {set_point(f):g} °C)" for f in unsettled_frames(ds, tolerance)]
    if not off:
        return []
    return [f"{len(off)} frame(s) measured more than {tolerance:g} °C from their set point (the sensor had not "
            f"settled): {', '.join(off[:5])}{' …' if len(off) > 5 else ''}; they are fitted at the temperature "
            "measured"]


def single_dark_conditions(groups: Sequence[Group]) -> list[int]:
    """The conditions of one dark frame (``subject`` dark, not photographs): a dark series' one frame per
    exposure and temperature.  The model predicts them from the chain alone (no scene estimate), so the pixel
    channel can fit them with the noise its variance law predicts; light frames of one condition would need
    their own scene estimate's noise and stay for defect detection only."""
    from forensics.io.dataset import is_dark_subject

    return [g.index for g in groups if g.n == 1 and not g.scenes and is_dark_subject(g.subject)]


def _assemble(ds: Dataset, groups: list[Group], repeated: list[int], parts: Any, shp: tuple[int, int],
              notes: list[str], has_time: bool, epoch_times: np.ndarray, border: int | None,
              single: list[int] | None = None) -> Measurements:
    """The :class:`Measurements` from the conditions' :class:`ConditionStats`, taken in condition order (so
    the float sums over conditions are the same whichever process computed each)."""
    single = [g for g in (single or []) if g not in repeated]
    G, R = len(groups), len(repeated) + len(single)
    mean_all, var_all, lo, hi, scene_all, var_resid = (np.zeros((G, *shp)) for _ in range(6))
    mean_a, mean_b = np.zeros((R, *shp)), np.zeros((R, *shp))
    n_a, n_b = np.zeros(R, int), np.zeros(R, int)
    rpos = {g: r for r, g in enumerate(repeated)}
    spos = {g: len(repeated) + k for k, g in enumerate(single)}
    photo_ms: dict[int, np.ndarray] = {}  # repeated condition → (2, H, W) residual mean squares per half
    lag = Lag1()
    blocks: list[np.ndarray] = []
    dtype = None
    excluded: list[tuple[str, str]] = []  # content-free frames (file, why)
    dropped: list[int] = []  # conditions content-free frames left too small
    for g, part in zip(groups, parts):
        excluded += [(name, why) for _, name, why in part.excluded]
        if isinstance(part, EmptyCondition):
            dropped.append(g.index)
            continue
        gone = {k for k, _, _ in part.excluded}
        g.frames = [f for k, f in enumerate(g.frames) if k not in gone]
        dtype = part.dtype if dtype is None else dtype  # the first frame's
        total = part.whole
        mean_all[g.index], var_all[g.index] = total.mean, total.var
        lo[g.index], hi[g.index] = total.minimum, total.maximum
        scene_all[g.index] = part.scene
        if part.found_scenes:
            g.scenes = True
            if PHOTOGRAPHS_NOTE not in notes:
                notes.append(PHOTOGRAPHS_NOTE)
        for terms in part.lag:
            lag.add_terms(terms)
        if g.index in spos:  # one frame: fitted, not scored; both "halves" are the frame
            mean_a[spos[g.index]] = mean_b[spos[g.index]] = total.mean
            n_a[spos[g.index]] = n_b[spos[g.index]] = 1
        if g.index not in rpos:
            continue
        r = rpos[g.index]
        a, b = part.halves
        mean_a[r], mean_b[r] = a.mean, b.mean
        n_a[r], n_b[r] = a.n, b.n
        var_resid[g.index] = part.var_resid
        if g.scenes:
            ms = part.half_ms
            ms[0] /= a.n
            ms[1] /= b.n
            photo_ms[r] = ms
            # a pixel's spread over different scenes is the scenes', not noise: what stands for its temporal
            # variance is the spread of its residual from each photograph's own scene estimate (noise and
            # the scenes' texture finer than the estimate), per frame rather than per residual
            var_all[g.index] = var_resid[g.index] / (1.0 + KERNEL_VAR)
        blocks.append(part.blocks)
    half_ms = None
    if photo_ms:
        half_ms = np.zeros((R, 2, *shp), np.float32)  # zero for conditions of repeats (not used there)
        for r, ms in photo_ms.items():
            half_ms[r] = ms
    if excluded:
        _refuse_content_free(ds, groups, dropped, excluded, notes)
    if dropped:  # keep the conditions measured, renumbered (rare: only here are arrays copied)
        keep = [g.index for g in groups if g.index not in dropped]
        keep_r = [r for r, g in enumerate(repeated + single) if g not in dropped]
        mean_all, var_all, lo, hi, scene_all, var_resid = (x[keep] for x in (mean_all, var_all, lo, hi, scene_all,
                                                                             var_resid))
        mean_a, mean_b, n_a, n_b = (x[keep_r] for x in (mean_a, mean_b, n_a, n_b))
        half_ms = half_ms[keep_r] if half_ms is not None else None
        renumber = {old: new for new, old in enumerate(keep)}
        repeated = [renumber[g] for g in repeated if g not in dropped]
        single = [renumber[g] for g in single if g not in dropped]
        groups = [g for g in groups if g.index not in dropped]
        for g in groups:
            g.index = renumber[g.index]
    full_scale = data_full_scale(ds, np.dtype(dtype), max(0.0, float(hi.max())))
    border = SCENE_SIZE // 2 if border is None else int(border)
    interior = np.zeros(shp, bool)
    interior[border:shp[0] - border, border:shp[1] - border] = True
    saturation = saturation_level(lo, hi, interior, full_scale)
    if saturation is not None:
        notes.append(f"the frames saturate at {saturation:g} DN, below the full scale {full_scale:g} DN (a full well "
                     "reached before the converter's top): readouts that reached it are censored")
    else:
        saturation = full_well_level(mean_all, groups, interior)
        if saturation is not None and saturation < full_scale:
            notes.append(f"hot pixels saturate in the dark frames from {saturation:g} DN on (their dark signal stops "
                         f"growing with the exposure there), below the full scale {full_scale:g} DN: readouts that "
                         "reached it are censored")
        else:
            saturation = None
    meas = Measurements(ds.root, shp, full_scale, border, epoch_times, has_time, groups, mean_all, var_all, lo, hi,
                        repeated, mean_a, mean_b, n_a, n_b, len(ds) - len(excluded), notes=notes,
                        var_resid=var_resid, half_ms=half_ms, scene_all=scene_all, saturation=saturation,
                        single=single)
    jpeg = any(Path(f.file).suffix.lower() in JPEG_SUFFIXES for f in ds.frames)
    meas.traits = NoiseTraits(lag.result(), blocks, jpeg)
    return meas


#: A saturation atom: at least this share of one condition's interior pixels read the same value in every frame.
SATURATION_SHARE = 0.01


def data_full_scale(ds: Dataset, dtype: np.dtype, maximum: float) -> float:
    """The converter's full scale: for integer FITS frames their container's (a CCD's 16-bit ADU are written as
    BITPIX 16 with BZERO 32768), else inferred from the largest value (:func:`infer_full_scale`: 12- and 14-bit
    data in 16-bit PNG or TIFF files).

    Why: a 16-bit CCD's dark series whose hottest pixel stays below 16,383 ADU was taken for 14-bit data, and a
    region or tile of the frames could get another full scale than its neighbour.  A converter that clips below
    its container is still found from the data (:func:`saturation_level`)."""
    from forensics.io.fits import is_fits

    if dtype.kind in "ui" and dtype != np.uint8 and ds.frames and all(is_fits(f.path) for f in ds.frames):
        return float(np.iinfo(dtype).max)
    return infer_full_scale(dtype, maximum)


def saturation_level(lo: np.ndarray, hi: np.ndarray, interior: np.ndarray, full_scale: float) -> float | None:
    """The readout value at which the data saturate below ``full_scale``, or None.

    A sensor whose full well fills before its converter's top reads one value, up to the noise after the well,
    wherever the light exceeds it (emva1288's camera at K = 0.1 DN/e⁻: 15,000 e⁻ read 1501 DN of 4095, a few
    readouts at 1502): an atom at the top of the readouts.  Found per condition from every pixel's smallest and
    largest readout over its frames (``lo``, ``hi``: conditions × H × W) as a value S that at least
    :data:`SATURATION_SHARE` of the interior pixels read in every frame (``lo == S``), with hardly any pixel just
    below it (``lo`` at S − 1 or S − 2: under a tenth as many — an atom, not the mode of a noisy level) and hardly
    any above it (``hi`` > S + 2: under a tenth as many there, and under half a percent of all the readouts of the
    data).  The highest such S is the bound, if the data reach well below it (the darkest condition's median
    under (S − 10)/2: a quantised, low-noise dark frame is an atom too); without one (a few stuck pixels at one
    value, a noisy flat's upper tail) the full scale stays the bound.
    """
    if lo.size == 0:
        return None
    lo_i = np.rint(lo[:, interior]).astype(np.int64)
    hi_i = np.rint(hi[:, interior]).astype(np.int64)
    n = int(interior.sum())
    found = []
    for low, high in zip(lo_i, hi_i):
        values, counts = np.unique(low, return_counts=True)
        top = int(np.argmax(counts))
        for k in np.flatnonzero(counts >= SATURATION_SHARE * n):
            level, c = int(values[k]), int(counts[k])
            below = int(np.sum((low == level - 1) | (low == level - 2)))
            above = int(np.sum(high > level + 2))
            if below <= 0.1 * c and above <= 0.1 * c and k >= top:
                found.append(level)
    if not found:
        return None
    level = max(found)  # the top of the data (a quantised low-noise dark frame can be an atom too, far below)
    floor = float(np.min(np.median(lo_i, axis=1)))  # the darkest condition's level
    if level >= full_scale or level < 2.0 * floor + 10.0 or np.sum(hi_i > level + 2) > 0.005 * hi_i.size:
        return None  # at the full scale anyway, no range of light below it, or readouts beyond it
    return float(level)


#: A dark pixel counts as saturated in a longer exposure when it grew by less than this share of the growth its
#: excess over the bulk in the shorter exposure predicts.
FULL_WELL_GROWTH = 0.5
#: ... and only where its rise from t₀ to t₁ (the rate's evidence) is at least this many times the frames' robust
#: spread at t₁: a clear signal, not the noise of a short baseline.
FULL_WELL_CLEAR = 30.0
#: The full-well level: the lowest saturated reading at and above which at least this share of the dark readings
#: are saturated ones, and at least :data:`FULL_WELL_PIXELS` of them.
FULL_WELL_SHARE = 0.5
FULL_WELL_PIXELS = 3
#: A saturated pixel keeps at least this share of its rise from t₀ to t₁ at t₂ (its saturated readings scatter by a
#: few per cent of the well, 62,154 then 61,005 ADU); a cosmic-ray hit at t₁ loses all of it.
FULL_WELL_KEPT = 0.5


def full_well_level(mean_all: np.ndarray, groups: Sequence[Group], interior: np.ndarray) -> float | None:
    """The readout from which hot pixels saturate in dark frames, or None.

    A cooled CCD's full well (or its anti-blooming drain) fills before the converter's top: a very hot pixel's
    dark signal grows with the exposure to ≈ 61,000–65,000 ADU and then stays there (the 2017 STL-1001E: 7,190,
    12,924, 18,911, 36,333, 63,436, 62,403 ADU at 10 … 300 s).  Such readouts do not follow the model's linear
    dark signal, and the fit followed them for ever (a tile with one such pixel still moving after 24 cycles).

    Unlike the atom of :func:`saturation_level` the level differs from pixel to pixel, so it is found from the
    pixels' own series.  For three dark conditions of one epoch, gain and temperature (within 1 °C) with
    exposures t₀ < t₁ < t₂ (t₀ = 0: the biases), a pixel reads saturated at t₂ when its rise from t₀ to t₁ is
    clear (at least :data:`FULL_WELL_CLEAR` times the frames' robust spread at t₁), the growth that rise predicts
    from t₁ to t₂ falls short by half (:data:`FULL_WELL_GROWTH`), and it keeps at least half its rise
    (:data:`FULL_WELL_KEPT`: a cosmic-ray hit or a telegraph pixel's high state at t₁ loses it).  The level is the
    lowest such readout at and above which most readouts at t₂ are saturated ones (:data:`FULL_WELL_SHARE`, at
    least :data:`FULL_WELL_PIXELS` of them): a telegraph pixel stalling at a few thousand ADU lies among thousands
    of hot pixels still growing, the full well above them all.

    Parameters
    ----------
    mean_all
        Per condition, every pixel's mean readout (conditions × H × W).
    groups
        The conditions (their ``index`` into ``mean_all``).
    interior
        The pixels to look at (H × W).

    Returns
    -------
    float or None
        The level in DN, or None without three dark exposures at one temperature or without saturated pixels.

    Examples
    --------
    >>> from types import SimpleNamespace as G
    >>> t = np.array([0.0, 10.0, 20.0])
    >>> rates = np.r_[np.full(95, 1.0), np.full(5, 3000.0)]       # five pixels fill a 40,000 DN well by 20 s
    >>> means = np.minimum(1000.0 + rates[None] * t[:, None], 40000.0).reshape(3, 10, 10)
    >>> means = means + np.random.default_rng(0).normal(0, 1, means.shape)
    >>> groups = [G(index=i, subject="dark", exposure_s=x, epoch=0, iso=None, temperature_c=-10.0, scenes=False)
    ...           for i, x in enumerate(t)]
    >>> full_well_level(means, groups, np.ones((10, 10), bool)) > 39_990
    True
    """
    from forensics.io.dataset import is_dark_subject

    darks = [g for g in groups if is_dark_subject(g.subject) and g.exposure_s is not None and not g.scenes]
    readings: list[np.ndarray] = []
    flags: list[np.ndarray] = []
    for g0 in darks:
        series = [g0]  # the next two exposures up at g0's epoch, gain and temperature
        for _ in range(2):
            later = [g for g in darks if g.exposure_s > series[-1].exposure_s and g.epoch == g0.epoch
                     and g.iso == g0.iso and (g.temperature_c is None) == (g0.temperature_c is None)
                     and (g.temperature_c is None or abs(g.temperature_c - g0.temperature_c) < 1.0)]
            if later:
                series.append(min(later, key=lambda g: g.exposure_s))
        if len(series) < 3:
            continue
        m0, m1, m2 = (mean_all[g.index][interior].astype(np.float64) for g in series)
        t0, t1, t2 = (g.exposure_s for g in series)
        spread = 1.4826 * float(np.median(np.abs(m1 - np.median(m1))))
        rise = m1 - m0
        predicted = rise * (t2 - t1) / (t1 - t0)  # the pixel's own rate between t0 and t1, carried on
        # stalled, but not fallen back: a cosmic-ray hit in the middle exposure, or a telegraph pixel in its high
        # state there, has a rise that is gone in the longer one
        stalled = ((rise >= FULL_WELL_CLEAR * max(spread, 1.0)) & (m2 - m1 < FULL_WELL_GROWTH * predicted)
                   & (m2 - m0 >= FULL_WELL_KEPT * rise))
        readings.append(m2)
        flags.append(stalled)
    if not readings:
        return None
    order = np.argsort(np.concatenate(readings))[::-1]  # every reading at t₂, from the top down
    values = np.concatenate(readings)[order]
    stalled_share = np.cumsum(np.concatenate(flags)[order]) / np.arange(1, len(order) + 1)
    count = np.cumsum(np.concatenate(flags)[order])
    ok = np.flatnonzero((stalled_share >= FULL_WELL_SHARE) & (count >= FULL_WELL_PIXELS)
                        & np.concatenate(flags)[order])
    return float(np.floor(values[ok[-1]])) if ok.size else None


def _refuse_content_free(ds: Dataset, groups: list[Group], dropped: list[int], excluded: list[tuple[str, str]],
                         notes: list[str]) -> None:
    """Refuse a dataset whose frames are all content-free, else say in the notes what was left out.

    Raises
    ------
    InputError
        Every frame, or every condition with two or more frames, is content-free.
    """
    first = f"first, {excluded[0][0]}: {excluded[0][1]}"
    if len(excluded) == len(ds):
        raise InputError(f"{ds.root}: every one of its {len(ds)} frames is content-free, so it holds nothing of the "
                         f"sensor to check ({first}); give exposed frames (not all black, all saturated or constant)")
    if all(g.index in dropped or g.n < 2 for g in groups):
        raise InputError(f"{ds.root}: {len(excluded)} of its {len(ds)} frames are content-free ({first}) and no "
                         "condition keeps two frames with content; the noise floor is measured from repeated frames")
    notes.append(f"{len(excluded)} content-free frame(s) left out ({first})"
                 + (f"; {len(dropped)} condition(s) without two frames with content dropped" if dropped else ""))


def _stackable(frame: np.ndarray, grey: np.ndarray, first_dtype: np.dtype | None) -> np.ndarray:
    """What a condition's stack accumulates of a frame: a grey 8- or 16-bit frame as it is (the accumulator's
    exact integer sums: 20 bytes a pixel instead of 48, the same statistics), anything else as ``grey``
    (float64).  ``first_dtype`` is the type accumulated for the condition's first frame (None for that frame):
    an integer frame that casts to it without loss is converted (8-bit among 16-bit), any other mixture is
    left for the accumulator to report."""
    if frame.ndim != 2 or frame.dtype not in (np.uint8, np.uint16):
        return grey
    if first_dtype is None or frame.dtype == first_dtype:
        return frame
    if first_dtype in (np.uint8, np.uint16) and np.can_cast(frame.dtype, first_dtype, "safe"):
        return frame.astype(first_dtype)
    return grey if first_dtype not in (np.uint8, np.uint16) else frame


@dataclass(frozen=True)
class LevelDrift:
    """How much the frames' overall level changes within a condition, against the noise of a frame mean."""

    var: float  #: variance of the frame-to-frame level changes (DN²; 0 when not above the noise)
    f: float  #: F statistic: frames' mean square over the frames × blocks interaction's
    p: float

    def material(self, pixel_var: float, alpha: float = 1e-3, share: float = 0.01) -> bool:
        """Significant (p < ``alpha``) and at least ``share`` of a pixel's temporal variance ``pixel_var``."""
        return self.p < alpha and self.var >= share * pixel_var


def level_drift(blocks: np.ndarray | Sequence[np.ndarray]) -> LevelDrift:
    """Frame-to-frame level changes from the frames' block means ``(n_frames, n_blocks)`` (or several
    conditions' arrays, pooled): a two-way analysis of variance, frames × blocks.

    A level change moves every block of a frame alike; noise moves the blocks independently (blocks are much
    larger than the noise's correlation length), so the frames' mean square is tested against the
    interaction's.  The interaction also holds any change of the scene's shape (a level change times the
    vignetting), which only makes the test conservative.
    """
    arrays = [blocks] if isinstance(blocks, np.ndarray) else list(blocks)
    ss_f = ss_e = 0.0
    df_f = df_e = 0
    n_blocks = []
    for x in arrays:
        t, b = x.shape if x.ndim == 2 else (0, 0)
        if t < 2 or b < 2:
            continue
        frame = x.mean(axis=1)
        inter = x - frame[:, None] - x.mean(axis=0)[None] + x.mean()
        ss_f += b * float(np.sum((frame - frame.mean()) ** 2))
        ss_e += float(np.sum(inter**2))
        df_f += t - 1
        df_e += (t - 1) * (b - 1)
        n_blocks.append(b)
    if df_f == 0 or ss_e <= 0:
        return LevelDrift(0.0, 0.0, 1.0)
    ms_f, ms_e = ss_f / df_f, ss_e / df_e
    f = ms_f / ms_e
    p = float(f_sf(f, df_f, df_e))
    return LevelDrift(max(ms_f - ms_e, 0.0) / float(np.mean(n_blocks)), f, p)
