"""Atomic output: every file and folder the toolkit writes appears whole or not at all.

Files are written to a temporary sibling and renamed into place; folders are
built under a temporary sibling name and renamed when complete.  An existing
output is refused unless ``force`` is true, and an input is never overwritten.
"""
from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from forensics._shared.errors import UsageError
from forensics._shared.jsonsafe import dumps


def refuse_existing(path: str | os.PathLike, force: bool) -> Path:
    """Raise :class:`UsageError` if ``path`` exists and ``force`` is false."""
    path = Path(path)
    if path.exists() and not force:
        raise UsageError(f"{path}: already exists; choose another output or pass --force to replace it")
    return path


def refuse_inputs(path: str | os.PathLike, inputs: Iterable[str | os.PathLike]) -> None:
    """Raise :class:`UsageError` if ``path`` is (or contains, or lies inside) one of ``inputs``.

    Paths are compared after resolving symbolic links (an output that does not exist yet is resolved as far as
    its folders exist), so a link or ``..`` cannot hide an input; the check is the same with or without force.
    """
    target = Path(path).resolve()
    for item in inputs:
        source = Path(item).resolve()
        if target == source:
            how = "is the input"
        elif source.is_relative_to(target):
            how = "contains the input"
        elif target.is_relative_to(source):
            how = "lies inside the input"
        else:
            continue
        raise UsageError(f"{path}: {how} {item}, which would be overwritten or deleted; choose an output outside "
                         "the inputs")


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike, force: bool = False, mode: str = "wb") -> Iterator[Any]:
    """Open a temporary file beside ``path``; rename it onto ``path`` on success, delete it on failure."""
    path = refuse_existing(path, force)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as handle:
            yield handle
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_text(path: str | os.PathLike, text: str, force: bool = False) -> Path:
    """Write ``text`` to ``path`` atomically."""
    with atomic_file(path, force=force, mode="w") as handle:
        handle.write(text)
    return Path(path)


def write_json(path: str | os.PathLike, obj: Any, force: bool = False) -> Path:
    """Write ``obj`` as indented standard JSON to ``path`` atomically (:func:`~forensics._shared.jsonsafe.dumps`)."""
    return write_text(path, dumps(obj, indent=2) + "\n", force=force)


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike, force: bool = False) -> Iterator[Path]:
    """Yield a temporary folder beside ``path``; on success it replaces ``path``, on failure it is removed."""
    path = refuse_existing(path, force)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent))
    try:
        yield tmp
        move_directory_into_place(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def move_directory_into_place(tmp: Path, path: Path) -> None:
    """Rename the finished folder ``tmp`` onto ``path``, replacing an existing ``path`` (moved aside first)."""
    if path.exists():
        old = path.with_name(f".{path.name}.old-{os.getpid()}")
        os.replace(path, old)
        os.replace(tmp, path)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, path)
