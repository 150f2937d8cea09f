"""The ``forensics`` console command: one parser, one subcommand per module of ``cli``."""
from __future__ import annotations

import argparse
import importlib
import sys
import warnings

from forensics import __version__
from forensics._shared.errors import InputError, UsageError
from forensics._shared.lifetime import Terminated, sigterm_as_interrupt

from forensics.cli.common import EXIT_BAD_INPUT, EXIT_USAGE

# Each module defines register(subparsers); order is the order in --help.
COMMAND_MODULES = ["demo", "simulate", "info", "fingerprint", "same_device", "identify", "cluster", "defects", "date", "validate", "model", "impact"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="forensics",
        description="What an image sensor leaves in its images: PRNU fingerprints, pixel defects, "
        "sensor ageing, dating, and checking a physical sensor model against measurements.",
        epilog="example:\n  forensics demo --out report\n\nRun 'forensics COMMAND --help' for each command.",
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


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "handler", None):
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    warnings.simplefilter("default")
    try:
        with sigterm_as_interrupt():  # SIGTERM (timeout, systemd, schedulers) cleans up as Ctrl-C does
            return int(args.handler(args) or 0)
    except InputError as exc:
        print(f"forensics: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except UsageError as exc:
        print(f"forensics: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt as exc:  # Ctrl-C: 130; SIGTERM (Terminated, a KeyboardInterrupt): 143
        print(f"forensics: {exc if isinstance(exc, Terminated) else 'interrupted'}", file=sys.stderr)
        return exc.exit_code if isinstance(exc, Terminated) else 130


if __name__ == "__main__":
    sys.exit(main())
