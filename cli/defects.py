"""``forensics defects``: detect stuck and partially stuck pixels; estimate how fast they grow."""
from __future__ import annotations

import argparse

from forensics.cli.common import (
    add_execution_options,
    add_input_options,
    add_output_options,
    command_parser,
    emit,
    executor_for,
    info,
    nonnegative_float,
    odd_int,
    open_input,
    positive_float,
    progress_for,
    warn,
)


def add_detection_options(parser: argparse.ArgumentParser) -> None:
    """--mask, --q, --sigma | --tau, --stuck-tolerance (shared with ``forensics date``)."""
    group = parser.add_argument_group("detection")
    group.add_argument("--mask", default="centre",
                       help="region analysed: centre[:FRACTION] leaves out the centre where the subject usually is "
                            "(default centre = centre:0.5), auto leaves out textured pixels, all, or a mask image "
                            "(non-zero = analysed)")
    group.add_argument("--q", type=odd_int, default=9,
                       help="median kernel size, odd (default 9); the memory it needs is estimated before the images "
                            "are read and refused above FORENSICS_MEMORY_LIMIT")
    thr = group.add_mutually_exclusive_group()
    thr.add_argument("--sigma", type=positive_float, default=None,
                     help="threshold τ = median + SIGMA·1.4826·MAD of d̂ (default 5)")
    thr.add_argument("--tau", type=positive_float, default=None, help="threshold τ on d̂ in DN, instead of --sigma")
    group.add_argument("--stuck-tolerance", type=nonnegative_float, default=0.0,
                       help="largest max − min (DN) still 'the same value in every image' (default 0; raise for "
                            "compressed or noisy data)")


def detection_kwargs(args: argparse.Namespace) -> dict:
    from forensics.defects.detection import DEFAULT_SIGMA, parse_mask

    sigma = None if args.tau is not None else (DEFAULT_SIGMA if args.sigma is None else args.sigma)
    return {"q": args.q, "sigma": sigma, "tau": args.tau, "mask": parse_mask(args.mask),
            "stuck_tolerance": args.stuck_tolerance}


def register(sub) -> None:
    parser = sub.add_parser("defects", help="detect pixel defects in image sets and estimate their growth rate",
                            description="Pixel defects from ordinary images (reference paper, section 3.2).")
    inner = parser.add_subparsers(dest="defects_command", metavar="WHAT")

    det = command_parser(
        inner, "detect", "find stuck and partially stuck pixels in a set of images of one device",
        "forensics defects detect aged/year_008 --mask centre:0.5 --q 9 --sigma 5 --report detect_report",
        "One streaming pass gives the mean, minimum, maximum and variance of every pixel over the K images. "
        "Stuck: the same value in every image (eq. 11). Partially stuck: d̂ = mean − median_q(mean) > τ (eq. 15), "
        "τ from a robust normal fit of d̂ (median, 1.4826·MAD) or given. Raw mosaics are analysed per CFA "
        "channel. Use at least 10 images, better 50 or more.")
    det.add_argument("set", help="dataset folder (images of one device, one size; manifest.csv optional)")
    add_detection_options(det)
    add_input_options(det)
    add_execution_options(det)
    add_output_options(det)
    det.set_defaults(handler=run_detect, inputs=("set", "--mask"), outputs=("--report",))

    gro = command_parser(
        inner, "growth", "estimate defect growth rates from sets of one device taken at different dates",
        "forensics defects growth aged/year_000 aged/year_008 aged/year_016 -o model.json --report growth_report",
        "Each set is one epoch, dated by the median 'captured' of its manifest (or EXIF). Reports the paper's "
        "γ, λ (eq. 16–19), Chapman's capture–recapture estimate, and rates in defects per megapixel per year "
        "with exact Garwood 95 % intervals; from three epochs a Poisson-regression test of linear growth. "
        "-o saves a growth model for 'forensics date --model'.")
    gro.add_argument("sets", nargs="+", metavar="SET", help="two or more dataset folders, one per epoch")
    gro.add_argument("-o", "--output", metavar="MODEL.json", help="save the growth model (for forensics date --model)")
    add_detection_options(gro)
    add_input_options(gro)
    add_execution_options(gro)
    add_output_options(gro)
    gro.set_defaults(handler=run_growth, inputs=("sets", "--mask"), outputs=("--output", "--report"))
    parser.set_defaults(handler=lambda args: parser.print_help() or 2)


def run_detect(args: argparse.Namespace) -> int:
    from forensics.defects.detection import detect_dataset
    from forensics.report.defects import detection_report
    from forensics.sensor.catalogue import PARTIAL, STUCK

    ds = open_input(args, args.set)
    if args.report:
        from forensics._shared.atomic import refuse_existing

        refuse_existing(args.report, args.force)
    with executor_for(args) as ex:
        result = detect_dataset(ds, progress=progress_for(args), executor=ex, **detection_kwargs(args))
        execution = ex.info().to_dict()
    for message in result.warnings:
        warn(message)

    def summary() -> str:
        lines = [f"{ds.root}: {result.n_images} images of {result.shape[1]}×{result.shape[0]}; analysed "
                 f"{result.megapixels:.4g} MP ({result.mask_spec.describe()}), q = {result.q}",
                 "threshold: " + ", ".join(f"{f.name} τ = {f.tau:.4g} DN (center {f.center:.4g}, σ {f.scale:.4g})"
                                           for f in result.fits)
                 + (f" = {result.sigma:g}σ" if result.sigma else " (given)"),
                 f"{result.count(PARTIAL)} partially stuck, {result.count(STUCK)} stuck"]
        rows = sorted(result.defect_rows(), key=lambda r: -r["z"])[:20]
        if rows:
            lines.append(f"{'x':>6} {'y':>6} {'kind':>8} {'amplitude':>10} {'z':>8}")
            lines += [f"{r['x']:6d} {r['y']:6d} {r['kind']:>8} {r['amplitude']:10.4g} {r['z']:8.2f}" for r in rows]
            if len(result.x) > 20:
                lines.append(f"… {len(result.x) - 20} more (--json for all)")
        return "\n".join(lines)

    emit(args, summary, lambda: {"set": str(ds.root), **result.to_dict(), "execution": execution})
    if args.report:
        path = detection_report(result, source=str(ds.root)).write(args.report, force=args.force)
        info(args, f"report: {path}")
    return 0


def run_growth(args: argparse.Namespace) -> int:
    from forensics._shared.atomic import refuse_existing
    from forensics._shared.errors import UsageError
    from forensics.defects.growth import epochs_from_datasets, estimate_growth
    from forensics.report.defects import growth_report

    if len(args.sets) < 2:
        raise UsageError("growth needs at least two sets (epochs) of the same device taken at different dates")
    if args.output:
        refuse_existing(args.output, args.force)
    if args.report:
        refuse_existing(args.report, args.force)
    datasets = [open_input(args, p) for p in args.sets]
    with executor_for(args) as ex:
        epochs = epochs_from_datasets(datasets, progress=progress_for(args), executor=ex, **detection_kwargs(args))
        execution = ex.info().to_dict()
    result = estimate_growth(epochs)
    for message in dict.fromkeys(result.warnings):
        warn(message)
    if args.output:
        result.model().save(args.output, force=args.force)

    def summary() -> str:
        th = result.threshold
        lines = [f"{len(result.dates)} epochs ({', '.join(f'{d:.2f}' for d in result.dates)}), analysed "
                 f"{result.area_mp:.4g} MP, threshold " + (f"{th['sigma']:g}σ" if th.get("sigma") else "given")
                 + f" (τ = {', '.join(f'{v:.4g}' for v in th['tau_per_epoch'])} DN), q = {th['q']}",
                 f"{'epoch':>10} {'partial':>8} {'stuck':>6}"]
        lines += [f"{d:10.2f} {p:8d} {s:6d}" for d, p, s in zip(result.dates, result.partial.counts,
                                                               result.stuck.counts)]
        for kg in (result.partial, result.stuck):
            r = kg.rate
            lines.append(f"rate {kg.kind}: {r.rate:.4g} defects/MP/year, 95 % [{r.ci[0]:.4g}, {r.ci[1]:.4g}] "
                         f"({r.count} new over {r.exposure:.4g} MP·years)")
            if kg.trend:
                lines.append(f"  linear growth test: p = {kg.trend.p_value:.3g} "
                             f"({'consistent' if kg.trend.linear else 'rejected'})")
        p = result.paper
        lines.append(f"paper eq. 16–19 (first vs last): n1 = {p.n1}, n2 = {p.n2}, n_match = {p.n_match}, "
                     f"γ = {p.gamma:.3g}, λ_ps = {p.lambda_ps:.4g}, λ_s = {p.lambda_s:.4g}, a_ps = {p.a_ps:.4g}")
        c = result.partial.chapman
        if c:
            lines.append(f"capture–recapture (Chapman): N̂ = {c.n_hat:.1f} partially stuck at the last epoch, "
                         f"95 % [{c.ci[0]:.1f}, {c.ci[1]:.1f}]")
        if args.output:
            lines.append(f"growth model: {args.output}")
        return "\n".join(lines)

    emit(args, summary, lambda: {**result.to_dict(), "model": args.output, "execution": execution})
    if args.report:
        path = growth_report(result, epochs=epochs).write(args.report, force=args.force)
        info(args, f"report: {path}")
    return 0
