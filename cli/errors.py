"""Every exception the command can meet, as one line on stderr and an exit code.

The library raises :class:`~forensics._shared.errors.InputError` (bad input data, exit 3) and
:class:`~forensics._shared.errors.UsageError` (a request that cannot be honoured as given, exit 2) on purpose,
with messages that name the file or field.  Everything else that can reach the command from the data or the
machine is mapped here too, so that a user never sees a traceback for a full disk, a symbolic-link loop, a
truncated ``.npz`` or a malformed CSV:

=============================================  ====  ====================================================
exception                                      exit  message
=============================================  ====  ====================================================
``UsageError``                                 2     its own
``InputError``                                 3     its own
``OSError``                                    3     the file name(s) and what the error means (disk full,
                                                     a folder where a file was expected, a link loop …)
``UnicodeError``, ``csv.Error``,               3     what is wrong with the data
``zipfile.BadZipFile``, ``EOFError``,
``json.JSONDecodeError``
``MemoryError``                                1     out of memory, and what to do
``KeyboardInterrupt``                          130   interrupted
``Terminated`` (SIGTERM, handled as Ctrl-C)    143   terminated by SIGTERM
anything else                                  1     ``internal error: …`` (a bug: please report it)
=============================================  ====  ====================================================

With ``FORENSICS_DEBUG=1`` in the environment the traceback is printed before the line.
"""
from __future__ import annotations

import csv
import errno
import json
import os
import zipfile

from forensics._shared.errors import InputError, UsageError
from forensics._shared.lifetime import Terminated
from forensics.cli.common import EXIT_BAD_INPUT, EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_USAGE

DEBUG_ENV = "FORENSICS_DEBUG"

#: What an operating-system error means for the user, and what to do about it.
_OS_REASONS = {
    errno.ENOSPC: "disk full (no space left on the device); free some space or write the output elsewhere",
    errno.EDQUOT: "disk quota exceeded; free some space or write the output elsewhere",
    errno.EISDIR: "is a folder, where a file was expected",
    errno.ENOTDIR: "a part of this path is not a folder",
    errno.ELOOP: "too many levels of symbolic links (a link that points to itself?)",
    errno.ENAMETOOLONG: "file name too long for the file system",
    errno.EACCES: "permission denied; check the file's permissions",
    errno.EPERM: "operation not permitted; check the file's permissions",
    errno.ENOENT: "no such file or folder",
    errno.EEXIST: "already exists (a file where a folder was expected?)",
    errno.EROFS: "read-only file system; write the output elsewhere",
    errno.EMFILE: "too many open files; raise the limit (ulimit -n) or use fewer --workers",
    errno.ENFILE: "too many open files on this system",
    errno.EIO: "input/output error (a failing disk or an unreachable network share?)",
    errno.EFBIG: "file too large (a file-size limit: see ulimit -f)",
    errno.ENXIO: "no such device (a special file, not a regular one?)",
}


def debug() -> bool:
    """Whether the user asked for tracebacks (``FORENSICS_DEBUG`` set to anything but empty or 0)."""
    return os.environ.get(DEBUG_ENV, "") not in ("", "0")


def _one_line(text: object) -> str:
    return " ".join(str(text).split())


def _os_error(exc: OSError) -> str:
    reason = _OS_REASONS.get(exc.errno) or _one_line(exc.strerror or exc)
    names = [os.fsdecode(n) for n in (exc.filename, exc.filename2) if n is not None]
    where = " → ".join(names)
    return f"{where}: {reason}" if where else reason


def _data_error(exc: BaseException) -> str:
    if isinstance(exc, json.JSONDecodeError):
        return f"malformed JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}"
    if isinstance(exc, UnicodeDecodeError):
        return (f"text that is not valid {exc.encoding} ({exc.reason} at byte {exc.start}); save the file as "
                "UTF-8")
    if isinstance(exc, UnicodeError):
        return f"text that cannot be encoded or decoded ({_one_line(exc)})"
    if isinstance(exc, csv.Error):
        return f"malformed CSV ({_one_line(exc)}); check the quoting of the manifest"
    if isinstance(exc, zipfile.BadZipFile):
        return f"a damaged .npz or zip file ({_one_line(exc)}); write it again"
    return f"a file ended early (truncated?): {_one_line(exc) or type(exc).__name__}"


def describe(exc: BaseException) -> tuple[int, str]:
    """The exit code and the one-line message (without the ``forensics: error:`` prefix) for ``exc``."""
    if isinstance(exc, UsageError):
        return EXIT_USAGE, str(exc)
    if isinstance(exc, InputError):
        return EXIT_BAD_INPUT, str(exc)
    if isinstance(exc, Terminated):  # SIGTERM, handled as Ctrl-C: 128 + the signal's number (143)
        return exc.exit_code, str(exc)
    if isinstance(exc, KeyboardInterrupt):
        return EXIT_INTERRUPTED, "interrupted"
    if isinstance(exc, OSError):
        return EXIT_BAD_INPUT, _os_error(exc)
    if isinstance(exc, (UnicodeError, csv.Error, zipfile.BadZipFile, EOFError, json.JSONDecodeError)):
        return EXIT_BAD_INPUT, _data_error(exc)
    if isinstance(exc, MemoryError):
        return EXIT_FAILURE, ("out of memory: this request needs more memory than is free; ask for less (fewer or "
                              "smaller images, a smaller region, fewer --workers) or run it on a larger machine")
    return EXIT_FAILURE, (f"internal error: {type(exc).__name__}: {_one_line(exc)} (rerun with {DEBUG_ENV}=1 "
                          "for the traceback; please report it)")
