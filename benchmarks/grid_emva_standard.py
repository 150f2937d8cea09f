#!/usr/bin/env python3
"""The model check on EMVA 1288 exposure-variant series from ``emva1288``'s own ``DatasetGenerator`` across seeds,
system gains, black offsets and bit depths (issue 27's first done-when criterion), side by side with
``emva1288.process`` on the same frames.

For every cell of the grid (bit depth × K × black offset × seed) one series is written
(:func:`forensics.fixtures.emva.make_standard_series`), ``forensics model check --auto --json`` runs on it as a whole
process, and so does emva1288's analysis (``benchmarks/emva1288_analysis.py`` in its own environment, as in
``bench_check_emva.py``).  Per run: did every step settle, did ``--auto`` add shot noise and the dark current the
camera has, is nothing flagged at the end, does the 95 % interval of the conversion gain (``shot_noise.g``) hold the
simulator's K (read back from the camera: it snaps K to its grid), and both tools' times.  The summary gives each
criterion per bit depth, K and offset, and the coverage of K's interval over every run (≈ 95 % if the intervals are
right: over n runs its binomial standard error is √(0.95·0.05/n)).

Black offsets: ``own`` is the generator's own choice (about 1 DN at K = 0.1 and 0 DN otherwise: the dark frames then
sit on the 0-DN bound, half their readouts censored); ``pedestal`` is 1 % of the full scale (2.55 DN at 8 bits,
41 DN at 12).  The frames are small (48 × 64, 8 exposure steps, 4 spatial frames: 40 frames), so both tools' times
are mostly their fixed costs; the full-size series is ``bench_check_emva.py --parts standard``.

Usage::

    .venv/bin/python benchmarks/grid_emva_standard.py --seeds 5 --work /tmp/grid --json /tmp/grid.json
    .venv/bin/python benchmarks/grid_emva_standard.py --bits 8 12 --gains 0.1 --offsets own --seeds 2
    .venv/bin/python benchmarks/grid_emva_standard.py --no-dither --bits 8 12 --gains 0.1 0.5 --offsets own --seeds 2
"""
from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_check_emva import (dark_reference, emva_analysis, fmt, forensics_auto, our_quantities, param,  # noqa: E402
                              their_quantities)

#: The series' design besides the grid's variables (the test's small frames: 40 frames of 48 × 64).
SHAPE, STEPS, SPATIAL = (48, 64), 8, 4
#: The camera's effects the check must add on every such series: at 22 °C its dark current doubles the dark level
#: over the exposure range, and its temporal noise has a shot-noise part wherever there is light.
EXPECTED = {"shot_noise", "dark_current"}


def offset_dn(name: str, bits: int) -> float | None:
    """The black offset of a grid cell: None for the generator's own choice, else 1 % of the full scale."""
    return None if name == "own" else 0.01 * (2**bits - 1)


def run_cell(work: Path, bits: int, gain: float, offset: str, seed: int, emva_python: str | None,
             timeout: float, dither: bool = True) -> dict:
    """Write one series, check it, analyse it with emva1288; the criteria and figures of the run."""
    from forensics.fixtures.emva import StandardSeries, make_standard_series

    series = replace(StandardSeries(), shape=SHAPE, steps=STEPS, spatial=SPATIAL, bit_depth=bits, K=gain,
                     blackoffset=offset_dn(offset, bits), dither=dither)
    folder = work / f"b{bits}-K{gain:g}-{offset}-s{seed}{'' if dither else '-nodither'}"
    if not (folder / "truth.json").exists():
        make_standard_series(folder, seed, series, force=True)
    truth = json.loads((folder / "truth.json").read_text())
    ours = forensics_auto(folder, timeout)
    theirs = emva_analysis(emva_python, descriptor=folder / "EMVA1288descriptor.txt", timeout=timeout) \
        if emva_python else None
    result = ours["result"]
    row = {"bits": bits, "K_nominal": gain, "offset": offset, "seed": seed, "K_true": truth["K"],
           "blackoffset": truth["blackoffset"], "ours_s": ours["wall"], "rc": ours["rc"],
           "theirs_s": theirs["wall"] if theirs else None,
           "their_K": (theirs["result"] or {}).get("K") if theirs else None}
    if result is None:
        return {**row, "converged": False, "added": [], "flagged": None, "K": None, "K_se": None, "covered": False,
                "stopped": f"no result (exit {ours['rc']}): {ours['stderr'].strip().splitlines()[-1:]}"}
    ours_q = our_quantities(result, series.temperature_c, dark_reference(folder))
    theirs_q = their_quantities(theirs["result"]) if theirs else {}
    row["quantities"] = {name: {"ours": ours_q[name][0], "se": ours_q[name][1], "theirs": theirs_q.get(name)}
                         for name in ("sigma_y_dark", "dark_current_DN_s")}
    k, k_se = param(result, "shot_noise.g")
    covered = k is not None and k_se is not None and abs(k - truth["K"]) <= 1.96 * k_se
    converged = all(p.get("converged", True) for p in result.get("params", []))
    return {**row, "converged": converged, "added": [s["added"] for s in result["path"] if s["added"]],
            "flagged": [c["effect"] for c in result.get("candidates", []) if c.get("flagged")],
            "K": k, "K_se": k_se, "covered": covered, "stopped": result.get("stopped")}


def passes(row: dict) -> dict[str, bool]:
    return {"settled": bool(row["converged"]), "adds shot noise and dark current": EXPECTED <= set(row["added"]),
            "nothing flagged": row["flagged"] == [], "K covered": bool(row["covered"])}


def report(rows: list[dict]) -> None:
    names = list(passes(rows[0]))
    print("| bits | K (DN/e⁻) | black offset | runs | " + " | ".join(names) + " | median time: ours / emva1288 |")
    print("|---|---|---|---|" + "---|" * len(names) + "---|")
    key = lambda r: (r["bits"], r["K_nominal"], r["offset"])  # noqa: E731
    for (bits, gain, offset), group in itertools.groupby(sorted(rows, key=key), key=key):
        group = list(group)
        counts = [sum(passes(r)[n] for r in group) for n in names]
        ours = sorted(r["ours_s"] for r in group)[len(group) // 2]
        theirs = [r["theirs_s"] for r in group if r["theirs_s"] is not None]
        tt = sorted(theirs)[len(theirs) // 2] if theirs else None
        offsets = sorted({round(r["blackoffset"], 2) for r in group})
        print(f"| {bits} | {gain:g} ({group[0]['K_true']:.4g}) | {offset} ({', '.join(map(str, offsets))} DN) | "
              f"{len(group)} | " + " | ".join(f"{c}/{len(group)}" for c in counts)
              + f" | {ours:.1f} s / {fmt(tt, '.2f')} s |")
    n = len(rows)
    ratios = sorted(r["ours_s"] / r["theirs_s"] for r in rows if r["theirs_s"])
    if ratios:
        print(f"\nwhole processes, ours / emva1288's: median {ratios[len(ratios) // 2]:.1f}×, largest {ratios[-1]:.1f}× "
              f"({len(ratios)} series)")
    for name, unit in (("sigma_y_dark", "DN"), ("dark_current_DN_s", "DN/s")):
        pairs = [(q["ours"], q["theirs"]) for r in rows for q in [r.get("quantities", {}).get(name, {})]
                 if q.get("ours") is not None and q.get("theirs")]
        if pairs:
            rel = sorted(o / t - 1 for o, t in pairs)
            print(f"{name} ({unit}), ours against emva1288's: median {100 * rel[len(rel) // 2]:+.1f} %, middle 90 % "
                  f"{100 * rel[len(rel) // 20]:+.1f} … {100 * rel[-1 - len(rel) // 20]:+.1f} % ({len(rel)} series)")
    cov = sum(r["covered"] for r in rows)
    print(f"\nK's 95 % interval holds the simulator's K in {cov} of {n} runs ({100 * cov / n:.1f} %; "
          f"binomial SE {100 * math.sqrt(0.95 * 0.05 / n):.1f} points)")
    for r in rows:
        bad = [k for k, v in passes(r).items() if not v]
        if bad:
            k = "—" if r["K"] is None else f"{r['K']:.4g} ± {fmt(r['K_se'], '.2g')}"
            print(f"- bits {r['bits']}, K {r['K_true']:.4g}, offset {r['offset']} ({r['blackoffset']:.3g} DN), seed "
                  f"{r['seed']}: fails {', '.join(bad)}; added {r['added']}, flagged {r['flagged']}, K {k} "
                  f"(emva1288 {fmt(r['their_K'])}); stopped: {r['stopped']}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bits", type=int, nargs="+", default=[8, 10, 12, 14])
    parser.add_argument("--gains", type=float, nargs="+", default=[0.1, 0.5, 2.0], help="system gains K (DN/e⁻)")
    parser.add_argument("--offsets", nargs="+", default=["own", "pedestal"], choices=["own", "pedestal"])
    parser.add_argument("--seeds", type=int, default=5, help="seeds 1 … N per cell")
    parser.add_argument("--work", type=Path, default=Path("/tmp/grid_emva_standard"))
    parser.add_argument("--workers", type=int, default=2, help="series checked at once (one process each)")
    parser.add_argument("--emva-python", default="/work/venv-emva/bin/python",
                        help="Python of an environment with emva1288 and NumPy < 2 ('' to skip its analysis)")
    parser.add_argument("--no-dither", action="store_true",
                        help="round the frames without the simulator's dither (a converter that does not dither)")
    parser.add_argument("--timeout", type=float, default=600.0)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    emva = args.emva_python if args.emva_python and Path(args.emva_python).exists() else None
    if args.emva_python and emva is None:
        print(f"[{args.emva_python} not found: emva1288's analysis skipped]", file=sys.stderr)
    args.work.mkdir(parents=True, exist_ok=True)
    cells = list(itertools.product(args.bits, args.gains, args.offsets, range(1, args.seeds + 1)))
    with ThreadPoolExecutor(args.workers) as pool:
        rows = list(pool.map(lambda c: run_cell(args.work, *c, emva, args.timeout, not args.no_dither), cells))
    report(rows)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
