"""``forensics identify``: which camera of a fingerprint database took each image of a set?"""
from __future__ import annotations

import argparse
import math
from pathlib import Path
from textwrap import fill
from typing import Any

from forensics.cli.common import (
    probability,
    add_execution_options,
    add_input_options,
    add_output_options,
    command_parser,
    emit,
    executor_for,
    info,
    open_input,
    progress_for,
)
from forensics.cli.common import positive_float  # option types: values checked where parsed


def register(sub) -> None:
    parser = command_parser(
        sub, "identify", "attribute each image of a set to a device of a fingerprint database (1:N), or 'unknown'",
        "forensics identify photos/ --db cameras.db --top 3 --scales 0.5:1.0 --report identify_report",
        fill("Every image is scored against every fingerprint of the database by PCE (one residual and one spectrum "
             "per image): at zero shift for full frames, over every offset for crops (images smaller than the "
             "frame), over a grid of scales with --scales for resized or digitally zoomed images, and in the "
             "orientations of --rotations.  The PCE's energy is taken over the shifts of the peak's 8×8 block phase "
             "(JPEG blocks make the null variance depend on it).  The best device is attributed when its "
             "false-alarm probability, corrected (weighted Šidák) for the number of fingerprints, positions, scales "
             "and rotations searched, is at most --pfa; 'ambiguous' when several devices reach it; otherwise the "
             "image is 'unknown'.  Same-size images at zero shift and crop/scale searches of other sensor sizes "
             "each get half of the false-alarm budget (both shown).  Content-free images (constant, black or "
             "saturated) are 'excluded'.  For large databases a compressed pre-screen (random projections) narrows "
             "the candidates of full-frame images first (--prescreen).", 100))
    parser.add_argument("set", metavar="SET", help="dataset folder of the images to identify")
    parser.add_argument("--db", required=True, metavar="DB", help="fingerprint database folder ('fingerprint db add')")
    parser.add_argument("--top", type=int, default=3, metavar="K", help="candidates listed per image (default 3)")
    parser.add_argument("--pfa", type=probability, default=1e-3, metavar="P",
                        help="false-alarm probability of an attribution over everything searched (default 0.001)")
    parser.add_argument("--scales", default=None, metavar="LO:HI[:STEP]",
                        help="search scales for resized images: 'LO:HI' (automatic step: at most 0.5 pixel off at "
                             "the image's edges), 'LO:HI:STEP', a list '0.5,0.75', or 'auto' (0.5:1.0); "
                             "default: scale 1 only")
    parser.add_argument("--rotations", choices=["auto", "none", "all"], default="auto",
                        help="orientations tried: 'auto' (as stored if it fits the frame, else both quarter turns), "
                             "'none', 'all' (every quarter turn, 180° included); default auto")
    parser.add_argument("--no-crop-search", dest="crop_search", action="store_false",
                        help="do not search the offset of images smaller than the frame")
    parser.add_argument("--prescreen", choices=["auto", "on", "off"], default="auto",
                        help="compressed pre-screen of full-frame images: 'auto' (on above 50 fingerprints), 'on', "
                             "'off' (default auto)")
    parser.add_argument("--sigma", type=positive_float, default=2.0, help="query residual noise level, 8-bit scale (default 2)")
    add_input_options(parser)
    add_execution_options(parser)
    add_output_options(parser)
    parser.set_defaults(handler=run, inputs=("set", "--db"), outputs=("--report",))



def run(args: argparse.Namespace) -> int:
    from forensics._shared.atomic import refuse_existing
    from forensics._shared.errors import UsageError
    from forensics.prnu.database import FingerprintDatabase
    from forensics.prnu.identify import identify, parse_scales

    if args.report:
        refuse_existing(args.report, args.force)  # before the work, not after
    if args.top < 1:
        raise UsageError(f"--top {args.top}: list at least one candidate")
    scales = None if args.scales is None else ("auto" if args.scales == "auto" else parse_scales(args.scales))
    db = FingerprintDatabase(args.db)
    ds = open_input(args, args.set)
    info(args, f"identifying {len(ds)} images of {ds.root} against {len(db)} fingerprints of {args.db} …")
    with executor_for(args) as ex:
        result = identify(ds, db, top_k=args.top, pfa=args.pfa, rotations=args.rotations, scales=scales,
                          crop_search=args.crop_search, prescreen=None if args.prescreen == "off" else args.prescreen,
                          sigma=args.sigma, executor=ex, progress=progress_for(args))
        execution = ex.info().to_dict()
    result.name = str(ds.root)
    if args.report:
        from forensics.report.identify import identification_report

        path = identification_report(result, _command(args)).write(args.report, force=args.force)
        info(args, f"report: {path}")
    payload = result.to_dict()
    payload["database"] = str(Path(args.db))
    payload["execution"] = execution
    emit(args, lambda: summary(result, str(args.db)), payload)
    return 0


def _fmt_p(p: float, log10: float) -> str:
    if p > 0:
        return f"{p:.2g}"
    return f"1e{log10:.0f}" if math.isfinite(log10) else "0"


def summary(result: Any, db: str) -> str:
    """The human summary of an :class:`forensics.prnu.identify.IdentificationResult`: one row per image."""
    n = len(result.queries)
    head = (f"Identification of {n} images of {result.name} against {len(result.devices)} fingerprints of {db} "
            f"(attributed when p_FA ≤ {result.pfa:g}, corrected for fingerprints × positions × scales × rotations)")
    rows = []
    for q in result.queries:
        best, second = q.best, q.runner_up
        rows.append([
            q.source,
            (" = ".join(q.matches) if q.decision == "ambiguous" else best.device_id) if best else "—",
            f"{best.pce:.1f}" if best else "—",
            _fmt_p(q.p_fa, q.log10_p_fa) if best else "—",
            f"{q.pce_threshold:.1f}" if math.isfinite(q.pce_threshold) else "—",
            q.decision,
            f"{second.device_id} ({second.pce:.1f})" if second else "—",
            best.geometry() if best else (q.note or ""),
        ])
    header = ["file", "best device", "PCE", "p_FA", "needed", "decision", "runner-up (PCE)", "geometry"]
    widths = [max(len(header[i]), *(len(r[i]) for r in rows)) if rows else len(header[i]) for i in range(len(header))]
    right = {2, 3, 4}

    def line(cells: list[str]) -> str:
        return "  ".join(c.rjust(w) if i in right else c.ljust(w) for i, (c, w) in enumerate(zip(cells, widths))).rstrip()

    lines = [head, line(header)] + [line(r) for r in rows]
    counts = result.counts()
    per_device = ", ".join(f"{d} {k}" for d, k in sorted(counts.items())) or "none"
    others = "".join(f", {result.n_decided(d)} {d}" for d in ("ambiguous", "excluded") if result.n_decided(d))
    lines.append(f"{result.n_attributed} attributed, {result.n_decided('unknown')} unknown{others}; per device: "
                 f"{per_device}")
    lines.append("'needed': the PCE the best device needed at this p_FA for this image (it grows with the search).")
    lines += _budget_lines(result.queries)
    lines += [f"{q.source}: {q.note}" for q in result.queries if q.decision in ("ambiguous", "excluded")]
    return "\n".join(lines)


def _budget_lines(queries: list[Any]) -> list[str]:
    """The split of the false-alarm budget between aligned and searched positions, once per distinct split."""
    splits: dict[tuple[Any, ...], int] = {}
    for q in queries:
        b = q.budget
        if b and b["aligned"]["n_tests"] and b["searched"]["n_tests"]:
            key = tuple((b[k]["n_tests"], b[k]["share"], b[k]["pce_threshold"]) for k in ("aligned", "searched"))
            splits[key] = splits.get(key, 0) + 1
    lines = []
    for ((n_al, s_al, t_al), (n_se, s_se, t_se)), count in splits.items():
        lines.append(f"false-alarm budget ({count} image(s)): aligned {100 * s_al:g} % over {n_al:,} test(s), PCE ≥ "
                     f"{t_al:.1f}; crop/scale search {100 * s_se:g} % over {n_se:,} position(s), PCE ≥ {t_se:.1f}")
    return lines




def _command(args: argparse.Namespace) -> str:
    """The command line that reproduces this run (shown at the top of the report)."""
    text = (f"forensics identify {args.set} --db {args.db} --top {args.top} --pfa {args.pfa:g} "
            f"--rotations {args.rotations} --prescreen {args.prescreen} --sigma {args.sigma:g}")
    if args.scales is not None:
        text += f" --scales {args.scales}"
    if not args.crop_search:
        text += " --no-crop-search"
    return text
