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
                 f" ({'manifest.csv' if s.has_manifest else 'no manifest; metadata from EXIF or FITS headers'})",
                 f"devices: {', '.join(str(d) for d in s.devices)}"]
        if s.captured:
            lines.append(f"captured: {s.captured[0]:.3f} … {s.captured[1]:.3f} (decimal years)")
        for e in s.epochs:
            lines.append(f"  epoch {e['start']:.3f}–{e['end']:.3f}: {e['n']} images")
        if len(s.conditions) > 1 or any(v is not None for k, v in s.conditions[0].items() if k != "n"):
            lines.append(f"{len(s.conditions)} acquisition conditions (exposure, ISO, temperature, subject)")
        if s.frame_types:
            lines.append(f"{'frame type':>10} {'exposure (s)':>12} {'set point (°C)':>14} {'frames':>6} "
                         f"{'measured (°C)':>16}")
        for row in s.frame_types:
            temps = row["temperature_c"]
            measured = "?" if temps is None else f"{temps[0]:+.2f} … {temps[1]:+.2f}"
            setpoint = ("?" if row["set_temperature_c"] is None and row["measured_c"] is None
                        else f"{row['set_temperature_c']:+.1f}" if row["measured_c"] is None
                        else f"measured {row['measured_c']:+.1f}")
            exposure = "?" if row["exposure_s"] is None else f"{row['exposure_s']:g}"
            lines.append(f"{row['frame_type']:>10} {exposure:>12} {setpoint:>14} {row['n']:>6} {measured:>16}")
            if row["off_set_point"]:
                lines.append(f"  more than 1 °C off the set point: {', '.join(row['off_set_point'])}")
        lines += [f"unreadable: {why}; replace or remove it" for why in s.unreadable]
        return "\n".join(lines)

    emit(args, lambda: printable(text()), summary.to_dict())
    return 0
