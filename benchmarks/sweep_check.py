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
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

PIXEL_EFFECTS = ("prnu", "dark_current", "gain", "nonlinearity", "dsnu")


def run_one(job: tuple[str, int]) -> dict:
    from forensics.fixtures.hidden import make_hidden
    from forensics.check import check

    effect, seed = job
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="sweep-check-") as tmp:
        data = Path(tmp) / "data"
        make_hidden(effect, data, rng=seed)
        if effect == "none":
            res = check(data, rng=seed)
            base, added = res, None
        else:
            added = check(data, add=[effect], rng=seed)
            base = added.baseline
    out = {"effect": effect, "seed": seed, "seconds": time.perf_counter() - started,
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
    fixed = not added.flagged and all(v >= 0.001 for v in gofs)
    specific = True
    if effect in PIXEL_EFFECTS:
        before, after = base.error["pixel"], added.error["pixel"]
        specific = after <= 1.1 and before >= 1.5 * after
    elif effect == "shot_noise":
        specific = added.error["variance"] is not None and added.error["variance"] <= 0.05
    elif effect == "accelerating_growth":
        specific = added.error["growth"] is not None and added.error["growth"] <= 3
    elif effect == "clusters":
        specific = added.gof["spatial"] is not None and added.gof["spatial"] >= 0.05
    out.update({"detect": detect, "fixed": fixed, "specific": specific, "pass": detect and fixed and specific})
    return out


def fmt(v: float | None, spec: str = ".3g") -> str:
    return "—" if v is None else format(v, spec)


def main(argv: list[str] | None = None) -> int:
    from forensics.fixtures.hidden import CANDIDATES, EXTRA

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=10, help="seeds per candidate (default 10)")
    parser.add_argument("--null", type=int, default=20, help="seeds with nothing hidden (default 20)")
    parser.add_argument("--only", action="append", help="only this candidate (repeatable)")
    parser.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--no-extra", action="store_true", help="only the seven candidates the issue names "
                        "(default: also the further built-in candidates, e.g. dsnu)")
    parser.add_argument("--json", help="also write every run's numbers to this file")
    args = parser.parse_args(argv)
    effects = args.only or list(CANDIDATES) + ([] if args.no_extra else list(EXTRA))
    jobs = [(e, s) for e in effects for s in range(1, args.seeds + 1)] + [("none", s) for s in range(1, args.null + 1)]
    started = time.perf_counter()
    with ProcessPoolExecutor(args.workers) as pool:
        runs = list(pool.map(run_one, jobs))
    elapsed = time.perf_counter() - started
    print(f"# Model-check sweep: {len(effects)} candidate(s) × {args.seeds} seeds + {args.null} null seeds "
          f"({elapsed:.0f} s on {args.workers} worker(s))\n")
    print("| hidden effect | flagged & ranked 1st | added: nothing flagged, all gof p ≥ 0.001 | effect criterion | "
          "criterion | base error (median) | added error (median) | median ΔBIC |")
    print("|---|---|---|---|---|---|---|---|")
    import numpy as np

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
            before = np.median([r["base_gof"]["spatial"] for r in rs])
            after = np.median([r["add_gof"]["spatial"] for r in rs])
            b, a = f"gof.spatial {before:.3g}", f"gof.spatial {after:.3g}"
        else:
            before = np.median([r["base_error"][key] for r in rs])
            after = np.median([r["add_error"][key] for r in rs])
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
    print(f"\nmean time per dataset (generate + checks): {np.mean([r['seconds'] for r in runs]):.1f} s")
    if args.json:
        Path(args.json).write_text(json.dumps(runs, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
