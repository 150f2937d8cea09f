"""Decoded frames on disk: read each frame once, then any part of it at the cost of that part.

A check of the whole frame in tiles (:mod:`forensics.check.tiles`) reads every frame once per tile.  A PNG, TIFF
or FITS file cannot be decoded in parts, so each tile would decode every whole frame: the reading grows with the
number of tiles × the frame's size, i.e. with the square of the frame (12 MP × 36 frames in 768 tiles of 125²:
≈ 27,600 decodes of 0.2 s, 1.5 CPU hours, against 7 CPU s once).  Here every frame is decoded once into a
``.npy`` file of its native dtype; a reader maps it (``numpy.load(mmap_mode="r")``) and slicing a tile touches
only the tile's rows (a few kB each).  The values are the decoder's, bit for bit, so every result is the same
as reading the files.

The files are named by a digest of the frame's path, so a sub-dataset (:meth:`~forensics.io.dataset.Dataset.subset`)
finds its frames' files too.  The cache is scratch space: :func:`frame_cache` makes it in a temporary directory
and removes it on leaving; on a cluster of several machines it must be on storage every worker sees (``scratch``).
"""
from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from forensics._shared.atomic import atomic_file
from forensics._shared.progress import Progress, no_progress
from forensics.io.dataset import Dataset

if TYPE_CHECKING:
    from forensics._shared.parallel import Executor

#: The free space kept beyond the decoded frames' bytes when deciding whether a cache fits on the scratch disk.
FREE_MARGIN = 1.1


def cached_name(path: str | os.PathLike) -> str:
    """The cache file's name of the frame at ``path`` (a digest of the path: independent of the frame's position).

    Examples
    --------
    >>> cached_name("/data/f0001.png") == cached_name("/data/f0001.png") != cached_name("/data/f0002.png")
    True
    """
    return hashlib.sha256(str(path).encode("utf-8", "surrogatepass")).hexdigest()[:24] + ".npy"


def decode_to(item: tuple[str, str]) -> None:
    """Decode the frame at ``item[0]`` into the ``.npy`` file ``item[1]`` (written atomically).  A work item
    (module-level)."""
    from forensics.io.images import read_image

    source, target = item
    pixels = read_image(source)
    with atomic_file(target) as fh:
        np.save(fh, pixels, allow_pickle=False)


def decoded_bytes(ds: Dataset) -> int:
    """The bytes of every frame of ``ds`` decoded (from the headers: no frame is decoded)."""
    total = 0
    for frame in ds.frames:
        info = frame.info()
        total += int(info.width) * int(info.height) * max(int(info.channels), 1) * int(np.dtype(info.dtype).itemsize)
    return total


@contextlib.contextmanager
def frame_cache(ds: Dataset, scratch: str | os.PathLike | None = None, progress: Progress = no_progress,
                executor: Executor | None = None) -> Iterator[tuple[Dataset, str | None]]:
    """Decode every frame of ``ds`` once into a temporary directory under ``scratch`` (default: the system's
    temporary directory) and yield ``(dataset reading from there, None)``; the directory is removed on leaving.

    Where the decoded frames would not fit on the scratch disk (with :data:`FREE_MARGIN`), nothing is written and
    ``(ds, why)`` is yielded: the dataset unchanged (each reader decodes the files itself, as without a cache) and
    a sentence saying so, for the caller's warnings.

    Examples
    --------
    >>> from forensics.io.dataset import open_dataset                            # doctest: +SKIP
    >>> with frame_cache(open_dataset("flats/")) as (ds, why):                  # doctest: +SKIP
    ...     whole = check_tiles(ds, size=128)                                    # doctest: +SKIP
    """
    from forensics._shared.parallel import resolve

    base = Path(scratch) if scratch is not None else Path(tempfile.gettempdir())
    need = decoded_bytes(ds)
    free = shutil.disk_usage(base).free
    if need * FREE_MARGIN > free:
        yield ds, (f"the decoded frames ({need / 1e9:.1f} GB) do not fit in {base} ({free / 1e9:.1f} GB free): every "
                   "tile decodes the files itself (slower for large frames; give scratch space with room for them)")
        return
    directory = tempfile.mkdtemp(prefix="forensics-frames-", dir=base)
    try:
        items = [(str(f.path), os.path.join(directory, cached_name(f.path))) for f in ds.frames]
        try:
            for _ in resolve(executor).map(decode_to, items, progress=progress, desc="decoding frames"):
                pass
        except OSError as exc:  # the disk filled up after all (frames larger decoded than their headers say)
            shutil.rmtree(directory, ignore_errors=True)  # now: the tiles run before the ``finally`` below
            yield ds, (f"decoding the frames into {base} failed ({exc.strerror or exc}): every tile decodes the files "
                       "itself (give scratch space with room for them)")
            return
        yield replace(ds, frame_cache=directory), None
    finally:
        shutil.rmtree(directory, ignore_errors=True)


def open_cached(directory: str, path: str | os.PathLike) -> np.ndarray:
    """The decoded frame of ``path`` from a cache ``directory``, mapped read-only (slicing reads only the slice)."""
    return np.load(os.path.join(directory, cached_name(path)), mmap_mode="r")
