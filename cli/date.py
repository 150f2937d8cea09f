"""``forensics date``: when was a set of images, or one image, taken — from its sensor defects."""
from __future__ import annotations

import argparse
from pathlib import Path

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
from forensics.cli.defects import add_detection_options, detection_kwargs


def register(sub) -> None:
    parser = command_parser(
        sub, "date", "estimate when a set of images or a single image was taken, from sensor defect growth",
        "forensics date query_set/ --reference aged/year_000 aged/year_008 aged/year_016 --report date_report\n"
        "  forensics date photo.png --model model.json --json",
        "QUERY is a folder (a set of images of one device) or one image file. The reference is either image sets "
        "of the same device at known dates (--reference; dated by their manifests) or a growth model saved by "
        "'forensics defects growth -o'. A set is dated from its count of defects (an exact interval carrying "
        "the query count's and the rate's Poisson uncertainty); a single image by which catalogued defects it "
        "shows (maximum likelihood over onset intervals, Fridrich & Goljan).")
    parser.add_argument("query", help="query set folder or single image file")
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--reference", nargs="+", metavar="SET", help="two or more reference sets of the device")
    src.add_argument("--model", metavar="FILE", help="growth model saved by 'forensics defects growth -o FILE'")
    add_detection_options(parser)
    add_input_options(parser)
    add_execution_options(parser)
    add_output_options(parser)
    parser.set_defaults(handler=run, inputs=("query", "--reference", "--model", "--mask"), outputs=("--report",))


def run(args: argparse.Namespace) -> int:
    from forensics._shared.atomic import refuse_existing
    from forensics.defects.dating import date_dataset, date_image
    from forensics._shared.errors import InputError, UsageError
    from forensics.defects.growth import GrowthModel, epochs_from_datasets, estimate_growth
    from forensics.io.images import is_raw, read_image, read_raw
    from forensics.report.defects import dating_report

    query = Path(args.query)
    if not query.exists():
        raise InputError(f"{query}: no such folder or image file")
    if args.report:
        refuse_existing(args.report, args.force)
    progress = progress_for(args)
    if args.model:
        model = GrowthModel.load(args.model)
    elif len(args.reference) < 2:
        raise UsageError("--reference needs at least two sets taken at different dates")
    with executor_for(args) as ex:
        if not args.model:
            epochs = epochs_from_datasets([open_input(args, p) for p in args.reference], progress=progress,
                                          executor=ex, **detection_kwargs(args))
            growth = estimate_growth(epochs)
            for message in dict.fromkeys(growth.warnings):
                warn(message)
            model = growth.model()
        if query.is_dir():
            result = date_dataset(model, open_input(args, query), progress=progress, executor=ex)
        else:
            image = read_image(query)
            cfa = read_raw(query).cfa_pattern if is_raw(query) else None
            result = date_image(model, image, cfa)
        execution = ex.info().to_dict()
    for message in result.warnings:
        warn(message)

    def summary() -> str:
        lo, hi = result.interval
        text = (f"{query}: estimated capture date {result.estimate:.3f}, interval "
                f"[{'…' if lo is None else f'{lo:.3f}'}, {'…' if hi is None else f'{hi:.3f}'}]")
        if hasattr(result, "position"):
            text += f"\n  {result.position}; {result.method}"
        else:
            post = result.posterior
            text += f"\n  most likely onset interval {result.best} of {len(post)} (relative likelihood " \
                    f"{post[result.best]:.2f}); {result.n_defects} catalogued defects in {len(result.groups)} groups"
        return text

    emit(args, summary, lambda: {"query": str(query), **result.to_dict(), "execution": execution})
    if args.report:
        path = dating_report(model, result, str(query)).write(args.report, force=args.force)
        info(args, f"report: {path}")
    return 0
