"""Loading a dataset into per-condition statistics: the first stage of the check.

Every frame is read once.  Frames are grouped by condition (epoch, exposure, ISO, temperature, subject);
each group's frames stream into :class:`~forensics.io.stack.StackAccumulator` s — all frames, and the even
and odd frames separately (the two halves the pixel channel fits and scores on).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import forensics.stats.spatial as sp
from forensics._shared.arrays import grey_mean, infer_full_scale
from forensics._shared.errors import InputError
from forensics._shared.progress import Progress, no_progress
from forensics.check.scene import SCENE_SIZE, scene_estimate
from forensics.io.dataset import Dataset, open_dataset, split_epochs
from forensics.io.stack import StackAccumulator


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

    @property
    def n(self) -> int:
        return len(self.frames)

    @property
    def condition(self) -> tuple[Any, ...]:
        return (self.exposure_s, self.iso, self.temperature_c, self.subject)

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
        return ", ".join(parts)


@dataclass
class Measurements:
    """Per-condition statistics of a dataset, ready for checking.

    Arrays indexed ``[g]`` run over :attr:`groups` (every condition); those
    indexed by the pixel channel run over :attr:`repeated` (conditions with at
    least two frames), in that order.
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


def _central_crop(h: int, w: int, max_size: int) -> tuple[slice, slice]:
    top, left = max(0, (h - max_size) // 2), max(0, (w - max_size) // 2)
    return slice(top, top + min(h, max_size)), slice(left, left + min(w, max_size))


def group_frames(ds: Dataset, epoch: np.ndarray, epoch_times: np.ndarray) -> list[Group]:
    """Frames grouped by (epoch, exposure, ISO, temperature, subject), in order of epoch and first frame."""
    keys: dict[tuple[Any, ...], list[int]] = {}
    for i, f in enumerate(ds.frames):
        keys.setdefault((int(epoch[i]), f.exposure_s, f.iso, f.temperature_c, f.subject), []).append(i)
    return [Group(j, k[0], float(epoch_times[k[0]]), k[1], k[2], k[3], k[4], idx)
            for j, (k, idx) in enumerate(sorted(keys.items(), key=lambda kv: (kv[0][0], kv[1][0])))]


def load_measurements(data: Dataset | str | Path, border: int | None = None, epoch_gap: float = 0.25,
                      max_size: int = 512, progress: Progress = no_progress) -> Measurements:
    """Read every frame once and reduce the dataset to per-condition statistics.

    Parameters
    ----------
    data
        A dataset or its folder.
    border
        Pixels ignored at each edge (default: half the scene window, 3).
    epoch_gap
        Capture-time gap (years) that starts a new epoch.
    max_size
        Larger frames are cropped to their central ``max_size × max_size`` pixels.

    Raises
    ------
    InputError
        No condition has two or more frames (the noise floor cannot be measured).
    """
    ds = data if isinstance(data, Dataset) else open_dataset(data)
    shape = ds.shape()
    notes = []
    h, w = shape[0], shape[1]
    crop = _central_crop(h, w, max_size)
    if h > max_size or w > max_size:
        notes.append(f"frames of {w}×{h} cropped to their central {min(w, max_size)}×{min(h, max_size)} pixels")
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
        raise InputError(f"{ds.root}: no condition has two or more frames; the noise floor is measured from repeated "
                         "frames of one condition (same exposure_s, iso, temperature_c, subject and epoch): "
                         "take at least 2 frames per condition")
    shp = (crop[0].stop - crop[0].start, crop[1].stop - crop[1].start)
    G, R = len(groups), len(repeated)
    mean_all, var_all, lo, hi = (np.zeros((G, *shp)) for _ in range(4))
    mean_a, mean_b = np.zeros((R, *shp)), np.zeros((R, *shp))
    n_a, n_b = np.zeros(R, int), np.zeros(R, int)
    rpos = {g: r for r, g in enumerate(repeated)}
    dtype = None
    for g in progress(groups, total=G, desc="frames"):
        whole, halves = StackAccumulator(), (StackAccumulator(), StackAccumulator())
        for j, i in enumerate(g.frames):
            img = ds.frames[i].load()
            dtype = img.dtype if dtype is None else dtype
            grey = grey_mean(img[crop], np.float64)
            whole.add(grey, name=ds.frames[i].file)
            halves[j % 2].add(grey, name=ds.frames[i].file)
        stats = whole.result()
        mean_all[g.index], var_all[g.index] = stats.mean, stats.var
        lo[g.index], hi[g.index] = stats.minimum, stats.maximum
        if g.index in rpos:
            r = rpos[g.index]
            a, b = halves[0].result(), halves[1].result()
            mean_a[r], mean_b[r] = a.mean, b.mean
            n_a[r], n_b[r] = a.n, b.n
    full_scale = infer_full_scale(np.dtype(dtype), max(0.0, float(hi.max())))
    border = SCENE_SIZE // 2 if border is None else int(border)
    meas = Measurements(ds.root, shp, full_scale, border, epoch_times, has_time, groups, mean_all, var_all, lo, hi,
                        repeated, mean_a, mean_b, n_a, n_b, len(ds), notes=notes)
    meas.scene_all = np.stack([scene_estimate(m) for m in mean_all])
    return meas
