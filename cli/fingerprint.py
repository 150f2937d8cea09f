"""``forensics fingerprint``: build a PRNU fingerprint from a set of images, match images against it."""
from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from textwrap import fill

from forensics.cli.common import (
    add_execution_options,
    add_input_options,
    add_output_options,
    command_parser,
    emit,
    executor_for,
    info,
    open_input,
    progress_for,
    warn,
)


def register(sub) -> None:
    parser = sub.add_parser("fingerprint", help="build PRNU camera fingerprints and match images against them",
                            description="Build a camera's PRNU fingerprint from a set of images, and score images "
                                        "against it (PCE at zero shift or NCC) with a decision at a threshold.")
    inner = parser.add_subparsers(dest="fingerprint_command", metavar="WHAT")

    build = command_parser(
        inner, "build", "estimate a camera's PRNU fingerprint from a set of images",
        "forensics fingerprint build flats/ -o camera.npz --region center:1024",
        fill("Maximum-likelihood fingerprint K = Σ W·I / Σ I² from the wavelet noise residuals W of every image in SET "
        "(streamed: one image in memory at a time; saturated pixels excluded), then zero-mean and DFT Wiener "
        "filtering.  20–50 bright, flat, unsaturated images (sky, wall, flat field) give the best fingerprint.  "
        "All images must have one size and orientation.  The images are summed in chunks on local worker "
        "processes (or a Dask cluster); the result does not depend on how many.  An interrupted build resumes "
        "from the chunks kept in .FP.partial/ beside the output when run again.", 100))
    build.add_argument("set", metavar="SET", help="dataset folder (images, optional manifest.csv)")
    build.add_argument("-o", "--output", metavar="FP", required=True, help="fingerprint file to write (.npz)")
    build.add_argument("--region", default="full",
                       help="'full' (default), 'center:N' (centred N×N crop), or 'corners' (the paper's four "
                            "128×128 corner patches; 'corners:N' for N×N)")
    build.add_argument("--sigma", type=float, default=3.0,
                       help="noise level of the wavelet denoiser on an 8-bit scale (default 3, the reference's)")
    add_input_options(build)
    add_execution_options(build)
    add_output_options(build, report=False)
    build.set_defaults(handler=run_build)

    match = command_parser(
        inner, "match", "score each image of a set against a fingerprint, with a decision",
        "forensics fingerprint match camera.npz photos/ --metric pce --threshold 60",
        fill("Each image's residual (σ = 2, zero-mean, DFT Wiener) is correlated with I·K over the fingerprint's region. "
        "PCE (default) is looked for at zero shift only, unless --shift-range is given; its false-alarm probability "
        "accounts for the shifts and orientations searched.  A portrait image of a landscape sensor is tried in both "
        "quarter turns.  NCC has no universal threshold (it scales as 1/√pixels): give --threshold to get decisions.", 100))
    match.add_argument("fingerprint", metavar="FP", help="fingerprint file written by 'fingerprint build'")
    match.add_argument("set", metavar="SET", help="dataset folder of the images to score")
    match.add_argument("--metric", choices=["pce", "ncc"], default="pce", help="score (default pce)")
    match.add_argument("--threshold", type=float, default=None,
                       help="decide 'match' when the score reaches it (default: 60 for PCE, none for NCC)")
    match.add_argument("--shift-range", type=_shift_range, default=0, metavar="R",
                       help="PCE only: search shifts up to ±R pixels (default 0: zero shift; 'all': every circular "
                            "shift, which inflates non-matching PCE)")
    match.add_argument("--sigma", type=float, default=2.0, help="query residual noise level, 8-bit scale (default 2)")
    add_input_options(match)
    add_execution_options(match)
    add_output_options(match)
    match.set_defaults(handler=run_match)
    parser.set_defaults(handler=lambda args: parser.print_help() or 2)


def _shift_range(text: str) -> int | None:
    if text.strip().lower() == "all":
        return None
    try:
        value = int(text)
        if value < 0:
            raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(f"--shift-range '{text}': give a whole number ≥ 0 or 'all'") from None
    return value


def run_build(args: argparse.Namespace) -> int:
    from forensics._shared.atomic import refuse_existing
    from forensics._shared.parallel import resumable_checkpoint
    from forensics.prnu.fingerprint import build_fingerprint, parse_region

    region = parse_region(args.region)
    out = Path(args.output)
    refuse_existing(out, args.force)  # before hours of work, not after
    ds = open_input(args, args.set)
    info(args, f"building a fingerprint from {len(ds)} images of {ds.root} ({region.spec}) …")
    # Finished chunks are kept in .FP.partial beside the output until it is written: an interrupted build resumes.
    partial = out.with_name(f".{out.name}.partial")
    with executor_for(args) as ex, resumable_checkpoint(partial, _build_config(ds, region, args.sigma),
                                                        args.force) as checkpoint:
        fp = build_fingerprint(ds.frames, region, args.sigma, progress=progress_for(args), executor=ex,
                               checkpoint=checkpoint)
        fp.save(out, force=args.force)
        execution = ex.info().to_dict()
    excluded = fp.parameters.get("excluded_pixel_fraction", 0.0)
    if fp.n_images < 10:
        warn(f"only {fp.n_images} images: a fingerprint from fewer than about 20 is noisy and matches weakly")

    def summary() -> str:
        h, w = fp.frame_shape
        return "\n".join([
            f"Fingerprint of {fp.n_images} images ({w}×{h}) from {ds.root} → {out}",
            f"  region {fp.region}: K is {fp.shape[1]}×{fp.shape[0]}, σ = {fp.sigma:g} (8-bit scale)",
            f"  K: standard deviation {float(fp.K.std()):.4g}; saturated pixels excluded: {100 * excluded:.2f} %",
            f"  next: forensics fingerprint match {out} IMAGES/",
        ])

    emit(args, summary, lambda: {"output": str(out), **fp.to_dict(), "k_std": float(fp.K.std()),
                                 "execution": execution})
    return 0


def _build_config(ds: Any, region: Any, sigma: float) -> dict[str, Any]:
    """What a build's chunks depend on: every input file (with its size and time) and the settings."""
    from forensics import __version__
    from forensics.prnu.fingerprint import CHUNK_IMAGES

    files = []
    for frame in ds.frames:
        try:
            stat = Path(frame.path).stat()
            files.append([str(frame.path), stat.st_size, stat.st_mtime_ns])
        except OSError:  # reported by the build itself, with the file's name
            files.append([str(frame.path), None, None])
    return {"command": "fingerprint build", "files": files, "region": region.spec, "sigma": sigma,
            "chunk_images": CHUNK_IMAGES, "version": __version__}


def run_match(args: argparse.Namespace) -> int:
    from forensics.prnu.fingerprint import Fingerprint
    from forensics.prnu.match import match_set
    from forensics.report.prnu import match_report

    fp = Fingerprint.load(args.fingerprint)
    ds = open_input(args, args.set)
    if fp.region.startswith("corners") and args.shift_range != 0 and args.metric == "pce":
        warn("a shift search on a 'corners' fingerprint compares unrelated patches; zero shift is the right test")
    info(args, f"scoring {len(ds)} images of {ds.root} against {args.fingerprint} ({args.metric}) …")
    with executor_for(args) as ex:
        result = match_set(fp, ds, args.metric, threshold=args.threshold, shift_range=args.shift_range,
                           sigma=args.sigma, progress=progress_for(args), name=str(args.fingerprint), executor=ex)
        execution = ex.info().to_dict()
    payload = result.to_dict()

    def summary() -> str:
        return _match_table(payload)

    if args.report:
        match_report(result).write(args.report, force=args.force)
        info(args, f"report: {Path(args.report) / 'index.html'}")
    emit(args, summary, {**payload, "execution": execution})
    return 0


def _fmt_p(p: float | None, log10: float | None) -> str:
    if p is None:
        return ""
    if p > 0:
        return f"{p:.2g}"
    return f"1e{log10:.0f}" if log10 is not None and math.isfinite(log10) else "0"


def _match_table(payload: dict[str, Any]) -> str:
    metric = payload["metric"]
    thr = payload["threshold"]
    head = (f"{payload['n_images']} images of {payload['set']} against {payload['fingerprint']} "
            f"(region {payload['region']}, {metric.upper()}"
            + (f" at {payload['shift_search']}" if metric == "pce" else "") + ")")
    width = max([len(r["file"]) for r in payload["scores"]] + [4])
    cols = f"{'file':<{width}}  {metric.upper():>10}"
    if metric == "pce":
        cols += f"  {'p_FA':>8}  {'NCC':>8}"
    cols += f"  {'rot':>3}  decision"
    lines = [head, cols]
    for r in payload["scores"]:
        line = f"{r['file']:<{width}}  {r['score']:>10.4g}"
        if metric == "pce":
            p = r["pce"] or {}
            line += f"  {_fmt_p(p.get('p_fa'), p.get('log10_p_fa')):>8}  {r['ncc']:>8.4f}"
        decision = "—" if r["match"] is None else ("match" if r["match"] else "no match")
        line += f"  {90 * r['rotation']:>3}  {decision}"
        lines.append(line)
    if thr is None:
        lines.append("no decisions: NCC has no universal threshold; give --threshold (or use --metric pce)")
    else:
        lines.append(f"{payload['n_match']} of {payload['n_images']} images reach the threshold {thr:g}")
    return "\n".join(lines)
