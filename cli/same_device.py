"""``forensics same-device``: were two image sets taken with one device?  The paper's protocol."""
from __future__ import annotations

import argparse
from pathlib import Path

from textwrap import fill

from forensics.cli.common import (
    add_dark_options,
    add_execution_options,
    add_input_options,
    add_output_options,
    command_parser,
    dark_for,
    emit,
    executor_for,
    info,
    open_input,
    progress_for,
    warn,
)
from forensics.cli.common import seed  # option types: values checked where parsed


def register(sub) -> None:
    parser = command_parser(
        sub, "same-device", "test whether two image sets come from one device (EER with a bootstrap interval)",
        "forensics same-device images_2009/ images_2013/ --seed 1 --report same_device_report",
        fill("The reference paper's protocol (section 4).  From each set, random disjoint images build a PRNU fingerprint "
        "(default 50) and are scored (default 800) by NCC against their own set's fingerprint (matching) and the "
        "other set's (non-matching).  The EER of matching against non-matching scores, with a 95 % bootstrap "
        "interval, decides: an interval containing 50 % means the sets cannot be told apart (consistent with one "
        "device); a low EER means different devices.  Then the fingerprint-ageing table (the paper's table 2): "
        "mean NCC between median-residual fingerprints of 50 images within and across the sets, and their "
        "consistency inter/√(intra·intra), 1 when both sets carry one unchanged pattern.  Smaller sets use "
        "fewer images, with a warning about statistical power.", 100))
    parser.add_argument("set_a", metavar="SET_A", help="first dataset folder (e.g. the older images)")
    parser.add_argument("set_b", metavar="SET_B", help="second dataset folder")
    parser.add_argument("--fingerprint-images", type=int, default=50, metavar="N",
                        help="images per set for its fingerprint (default 50; at most half the set)")
    parser.add_argument("--score-images", type=int, default=800, metavar="N",
                        help="images per set to score (default 800; fewer if the set is smaller)")
    parser.add_argument("--region", default="corners",
                        help="where the fingerprint is taken: 'corners' (default: the paper's four 128×128 corner "
                             "patches; 'corners:N'), 'center:N', or 'full'")
    parser.add_argument("--seed", type=seed, default=0, help="seed of the random selections and bootstraps (default 0)")
    parser.add_argument("--bootstrap", type=int, default=1000, metavar="B",
                        help="bootstrap replicates for the intervals (default 1000)")
    parser.add_argument("--ageing-fingerprints", type=int, default=16, metavar="N",
                        help="fingerprints per set in the ageing table (default 16; 0 skips the table)")
    parser.add_argument("--ageing-images", type=int, default=50, metavar="N",
                        help="images per ageing fingerprint (default 50)")
    parser.add_argument("--ageing-residual", choices=["median", "wavelet"], default="median",
                        help="residual of the ageing fingerprints (default median, as the paper)")
    add_input_options(parser)
    add_dark_options(parser, second=True)
    add_execution_options(parser)
    add_output_options(parser)
    parser.set_defaults(handler=run, inputs=("set_a", "set_b", "--dark", "--dark-b"), outputs=("--report",))


def run(args: argparse.Namespace) -> int:
    from forensics._shared.atomic import refuse_existing
    from forensics.prnu.samedevice import same_device
    from forensics.report.prnu import same_device_report

    if args.report:
        refuse_existing(args.report, args.force)  # before the work, not after
    ds_a, ds_b = open_input(args, args.set_a), open_input(args, args.set_b)
    info(args, f"same-device test: {len(ds_a)} images of {ds_a.root} against {len(ds_b)} of {ds_b.root} …")
    names = (_name(args.set_a), _name(args.set_b))
    if names[0] == names[1]:
        names = (str(args.set_a), str(args.set_b))
    with executor_for(args) as ex:
        dark_a = dark_for(args, args.dark, ex)
        dark_b = dark_for(args, args.dark_b, ex) if args.dark_b else dark_a
        result = same_device(
            ds_a, ds_b, args.seed, dark=None if dark_a is None and dark_b is None else (dark_a, dark_b),
            fingerprint_images=args.fingerprint_images, score_images=args.score_images, region=args.region,
            n_boot=args.bootstrap, ageing=args.ageing_fingerprints > 0,
            ageing_fingerprints=max(args.ageing_fingerprints, 0), ageing_images=args.ageing_images,
            ageing_residual=args.ageing_residual, names=names, progress=progress_for(args), executor=ex,
        )
        execution = ex.info().to_dict()
    for message in result.warnings:
        warn(message)
    if args.report:
        path = same_device_report(result, _command(args)).write(args.report, force=args.force)
        info(args, f"report: {path}")
    payload = result.to_dict()
    payload["parameters"]["seed"] = args.seed
    payload["sets"]["a"]["folder"] = str(ds_a.root)
    payload["sets"]["b"]["folder"] = str(ds_b.root)
    payload["execution"] = execution
    emit(args, lambda: summary(result), payload)
    return 0


def _name(folder: str) -> str:
    path = Path(folder)
    return path.resolve().name or str(path)


def summary(result) -> str:
    """The human summary of a :class:`forensics.prnu.samedevice.SameDeviceResult`."""
    e = result.eer
    lines = [f"Same-device test (NCC on region {result.region}, {e.n_boot} bootstrap replicates)"]
    for s in (result.set_a, result.set_b):
        p = s.plan
        lines.append(f"  {p.name}: {p.n_available} images; fingerprint from {len(p.fingerprint)}, "
                     f"{len(p.score)} scored")
    g_median, i_median = result.median_scores
    lines.append(f"  matching scores (own set's fingerprint):       n = {e.n_genuine:5d}, median NCC {g_median:.4f}")
    lines.append(f"  non-matching scores (other set's fingerprint): n = {e.n_impostor:5d}, median NCC {i_median:.4f}")
    lines.append(f"  EER {100 * e.eer:.2f} %   {100 * e.level:g} % interval [{100 * e.ci[0]:.2f} %, "
                 f"{100 * e.ci[1]:.2f} %]   (AUC {e.auc:.3f})")
    lines.append(f"  verdict: {e.verdict}")
    t = result.ageing
    if t is not None:
        lines.append("")
        lines.append(f"Fingerprint ageing ({t.residual} residual; {t.n_fingerprints[0]} and {t.n_fingerprints[1]} "
                     f"fingerprints of {t.images_per_fingerprint[0]} and {t.images_per_fingerprint[1]} images)")
        width = max(len(s.label) for s in t.statistics)
        lines.append(f"  {'pairs':<{width}}  {'mean':>8}  {f'{100 * t.level:g} % interval':>20}  {'pairs':>5}")
        for s in t.statistics:
            ci = f"[{s.ci[0]:.4f}, {s.ci[1]:.4f}]" if s.ci is not None else "—"
            lines.append(f"  {s.label:<{width}}  {s.mean:>8.4f}  {ci:>20}  {s.n_pairs:>5}")
        lines.append(f"  {t.verdict}")
    return "\n".join(lines)


def _command(args: argparse.Namespace) -> str:
    """The command line that reproduces this run (shown at the top of the report)."""
    return (f"forensics same-device {args.set_a} {args.set_b} --fingerprint-images {args.fingerprint_images} "
            f"--score-images {args.score_images} --region {args.region} --seed {args.seed} "
            f"--bootstrap {args.bootstrap} --ageing-fingerprints {args.ageing_fingerprints} "
            f"--ageing-images {args.ageing_images} --ageing-residual {args.ageing_residual}"
            + "".join(f" {flag} {value}" for flag, value in (("--dark", args.dark), ("--dark-b", args.dark_b),
                                                              ("--dark-doubling", args.dark_doubling)) if value)
            + (f" --dark-scale {args.dark_scale}" if args.dark or args.dark_b else ""))
