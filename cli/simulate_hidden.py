"""``forensics simulate hidden``: a lab dataset with one hidden effect (or none, or several), for testing the model
check."""
from __future__ import annotations

import argparse

from forensics.cli.common import add_output_options, command_parser, emit, progress_for, seed


def register(inner) -> None:
    parser = command_parser(
        inner, "hidden", "write a dataset with one hidden sensor effect (or none, or several) and its truth.json",
        "forensics simulate hidden nonlinearity data/ --seed 1\n  forensics simulate hidden prnu,dark_current data2/",
        "Simulate one device (base model: growth, offset, stuck, read noise) with a hidden effect (or several: "
        "comma-separated or repeated, e.g. 'prnu,dark_current' or 'prnu dark_current') and "
        "write what a lab would measure: dark frames and flat fields at two levels with vignetting, 3 exposure "
        "times, 2 ISO values, 2 temperatures, 2 frames per condition at the last of 10 yearly epochs, and a "
        "reference condition at every epoch.  Output: images, manifest.csv (captured, exposure_s, iso, "
        "temperature_c, subject) and truth.json.  Then run 'forensics model check OUT'.")
    parser.add_argument("effect", nargs="+", metavar="EFFECT",
                        help="prnu, dark_current, gain, nonlinearity, shot_noise, clusters, accelerating_growth, "
                             "dsnu, none, module:Class or path/to/file.py:Class; several: comma-separated or repeated")
    parser.add_argument("out", help="output folder (created; refused if it exists unless --force)")
    parser.add_argument("--seed", type=seed, default=0, help="seed of the device and the frames' noise (default 0)")
    from forensics.fixtures.hidden import CONVENTIONS

    parser.add_argument("--convention", default="project", choices=list(CONVENTIONS), metavar="NAME",
                        help="how frames are formed, one of: " + "; ".join(
                            f"{n} ({d.bit_depth}-bit, {d.shape[1]}×{d.shape[0]}, black level {d.black_level:g} DN, "
                            f"light pedestal {d.pedestal:g}, read noise {d.read_noise:g} DN, noise on stuck "
                            f"{'yes' if d.noise_on_stuck else 'no'}, vignetting {d.vignetting:g}, stuck share "
                            f"{d.rates[1] / sum(d.rates):.2g}, ISO gain {d.iso_gain}, {len(d.ages)} epochs)"
                            for n, d in CONVENTIONS.items()) + ". Default project; truth.json records it")
    add_output_options(parser, report=False)
    parser.set_defaults(handler=run, inputs=("effect",), outputs=("out",))


def run(args: argparse.Namespace) -> int:
    from forensics.fixtures.hidden import convention, make_hidden

    specs = [x.strip() for arg in args.effect for x in arg.split(",") if x.strip()]
    spec = specs[0] if len(specs) == 1 else specs
    result = make_hidden(spec, args.out, rng=args.seed, design=convention(args.convention), force=args.force,
                         progress=progress_for(args))

    def summary() -> str:
        truth = result.truth
        hidden = " + ".join(truth["hidden_effects"]) or "nothing"
        params = "; ".join(", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in p.items())
                           for p in truth["hidden_params"].values() if p)
        counts = truth["defect_counts"]
        return (f"Wrote {result.n_frames} frames to {result.out} with {hidden} hidden"
                + (f" ({params})" if params else "") + f", convention {truth['convention']['name']}\n"
                f"defects at the last epoch: {counts['partial'][-1]} partially stuck, {counts['stuck'][-1]} stuck\n"
                f"truth: {result.out / 'truth.json'}\n"
                f"next: forensics model check {result.out}")

    emit(args, summary, result.to_dict())
    return 0
