#!/usr/bin/env python3
"""Full sweep of the model check on data with a hidden effect (issue 5's acceptance criteria).

For every candidate effect and seed: write a dataset with that effect hidden
(``fixtures.hidden``), run the base check and the check with the effect added,
and test the issue's criteria; for the null case (nothing hidden), run the base
check only.  Prints one Markdown table per part and a summary.

Usage::

    .venv/bin/python benchmarks/sweep_check.py                 # 7 (+1 extra) candidates × 10 seeds + 20 null seeds
    .venv/bin/python benchmarks/sweep_check.py --seeds 3 --null 5 --workers 2
    .venv/bin/python benchmarks/sweep_check.py --only gain --seeds 10
    .venv/bin/python benchmarks/sweep_check.py --conventions project,camera,8bit,14bit --seeds 3 --null 5
    .venv/bin/python benchmarks/sweep_check.py --combo prnu,dark_current --combo gain,accelerating_growth
    .venv/bin/python benchmarks/sweep_check.py --conventions project,camera,8bit,14bit --scheduler tcp://HEAD:8786
    .venv/bin/python benchmarks/sweep_check.py --done-when --json sweep.json   # issue 27's whole sweep, one pool

Runs go through the execution layer (``--workers`` local processes, or a Dask cluster with ``--scheduler``);
with ``--json OUT`` every finished run is kept in ``OUT.partial/`` and a stopped sweep, started again with the
same arguments, resumes from the runs it finished.

With ``--combo A,B[,C]`` (repeatable; ``none`` for nothing hidden) the sweep hides several effects at once and
runs forward selection (``forensics model check --auto``) instead: per combination, the seeds where it added
exactly the hidden effects and ended with nothing flagged, and the median errors before (base) and after.
Given with ``--conventions`` or ``--only``, both parts run in one pool (``--done-when``: the issue's whole sweep).

Criteria (per run):
* base: the hidden effect is flagged and ranked first;
* added: nothing flagged, every gof p ≥ 0.001, and per effect
  error.pixel ≤ 1.1 and ≥ 1.5× lower than before (prnu, dark_current, gain,
  nonlinearity), error.variance ≤ 0.05 (shot_noise), error.growth ≤ 3
  (accelerating_growth), gof.spatial ≥ 0.05 (clusters);
* null: nothing flagged.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from forensics._shared.atomic import write_text  # noqa: E402 — after the path set-up

PIXEL_EFFECTS = ("prnu", "dark_current", "gain", "nonlinearity", "dsnu")
DONE_WHEN_CONVENTIONS = ("project", "14bit", "camera", "8bit")
DONE_WHEN_COMBOS = ("prnu,dark_current", "dark_current,shot_noise", "gain,accelerating_growth",
                    "prnu,dark_current,shot_noise", "gain,clusters,accelerating_growth", "none")
CONVENTION_COST_ORDER = {"camera": 0, "8bit": 1, "14bit": 2, "project": 3}


def median_of(values: list) -> float:
    """Median of the values reported (a fit that did not converge reports None: left out; NaN if none)."""
    import numpy as np

    kept = [v for v in values if v is not None]
    return float(np.median(kept)) if kept else float("nan")


def known_effects(design, effect: str) -> list[str]:
    """Effects a convention puts in every device, which the user knows of and names (``--add``): the ISO
    amplifier of a convention with an analogue gain (unless the gain is the hidden effect itself)."""
    return ["gain"] if design.iso_gain != "none" and effect != "gain" else []


def run_one(job: tuple[str, int] | tuple[str, int, str]) -> dict:
    from forensics.check.pipeline import base_model, prepare, resolve_effects, run_check
    from forensics.fixtures.hidden import convention, make_hidden

    effect, seed = job[:2]
    conv = job[2] if len(job) > 2 else "project"  # (effect, seed[, convention])
    design = convention(conv)
    known = known_effects(design, effect)
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="sweep-check-") as tmp:
        data = Path(tmp) / "data"
        make_hidden(effect, data, rng=seed, design=design)
        ev, _ = prepare(data, known, seed, 199)
        start = [*base_model(ev.black_level), *resolve_effects(known)]
        base = run_check(ev, start)
        added = None if effect == "none" else run_check(ev, [*start, *resolve_effects([effect])])
    out = {"effect": effect, "seed": seed, "convention": conv, "known": known,
           "seconds": time.perf_counter() - started,
           "base_flagged": base.flagged, "base_top": base.candidates[0].effect if base.candidates else None,
           "base_error": base.error, "base_gof": base.gof,
           "base_ranking": [(c.effect, round(c.delta_bic, 1)) for c in base.candidates]}
    if effect == "none":
        out["pass"] = not base.flagged
        return out
    rank = [c.effect for c in base.candidates].index(effect) + 1 if effect in [c.effect for c in base.candidates] else None
    hidden = next((c for c in base.candidates if c.effect == effect), None)
    out.update({"rank": rank, "hidden_dbic": hidden.delta_bic if hidden else None,
                "hidden_flagged": bool(hidden and hidden.flagged),
                "add_flagged": added.flagged, "add_error": added.error, "add_gof": added.gof})
    detect = out["hidden_flagged"] and rank == 1
    gofs = [v for v in added.gof.values() if v is not None]
    converged = added.error["pixel"] is not None  # a fit that did not converge reports no error: not fixed
    fixed = converged and not added.flagged and all(v >= 0.001 for v in gofs)
    specific = True
    if effect in PIXEL_EFFECTS:
        before, after = base.error["pixel"], added.error["pixel"]
        specific = after is not None and before is not None and after <= 1.1 and before >= 1.5 * after
    elif effect == "shot_noise":
        specific = added.error["variance"] is not None and added.error["variance"] <= 0.05
    elif effect == "accelerating_growth":
        specific = added.error["growth"] is not None and added.error["growth"] <= 3
    elif effect == "clusters":
        specific = added.gof["spatial"] is not None and added.gof["spatial"] >= 0.05
    out.update({"detect": detect, "fixed": fixed, "specific": specific, "pass": detect and fixed and specific})
    return out


def run_auto(job: tuple[tuple[str, ...], int]) -> dict:
    """One dataset with several hidden effects through forward selection (``--auto``)."""
    from forensics.check import check_auto
    from forensics.fixtures.hidden import make_hidden

    combo, seed = job
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="sweep-auto-") as tmp:
        data = Path(tmp) / "data"
        make_hidden([] if combo == ("none",) else list(combo), data, rng=seed)
        sel = check_auto(data, rng=seed)
    hidden = set() if combo == ("none",) else set(combo)
    first, last = sel.steps[0], sel.steps[-1]
    exact = set(sel.added) == hidden
    pixel_ok = last.error["pixel"] is not None and last.error["pixel"] <= 1.1
    return {"combo": "+".join(combo), "seed": seed, "seconds": time.perf_counter() - started,
            "added": sel.added, "stopped": sel.stopped, "reason": sel.reason, "base_flagged": first.flagged,
            "final_flagged": last.flagged, "base_error": first.error, "final_error": last.error,
            "base_gof": first.gof, "final_gof": last.gof, "exact": exact, "pixel_ok": pixel_ok,
            "pass": exact and not last.flagged and pixel_ok,
            "path": [(s.label, s.error["pixel"], s.flagged, [a.reason for a in s.rejected]) for s in sel.steps],
            "rejected": [a.reason for a in sel.rejected]}


def combo_jobs(combos: list[tuple[str, ...]], seeds: int) -> list[tuple[tuple[str, ...], int]]:
    return [(c, s) for c in combos for s in range(1, seeds + 1)]


def print_combo_tables(runs: list[dict], combos: list[tuple[str, ...]]) -> None:
    """The combination sweep through forward selection: one Markdown table and the failing runs."""
    import numpy as np

    print("| hidden effects | added exactly the hidden ones | ends with nothing flagged | final error.pixel ≤ 1.1 | "
          "all three | error.pixel base → final (median) | variance | growth | median steps |")
    print("|---|---|---|---|---|---|---|---|---|")

    def med(rs: list[dict], which: str, key: str) -> str:
        vals = [r[which][key] for r in rs if r[which][key] is not None]
        return fmt(float(np.median(vals))) if vals else "—"

    for c in combos:
        rs = [r for r in runs if r["combo"] == "+".join(c)]
        n = len(rs)
        print(f"| {' + '.join(c)} | {sum(r['exact'] for r in rs)}/{n} | {sum(not r['final_flagged'] for r in rs)}/{n} | "
              f"{sum(r['pixel_ok'] for r in rs)}/{n} | {sum(r['pass'] for r in rs)}/{n} | "
              f"{med(rs, 'base_error', 'pixel')} → {med(rs, 'final_error', 'pixel')} | "
              f"{med(rs, 'base_error', 'variance')} → {med(rs, 'final_error', 'variance')} | "
              f"{med(rs, 'base_error', 'growth')} → {med(rs, 'final_error', 'growth')} | "
              f"{np.median([len(r['path']) - 1 for r in rs]):g} |")
    fails = [r for r in runs if not r["pass"]]
    if fails:
        print("\nRuns that failed a criterion:\n")
        for r in fails:
            path = " → ".join(f"{lab} (pixel {fmt(px)}, flagged {fl or '—'})" for lab, px, fl, _ in r["path"])
            print(f"- {r['combo']}, seed {r['seed']}: {path}; stopped: {r['stopped']}")
    print(f"\nmean time per dataset (generate + forward selection): {np.mean([r['seconds'] for r in runs]):.1f} s")


def run_any(job: tuple) -> dict:
    """One job of either part, so both parts share one pool: a combination job is ``(combo_tuple, seed)``."""
    return run_auto(job) if isinstance(job[0], tuple) else run_guarded(job)


def run_logged(fn, jobs: list, workers: int, json_out: str | None, scheduler: str | None = None) -> list[dict]:
    """``fn`` over ``jobs`` on the execution layer, in job order.  With ``json_out`` each finished run is kept in
    ``<json_out>.partial/`` (a sweep takes hours: a stopped one resumes from what it finished)."""
    import contextlib

    from forensics._shared.parallel import open_executor, resumable_checkpoint

    config = {"sweep": fn.__name__, "jobs": [list(map(str, j)) for j in jobs]}
    partial = Path(str(json_out) + ".partial") if json_out else None
    with open_executor(workers, scheduler) as ex, \
            (resumable_checkpoint(partial, config) if partial else contextlib.nullcontext()) as checkpoint:
        if ex.backend == "dask":
            print(f"Dask dashboard: {ex.info().dashboard}", file=sys.stderr)
        return list(ex.map(fn, jobs, checkpoint=checkpoint))


def run_guarded(job: tuple[str, int, str]) -> dict:
    """:func:`run_one`, a crash recorded as a failed run (a convention's data may break a step of the check)."""
    try:
        return run_one(job)
    except Exception as exc:  # noqa: BLE001 — reported in the table, not hidden
        return {"effect": job[0], "seed": job[1], "convention": job[2], "crashed": f"{type(exc).__name__}: {exc}",
                "pass": False, "seconds": 0.0}


def print_tables(runs: list[dict], effects: list[str]) -> None:
    """One Markdown table of the criteria per hidden effect, then the runs that failed a criterion."""
    import numpy as np

    for r in runs:
        if "crashed" in r:
            print(f"- CRASHED: {r['effect']}, seed {r['seed']}: {r['crashed']}")
    runs = [r for r in runs if "crashed" not in r]
    print("| hidden effect | flagged & ranked 1st | added: nothing flagged, all gof p ≥ 0.001 | effect criterion | "
          "criterion | base error (median) | added error (median) | median ΔBIC |")
    print("|---|---|---|---|---|---|---|---|")
    for e in effects:
        rs = [r for r in runs if r["effect"] == e]
        if not rs:
            continue
        n = len(rs)
        if e in PIXEL_EFFECTS:
            crit, key = "error.pixel ≤ 1.1 and ≥ 1.5× lower", "pixel"
        elif e == "shot_noise":
            crit, key = "error.variance ≤ 0.05", "variance"
        elif e == "accelerating_growth":
            crit, key = "error.growth ≤ 3", "growth"
        else:
            crit, key = "gof.spatial ≥ 0.05", "spatial"
        if key == "spatial":
            before = median_of([r["base_gof"]["spatial"] for r in rs])
            after = median_of([r["add_gof"]["spatial"] for r in rs])
            b, a = f"gof.spatial {before:.3g}", f"gof.spatial {after:.3g}"
        else:
            before = median_of([r["base_error"][key] for r in rs])
            after = median_of([r["add_error"][key] for r in rs])
            b, a = f"{key} {before:.3g}", f"{key} {after:.3g}"
        dbic = np.median([r["hidden_dbic"] for r in rs])
        print(f"| {e} | {sum(r['detect'] for r in rs)}/{n} | {sum(r['fixed'] for r in rs)}/{n} | "
              f"{sum(r['specific'] for r in rs)}/{n} | {crit} | {b} | {a} | {dbic:.3g} |")
    nulls = [r for r in runs if r["effect"] == "none"]
    if nulls:
        print(f"| none | nothing flagged in {sum(r['pass'] for r in nulls)}/{len(nulls)} | | | | "
              f"pixel {np.median([r['base_error']['pixel'] for r in nulls]):.3g} | | |")
    print()
    fails = [r for r in runs if not r["pass"]]
    if fails:
        print("Runs that failed a criterion:\n")
        for r in fails:
            if r["effect"] == "none":
                print(f"- none, seed {r['seed']}: flagged {r['base_flagged']}")
            else:
                print(f"- {r['effect']}, seed {r['seed']}: rank {r['rank']}, base flagged {r['base_flagged']}, "
                      f"added flagged {r['add_flagged']}, added gof "
                      f"{ {k: fmt(v) for k, v in r['add_gof'].items()} }, base error {fmt(r['base_error']['pixel'])} → "
                      f"{fmt(r['add_error']['pixel'])}, variance {fmt(r['add_error']['variance'])}, growth "
                      f"{fmt(r['add_error']['growth'])}")


def print_summary(runs: list[dict], effects: list[str], convs: list[str]) -> None:
    """One table across conventions: per hidden effect, the runs meeting every criterion (and which criterion
    the others missed: named first, fixed by adding it, the effect's own criterion); the null runs flagging
    nothing.  The issue's bar: ≥ 9/10 per effect, ≥ 19/20 null."""
    print("| hidden effect | " + " | ".join(convs) + " |")
    print("|---|" + "---|" * len(convs))
    for e in [*effects, "none"]:
        cells = []
        for c in convs:
            rs = [r for r in runs if r["effect"] == e and r["convention"] == c and "crashed" not in r]
            crashed = sum(1 for r in runs if r["effect"] == e and r["convention"] == c and "crashed" in r)
            n = len(rs) + crashed
            if not n:
                cells.append("—")
                continue
            ok = sum(bool(r["pass"]) for r in rs)
            cell = f"{ok}/{n}"
            if e != "none" and ok < n:
                cell += (f" (first {sum(bool(r['detect']) for r in rs)}, fixed {sum(bool(r['fixed']) for r in rs)}, "
                         f"criterion {sum(bool(r['specific']) for r in rs)}" + (f", crashed {crashed}" if crashed else "")
                         + ")")
            cells.append(cell)
        print(f"| {'none (nothing flagged)' if e == 'none' else e} | " + " | ".join(cells) + " |")
    print()


def fmt(v: float | None, spec: str = ".3g") -> str:
    return "—" if v is None else format(v, spec)


def main(argv: list[str] | None = None) -> int:
    from forensics.fixtures.hidden import CANDIDATES, CONVENTIONS, EXTRA, convention

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=10, help="seeds per candidate (default 10)")
    parser.add_argument("--null", type=int, default=20, help="seeds with nothing hidden (default 20)")
    parser.add_argument("--only", action="append", help="only this candidate (repeatable)")
    parser.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--scheduler", default=None, help="a Dask scheduler address (default: local processes)")
    parser.add_argument("--no-extra", action="store_true", help="only the seven candidates the issue names "
                        "(default: also the further built-in candidates, e.g. dsnu)")
    parser.add_argument("--json", help="also write every run's numbers to this file")
    parser.add_argument("--combo", action="append", metavar="A,B[,C]",
                        help="hide these effects together and run forward selection (--auto) instead (repeatable; "
                             "'none' for nothing hidden)")
    parser.add_argument("--conventions", metavar="NAME,…",
                        help="run the sweep on data of each of these generator conventions (fixtures.hidden "
                             "CONVENTIONS: " + ", ".join(CONVENTIONS) + "); one table per convention")
    parser.add_argument("--done-when", action="store_true",
                        help="the issue's whole sweep in one run: conventions " + ",".join(DONE_WHEN_CONVENTIONS) +
                             " and the combinations " + "; ".join(DONE_WHEN_COMBOS) + " (with the default seeds)")
    args = parser.parse_args(argv)
    if args.done_when:
        args.conventions = args.conventions or ",".join(DONE_WHEN_CONVENTIONS)
        args.combo = args.combo or list(DONE_WHEN_COMBOS)
    combos = [tuple(x.strip() for x in c.split(",") if x.strip()) for c in args.combo or []]
    # --combo alone runs the combinations only (as before); with --conventions or --only, both parts in one pool
    singles = not combos or bool(args.conventions or args.only)
    effects = args.only or list(CANDIDATES) + ([] if args.no_extra else list(EXTRA))
    convs = [c.strip() for c in args.conventions.split(",") if c.strip()] if args.conventions else ["project"]
    for c in convs:
        convention(c)  # unknown names fail before any work
    jobs: list[tuple] = []
    if singles:
        jobs = [(e, s, c) for c in convs for e in effects for s in range(1, args.seeds + 1)] + \
            [("none", s, c) for c in convs for s in range(1, args.null + 1)]
        # Longest first, so the workers finish together: the per-dataset cost is set by the convention's frame
        # size and depth (RESULTS_check.md: camera ≈ 90 s, 8bit ≈ 30 s, 14bit ≈ 16 s, project ≈ 9 s of a worker),
        # and a null dataset runs one check where the others run two.
        jobs.sort(key=lambda j: (CONVENTION_COST_ORDER.get(j[2], len(CONVENTION_COST_ORDER)), j[0] == "none"))
    jobs += combo_jobs(combos, args.seeds)
    started = time.perf_counter()
    runs = run_logged(run_any, jobs, args.workers, args.json, args.scheduler)
    elapsed = time.perf_counter() - started
    singles_runs = [r for r in runs if "combo" not in r]
    combo_runs = [r for r in runs if "combo" in r]
    parts = []
    if singles:
        parts.append(f"{len(effects)} candidate(s) × {args.seeds} seeds + {args.null} null seeds"
                     + (f", conventions {', '.join(convs)}" if args.conventions else ""))
    if combos:
        parts.append(f"forward selection (--auto) on {len(combos)} combination(s) × {args.seeds} seeds")
    print(f"# Model-check sweep: {'; '.join(parts)} ({elapsed:.0f} s on {args.workers} worker(s))\n")
    if singles and args.conventions:
        for conv in convs:
            d = convention(conv)
            print(f"## Convention {conv}: {d.bit_depth}-bit {d.shape[1]}×{d.shape[0]}, {len(d.ages)} epochs, black level "
                  f"{d.black_level:g} DN, light pedestal {d.pedestal * d.level_scale:g} DN, read noise {d.read_noise:g} DN "
                  f"({'also' if d.noise_on_stuck else 'not'} on stuck pixels), vignetting {d.vignetting:g}, stuck share "
                  f"{d.rates[1] / sum(d.rates):.2g}, ISO gain {d.iso_gain}\n")
            print_tables([r for r in singles_runs if r["convention"] == conv], effects)
        if len(convs) > 1:
            print("## All conventions: runs meeting every criterion\n")
            print_summary(singles_runs, effects, convs)
    elif singles:
        print_tables(singles_runs, effects)
    if singles:
        import numpy as np

        print(f"\nmean time per dataset (generate + checks): {np.mean([r['seconds'] for r in singles_runs]):.1f} s")
    if combos:
        print("\n## Forward selection (--auto), project convention\n")
        print_combo_tables(combo_runs, combos)
    if args.json:
        write_text(args.json, json.dumps(runs, indent=1, default=float), force=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
