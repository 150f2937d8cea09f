"""``forensics model``: list the sensor model's effects; check the model against measurements."""
from __future__ import annotations

import argparse
import math
import os
from typing import Any

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
)


def max_steps(args: argparse.Namespace) -> dict[str, int]:
    """``--max-steps`` as a keyword of :func:`~forensics.check.check_auto`; none when not given, so the library's
    default holds (not imported here: the parser stays fast to build)."""
    return {} if args.max_steps is None else {"max_steps": args.max_steps}


def register(sub) -> None:
    parser = sub.add_parser(
        "model", help="the physical sensor model: its effects, and checking it against measurements",
        description="The physical sensor model (the effects the simulator uses) and its check against measured "
                    "images: fit, show where it fails, name the missing effect, add it.")
    inner = parser.add_subparsers(dest="model_command", metavar="WHAT")

    effects = command_parser(inner, "effects", "list every effect: physics, parameters, needed manifest fields",
                             "forensics model effects")
    effects.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    effects.set_defaults(handler=run_effects, inputs=(), outputs=())

    check = command_parser(
        inner, "check", "fit the sensor model to a dataset, show where it fails and name the missing effect",
        "forensics model check data/ --add nonlinearity --report report/\n"
        "  forensics model check data/ --auto --report report/   # add flagged effects one at a time\n"
        "  forensics model check darks/ --auto --tiles 256       # a whole 1 MP frame, tile by tile",
        "Fit the base model (its effects are listed by 'forensics model effects') plus the --add effects to a dataset "
        "(images + manifest.csv with captured, exposure_s, iso, temperature_c; repeated frames per condition). "
        "Prints the fitted parameters with standard errors, the held-out error (1.0 = the noise floor measured "
        "from repeated frames), a table of checks, and the candidate effects ranked by predicted ΔBIC, flagged "
        "on strong evidence (ΔBIC > 10 and Holm-adjusted p < 0.01).  With --add, the base model is checked "
        "too and the error shown before and after.  With --auto, forward selection: starting from the base model "
        "plus any --add effects, add the top flagged candidate, refit, and repeat until nothing is flagged (an "
        "addition that lowers no error and raises no failing gof p is not kept; the next flagged one is tried "
        "once); the path base → +A → +B … is printed as a ladder with the error and gof at each step.  With "
        "--tiles SIZE, frames of any size: every tile is checked on its own and the tiles combined.")
    check.add_argument("data", help="dataset folder")
    check.add_argument("--add", action="append", default=[], metavar="EFFECT",
                       help="add an effect: a name from 'forensics model effects', module:Class or "
                            "path/to/file.py:Class (repeatable)")
    check.add_argument("--seed", type=seed, default=0, help="seed of the Monte-Carlo simulations (default 0)")
    check.add_argument("--auto", action="store_true",
                       help="forward selection: add flagged candidates one at a time until nothing is flagged")
    check.add_argument("--max-steps", type=positive_int, default=None, metavar="N",
                       help="with --auto: add at most N effects "
                            "(default: the library's forensics.check.select.DEFAULT_MAX_STEPS, 8)")
    check.add_argument("--region", default=None, metavar="TOP,LEFT,HEIGHT,WIDTH",
                       help="check only this part of every frame (pixels; a single number N: the central N×N); "
                            "default the whole frame, whatever its size; the warnings say which region was used")
    check.add_argument("--tiles", type=positive_int, default=None, metavar="SIZE",
                       help="check the whole frame in tiles of about SIZE×SIZE pixels (the memory of one tile per "
                            "worker; frames of any size) and combine them: the global parameters by their "
                            "information, with a test of whether the tiles agree on each (a dark rate or gain that "
                            "changes across the sensor); with --auto the effects are chosen on the central tile")
    check.add_argument("--scratch", default=None, metavar="DIR",
                       help="with --tiles: where the frames are decoded once for the tiles (default the system's "
                            "temporary directory; removed afterwards; needs room for every frame decoded)")
    add_input_options(check)
    add_execution_options(check, default="every core, or this process for a check of fewer than 10 M pixel-frames")
    add_output_options(check)
    check.set_defaults(handler=run_check, inputs=("data", "--add"), outputs=("--report",))
    parser.set_defaults(handler=lambda args: parser.print_help() or 2)


# ------------------------------------------------------------------------------------------- effects
def run_effects(args: argparse.Namespace) -> int:
    from forensics.sensor.effects import describe_effects

    rows = describe_effects()

    def summary() -> str:
        lines = []
        for role, title in (("base", "Base model"), ("candidate", "Candidate effects")):
            lines.append(f"{title}:")
            for e in (r for r in rows if r["role"] == role):
                fields = ", ".join(e["fields"]) or "—"
                lines.append(f"  {e['name']:<20} {e['description']}")
                lines.append(f"  {'':<20} stage {e['stage']}; needs: {fields}")
                for p in e["params"]:
                    default = p["default"]
                    default = f"{default:g}" if isinstance(default, float) else str(default)
                    extra = []
                    if p["null"] is not None:
                        extra.append(f"null {p['null']:g}")
                    if p["free"]:
                        extra.append("fitted")
                    unit = f" {p['unit']}" if p["unit"] else ""
                    tail = f" [{', '.join(extra)}]" if extra else ""
                    lines.append(f"  {'':<22}{p['name']} = {default}{unit}{tail}: {p['doc']}")
            lines.append("")
        lines.append("Add an effect to the check with --add NAME, module:Class or path/to/file.py:Class.")
        return "\n".join(lines)

    emit(args, summary, {"effects": rows})
    return 0


# ------------------------------------------------------------------------------------------- check
def run_check(args: argparse.Namespace) -> int:
    from forensics._shared.atomic import refuse_existing
    from forensics.check import check
    from forensics.report.check import check_report

    if args.report:
        refuse_existing(args.report, args.force)
    if args.tiles is not None:
        return _run_tiles(args)
    if args.scratch is not None:
        from forensics._shared.errors import UsageError

        raise UsageError("--scratch is where --tiles decodes the frames once; without --tiles nothing is decoded twice")
    if args.auto:
        return _run_auto(args)
    if args.max_steps is not None:
        from forensics._shared.errors import UsageError

        raise UsageError("--max-steps needs --auto")
    info(args, f"forensics model check: reading {args.data} …")
    ds = open_input(args, args.data)
    region = parse_region(args.region, ds)
    advise_tiles(args, ds, region)
    with executor_for(args, small=too_small_for_workers(ds, region)) as ex:
        result = check(ds, add=args.add, rng=args.seed, progress=progress_for(args), region=region, executor=ex)
        execution = ex.info()
    if args.report:
        path = check_report(result, title=f"Model check: {args.data}").write(args.report, force=args.force)
        info(args, f"report: {path}")
    emit(args, lambda: format_check(result), lambda: {**result.to_dict(), "execution": execution.to_dict()})
    return 0


def _run_auto(args: argparse.Namespace) -> int:
    from forensics.check import check_auto
    from forensics.report.check import selection_report

    info(args, f"forensics model check --auto: reading {args.data} …")
    ds = open_input(args, args.data)
    region = parse_region(args.region, ds)
    advise_tiles(args, ds, region)
    with executor_for(args, small=too_small_for_workers(ds, region)) as ex:
        sel = check_auto(ds, add=args.add, rng=args.seed, **max_steps(args),
                         progress=progress_for(args), region=region, executor=ex)
        execution = ex.info()
    if args.report:
        path = selection_report(sel, title=f"Model check (--auto): {args.data}").write(args.report, force=args.force)
        info(args, f"report: {path}")
    emit(args, lambda: format_check(sel.result) + "\n\n" + format_ladder(sel),
         lambda: {**sel.to_dict(), "execution": execution.to_dict()})
    return 0


def _run_tiles(args: argparse.Namespace) -> int:
    from forensics._shared.errors import UsageError
    from forensics.check import check_auto, check_tiles, resolve_effects
    from forensics.check.measurements import central_region
    from forensics.check.tiles import start_values
    from forensics.report.check import tiles_report

    if args.region is not None:
        raise UsageError("--tiles checks the whole frame; --region checks a part of it: give one of them")
    if args.max_steps is not None and not args.auto:
        raise UsageError("--max-steps needs --auto")
    if args.scratch is not None and not (os.path.isdir(args.scratch) and os.access(args.scratch, os.W_OK | os.X_OK)):
        raise UsageError(f"--scratch {args.scratch}: not a writable directory; give one with room for the decoded frames")
    info(args, f"forensics model check --tiles {args.tiles}: reading {args.data} …")
    ds = open_input(args, args.data)
    add, sel = list(args.add), None
    with executor_for(args) as ex:
        if args.auto:
            sel = check_auto(ds, add=args.add, rng=args.seed, **max_steps(args),
                             progress=progress_for(args), region=central_region(ds.shape(), args.tiles), executor=ex)
            given = {e.key for e in resolve_effects(args.add)}
            add += [k for k in _added(sel.result) if k not in given]
        # the tiles' fits start from the central tile's fitted values (each still fits to convergence)
        start = None if sel is None else start_values(sel.result.params)
        tiled = check_tiles(ds, add=add, size=args.tiles, rng=args.seed, progress=progress_for(args), executor=ex,
                            start=start, scratch=args.scratch)
        execution = ex.info()
    if args.report:
        path = tiles_report(tiled, sel, title=f"Model check (--tiles {args.tiles}): {args.data}").write(
            args.report, force=args.force)
        info(args, f"report: {path}")
    ladder = "" if sel is None else format_ladder(sel) + "\n\n"
    emit(args, lambda: ladder + format_tiles(tiled),
         lambda: {**tiled.to_dict(), "selection": None if sel is None else sel.to_dict(),
                  "execution": execution.to_dict()})
    return 0


def format_tiles(tiled: Any) -> str:
    """The human summary of a :class:`forensics.check.TiledCheck`."""
    h, w = tiled.shape
    n = len(tiled.tiles)
    lines = [f"Whole frame in tiles: {w}×{h} px in {n} tiles of about {tiled.size}×{tiled.size} (each read with a "
             f"3-px halo, scored once)", f"Model: {' + '.join(tiled.effects)}", "",
             "Global parameters, combined over the tiles by their information (p same: the tiles agree on it)",
             f"  {'parameter':<32} {'value':>24}   {'tiles':>5} {'spread':>9} {'p same':>9}"]
    for p in tiled.params:
        e = p.estimate
        value = f"{_g(e.value, '.5g')} ± {_g(e.se, '.2g')} {e.unit}".strip()
        lines.append(f"  {e.label:<32} {value:>24}   {p.tiles:>5} {_g(p.spread, '9.2g')} {_p(p.p_same):>9}")
    for p in tiled.patterns:
        value = f"{_g(p.size, '.4g')} ± {_g(p.size_se, '.2g')}"
        lines.append(f"  {p.effect + '.' + p.name + ' (size)':<32} {value:>24}   {p.tiles:>5} {_g(p.spread, '9.2g')} "
                     f"{_p(p.p_same):>9}")
    if tiled.uncombined:
        lines.append("  not combined (the tiles' values: median [smallest, largest]):")
        for u in tiled.uncombined:
            if u.median is None:
                spread = ""
            elif _g(u.low, '.4g') == _g(u.high, '.4g'):  # (every tile at the same value, to the digits shown)
                spread = f"{_g(u.median, '.4g')} {u.unit}".rstrip()
            else:
                spread = f"{_g(u.median, '.4g')} [{_g(u.low, '.4g')}, {_g(u.high, '.4g')}] {u.unit}".rstrip()
            lines.append(f"    {u.label:<30} {spread:>30}   {u.tiles:>5} tiles: {u.reason}")
    if tiled.joint_p_same is not None:
        lines.append(f"  all parameters jointly: Q = {_g(tiled.joint_q)} on {tiled.joint_df} df, p {_p(tiled.joint_p_same)}")
    e = tiled.error
    classes = ", ".join(f"{k} {_g(v)}" for k, v in e["classes"].items() if v is not None)
    lines += ["", "Error (held-out, pooled over the tiles; 1.0 = the noise floor)",
              f"  pixel     {_g(e['pixel'])}   ({classes})", f"  variance  {_g(e['variance'])}",
              "", "Goodness of fit (p-values, the tiles' combined by Fisher's method)",
              "  " + "   ".join(f"{k} {_p(v)}" for k, v in tiled.gof.items()),
              "", "Candidates (score statistics summed over the tiles; flagged: ΔBIC > 10, for a fixed pattern also as "
              "far as both halves of the repeats show it, and Holm-adjusted p < 0.01)"]
    for i, c in enumerate(tiled.candidates, 1):
        flag = "FLAGGED" if c.flagged else ""
        lines.append(f"  {i}. {c.effect:<20} ΔBIC {_g(c.delta_bic, '10.4g')}   p {_p(c.p):<9} "
                     f"flagged alone in {c.flagged_tiles} of {c.tested_tiles} tiles{_halves(c)}   {flag}".rstrip())
    lines.append("")
    differ = [p.estimate.label for p in tiled.params if p.p_same is not None and p.p_same < 0.001]
    if differ:
        lines.append(f"Not the same across the sensor (p < 0.001): {', '.join(differ)} — a spatial effect the model "
                     "lacks (e.g. amplifier glow raising the dark rate near a corner, a gain gradient); the "
                     "report maps each tile's value")
    if tiled.flagged:
        lines.append(f"Most likely missing: {tiled.flagged[0]}.")
    elif not differ:
        lines.append("Nothing flagged, and the tiles agree on every parameter.")
    if tiled.warnings:
        lines += ["", "Warnings"] + [f"  - {w}" for w in tiled.warnings]
    return "\n".join(lines)


def advise_tiles(args: argparse.Namespace, ds: Any, region: tuple[int, int, int, int] | None) -> None:
    """A note (stderr, not with --quiet) when one fit of the frames or region would hold many GB."""
    from forensics.check.tiles import whole_frame_advice

    h, w = ds.shape() if region is None else region[2:]
    advice = whole_frame_advice(int(h) * int(w), len(ds.frames))
    if advice:
        info(args, f"note: {advice}")


#: Pixel-frames (pixels of the checked region × frames) below which the check runs in one process unless
#: ``--workers`` says otherwise.  Its parallel parts (reading the frames, the pixel blocks) do not repay starting
#: worker processes (≈ 0.7 s) on small data: the EMVA 1288 standard series (7.4 M pixel-frames) took 41.2 s on
#: one process and 41.9 s on two, a 128² hidden-effect dataset (1.8 M) 5.4 and 6.1 s (``benchmarks/RESULTS_check.md``).
POOL_MIN_PIXEL_FRAMES = 10_000_000


def too_small_for_workers(ds: Any, region: tuple[int, int, int, int] | None) -> bool:
    """Whether the check of ``ds`` (or of ``region``) is below :data:`POOL_MIN_PIXEL_FRAMES`."""
    h, w = ds.shape() if region is None else region[2:]
    return int(h) * int(w) * len(ds.frames) < POOL_MIN_PIXEL_FRAMES


def parse_region(spec: str | None, ds: Any) -> tuple[int, int, int, int] | None:
    """``--region``: ``TOP,LEFT,HEIGHT,WIDTH`` or ``N`` (the central N×N of the frames of the dataset ``ds``);
    None: whole frames."""
    from forensics._shared.errors import UsageError

    if spec is None:
        return None
    try:
        values = [int(v) for v in spec.split(",")]
    except ValueError:
        values = []
    if len(values) == 1 and values[0] > 0:
        from forensics.check.measurements import central_region

        return central_region(ds.shape(), values[0])
    if len(values) != 4 or min(values) < 0 or min(values[2:]) < 1:
        raise UsageError(f"--region {spec!r}: give TOP,LEFT,HEIGHT,WIDTH in pixels (e.g. 0,0,1024,1024) or one "
                         "size N for the central N×N")
    return values[0], values[1], values[2], values[3]


def format_ladder(sel: Any) -> str:
    """The forward-selection path of a :class:`forensics.check.SelectionResult`, one line per step."""
    width = max(12, *(len(s.label) for s in sel.steps))
    lines = ["Forward selection (--auto): each step adds the top flagged candidate and refits",
             (f"  {'step':<{width}}  {'error: pixel':>12} {'variance':>9} {'growth':>8}   "
              f"{'gof p: pixel':>12} {'variance':>9} {'growth':>8} {'spatial':>8}   flagged")]
    for s in sel.steps:
        e, g = s.error, s.gof
        lines.append(f"  {s.label:<{width}}  {_g(e['pixel']):>12} {_g(e['variance']):>9} {_g(e['growth']):>8}   "
                     f"{_p(g['pixel']):>12} {_p(g['variance']):>9} {_p(g['growth']):>8} {_p(g['spatial']):>8}   "
                     f"{', '.join(s.flagged) or '—'}")
        for a in s.rejected:
            lines.append(f"  {'':<{width}}  (tried first, not kept: {a.reason})")
    for a in sel.rejected:
        lines.append(f"  (tried, not kept: {a.reason})")
    lines.append(f"Stopped: {sel.stopped}.")
    if sel.added:
        lines.append("Same model by hand: forensics model check " + str(sel.result.data["folder"]) + " "
                     + " ".join(f"--add {a}" for a in [*_added(sel.steps[0].result), *sel.added]))
    return "\n".join(lines)


def _halves(c) -> str:
    """A note where a candidate's ΔBIC counted only as far as both halves show its pattern is below the bar."""
    from forensics.check.diagnosis import FLAG_DBIC

    confirmed = c.delta_bic_confirmed
    if confirmed is None or confirmed > FLAG_DBIC or c.delta_bic <= FLAG_DBIC:
        return ""
    return f"   (both halves: ΔBIC {_g(confirmed, '.4g')}, not flagged)"


def _g(v: Any, spec: str = ".3g") -> str:
    if v is None:
        return "—"
    if isinstance(v, float) and (math.isnan(v) or math.isinf(v)):
        return str(v)
    return format(v, spec)


def _p(v: float | None) -> str:
    if v is None:
        return "—"
    if v < 1e-300:
        return "< 1e-300"
    return f"{v:.2g}"


def format_check(result: Any) -> str:
    """The human summary of a :class:`forensics.check.CheckResult`."""
    d = result.data
    lines = [f"Data: {d['frames']} frames, {d['conditions']} conditions ({d['repeated_conditions']} repeated), "
             f"{len(d['epochs'])} epochs, {d['size'][0]}×{d['size'][1]} px, full scale {d['full_scale']:g} DN, "
             f"{d['light_levels']} light levels",
             f"Model: {' + '.join(result.effects)}", "", "Fitted parameters"]
    for p in result.params:
        if not (p.identifiable and p.converged) or p.bound:
            lines.append(f"  {p.label:<32} {p.summary()}")
            continue
        se = "" if p.se is None else f" ± {_g(p.se)}"
        lines.append(f"  {p.label:<32} {_g(p.value, '.4g')}{se} {p.unit}".rstrip())
    for p in result.patterns:
        if not p.blocks:
            continue
        # a random effect's spread (sigma_k, sigma_o) is its size in the frames where measured (fit.hypers_from_sizes)
        sized = p.size is not None and p.hyper is not None and p.hyper_value == p.size
        shown = p.hyper and p.hyper_value is not None and not sized
        hyper = f" (sets {p.hyper} = {_g(p.hyper_value)})" if shown else ""
        size = f"; size in the frames {_g(p.size)} ± {_g(p.size_se)}" if p.size is not None else ""
        size += f" (sets {p.hyper})" if sized else ""
        lines.append(f"  {p.effect + '.' + p.name:<32} pattern over {p.blocks} blocks: rms {_g(p.rms)}, "
                     f"max |value| {_g(p.maximum)}{hyper}{size}")
    q = getattr(result, "quantiser", None)
    if q and q.get("compared"):
        chi2 = "; ".join(f"{k} {_g(v, '.5g')}" for k, v in q["variance_chi2"].items())
        kind = f"rounding after a uniform dither of {q['dither']:g} DN" if q["dither"] else "rounding, no dither"
        lines.append(f"  {'converter':<32} {kind} (the variance channel's χ²: {chi2})")
    if d.get("dark_series"):
        from forensics.check.darkfigures import format_dark_figures

        lines += ["", *format_dark_figures(d["dark_series"])]
    e = result.error
    before = result.baseline.error if result.baseline is not None else None

    def was(key: str) -> str:
        return f"   (before: {_g(before[key])})" if before is not None else ""

    classes = ", ".join(f"{k} {_g(v)}" for k, v in e["classes"].items() if v is not None)
    lines += ["", "Error (held-out; 1.0 = the noise floor measured from repeated frames)",
              f"  pixel     {_g(e['pixel'])}   ({classes}){was('pixel')}",
              f"  variance  {_g(e['variance'])}   (RMS of ln observed/predicted temporal variance){was('variance')}",
              f"  growth    {_g(e['growth'])}   (Poisson deviance per degree of freedom of defect counts){was('growth')}",
              "", "Goodness of fit (p-values)",
              "  " + "   ".join(f"{k} {_p(v)}" for k, v in result.gof.items())]
    if result.baseline is not None:
        lines.append("  before: " + "   ".join(f"{k} {_p(v)}" for k, v in result.baseline.gof.items()))
    lines += ["", "Checks", f"  {'statistic':<66} {'measured':>10} {'predicted':>10} {'z':>9}"]
    for c in result.checks:
        lines.append(f"  {c.statistic[:66]:<66} {_g(c.measured, '10.4g')} {_g(c.predicted, '10.4g')} "
                     f"{_g(c.z, '9.3g')}")
    lines += ["", "Candidates, ranked by predicted ΔBIC (flagged: ΔBIC > 10, for a fixed pattern also as far as both "
              "halves of the repeats show it, and Holm-adjusted p < 0.01)"]
    if not result.candidates:
        lines.append("  (none tested)")
    for i, c in enumerate(result.candidates, 1):
        flag = "FLAGGED" if c.flagged else ""
        lines.append(f"  {i}. {c.effect:<20} ΔBIC {_g(c.delta_bic, '10.4g')}   p {_p(c.p):<9}{_halves(c)} {flag}".rstrip())
        lines.append(f"     {c.evidence}")
    flagged = result.flagged
    lines.append("")
    if flagged:
        lines.append(f"Most likely missing: {flagged[0]}. Try: forensics model check {d['folder']} "
                     + " ".join(f"--add {a}" for a in [*_added(result), flagged[0]]))
    else:
        lines.append("Nothing flagged: no candidate effect is supported strongly by these data.")
    structure = getattr(result, "structure", None)
    if structure is not None and structure.named is not None:
        hint = (" (a flagged candidate may explain part of it: check again with it added)" if flagged else
                " (no candidate explains it: a user's own effect, --add file.py:Class, may)")
        lines.append(f"Unexplained structure: {structure.named.summary()}{hint}")
    if result.warnings:
        lines += ["", "Warnings"] + [f"  - {w}" for w in result.warnings]
    return "\n".join(lines)


def _added(result: Any) -> list[str]:
    from forensics.check import base_model

    base = set(result.baseline.effects) if result.baseline is not None else {e.key for e in base_model()}
    return [e for e in result.effects if e not in base]
