"""Benchmark of the recognition experiment on the execution layer: one reduced run per worker count.

Run::

    /work/main/.venv/bin/python benchmarks/bench_parallel_impact.py [--classes 20] [--samples 3]
        [--sensors A,B,H*100] [--years 0,48,96] [--workers 1,2] [--scheduler ADDRESS] [--repeat 1]

Each case is ``run_impact`` (Masek and Ko, both protocols) on the same synthetic iris set: ``--workers 1`` in
this process, ``N > 1`` on N local worker processes, and with ``--scheduler`` also on that Dask cluster.  Every
case's EERs, intervals, trends and spreads are checked identical to the first case's, so a speed-up is never
bought with a different answer.  The default size takes about a minute in one process on a 2-core machine.
"""
from __future__ import annotations

import argparse
import os
import platform
import tempfile
from pathlib import Path

from _timing import timeit  # benchmarks/ is on sys.path when a script runs

from forensics._shared.parallel import Executor
from forensics.impact.experiment import parse_sensors, run_impact
from forensics.impact.irises import simulate_irises
from forensics.impact.matchers import load_matchers
from forensics.io.dataset import open_dataset
from forensics.sensor.simulate import parse_years


def comparable(result) -> dict:
    out = result.to_dict()
    out.pop("elapsed_s")
    out.pop("resumed_units")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--classes", type=int, default=20)
    parser.add_argument("--samples", type=int, default=3)
    parser.add_argument("--sensors", default="A,B,H*100")
    parser.add_argument("--years", default="0,48,96")
    parser.add_argument("--workers", default="1,2", help="comma list of worker counts (1 = in-process)")
    parser.add_argument("--scheduler", help="also time a Dask cluster (address, or 'local')")
    parser.add_argument("--boot", type=int, default=500)
    parser.add_argument("--repeat", type=int, default=1)
    args = parser.parse_args()
    print(f"# bench_parallel_impact on {platform.processor() or platform.machine()}, {os.cpu_count()} cores")
    with tempfile.TemporaryDirectory() as scratch:
        root = Path(scratch) / "irises"
        simulate_irises(root, args.classes, args.samples, rng=1)
        source = open_dataset(root)
        sensors = parse_sensors(args.sensors, source.shape()[:2], 8)
        ages = parse_years(args.years)
        tasks = len(sensors) * len(ages)
        print(f"{len(source)} images ({args.classes} eyes × {args.samples}), sensors {args.sensors}, ages {ages}: "
              f"{tasks} (sensor, age) tasks, {tasks * len(source)} aged images, masek + ko, both protocols, "
              f"{args.boot} class resamples\n")
        cases = [(f"--workers {w}", ("in-process", int(w), None) if int(w) == 1 else ("processes", int(w), None))
                 for w in args.workers.split(",")]
        if args.scheduler:
            cases.append((f"--scheduler {args.scheduler}", ("dask", 2, args.scheduler)))
        reference, base = None, None
        for label, (backend, workers, scheduler) in cases:
            with Executor(backend, workers=workers, scheduler=scheduler) as ex:
                def once(ex=ex):
                    return run_impact(source, sensors, ages, load_matchers(["masek", "ko"]), rng=7, n_boot=args.boot,
                                      executor=ex)

                best, median, result = timeit(once, args.repeat)
            if reference is None:
                reference, base = comparable(result), best
            assert comparable(result) == reference, f"{label}: result differs from the first case"
            print(f"  {label:28s} best {best:7.2f} s  median {median:7.2f} s  speed-up {base / best:5.2f}×  "
                  f"(identical result)")


if __name__ == "__main__":
    main()
