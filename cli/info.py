"""``forensics info``: what a dataset folder or an image file holds."""
from __future__ import annotations

import argparse
import os
from pathlib import Path

from forensics._shared.text import printable
from forensics.cli.common import add_input_options, add_output_options, command_parser, emit, open_input


def register(sub) -> None:
    parser = command_parser(sub, "info", "describe a dataset folder or an image file",
                            "forensics info photos/2013/ --json",
                            "Size, dtype, devices, capture dates, epochs and acquisition conditions of a dataset "
                            "(or the header, EXIF and CFA layout of one file).")
    parser.add_argument("path", help="dataset folder or image file")
    add_input_options(parser)
    add_output_options(parser, report=False)
    parser.set_defaults(handler=run, inputs=("path",), outputs=())


def run(args: argparse.Namespace) -> int:
    from forensics.io.describe import summarize_dataset, summarize_file

    path = Path(args.path)
    # File names, EXIF strings and manifest fields are untrusted: escaped before they reach the terminal.
    if os.path.lexists(path) and not path.is_dir():  # a file, or something posing as one: described or refused
        data = summarize_file(path)
        emit(args, lambda: printable("\n".join(f"{k:>12}: {v}" for k, v in data.items() if v not in (None, {}, []))),
             data)
        return 0
    summary = summarize_dataset(open_input(args, path))

    def text() -> str:
        s = summary
        lines = [f"{s.root}: {s.n_images} images, {'×'.join(map(str, s.shape[1::-1]))}"
                 f"{'×' + str(s.shape[2]) if len(s.shape) == 3 else ''} {s.dtype}"
                 f" ({'manifest.csv' if s.has_manifest else 'no manifest; metadata from EXIF'})",
                 f"devices: {', '.join(str(d) for d in s.devices)}"]
        if s.captured:
            lines.append(f"captured: {s.captured[0]:.3f} … {s.captured[1]:.3f} (decimal years)")
        for e in s.epochs:
            lines.append(f"  epoch {e['start']:.3f}–{e['end']:.3f}: {e['n']} images")
        if len(s.conditions) > 1 or any(v is not None for k, v in s.conditions[0].items() if k != "n"):
            lines.append(f"{len(s.conditions)} acquisition conditions (exposure, ISO, temperature, subject)")
        return "\n".join(lines)

    emit(args, lambda: printable(text()), summary.to_dict())
    return 0
