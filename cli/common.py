"""Shared plumbing of the command layer: output options, option types, the input/output guard, emitting
results, exit codes.

Every command module defines ``register(subparsers)`` which adds its parser and sets ``handler`` (a function
``handler(args) -> int``) and declares which of its arguments name inputs and which outputs::

    parser.set_defaults(handler=run, inputs=("set", "--db"), outputs=("--report",))

:func:`~forensics.cli.main.main` applies :func:`guard_outputs` to that declaration once, before any handler
runs.  Handlers parse nothing themselves beyond ``args``, call the library, and hand a result to :func:`emit`.
Option values are checked where argparse parses them (the ``type=`` functions below: exit 2).  Everything
printed for a human passes :func:`~forensics._shared.text.printable` here, in :func:`say`.  Nothing here does
science.
"""
from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
from collections.abc import Callable, Iterator
from typing import Any, TextIO

from forensics._shared.jsonsafe import dumps
from forensics._shared.progress import Progress, choose_progress
from forensics._shared.text import printable

EXIT_OK = 0
#: Unexpected failures (a bug: "internal error"), out of memory, and `validate` missing an acceptance figure.
EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_BAD_INPUT = 3
EXIT_INTERRUPTED = 130


def add_output_options(parser: argparse.ArgumentParser, report: bool = True) -> None:
    """Add ``--json``, ``--report DIR``, ``--quiet`` and ``--force`` to ``parser``."""
    group = parser.add_argument_group("output")
    group.add_argument("--json", action="store_true", help="print one JSON object on stdout instead of the summary")
    if report:
        group.add_argument("--report", metavar="DIR", help="write an HTML report with PNG plots into DIR")
    group.add_argument("--quiet", action="store_true", help="no progress bar")
    group.add_argument("--force", action="store_true", help="replace existing outputs")


def add_execution_options(parser: argparse.ArgumentParser, default: str = "every core") -> None:
    """Add ``--workers N`` and ``--scheduler ADDRESS`` (the execution layer, :mod:`forensics._shared.parallel`);
    ``default`` says what the command does without ``--workers``."""
    group = parser.add_argument_group("execution")
    group.add_argument("--workers", type=positive_int, default=None, metavar="N",
                       help=f"worker processes (default: {default}; 1 runs everything in this process)")
    group.add_argument("--scheduler", default=None, metavar="ADDRESS",
                       help="run on a Dask cluster: its scheduler address (tcp://host:8786), or 'local' for a "
                            "cluster on this machine (default: $FORENSICS_SCHEDULER, else local processes)")


# ----------------------------------------------------------------------------- option types (exit 2)
def _number(text: str, kind: type = float) -> float:
    """``text`` as a finite number of ``kind`` (int accepts ``1e3``-style only when whole), else ArgumentTypeError."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"'{text}' is not a finite number")
    if kind is int:
        if not value.is_integer():
            raise argparse.ArgumentTypeError(f"'{text}' is not a whole number")
        return int(value)
    return value


def finite_float(text: str) -> float:
    """argparse type: any finite number (NaN and ±inf refused)."""
    return _number(text)


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0 (a threshold, a noise level, a scale)."""
    value = _number(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"'{text}': give a number greater than 0")
    return value


def nonnegative_float(text: str) -> float:
    """argparse type: a finite number ≥ 0 (a tolerance, a noise level that may be zero)."""
    value = _number(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"'{text}': give a number ≥ 0")
    return value


def positive_int(text: str) -> int:
    """argparse type: a whole number ≥ 1 (a count)."""
    value = _number(text, int)
    if value < 1:
        raise argparse.ArgumentTypeError(f"'{text}': give a whole number ≥ 1")
    return value


def seed(text: str) -> int:
    """argparse type of ``--seed``: a whole number ≥ 0 (what :class:`numpy.random.SeedSequence` takes)."""
    value = _number(text, int)
    if value < 0:
        raise argparse.ArgumentTypeError(f"'{text}': a seed is a whole number ≥ 0")
    return value


def odd_int(text: str) -> int:
    """argparse type of a median kernel size: an odd whole number ≥ 1."""
    value = _number(text, int)
    if value < 1 or value % 2 == 0:
        raise argparse.ArgumentTypeError(f"'{text}': give an odd whole number ≥ 1 (e.g. 9)")
    return value


def probability(text: str) -> float:
    """argparse type of ``--pfa``: a probability strictly between 0 and 1."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0 < value < 1:
        raise argparse.ArgumentTypeError(f"--pfa '{text}': give a probability between 0 and 1, e.g. 1e-3")
    return value


#: Smallest side of an image the commands write (the defect and PRNU statistics need a few blocks of 8).
MIN_SIDE = 8


def frame_size(text: str) -> tuple[int, int]:
    """argparse type of ``--size WIDTHxHEIGHT``: ``(height, width)``, both whole numbers ≥ :data:`MIN_SIDE`.

    The memory such a frame needs is checked by the library before anything is drawn.
    """
    parts = text.lower().split("x")
    try:
        w, h = (int(v) for v in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}': give WIDTHxHEIGHT in pixels, e.g. 640x480") from None
    if w < MIN_SIDE or h < MIN_SIDE:
        raise argparse.ArgumentTypeError(f"'{text}': width and height must be at least {MIN_SIDE} pixels")
    return h, w


def years(text: str) -> list[float]:
    """argparse type of ``--years``: :func:`forensics.sensor.simulate.parse_years` (finite, ≥ 0, distinct, at
    most ``FORENSICS_MAX_AGES`` ages)."""
    from forensics._shared.errors import UsageError
    from forensics.sensor.simulate import parse_years

    try:
        return parse_years(text)
    except UsageError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--years ")) from None


def add_input_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--allow-outside`` (manifest rows may name files outside the dataset folder)."""
    parser.add_argument("--allow-outside", action="store_true",
                        help="accept manifest rows naming files outside the dataset folder (absolute paths, '..', "
                             "links leaving it); refused by default")


def add_dark_options(parser: argparse.ArgumentParser, second: bool = False) -> None:
    """Add ``--dark DARKSET`` and ``--dark-doubling T_D`` (and ``--dark-b`` for a second set's own darks)."""
    group = parser.add_argument_group("dark calibration (raw CCD frames)")
    group.add_argument("--dark", metavar="DARKSET",
                       help="folder of bias and dark frames (FITS EXPTIME/IMAGETYP or a manifest's exposure_s and "
                            "frame_type) of this camera: every frame is calibrated as frame - offset - "
                            "rate*exposure before its residual, so the fingerprint holds PRNU, not the dark pattern"
                            + (" (both sets, unless --dark-b gives SET_B its own)" if second else ""))
    if second:
        group.add_argument("--dark-b", metavar="DARKSET", help="SET_B's own bias and dark frames (another camera)")
    group.add_argument("--dark-scale", choices=["exposure", "fit"], default="exposure",
                       help="scale the dark pattern to each frame by its exposure (default; a frame that shows no dark "
                            "pattern, dark-subtracted already, is refused) or by the share of it the frame shows "
                            "('fit': also right for frames the capture software reduced)")
    group.add_argument("--dark-doubling", type=positive_float, metavar="T_D", default=None,
                       help="doubling temperature of the dark current (°C) to scale darks taken at another "
                            "temperature than the frames (default: refuse such frames)")


def dark_for(args: argparse.Namespace, folder: Any, executor: Any) -> Any:
    """The dark calibration of ``folder`` (None for None), fitted on ``executor`` (streamed)."""
    if folder is None:
        return None
    from forensics.prnu.calibration import dark_calibration

    darks = folder if hasattr(folder, "frames") else open_input(args, folder)
    folder = getattr(darks, "root", folder)
    info(args, f"dark calibration from {folder} …")
    cal = dark_calibration(darks, doubling_c=args.dark_doubling, scale=args.dark_scale, executor=executor,
                           progress=progress_for(args))
    for message in cal.warnings:
        warn(f"dark set {folder}: {message}")
    return cal


def open_input(args: argparse.Namespace, folder: Any) -> Any:
    """Open a dataset the way the user asked (``--allow-outside``)."""
    from forensics.io.dataset import open_dataset

    return open_dataset(folder, allow_outside=getattr(args, "allow_outside", False))


@contextlib.contextmanager
def executor_for(args: argparse.Namespace, small: bool = False) -> Iterator[Any]:
    """The command's one executor (``--workers``, ``--scheduler``; ``small``: without ``--workers``, this process —
    see :func:`~forensics._shared.parallel.open_executor`); prints the Dask dashboard when a cluster is used."""
    from forensics._shared.parallel import open_executor

    with open_executor(getattr(args, "workers", None), getattr(args, "scheduler", None), small=small) as executor:
        if executor.backend == "dask":
            run = executor.info()
            info(args, f"Dask cluster {run.scheduler} ({run.workers} workers); dashboard: {run.dashboard}")
        yield executor


def command_parser(subparsers: Any, name: str, help: str, example: str, description: str | None = None) -> argparse.ArgumentParser:
    """Create a subcommand parser whose ``--help`` ends with an example."""
    return subparsers.add_parser(
        name,
        help=help,
        description=description or help,
        epilog=f"example:\n  {example}",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )


def progress_for(args: argparse.Namespace) -> Progress:
    """The progress wrapper the user asked for (silent with --quiet, --json or no terminal)."""
    return choose_progress(quiet=getattr(args, "quiet", False) or getattr(args, "json", False))


def say(text: str, stream: TextIO | None = None, end: str = "\n") -> None:
    """Write ``text`` and ``end`` to ``stream`` (default stdout) for a human: the one place where what the
    command prints is made safe — untrusted text (file names, manifest fields) is escaped, so an escape
    sequence in it cannot act on the terminal."""
    stream = sys.stdout if stream is None else stream
    stream.write(printable(text) + end)


def emit(args: argparse.Namespace, summary: str | Callable[[], str], payload: dict[str, Any] | Callable[[], dict[str, Any]]) -> None:
    """Print ``payload`` as one JSON object with --json, else the human ``summary``."""
    if getattr(args, "json", False):
        obj = payload() if callable(payload) else payload
        sys.stdout.write(dumps(obj, indent=2))  # json escapes control characters itself
        sys.stdout.write("\n")
    else:
        text = summary() if callable(summary) else summary
        say(text.rstrip("\n"))


def info(args: argparse.Namespace, message: str) -> None:
    """A note for the user on stderr (suppressed by --quiet)."""
    if not getattr(args, "quiet", False):
        say(message, sys.stderr)


def warn(message: str) -> None:
    """A warning on stderr, always shown."""
    say(f"warning: {message}", sys.stderr)


# ----------------------------------------------------------------------------- inputs and outputs
def _dest(name: str) -> str:
    """The attribute of ``args`` behind an argument as declared (``--report`` → ``report``, ``set`` → ``set``)."""
    return name.lstrip("-").replace("-", "_")


def _values(value: Any) -> Iterator[str]:
    """The path strings of an argument's value (a string or a list of them; None for an absent option)."""
    if value is None:
        return
    if isinstance(value, (list, tuple)):
        for item in value:
            yield from _values(item)
    else:
        yield os.fspath(value) if isinstance(value, os.PathLike) else str(value)


def _input_paths(value: Any) -> Iterator[str]:
    """Every existing path an input argument may name: the value itself, and the parts of a spec such as
    ``A,H*500,sensor.json`` (comma lists) or ``file.py:Class`` (a user's plug-in).  Words that are no path
    (``centre``, ``masek``, a preset letter) are dropped because no such file exists."""
    for text in _values(value):
        candidates = {text}
        for part in text.split(","):
            part = part.strip()
            candidates.add(part)
            head, sep, _ = part.rpartition(":")
            if sep and head.endswith(".py"):
                candidates.add(head)
        yield from (c for c in candidates if c and os.path.lexists(c))


def declared_paths(args: argparse.Namespace) -> tuple[list[str], list[tuple[str, str]]]:
    """The command's input paths, and its outputs as ``(argument, path)``, from its parser's declaration."""
    inputs = [p for name in getattr(args, "inputs", ()) for p in _input_paths(getattr(args, _dest(name), None))]
    outputs = [(name, p) for name in getattr(args, "outputs", ()) for p in _values(getattr(args, _dest(name), None))]
    return inputs, outputs


def guard_outputs(args: argparse.Namespace) -> None:
    """Refuse any output that is, contains or lies inside an input (:func:`~forensics._shared.atomic.refuse_inputs`),
    with or without --force, before any work is done and before anything is replaced or deleted.

    Raises
    ------
    UsageError
        Naming the output argument, the output and the input it would overwrite.
    """
    from forensics._shared.atomic import refuse_inputs
    from forensics._shared.errors import UsageError

    inputs, outputs = declared_paths(args)
    for name, path in outputs:
        try:
            refuse_inputs(path, inputs)
        except UsageError as exc:
            raise UsageError(f"{name} {exc}" if name.startswith("-") else str(exc)) from None
