"""Atomic output: every file and folder the toolkit writes appears whole or not at all.

Files are written to a temporary sibling and renamed into place; folders are
built under a temporary sibling name and renamed when complete.  An existing
output is refused unless ``force`` is true, and an input is never overwritten.

Temporary files and folders are created with the mode a plain ``open()`` or
``mkdir()`` would give (``0o666`` / ``0o777`` less the umask, default ACLs
applied by the kernel), not :func:`tempfile.mkstemp`'s private ``0o600`` /
``0o700``: the rename keeps the mode, and outputs on shared storage must be as
readable as the user's umask says (:func:`mkstemp_like_open`,
:func:`mkdtemp_like_mkdir`).
"""
from __future__ import annotations

import contextlib
import errno
import os
import secrets
import shutil
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from forensics._shared.errors import UsageError
from forensics._shared.jsonsafe import dumps

#: Errors of the device written to rather than of the program: a full disk, a quota, a file-size limit.
#: Python reports them without a file name when they come from ``write()`` or ``close()``.
_DEVICE_ERRORS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO, errno.EROFS})
_ATTEMPTS = 100


def refuse_existing(path: str | os.PathLike, force: bool, *, file: bool = False) -> Path:
    """Raise :class:`UsageError` if ``path`` exists and ``force`` is false.

    With ``file=True`` (the output is one file) an existing *folder* is refused even with ``force``: a folder
    is never deleted to make room for a file (``-o FOLDER`` is more likely a slip for ``-o FOLDER/NAME``).
    """
    path = Path(path)
    if file and path.is_dir():
        raise UsageError(f"{path}: is a folder, and the output is a file; give a file name (e.g. {path}/NAME), "
                         "or remove the folder first")
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


def _temporary_name(folder: Path, prefix: str, suffix: str) -> Path:
    return folder / f"{prefix}{secrets.token_hex(4)}{suffix}"


def mkstemp_like_open(prefix: str = "", suffix: str = "", dir: str | os.PathLike = ".") -> tuple[int, str]:
    """:func:`tempfile.mkstemp` (a new file of a random name, opened for writing), with the mode ``open()`` gives.

    The file is created with ``O_CREAT | O_EXCL`` (never an existing file or symbolic link, as ``mkstemp``) and
    mode ``0o666``, so the kernel applies the umask and any default ACL exactly as for a plain ``open(path,
    'w')``.  Returns ``(fd, path)``.
    """
    folder = Path(dir)
    flags = os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0)
    for _ in range(_ATTEMPTS):
        name = _temporary_name(folder, prefix, suffix)
        try:
            return os.open(name, flags, 0o666), str(name)
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, "no free temporary name", str(folder / f"{prefix}*{suffix}"))


def mkdtemp_like_mkdir(prefix: str = "", suffix: str = "", dir: str | os.PathLike = ".") -> Path:
    """:func:`tempfile.mkdtemp` (a new folder of a random name) with the mode ``mkdir()`` gives (``0o777`` less the
    umask), so that a folder renamed into place is as accessible as one made directly."""
    folder = Path(dir)
    for _ in range(_ATTEMPTS):
        name = _temporary_name(folder, prefix, suffix)
        try:
            name.mkdir(0o777)
            return name
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, "no free temporary name", str(folder / f"{prefix}*{suffix}"))


def current_umask() -> int:
    """This process's umask, read without changing it (``/proc/self/status`` on Linux).

    ``os.umask`` can only be read by setting it, which for a moment changes the mode of files that other
    threads create; where ``/proc`` does not tell, it is set to the most private value for that moment.
    """
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    old = os.umask(0o077)
    os.umask(old)
    return old


def _name_the_file(exc: OSError, path: Path) -> OSError:
    """``exc`` with ``path`` as its file name when it is a device error reported without one (ENOSPC from write)."""
    if exc.filename is None and exc.errno in _DEVICE_ERRORS:
        named = OSError(exc.errno, exc.strerror or os.strerror(exc.errno), str(path))  # same subclass by errno
        named.__cause__ = exc
        return named
    return exc


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike, force: bool = False, mode: str = "wb") -> Iterator[Any]:
    """Open a temporary file beside ``path``; rename it onto ``path`` on success, delete it on failure.

    The file gets the mode ``open()`` would give it (umask applied).  A full disk or quota while writing is
    raised as :class:`OSError` naming ``path``, after the temporary file is removed.  An existing folder at
    ``path`` is refused (:func:`refuse_existing` with ``file=True``).
    """
    path = refuse_existing(path, force, file=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = mkstemp_like_open(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as handle:
            yield handle
        os.replace(tmp, path)
    except OSError as exc:
        _remove_quietly(tmp)
        named = _name_the_file(exc, path)
        if named is exc:
            raise
        raise named from exc
    except BaseException:
        _remove_quietly(tmp)
        raise


def _remove_quietly(path: str | os.PathLike) -> None:
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)


def write_bytes(path: str | os.PathLike, data: bytes, force: bool = False) -> Path:
    """Write ``data`` to ``path`` atomically."""
    with atomic_file(path, force=force, mode="wb") as handle:
        handle.write(data)
    return Path(path)


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
    """Yield a temporary folder beside ``path``; on success it replaces ``path``, on failure it is removed.

    The folder gets the mode ``mkdir()`` would give it (umask applied).
    """
    path = refuse_existing(path, force)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = mkdtemp_like_mkdir(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    try:
        yield tmp
        move_directory_into_place(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def move_directory_into_place(tmp: Path, path: Path) -> None:
    """Rename the finished folder ``tmp`` onto ``path``, replacing an existing ``path`` (moved aside first).

    What was at ``path`` — a folder or a file — is removed after the rename, so nothing of it is left beside.
    """
    if path.exists() or path.is_symlink():
        old = path.with_name(f".{path.name}.old-{os.getpid()}")
        os.replace(path, old)
        os.replace(tmp, path)
        if old.is_dir() and not old.is_symlink():
            shutil.rmtree(old, ignore_errors=True)
        else:
            _remove_quietly(old)
    else:
        os.replace(tmp, path)
