"""``forensics impact``: does sensor ageing change a recognition system's EER?  (The paper's section 5.)"""
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
    open_input,
    positive_int,
    progress_for,
    seed,
    years,
)


def register(sub) -> None:
    parser = command_parser(
        sub, "impact", "measure what sensor ageing does to a recognition system's EER",
        "forensics impact irises/ --sensors A,B,H --years 0:96:8 --matcher masek --matcher ko --seed 1 "
        "--report impact_report",
        "Age a labelled dataset (manifest column 'subject' = class of each image; left and right eye are two "
        "classes) with virtual sensors, score all genuine and impostor pairs with each matcher at every age, and "
        "report the EER with a class-bootstrap interval, its paired trend against age, and the spread across "
        "sensors.  Protocols: same-age (the paper's: enrolment and probe aged together) and enrol-0 (enrolment "
        "at age 0, probe at age T).  Matchers: built-in 'masek' (1-D Log-Gabor iris code), 'ko' (cumulative "
        "sums) and the paper's 'qsw', 'dct', 'cr' and 'cb', a Python class as module:Class or file.py:Class (encode(image), compare(a, b), "
        "higher_is_similar), or an external program as cmd:COMMAND (see forensics.impact.matchers).")
    parser.add_argument("src", help="dataset folder with a manifest whose 'subject' column names each image's class")
    parser.add_argument("--sensors", default="A,B,C,D,E,F,G,H",
                        help="comma list of presets A–H, a preset with a rate factor (H*100), or sensor.json files "
                             "(default A,B,C,D,E,F,G,H)")
    parser.add_argument("--years", type=years, default="0:96:8",
                        help="ages START:STOP:STEP or a list (default 0:96:8); at most 1,000 unless "
                             "FORENSICS_MAX_AGES allows more")
    parser.add_argument("--matcher", action="append", metavar="NAME",
                        help="matcher (repeatable; built in: masek, ko, qsw, dct, cr, cb; default: masek and ko)")
    parser.add_argument("--segmentation", choices=["caht", "wahet"], default="caht",
                        help="segmentation of the built-in matchers: contrast-adjusted Hough (caht, default) or "
                             "weighted adaptive Hough and ellipsopolar transforms (wahet), the paper's two")
    parser.add_argument("--protocol", choices=["same-age", "enrol-0", "both"], default="both",
                        help="comparison protocol (default both)")
    parser.add_argument("--impostors", type=positive_int, metavar="N",
                        help="score a uniform random sample of N impostor pairs (the same at every age) instead of all")
    parser.add_argument("--boot", type=positive_int, default=1000, help="class-bootstrap replicates (default 1000)")
    parser.add_argument("--seed", type=seed, default=0, help="seed of the sensors' histories and the bootstrap (default 0)")
    parser.add_argument("--checkpoint", metavar="DIR",
                        help="keep finished (sensor, age) results in DIR; a rerun with the same settings resumes")
    add_input_options(parser)
    add_execution_options(parser)
    add_output_options(parser)
    parser.set_defaults(handler=run, inputs=("src", "--sensors", "--matcher"), outputs=("--report", "--checkpoint"))


def run(args: argparse.Namespace) -> int:
    from forensics._shared.errors import UsageError
    from forensics.impact.experiment import PROTOCOLS, parse_sensors, run_impact
    from forensics.impact.matchers import load_matchers
    from forensics.sensor.simulate import check_ageing_request, source_bit_depth

    if args.boot < 100:
        raise UsageError("--boot: use at least 100 replicates for a 95 % interval")
    if args.report and not args.force:
        from forensics._shared.atomic import refuse_existing

        refuse_existing(args.report, False)
    source = open_input(args, args.src)
    shape = source.shape()[:2]
    bits = source_bit_depth(source.frames[0].info().dtype)
    sensors = parse_sensors(args.sensors, shape, bits)
    ages = args.years
    for sensor in sensors:
        check_ageing_request(sensor.model, ages, f"sensor {sensor.name}")
    matchers = load_matchers(args.matcher or ["masek", "ko"], segmentation=args.segmentation)
    protocols = list(PROTOCOLS) if args.protocol == "both" else [args.protocol]
    with executor_for(args) as ex:
        result = run_impact(source, sensors, ages, matchers, rng=args.seed, protocols=protocols, n_boot=args.boot,
                            impostors=args.impostors, checkpoint=args.checkpoint, progress=progress_for(args),
                            executor=ex)
        execution = ex.info().to_dict()
    if args.report:
        from forensics.report.impact import impact_report

        page = impact_report(result).write(args.report, force=args.force)
        info(args, f"report: {page}")
    emit(args, lambda: summary(result), lambda: {**result.to_dict(), "execution": execution})
    return 0


def summary(result) -> str:
    from forensics.impact.experiment import PROTOCOLS

    lines = [f"{result.n_images} images, {result.n_classes} classes: {result.n_genuine:,} genuine and "
             f"{result.n_impostor:,} impostor comparisons per age"
             + (" (impostor pairs sampled)" if result.impostors_sampled else ""),
             f"EER with {100 * result.level:g} % class-bootstrap intervals ({result.n_boot} resamples), "
             f"{len(result.ages)} ages from {result.ages[0]:g} to {result.ages[-1]:g} years"]
    for protocol in result.protocols:
        lines.append("")
        lines.append(f"protocol {protocol}: {PROTOCOLS[protocol]}")
        for matcher in result.matchers:
            for sensor in result.sensors:
                first = result.unit(sensor, result.ages[0], matcher, protocol).eer
                last = result.unit(sensor, result.ages[-1], matcher, protocol).eer
                line = (f"  {matcher:>8} {sensor:>7}: EER {100 * first.estimate:5.2f} % "
                        f"[{100 * first.ci[0]:.2f}, {100 * first.ci[1]:.2f}] → {100 * last.estimate:5.2f} % "
                        f"[{100 * last.ci[0]:.2f}, {100 * last.ci[1]:.2f}]")
                if len(result.ages) > 1:
                    line += "; " + result.trend(sensor, matcher, protocol).describe()
                failed = max(len(u.failed_images) for u in result.trajectory(sensor, matcher, protocol))
                if failed:
                    line += f"; up to {failed} image(s) per age failed segmentation (their comparisons: non-matches)"
                lines.append(line)
    if result.resumed_units:
        lines.append(f"\n{result.resumed_units} results taken from the checkpoint")
    if result.reused_units:
        lines.append(f"{result.reused_units} results reused from a sensor and age with byte-identical aged images")
    if result.copied_pairs:
        share = result.copied_pairs / (result.copied_pairs + result.computed_pairs)
        lines.append(f"{result.copied_pairs:,} comparisons ({share:.0%}) copied from byte-identical templates, "
                     f"{result.computed_pairs:,} computed")
    if result.reused_templates:
        lines.append(f"{result.reused_templates:,} templates reused from the previous age (rubber-sheet band unchanged)")
    if result.reused_steps:
        lines.append(f"{result.reused_steps:,} segmentation steps reused from the previous age (inputs unchanged)")
    lines.append(f"({result.elapsed_s:.1f} s)")
    return "\n".join(lines)
