"""Writing a clustering (:func:`forensics.prnu.cluster.cluster_images`) as a dataset folder, one sub-folder per
device found; the input images are never modified.
"""
from __future__ import annotations

import os
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from forensics._shared.errors import InputError, UsageError

if TYPE_CHECKING:  # cluster re-exports this module's function, so it is imported here only for the types
    from forensics.prnu.cluster import ClusterResult

__all__ = ["write_cluster_dataset"]


def _place(src: Path, dst: Path) -> str:
    """Hard-link ``src`` to ``dst`` (same file system), else copy it; never a symbolic link."""
    try:
        os.link(src, dst)
        return "link"
    except OSError:
        shutil.copy2(src, dst)
        return "copy"


def write_cluster_dataset(result: ClusterResult, out: str | os.PathLike, *, captured: Sequence[float | None] | None = None,
                          force: bool = False) -> dict[str, Any]:
    """Write the clusters as a dataset folder, atomically; the input images are never modified.

    Layout: ``OUT/<device>/<image>`` (``OUT/unattributed/`` for images attributed to no device), each image
    hard-linked when the output is on the input's file system, else copied (never a symbolic link, which a
    manifest would refuse as leaving the folder; a hard link shares the input's bytes, so edit copies, not
    these files); ``OUT/manifest.csv`` with ``file, device, source_file``
    (+ ``captured`` when known), ``device`` empty for unattributed images; one ``manifest.csv`` per device
    folder, so ``forensics fingerprint build OUT/cluster-01`` works as it is; ``clusters.json``
    (:meth:`ClusterResult.to_dict`) and ``similarity.npz`` (each size group's z matrix and its files).

    Parameters
    ----------
    result : ClusterResult
    out : path
    captured : sequence of float or None, optional
        Capture time (decimal year) of each image, in input order.
    force : bool
        Replace an existing ``out``.

    Returns
    -------
    dict
        ``{"output", "linked", "copied"}``.

    Raises
    ------
    UsageError
        ``out`` exists (without ``force``) or holds one of the inputs.
    InputError
        An image's source is not a file (images given as arrays cannot be written).
    """
    from forensics._shared.atomic import atomic_directory, refuse_existing, write_json
    from forensics.io.dataset import write_manifest
    from forensics.prnu.cluster import UNATTRIBUTED

    out = refuse_existing(out, force)
    sources = [Path(a.source) for a in result.images]
    for a, src in zip(result.images, sources):
        if not src.is_file():
            raise InputError(f"{a.source}: not a file; only images read from files can be written to a dataset")
        if src.resolve().is_relative_to(out.resolve()):
            raise UsageError(f"{out}: holds the input {src}; choose an output outside the inputs")
    if captured is not None and len(captured) != len(result.images):
        raise UsageError(f"{len(captured)} capture times for {len(result.images)} images; give one per image")
    counts = {"link": 0, "copy": 0}
    with atomic_directory(out, force=force) as tmp:
        rows: list[dict[str, Any]] = []
        per_folder: dict[str, list[dict[str, Any]]] = {}
        used: set[str] = set()
        for a, src in zip(result.images, sources):
            folder = a.cluster or UNATTRIBUTED
            name = _unique_name(folder, src.name, used)
            (tmp / folder).mkdir(exist_ok=True)
            counts[_place(src, tmp / folder / name)] += 1
            row: dict[str, Any] = {"file": f"{folder}/{name}", "device": a.cluster or "", "source_file": str(src)}
            if captured is not None and captured[a.index] is not None:
                row["captured"] = captured[a.index]
            rows.append(row)
            per_folder.setdefault(folder, []).append({**row, "file": name})
        write_manifest(tmp / "manifest.csv", rows)
        for folder, folder_rows in per_folder.items():
            write_manifest(tmp / folder / "manifest.csv", folder_rows)
        write_json(tmp / "clusters.json", result.to_dict())
        arrays = {f"group{g.index}": z for g, z in zip(result.groups, result.similarity)}
        arrays.update({f"group{g.index}_files": np.array([result.images[i].file for i in g.members], dtype=str)
                       for g in result.groups})
        np.savez_compressed(tmp / "similarity.npz", **arrays)
    return {"output": str(out), "linked": counts["link"], "copied": counts["copy"]}


def _unique_name(folder: str, name: str, used: set[str]) -> str:
    """``name`` in ``folder``, with ``-2``, ``-3``, … before the suffix when taken (case-insensitively)."""
    stem, suffix = os.path.splitext(name)
    candidate, k = name, 1
    while f"{folder}/{candidate}".lower() in used:
        k += 1
        candidate = f"{stem}-{k}{suffix}"
    used.add(f"{folder}/{candidate}".lower())
    return candidate
