"""Shared plumbing of the command layer: output options, emitting results, exit codes.

Every command module defines ``register(subparsers)`` which adds its parser and
sets ``handler`` (a function ``handler(args) -> int``).  Handlers parse nothing
themselves beyond ``args``, call the library, and hand a result to
:func:`emit`.  Nothing here does science.
"""
from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Callable, Iterator
from typing import Any

from forensics._shared.jsonsafe import dumps
from forensics._shared.progress import Progress, choose_progress

EXIT_OK = 0
EXIT_USAGE = 2
EXIT_BAD_INPUT = 3


def add_output_options(parser: argparse.ArgumentParser, report: bool = True) -> None:
    """Add ``--json``, ``--report DIR``, ``--quiet`` and ``--force`` to ``parser``."""
    group = parser.add_argument_group("output")
    group.add_argument("--json", action="store_true", help="print one JSON object on stdout instead of the summary")
    if report:
        group.add_argument("--report", metavar="DIR", help="write an HTML report with PNG plots into DIR")
    group.add_argument("--quiet", action="store_true", help="no progress bar")
    group.add_argument("--force", action="store_true", help="replace existing outputs")


def add_execution_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--workers N`` and ``--scheduler ADDRESS`` (the execution layer, :mod:`forensics._shared.parallel`)."""
    group = parser.add_argument_group("execution")
    group.add_argument("--workers", type=int, default=None, metavar="N",
                       help="worker processes (default: every core; 1 runs everything in this process)")
    group.add_argument("--scheduler", default=None, metavar="ADDRESS",
                       help="run on a Dask cluster: its scheduler address (tcp://host:8786), or 'local' for a "
                            "cluster on this machine (default: $FORENSICS_SCHEDULER, else local processes)")


def probability(text: str) -> float:
    """argparse type of ``--pfa``: a probability strictly between 0 and 1."""
    import math

    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0 < value < 1:
        raise argparse.ArgumentTypeError(f"--pfa '{text}': give a probability between 0 and 1, e.g. 1e-3")
    return value


def add_input_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--allow-outside`` (manifest rows may name files outside the dataset folder)."""
    parser.add_argument("--allow-outside", action="store_true",
                        help="accept manifest rows naming files outside the dataset folder (absolute paths, '..', "
                             "links leaving it); refused by default")


def open_input(args: argparse.Namespace, folder: Any) -> Any:
    """Open a dataset the way the user asked (``--allow-outside``)."""
    from forensics.io.dataset import open_dataset

    return open_dataset(folder, allow_outside=getattr(args, "allow_outside", False))


@contextlib.contextmanager
def executor_for(args: argparse.Namespace) -> Iterator[Any]:
    """The command's one executor (``--workers``, ``--scheduler``); prints the Dask dashboard when a cluster is used."""
    from forensics._shared.parallel import open_executor

    with open_executor(getattr(args, "workers", None), getattr(args, "scheduler", None)) as executor:
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


def emit(args: argparse.Namespace, summary: str | Callable[[], str], payload: dict[str, Any] | Callable[[], dict[str, Any]]) -> None:
    """Print ``payload`` as one JSON object with --json, else the human ``summary``."""
    if getattr(args, "json", False):
        obj = payload() if callable(payload) else payload
        sys.stdout.write(dumps(obj, indent=2))
        sys.stdout.write("\n")
    else:
        text = summary() if callable(summary) else summary
        sys.stdout.write(text.rstrip("\n") + "\n")


def info(args: argparse.Namespace, message: str) -> None:
    """A note for the user on stderr (suppressed by --quiet)."""
    if not getattr(args, "quiet", False):
        print(message, file=sys.stderr)


def warn(message: str) -> None:
    """A warning on stderr, always shown."""
    print(f"warning: {message}", file=sys.stderr)
