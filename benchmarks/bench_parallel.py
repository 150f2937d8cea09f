"""Benchmark: the execution layer — speed-up with workers, and the per-task cost of each backend.

Sections
1. ageing: ``age_dataset`` of N scenes of 640×480 over 13 ages (sensor H) with 1 process (in-process), 2 local
   processes and a 2-worker Dask LocalCluster; the outputs are checked identical.
2. fingerprinting: ``forensics fingerprint build`` of N 8-bit 1024×768 images with --workers 1 and 2.
3. per-task overhead: tasks that do nothing (the backend's own cost per task) and ≈ 30 ms tasks, on local
   processes and Dask, against the plain in-process loop.

Run:  .venv/bin/python benchmarks/bench_parallel.py --images 48
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from forensics._shared.parallel import Executor
from forensics.fixtures import workitems
from forensics.io.images import read_image
from forensics.sensor.presets import preset
from forensics.sensor.simulate import age_dataset, make_scenes, parse_years


def _wall(func) -> tuple[float, object]:
    start = time.perf_counter()
    out = func()
    return time.perf_counter() - start, out


def _same_tree(a: Path, b: Path) -> bool:
    files = sorted(p.relative_to(a) for p in a.rglob("*.png"))
    return files == sorted(p.relative_to(b) for p in b.rglob("*.png")) and all(
        np.array_equal(read_image(a / f), read_image(b / f)) for f in files)


def bench_ageing(root: Path, n: int, cluster) -> None:
    src = make_scenes(root / "scenes", n, (480, 640), rng=1)
    model = preset("H", (480, 640), rate_scale=100.0)
    ages = parse_years("0:96:8")
    runs = {"1 process (in-process)": Executor("in-process"), "2 processes": Executor("processes", workers=2)}
    if cluster is not None:
        runs["Dask LocalCluster, 2 workers"] = Executor("dask", scheduler=cluster.scheduler_address)
    times = {}
    for label, ex in runs.items():
        out = root / f"aged-{len(times)}"
        with ex:
            times[label], _ = _wall(lambda: age_dataset(src, out, model, ages, rng=5, executor=ex))
    base = times["1 process (in-process)"]
    print(f"\nageing: {n} images of 640×480 × {len(ages)} ages ({n * len(ages)} aged images written)")
    for i, (label, t) in enumerate(times.items()):
        same = "" if i == 0 else ("; identical images" if _same_tree(root / "aged-0", root / f"aged-{i}") else "; DIFFERENT")
        print(f"  {label:32s} {t:7.2f} s  {1000 * t / (n * len(ages)):6.1f} ms per aged image  "
              f"speed-up {base / t:4.2f}×{same}")


def bench_fingerprint(root: Path, n: int) -> None:
    src = make_scenes(root / "fp-scenes", n, (768, 1024), rng=2, kind="photo")
    exe = str(Path(sys.executable).with_name("forensics"))
    times = {}
    for workers in (1, 2):
        out = root / f"fp-{workers}.npz"
        cmd = [exe, "fingerprint", "build", str(src.root), "-o", str(out), "--workers", str(workers), "--quiet"]
        t, proc = _wall(lambda: subprocess.run(cmd, capture_output=True, text=True))
        if proc.returncode != 0:
            print(f"  fingerprint build failed: {proc.stderr.strip()}")
            return
        times[workers] = t
    print(f"\nfingerprint build: {n} images of 1024×768 (command wall time, start-up included)")
    for w, t in times.items():
        print(f"  --workers {w}   {t:7.2f} s  {1000 * t / n:6.1f} ms per image  speed-up {times[1] / t:4.2f}×")


def bench_overhead(cluster, small: int, large: int) -> None:
    print("\nper-task cost (wall / tasks; 'overhead' = what the backend adds per task beyond the work itself)")
    t_item = min(_wall(lambda: workitems.busy(0))[0] for _ in range(3))
    plain_small, _ = _wall(lambda: [workitems.echo(i) for i in range(small)])
    print(f"  plain loop: empty task {1e6 * plain_small / small:8.1f} µs; busy task {1000 * t_item:6.1f} ms")
    backends = {"local processes (2)": lambda: Executor("processes", workers=2)}
    if cluster is not None:
        backends["Dask LocalCluster (2)"] = lambda: Executor("dask", scheduler=cluster.scheduler_address)
    for label, make in backends.items():
        with make() as ex:
            list(ex.map(workitems.echo, range(8)))  # warm the workers
            t_small, _ = _wall(lambda: list(ex.map(workitems.echo, range(small))))
            t_large, _ = _wall(lambda: list(ex.map(workitems.busy, range(large))))
        overhead_large = t_large * 2 / large - t_item
        print(f"  {label:24s} empty tasks: {1e6 * t_small / small:8.1f} µs per task;  busy tasks: "
              f"{1000 * t_large / large:6.1f} ms per task (2 in parallel), overhead {1000 * overhead_large:+6.1f} ms "
              f"per task = {100 * overhead_large / t_item:+.0f} % of the work")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--images", type=int, default=48)
    parser.add_argument("--fingerprint-images", type=int, default=48)
    parser.add_argument("--small-tasks", type=int, default=2000)
    parser.add_argument("--large-tasks", type=int, default=100)
    parser.add_argument("--no-dask", action="store_true")
    parser.add_argument("--only", choices=["ageing", "fingerprint", "overhead"], default=None)
    args = parser.parse_args()
    print(f"machine: {os.cpu_count()} CPUs; load average before the run {os.getloadavg()[0]:.2f} "
          f"(1 min), {os.getloadavg()[1]:.2f} (5 min)")
    cluster = None
    if not args.no_dask:
        from distributed import LocalCluster

        cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                               silence_logs=40)
    root = Path(tempfile.mkdtemp(prefix="bench-parallel-"))
    try:
        if args.only in (None, "ageing"):
            bench_ageing(root, args.images, cluster)
        if args.only in (None, "fingerprint"):
            bench_fingerprint(root, args.fingerprint_images)
        if args.only in (None, "overhead"):
            bench_overhead(cluster, args.small_tasks, args.large_tasks)
    finally:
        shutil.rmtree(root, ignore_errors=True)
        if cluster is not None:
            cluster.close()
    print(f"\nload average after the run {os.getloadavg()[0]:.2f} (1 min)")


if __name__ == "__main__":
    main()
