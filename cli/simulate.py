"""``forensics simulate``: age image sets, make scene sets, write data with a hidden effect."""
from __future__ import annotations

import argparse

from forensics.cli.common import (add_execution_options, add_input_options, add_output_options, command_parser, emit,
                                  executor_for, finite_float, frame_size, info, open_input, positive_float,
                                  positive_int, progress_for, seed, years)


def register(sub) -> None:
    parser = sub.add_parser("simulate", help="simulate sensor ageing and synthetic data sets",
                            description="Simulate sensor ageing (the paper's AGEDIMAGESEQUENCE) and synthetic data.")
    inner = parser.add_subparsers(dest="simulate_command", metavar="WHAT")

    age = command_parser(inner, "age", "age a folder of images with a virtual sensor",
                         "forensics simulate age scenes/ aged/ --sensor A --years 0:96:8 --seed 1",
                         "Write one dataset per time step (images + manifest.csv with 'captured'), the ground-truth "
                         "defect catalogue defects.csv and sensor.json.  Source images must be 8- or 16-bit and one size.  "
                         "Images are aged in parallel (one task per source image; --workers, --scheduler); the "
                         "output is built in .OUT.partial beside it, and an interrupted run resumes from the images "
                         "already aged when the same command is run again.")
    age.add_argument("src", help="source dataset folder (images captured at T0)")
    age.add_argument("out", help="output folder (created; refused if it exists unless --force)")
    age.add_argument("--sensor", default="A", help="virtual sensor of the paper's table 4: A–H (default A)")
    age.add_argument("--years", type=years, default="0:96:8",
                     help="sample ages START:STOP:STEP or a list (default 0:96:8); at most 1,000 ages (one folder "
                          "each) unless FORENSICS_MAX_AGES allows more")
    age.add_argument("--seed", type=seed, default=0, help="seed of the device's defect history (default 0)")
    age.add_argument("--start", type=finite_float, default=2000.0,
                     help="decimal year of T0 for the manifests (default 2000.0)")
    age.add_argument("--counting", choices=["poisson", "deterministic"], default="poisson",
                     help="Poisson arrival counts (default) or the paper's deterministic (T − T0)·λ")
    age.add_argument("--rate-scale", type=positive_float, default=1.0, help="multiply the preset's rates (default 1)")
    add_input_options(age)
    add_execution_options(age)
    add_output_options(age, report=False)
    age.set_defaults(handler=run_age, inputs=("src",), outputs=("out",))

    scenes = command_parser(inner, "scenes", "write scene images (bundled photographs and textures)",
                            "forensics simulate scenes scenes/ --count 50 --size 640x480 --seed 1")
    scenes.add_argument("out", help="output folder")
    scenes.add_argument("--count", type=positive_int, default=50, help="number of images (default 50)")
    scenes.add_argument("--size", type=frame_size, default="640x480", help="WIDTHxHEIGHT (default 640x480)")
    scenes.add_argument("--bits", type=int, choices=[8, 16], default=8, help="bit depth (default 8)")
    scenes.add_argument("--rgb", action="store_true", help="colour images (default grey)")
    scenes.add_argument("--kind", choices=["mixed", "photo", "texture"], default="mixed", help="scene type")
    scenes.add_argument("--format", choices=["png", "tif"], default="png", help="file format (default png)")
    scenes.add_argument("--seed", type=seed, default=0, help="random seed (default 0)")
    add_output_options(scenes, report=False)
    scenes.set_defaults(handler=run_scenes, inputs=(), outputs=("out",))

    irises = command_parser(inner, "irises", "write a synthetic near-infrared iris set (IITD-like, 8-bit, 320×240)",
                            "forensics simulate irises irises/ --classes 224 --samples 10 --seed 1",
                            "Per class (one eye) a fixed iris texture; per sample a different pupil dilation, rotation, "
                            "position, focus, illumination, eyelid and eyelash occlusion, specular reflection and "
                            "sensor noise.  Writes the images, manifest.csv (subject = class, e.g. 001_L) and truth.csv "
                            "(pupil and limbus circles of every image).")
    irises.add_argument("out", help="output folder")
    irises.add_argument("--classes", type=positive_int, default=224, help="number of classes (eyes; default 224)")
    irises.add_argument("--samples", type=positive_int, default=10, help="images per class (default 10)")
    irises.add_argument("--size", type=frame_size, default="320x240", help="WIDTHxHEIGHT (default 320x240)")
    irises.add_argument("--seed", type=seed, default=0, help="random seed (default 0)")
    add_output_options(irises, report=False)
    irises.set_defaults(handler=run_irises, inputs=(), outputs=("out",))

    import importlib.util

    if importlib.util.find_spec("forensics.cli.simulate_hidden") is not None:  # added by the model-check work
        from . import simulate_hidden

        simulate_hidden.register(inner)
    parser.set_defaults(handler=lambda args: parser.print_help() or 2)


def run_age(args: argparse.Namespace) -> int:
    from pathlib import Path

    from forensics.sensor.presets import preset
    from forensics.sensor.simulate import age_dataset, check_ageing_request, source_bit_depth

    source = open_input(args, args.src)
    ages = args.years
    shape = source.shape()
    bits = source_bit_depth(source.frames[0].info().dtype)
    model = preset(args.sensor, shape[:2], bit_depth=bits, t0=args.start, counting=args.counting,
                   rate_scale=args.rate_scale)
    check_ageing_request(model, ages, f"sensor {args.sensor.upper()} × {args.rate_scale:g} on {shape[1]}×{shape[0]}")
    partial = Path(args.out).with_name(f".{Path(args.out).name}.partial")
    if partial.exists():
        info(args, f"resuming from {partial}")
    with executor_for(args) as executor:
        result = age_dataset(source, args.out, model, ages, args.seed, start_year=args.start,
                             sensor_name=args.sensor.upper(), force=args.force, progress=progress_for(args),
                             executor=executor)
        execution = executor.info().to_dict()

    def summary() -> str:
        lines = [f"Aged {result.n_images} images of {shape[1]}×{shape[0]} ({bits}-bit) with sensor "
                 f"{args.sensor.upper()} over {len(ages)} steps → {result.out}",
                 f"{'age (years)':>12} {'partial':>8} {'stuck':>6}"]
        for a, p, s in zip(ages, result.counts["partial"], result.counts["stuck"]):
            lines.append(f"{a:12g} {p:8d} {s:6d}")
        lines.append(f"ground truth: {result.out / 'defects.csv'}, {result.out / 'sensor.json'}")
        return "\n".join(lines)

    emit(args, summary, {**result.to_dict(), "execution": execution})
    return 0


def run_scenes(args: argparse.Namespace) -> int:
    from forensics.sensor.simulate import make_scenes

    shape = args.size
    size = f"{shape[1]}x{shape[0]}"
    ds = make_scenes(args.out, args.count, shape, args.seed, channels=3 if args.rgb else 1, bit_depth=args.bits,
                     kind=args.kind, force=args.force, progress=progress_for(args), ext=f".{args.format}")
    emit(args, f"Wrote {len(ds)} scene images of {size} ({args.bits}-bit, {'RGB' if args.rgb else 'grey'}) "
               f"to {ds.root}", {"out": str(ds.root), "count": len(ds), "size": size, "bits": args.bits})
    return 0


def run_irises(args: argparse.Namespace) -> int:
    from forensics.impact.irises import simulate_irises

    shape = args.size
    result = simulate_irises(args.out, args.classes, args.samples, args.seed, size=shape, force=args.force,
                             progress=progress_for(args))
    emit(args, f"Wrote {args.classes * args.samples} iris images ({args.classes} classes × {args.samples} samples, "
               f"{shape[1]}x{shape[0]}, 8-bit) to {args.out}", result.to_dict())
    return 0
