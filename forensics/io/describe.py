"""Summaries of datasets and image files (what ``forensics info`` shows)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from forensics.io.dataset import Dataset
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
    return DatasetSummary(str(ds.root), len(ds), list(shape), dtype, ds.has_manifest, ds.devices(),
                          [min(known), max(known)] if known else None, epochs, conditions)


def summarize_file(path: str | Path) -> dict[str, Any]:
    """Header, EXIF and (for raw files) CFA pattern and levels of one image file."""
    path = Path(path)
    if is_raw(path):
        raw = read_raw(path)
        info: ImageInfo = raw.info
        extra = {"cfa_pattern": raw.cfa_pattern, "black_level": list(raw.black_level), "white_level": raw.white_level}
    else:
        info, extra = read_info(path), {}
    out = {k: v for k, v in asdict(info).items() if k != "extra"}
    out["dtype"] = str(np.dtype(info.dtype))
    out["path"] = str(path)
    out["captured"] = info.captured.isoformat() if info.captured else None
    return {**out, **extra}
