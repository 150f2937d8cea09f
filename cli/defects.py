"""``forensics defects``: detect stuck and partially stuck pixels; estimate how fast they grow."""
from __future__ import annotations

import argparse
from typing import Any

from forensics.cli.common import (
    add_execution_options,
    add_input_options,
    add_output_options,
    command_parser,
    emit,
    executor_for,
    finite_float,
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
    group.add_argument("--mask", default=None,
                       help="region analysed: centre[:FRACTION] leaves out the centre where the subject usually is "
                            "(default centre = centre:0.5; for a dark series all), auto leaves out textured pixels, "
                            "all, or a mask image (non-zero = analysed)")
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


def add_dark_options(parser: argparse.ArgumentParser, save_law: bool = False) -> None:
    """Options of a dark-frame series (biases and darks at several exposures; shared with ``forensics date``)."""
    group = parser.add_argument_group(
        "dark-frame series (FITS biases and darks, or a manifest with subject 'dark': used automatically)")
    group.add_argument("--rate-threshold", type=positive_float, default=None, metavar="ADU/s",
                       help="hot pixel: dark rate above this many ADU/s at --t-ref (default: 5 robust σ above the "
                            "median, a threshold of this series only)")
    group.add_argument("--t-ref", type=finite_float, default=None, metavar="°C",
                       help="reference temperature of the rates and the threshold (default: the coldest set point; "
                            "one temperature: the series' own)")
    law = group.add_mutually_exclusive_group()
    law.add_argument("--law", metavar="LAW.json", default=None,
                     help="temperature law saved by 'defects detect --save-law' (default: fitted on the series when "
                          "it spans two temperatures)")
    law.add_argument("--doubling", type=positive_float, default=None, metavar="°C",
                     help="one doubling temperature T_d for every pixel instead of a fitted law")
    group.add_argument("--gain", type=positive_float, default=None, metavar="e-/ADU",
                       help="conversion gain of the noise model (default: from flat pairs in the set, else EGAIN)")
    if save_law:
        group.add_argument("--save-law", metavar="LAW.json", default=None,
                           help="write the temperature law fitted on this series (for series at one temperature)")


def dark_settings(args: argparse.Namespace) -> Any:
    """The :class:`~forensics.defects.darkdetect.DarkSettings` the options ask for."""
    from forensics.defects.darkdetect import DarkSettings
    from forensics.defects.darklaw import TemperatureLaw
    from forensics.defects.detection import MaskSpec, parse_mask

    law = TemperatureLaw.load(args.law) if args.law else (
        TemperatureLaw.constant(args.doubling) if args.doubling is not None else None)
    return DarkSettings(threshold=args.rate_threshold, t_ref=args.t_ref, law=law, gain=args.gain,
                        sigma=args.sigma if args.sigma is not None else 5.0,
                        mask=parse_mask(args.mask) if args.mask else MaskSpec("all"))


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
    add_dark_options(det, save_law=True)
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
    add_dark_options(gro)
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
    from forensics.defects.darkdetect import is_dark_series

    if is_dark_series(ds):
        return run_dark_detect(args, ds)
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
    from forensics.defects.darkdetect import dark_epochs, is_dark_series

    with executor_for(args) as ex:
        if all(is_dark_series(ds) for ds in datasets):
            epochs = dark_epochs(datasets, dark_settings(args), progress=progress_for(args), executor=ex)
        else:
            epochs = epochs_from_datasets(datasets, progress=progress_for(args), executor=ex,
                                          **detection_kwargs(args))
        execution = ex.info().to_dict()
    result = estimate_growth(epochs)
    for message in dict.fromkeys(result.warnings):
        warn(message)
    if args.output:
        result.model().save(args.output, force=args.force)

    def summary() -> str:
        th = result.threshold
        unit = th.get("units", "DN")
        lines = [f"{len(result.dates)} epochs ({', '.join(f'{d:.2f}' for d in result.dates)}), analysed "
                 f"{result.area_mp:.4g} MP, threshold " + (f"{th['sigma']:g}σ" if th.get("sigma") else "given")
                 + f" (τ = {', '.join(f'{v:.4g}' for v in th['tau_per_epoch'])} {unit}"
                 + (f" at {th['t_ref_c']:+.1f} °C" if th.get("t_ref_c") is not None else "") + f"), q = {th['q']}",
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


def run_dark_detect(args: argparse.Namespace, ds: Any) -> int:
    """``defects detect`` on a dark-frame series: every pixel's dark rate, the temperature law, hot pixels."""
    from forensics._shared.atomic import refuse_existing
    from forensics.defects.darkdetect import detect_dark_dataset
    from forensics.report.darkseries import dark_report

    if args.save_law:
        refuse_existing(args.save_law, args.force)
    with executor_for(args) as ex:
        result = detect_dark_dataset(ds, dark_settings(args), progress=progress_for(args), executor=ex)
        execution = ex.info().to_dict()
    for message in result.warnings:
        warn(message)
    if args.save_law:
        if result.law is None:
            warn("no temperature law to save: the series has one temperature and none was given")
        else:
            result.law.save(args.save_law, force=args.force)
            info(args, f"temperature law: {args.save_law}")
    emit(args, lambda: dark_summary(ds.root, result), lambda: {"set": str(ds.root), **result.to_dict(),
                                                               "execution": execution})
    if args.report:
        path = dark_report(result, source=str(ds.root)).write(args.report, force=args.force)
        info(args, f"report: {path}")
    return 0


def dark_summary(root: Any, result: Any) -> str:
    """The human summary of a dark-series detection (text only)."""
    from forensics.sensor.catalogue import PARTIAL, STUCK

    fit = result.series
    lines = [f"{root}: dark series of {fit.n_frames} frames, {fit.shape[1]}×{fit.shape[0]}, in "
             f"{len(fit.groups)} temperature group(s)"]
    lines.append(f"{'group':<22} {'T (°C)':>14} {'frames':>6} {'bias (ADU)':>11} {'read noise':>10} "
                 f"{'median rate (ADU/s) [95 %]':>30} {'cosmic rays':>11} {'misfits':>7}")
    for g in fit.groups:
        lo, hi = g.median_rate_ci()
        temp = "?" if g.temperature_c is None else f"{g.temperature_c:+.2f} ± {g.temperature_se:.2f}"
        lines.append(f"{g.label:<22} {temp:>14} {len(g.frames):>6} {g.bias_level:>11.1f} {g.read_noise:>10.2f} "
                     f"{g.median_rate:>12.4g} [{lo:.4g}, {hi:.4g}] {g.outliers:>11} {int(g.misfit.sum()):>7}")
    for row in result.at_set_points:
        lines.append(f"  median rate at the set point {row['set_temperature_c']:+.1f} °C: "
                     f"{row['median_rate_adu_per_s']:.4g} [{row['ci'][0]:.4g}, {row['ci'][1]:.4g}] ADU/s")
    gains = [f"used {fit.gain_used:.3g} ({fit.gain_source})"]
    for key, label in (("flat_pairs", "flat pairs"), ("dark_shot_noise", "dark shot noise")):
        if key in fit.gain:
            est = fit.gain[key]
            gains.append(f"{label} {est['gain_e_per_adu']:.3g} [{est['ci'][0]:.3g}, {est['ci'][1]:.3g}]")
    if fit.gain.get("header_e_per_adu"):
        gains.append(f"header EGAIN {fit.gain['header_e_per_adu']:.3g}")
    lines.append("conversion gain (e⁻/ADU): " + "; ".join(gains))
    if result.law is not None:
        b = result.law.bulk
        lo, hi = b.doubling_ci()
        lines.append(f"temperature law ({result.law_source}): bulk T_d = {b.doubling:.2f} °C "
                     f"[{lo:.2f}, {'∞' if hi is None else f'{hi:.2f}'}]")
        for c in result.law.classes:
            lo, hi = c.doubling_ci()
            lines.append(f"  pixels near {c.rate:.3g} ADU/s ({c.n}): T_d = {c.doubling:.2f} °C "
                         f"[{lo:.2f}, {'∞' if hi is None else f'{hi:.2f}'}]")
    for f in fit.named_frames():
        lines.append(f"frame {f.name}: {f.reason or '; '.join(f.problems)}")
    t_ref = "?" if result.t_ref is None else f"{result.t_ref:+.2f} °C"
    lo, hi = result.count_ci
    text = (f"hot pixels: {result.count(PARTIAL)} with a dark rate above {result.threshold_rate:.4g} ADU/s at {t_ref} "
            f"(Poisson 95 % [{lo:.0f}, {hi:.0f}]")
    if result.count_law_range:
        text += f"; {result.count_law_range[0]}–{result.count_law_range[1]} over the law's interval"
    lines.append(text + f"), {result.count(STUCK)} stuck; analysed {result.megapixels:.4g} MP")
    return "\n".join(lines)
