"""``forensics validate``: check the defect estimators on simulated devices whose truth is known."""
from __future__ import annotations

import argparse

from forensics.cli.common import (
    add_execution_options,
    add_output_options,
    command_parser,
    emit,
    executor_for,
    frame_size,
    info,
    nonnegative_float,
    positive_int,
    progress_for,
    seed,
)


def register(sub) -> None:
    parser = command_parser(
        sub, "validate", "run the defect estimators on simulated devices with known truth and score them",
        "forensics validate defects --sensor F --trials 400 --seed 1 --report validation",
        "Each trial realises a device from a preset of the paper (16-bit, with read noise; rates scaled so a "
        "small frame collects defects), images it through the sensor model and runs the real pipeline. "
        "'defects': detection recall and precision, bias/RMSE/coverage of the growth-rate interval. 'dating': "
        "coverage of set-dating intervals and single-image dating accuracy. Exit status 1 when an acceptance "
        "figure is missed.")
    parser.add_argument("what", choices=["defects", "dating"], help="which estimators to validate")
    parser.add_argument("--sensor", default="F", help="paper preset A–H (default F)")
    parser.add_argument("--trials", type=positive_int, default=100, help="number of trials (default 100; ≥ 400 for the "
                                                                "acceptance figures)")
    parser.add_argument("--seed", type=seed, default=0, help="random seed (default 0)")
    parser.add_argument("--size", type=frame_size, default="128x128",
                        help="WIDTHxHEIGHT of the simulated frames (default 128x128)")
    parser.add_argument("--images", type=positive_int, default=50, help="images per epoch, K (default 50)")
    parser.add_argument("--bits", type=int, choices=[8, 16], default=16, help="bit depth (default 16)")
    parser.add_argument("--read-noise", type=nonnegative_float, default=40.0, help="read noise σ in DN (default 40)")
    parser.add_argument("--scenes", choices=["smooth", "mixed", "photo", "texture"], default="smooth",
                        help="scene pool: smooth low-texture scenes (default) or the toolkit's scene kinds")
    add_execution_options(parser)
    add_output_options(parser)
    parser.set_defaults(handler=run, inputs=(), outputs=("--report",))


def run(args: argparse.Namespace) -> int:
    from forensics._shared.atomic import refuse_existing
    from forensics._shared.errors import UsageError
    from forensics.sensor.presets import PRESETS
    from forensics.report.validate import validation_report
    from forensics.validate.trials import ValidationSettings, check_request, validate_dating, validate_defects

    if args.sensor.upper() not in PRESETS:
        raise UsageError(f"unknown sensor preset '{args.sensor}'; choose one of {', '.join(PRESETS)}")
    if args.report:
        refuse_existing(args.report, args.force)
    shape = args.size
    settings = ValidationSettings(sensor=args.sensor.upper(), shape=shape, bit_depth=args.bits,
                                  read_noise=args.read_noise, images=args.images, scenes=args.scenes)
    fn = validate_defects if args.what == "defects" else validate_dating
    with executor_for(args) as ex:
        check_request(settings, ex.info().workers)
        result = fn(settings, args.trials, rng=args.seed, progress=progress_for(args), executor=ex)
        execution = ex.info()

    def summary() -> str:
        rows = result.table()
        width = max(len(r[0]) for r in rows)
        lines = [f"validate {args.what}: {result.trials} trials, sensor {settings.sensor} "
                 f"({settings.bit_depth}-bit {shape[1]}×{shape[0]}, rates ×{settings.rate_scale():.4g}), seed {args.seed}"]
        lines += [f"{r[0]:<{width}}  {r[1]:>6}  {r[2]:>9}  {r[3]:>22}  {r[4]:>12}  {r[5]}" for r in rows]
        lines.append("all acceptance figures met" if result.passed else "some acceptance figures NOT met")
        return "\n".join(lines)

    emit(args, summary, lambda: {**result.to_dict(), "execution": execution.to_dict()})
    if args.report:
        path = validation_report(result).write(args.report, force=args.force)
        info(args, f"report: {path}")
    return 0 if result.passed else 1
