"""The full validation sweep (≥ 400 trials each) whose table goes into benchmarks/RESULTS_defects.md.

    .venv/bin/python benchmarks/sweep_validate.py --trials 400 --seed 2024 --jobs 2

Runs exactly the trials of ``forensics validate defects`` and ``forensics
validate dating`` (same per-trial seeds) on the execution layer (local worker
processes, or a Dask cluster with ``--scheduler``), and prints the result
tables as Markdown.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from forensics._shared.parallel import open_executor  # noqa: E402
from forensics.validate import trials as V  # noqa: E402


def markdown(result: V.ValidationResult) -> str:
    lines = ["| quantity | trials | value | 95 % interval | acceptance | |", "|---|---:|---:|---|---|---|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in result.table()]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=400)
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--sensor", default="F")
    ap.add_argument("--jobs", type=int, default=2, help="local worker processes (default 2)")
    ap.add_argument("--scheduler", default=None, help="a Dask scheduler address instead of local processes")
    ap.add_argument("--scenes", default="smooth")
    ap.add_argument("--what", choices=["defects", "dating", "both"], default="both")
    args = ap.parse_args()
    settings = V.ValidationSettings(sensor=args.sensor, scenes=args.scenes)
    defects = dating = None
    with open_executor(args.jobs, args.scheduler) as ex:
        if args.what in ("defects", "both"):
            t = time.perf_counter()
            defects = V.validate_defects(settings, args.trials, args.seed, executor=ex)
            t_def = time.perf_counter() - t
        if args.what in ("dating", "both"):
            t = time.perf_counter()
            dating = V.validate_dating(settings, args.trials, args.seed, executor=ex)
            t_dat = time.perf_counter() - t
    s = settings
    print(f"settings: sensor {s.sensor}, {s.bit_depth}-bit {s.shape[1]}x{s.shape[0]}, read noise {s.read_noise:g} DN, "
          f"K = {s.images} per epoch (single-image references: K = {s.dating_images} yearly over {s.dating_years} "
          f"years), scenes '{s.scenes}', rates x{s.rate_scale():.4g}, q = {s.q}, tau = {s.sigma:g} sigma, "
          f"seed {args.seed}, {args.jobs} processes")
    if defects:
        print(f"\n### validate defects ({args.trials} trials, {t_def:.0f} s)\n")
        print(markdown(defects))
        curve = defects.curves["recall_vs_amplitude_sigma"]
        print("\nrecall by amplitude (units of sigma of d-hat): " +
              ", ".join(f"{c[0]:.1f}: {c[2]:.3f} (n={c[1]})" for c in curve if c[2] is not None))
    if dating:
        print(f"\n### validate dating ({args.trials} trials, {t_dat:.0f} s)\n")
        print(markdown(dating))
        print(f"\nsingle-image |interval error| histogram: {dating.curves['interval_error_histogram']}")
    print(f"\nall acceptance figures met: {all(r.passed for r in (defects, dating) if r)}")


if __name__ == "__main__":
    main()
