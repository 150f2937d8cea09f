"""Summaries of datasets and image files (what ``forensics info`` shows)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from forensics.io.dataset import Dataset, set_point, temperature_groups
from forensics.io.images import ImageInfo, is_raw, read_info, read_raw


@dataclass
class DatasetSummary:
    """Size, dtype, devices, capture span, epochs and conditions of a dataset."""

    root: str
    n_images: int
    shape: list[int]
    dtype: str
    has_manifest: bool
    devices: list[str | None]
    captured: list[float] | None
    epochs: list[dict[str, Any]] = field(default_factory=list)
    conditions: list[dict[str, Any]] = field(default_factory=list)
    frame_types: list[dict[str, Any]] = field(default_factory=list)
    #: files whose header reads but whose pixels cannot (a truncated FITS file), with why: every command that reads
    #: pixels refuses them, so ``info`` names them first
    unreadable: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def summarize_dataset(ds: Dataset) -> DatasetSummary:
    """Read every header once and summarise the dataset (raises InputError on mixed sizes)."""
    shape = ds.shape()
    dtype = str(ds[0].info().dtype)
    times = [f.captured for f in ds]
    known = [t for t in times if t is not None]
    epochs: list[dict[str, Any]] = []
    if len(known) == len(times):
        for epoch in ds.epochs():
            t = epoch.captured_times()
            epochs.append({"start": float(t.min()), "end": float(t.max()), "n": len(epoch)})
    conditions = [{"exposure_s": k[0], "iso": k[1], "temperature_c": k[2], "subject": k[3], "n": len(v)}
                  for k, v in ds.conditions().items()]
    unreadable = [str(f.info().extra["truncated"]) for f in ds if f.info().extra.get("truncated")]
    return DatasetSummary(str(ds.root), len(ds), list(shape), dtype, ds.has_manifest, ds.devices(),
                          [min(known), max(known)] if known else None, epochs, conditions, frame_types(ds),
                          unreadable)


def frame_types(ds: Dataset) -> list[dict[str, Any]]:
    """Calibration frames (FITS IMAGETYP or a manifest ``frame_type``) by type, exposure and temperature group: how
    many, the measured temperatures, and the frames measured more than a degree off their set point.

    The temperature group is the one ``defects detect`` uses (:func:`~forensics.io.dataset.temperature_groups`):
    the set point, or for frames without one a cluster of measured temperatures (``measured_c``, its centre) — so
    that biases at −10 and −5 °C without SET-TEMP are two rows, not one spanning both."""
    from forensics.io.fits import SETPOINT_TOLERANCE_C

    typed = [f for f in ds if f.get("frame_type")]
    keys = temperature_groups([set_point(f) for f in typed], [f.temperature_c for f in typed], SETPOINT_TOLERANCE_C)
    groups: dict[tuple[Any, ...], list[Any]] = {}
    for frame, (how, temperature) in zip(typed, keys):
        groups.setdefault((frame.get("frame_type"), frame.exposure_s, how, temperature), []).append(frame)
    rows = []
    for (kind, exposure, how, temperature), frames in sorted(
            groups.items(), key=lambda kv: (str(kv[0][0]), kv[0][3] or 0.0, kv[0][1] or 0.0)):
        setpoint = temperature if how == "set" else None
        temps = [f.temperature_c for f in frames if f.temperature_c is not None]
        off = [f.file for f in frames if setpoint is not None and f.temperature_c is not None
               and abs(f.temperature_c - setpoint) > SETPOINT_TOLERANCE_C]
        rows.append({"frame_type": kind, "exposure_s": exposure, "set_temperature_c": setpoint,
                     "measured_c": temperature if how == "measured" else None, "n": len(frames),
                     "temperature_c": [min(temps), max(temps)] if temps else None, "off_set_point": off})
    return rows


def summarize_file(path: str | Path) -> dict[str, Any]:
    """Header, EXIF and (for raw files) CFA pattern and levels of one image file."""
    path = Path(path)
    if is_raw(path):
        raw = read_raw(path)
        info: ImageInfo = raw.info
        extra = {"cfa_pattern": raw.cfa_pattern, "black_level": list(raw.black_level), "white_level": raw.white_level}
    else:
        info = read_info(path)
        extra = {k: v for k, v in info.extra.items() if v not in (None, [], "")}  # a FITS header's conditions
    out = {k: v for k, v in asdict(info).items() if k != "extra"}
    out["dtype"] = str(np.dtype(info.dtype))
    out["path"] = str(path)
    out["captured"] = info.captured.isoformat() if info.captured else None
    return {**out, **extra}
