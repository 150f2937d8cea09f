"""The ``forensics`` console command: one parser, one subcommand per module of ``cli``.

:func:`main` is the only place that turns what happened into an exit code: the declared outputs are checked
against the declared inputs (:func:`~forensics.cli.common.guard_outputs`) before the handler runs, every
exception becomes one line on stderr (:mod:`forensics.cli.errors`), and everything printed for a human is
escaped (:func:`~forensics.cli.common.say`).
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import sys
import traceback
import warnings
from collections.abc import Iterator

from forensics import __version__
from forensics._shared.lifetime import sigterm_as_interrupt
from forensics.cli.common import EXIT_FAILURE, EXIT_USAGE, guard_outputs, say
from forensics.cli.errors import debug, describe

# Each module defines register(subparsers); order is the order in --help.
COMMAND_MODULES = ["demo", "simulate", "info", "fingerprint", "same_device", "identify", "cluster", "defects", "date", "validate", "model", "impact"]


class Parser(argparse.ArgumentParser):
    """argparse with its messages escaped: an error quotes what was typed (or a script passed on), which may
    hold control characters.  Subparsers inherit the class."""

    def _print_message(self, message: str, file=None) -> None:  # noqa: ANN001 - argparse's signature
        if message:
            say(message, file or sys.stderr, end="")


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="forensics",
        description="What an image sensor leaves in its images: PRNU fingerprints, pixel defects, "
        "sensor ageing, dating, and checking a physical sensor model against measurements.",
        epilog="example:\n  forensics demo --out report\n\nRun 'forensics COMMAND --help' for each command.\n\n"
               "exit status: 0 done, 1 failed (an internal error: please report it; or out of memory),\n"
               "  2 usage error, 3 bad input data or files, 130 interrupted (Ctrl-C), 143 terminated (SIGTERM)\n"
               "environment: FORENSICS_DEBUG=1 shows the traceback of a failure; FORENSICS_MEMORY_LIMIT (e.g. 64G)\n"
               "  and FORENSICS_MAX_AGES (default 1000) bound what one request may ask for",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"forensics {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(f"forensics.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"forensics.cli.{name}":
                continue  # command not built yet
            raise
        module.register(sub)
    return parser


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ANN001
    """Library warnings as one escaped line (the default format adds the source file and line of code)."""
    say(f"warning: {message}", file or sys.stderr)


@contextlib.contextmanager
def _terminal() -> Iterator[None]:
    """Warnings shown once per place as one line (restored afterwards: tests call :func:`main` many times), and
    text the terminal cannot encode (a non-UTF-8 locale) escaped rather than raising."""
    with warnings.catch_warnings():
        warnings.simplefilter("default")
        if not debug():
            warnings.showwarning = _show_warning
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(AttributeError, ValueError):  # not a TextIOWrapper (pytest's capture)
                stream.reconfigure(errors="backslashreplace")
        yield


def _fail(exc: BaseException) -> int:
    """Print the one line for ``exc`` (after its traceback with FORENSICS_DEBUG=1); return the exit code."""
    code, message = describe(exc)
    if debug() and not isinstance(exc, KeyboardInterrupt):
        traceback.print_exception(exc, file=sys.stderr)
    prefix = "forensics: " if isinstance(exc, KeyboardInterrupt) else "forensics: error: "
    say(prefix + message, sys.stderr)
    return code


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "handler", None):
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    with _terminal():
        try:
            guard_outputs(args)  # before any work, and before anything is replaced or deleted
            with sigterm_as_interrupt():  # SIGTERM (timeout, systemd, schedulers) cleans up as Ctrl-C does
                return int(args.handler(args) or 0)
        except BrokenPipeError:
            # The reader went away (``forensics … | head``): nobody is left to read a message.
            with contextlib.suppress(OSError, ValueError):
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return EXIT_FAILURE
        except (Exception, KeyboardInterrupt) as exc:  # noqa: BLE001 - every exception becomes one line
            return _fail(exc)


if __name__ == "__main__":
    sys.exit(main())
