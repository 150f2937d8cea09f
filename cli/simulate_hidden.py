"""``forensics simulate hidden``: a lab dataset with one hidden effect (or none), for testing the model check."""
from __future__ import annotations

import argparse

from forensics.cli.common import add_output_options, command_parser, emit, progress_for


def register(inner) -> None:
    parser = command_parser(
        inner, "hidden", "write a dataset with one hidden sensor effect (or none) and its truth.json",
        "forensics simulate hidden nonlinearity data/ --seed 1",
        "Simulate one device (base model: growth, offset, stuck, read noise) with at most one hidden effect and "
        "write what a lab would measure: dark frames and flat fields at two levels with vignetting, 3 exposure "
        "times, 2 ISO values, 2 temperatures, 2 frames per condition at the last of 10 yearly epochs, and a "
        "reference condition at every epoch.  Output: images, manifest.csv (captured, exposure_s, iso, "
        "temperature_c, subject) and truth.json.  Then run 'forensics model check OUT'.")
    parser.add_argument("effect", help="prnu, dark_current, gain, nonlinearity, shot_noise, clusters, "
                                       "accelerating_growth, dsnu, none, module:Class or path/to/file.py:Class")
    parser.add_argument("out", help="output folder (created; refused if it exists unless --force)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the device and the frames' noise (default 0)")
    add_output_options(parser, report=False)
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from forensics.fixtures.hidden import make_hidden

    result = make_hidden(args.effect, args.out, rng=args.seed, force=args.force, progress=progress_for(args))

    def summary() -> str:
        truth = result.truth
        hidden = truth["hidden"] or "nothing"
        params = ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
                           for k, v in (truth["params"] or {}).items())
        counts = truth["defect_counts"]
        return (f"Wrote {result.n_frames} frames to {result.out} with {hidden} hidden"
                + (f" ({params})" if params else "") + "\n"
                f"defects at the last epoch: {counts['partial'][-1]} partially stuck, {counts['stuck'][-1]} stuck\n"
                f"truth: {result.out / 'truth.json'}\n"
                f"next: forensics model check {result.out}")

    emit(args, summary, result.to_dict())
    return 0
