"""Benchmark: the execution layer — speed-up with workers, and the per-task cost of each backend.

Sections
1. ageing: ``age_dataset`` of N scenes of 640×480 over 13 ages (sensor H) with 1 process (in-process), 2 local
   processes and a 2-worker Dask LocalCluster; the outputs are checked identical.
2. fingerprinting: ``build_fingerprint`` of N 8-bit 2048×1536 images in one process (one thread, and the
   default two FFT/wavelet threads), on 2 local processes and on the 2-worker cluster; checked identical.
3. per-task overhead: tasks that do nothing (the backend's own cost per task) and ≈ 60 ms tasks, on local
   processes and Dask, against the plain in-process loop.

Run:  .venv/bin/python benchmarks/bench_parallel.py --images 48
"""
from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from forensics._shared.parallel import Executor
from forensics.fixtures import workitems
from forensics.io.images import read_image
from forensics.sensor.presets import preset
from forensics.sensor.simulate import age_dataset, make_scenes, parse_years

FP_SHAPE = (1536, 2048)  # 3 MP


class _DaskCase:
    """An executor on a 2-worker LocalCluster started for one case only: an idle cluster in this process (its
    scheduler's event loop) measurably slows the other backends' cases, so it never overlaps them."""

    def __enter__(self) -> Executor:
        from forensics._shared.parallel import start_local_cluster

        self.cluster = start_local_cluster(2)
        self.executor = Executor("dask", scheduler=self.cluster.scheduler_address)
        return self.executor

    def __exit__(self, *exc) -> None:
        self.executor.close()
        self.cluster.close()


def _wall(func) -> tuple[float, object]:
    start = time.perf_counter()
    out = func()
    return time.perf_counter() - start, out


def _same_tree(a: Path, b: Path) -> bool:
    files = sorted(p.relative_to(a) for p in a.rglob("*.png"))
    return files == sorted(p.relative_to(b) for p in b.rglob("*.png")) and all(
        np.array_equal(read_image(a / f), read_image(b / f)) for f in files)


def bench_ageing(root: Path, n: int, dask: bool) -> None:
    src = make_scenes(root / "scenes", n, (480, 640), rng=1)
    model = preset("H", (480, 640), rate_scale=100.0)
    ages = parse_years("0:96:8")
    runs = {"1 process (in-process)": lambda: Executor("in-process"),
            "2 processes": lambda: Executor("processes", workers=2)}
    if dask:
        runs["Dask LocalCluster, 2 workers"] = _DaskCase
    times = {}
    for label, make in runs.items():
        out = root / f"aged-{len(times)}"
        with make() as ex:
            times[label], _ = _wall(lambda: age_dataset(src, out, model, ages, rng=5, executor=ex))
    base = times["1 process (in-process)"]
    print(f"\nageing: {n} images of 640×480 × {len(ages)} ages ({n * len(ages)} aged images written)")
    for i, (label, t) in enumerate(times.items()):
        same = "" if i == 0 else ("; identical images" if _same_tree(root / "aged-0", root / f"aged-{i}") else "; DIFFERENT")
        print(f"  {label:32s} {t:7.2f} s  {1000 * t / (n * len(ages)):6.1f} ms per aged image  "
              f"speed-up {base / t:4.2f}×{same}")


def bench_fingerprint(root: Path, n: int, dask: bool, shape: tuple[int, int]) -> None:
    from forensics.io.dataset import open_dataset
    from forensics.prnu.fingerprint import build_fingerprint, parse_region

    src = make_scenes(root / f"fp-scenes-{shape[1]}", n, shape, rng=2, kind="photo")
    frames = open_dataset(src.root).frames
    region = parse_region("full")
    cases = [("1 process, 1 thread", "1", lambda: Executor("in-process")),
             ("1 process, 2 threads (FFT, wavelets)", None, lambda: Executor("in-process")),
             ("2 processes", None, lambda: Executor("processes", workers=2))]
    if dask:
        cases.append(("Dask LocalCluster, 2 workers", None, _DaskCase))
    print(f"\nfingerprint build: {n} images of {shape[1]}×{shape[0]} (library call; the workers' start-up and the serial Wiener filtering of the result included)")
    base = reference = None
    for label, threads, make in cases:
        saved = os.environ.pop("FORENSICS_THREADS", None)
        if threads:
            os.environ["FORENSICS_THREADS"] = threads
        try:
            with make() as ex:
                t, fp = _wall(lambda: build_fingerprint(frames, region, 3.0, executor=ex))
        finally:
            os.environ.pop("FORENSICS_THREADS", None)
            if saved is not None:
                os.environ["FORENSICS_THREADS"] = saved
        base = base or t
        same = "" if reference is None else ("; identical fingerprint" if np.array_equal(fp.K, reference) else "; DIFFERENT")
        reference = fp.K if reference is None else reference
        print(f"  {label:38s} {t:7.2f} s  {1000 * t / n:6.1f} ms per image  speed-up {base / t:4.2f}×{same}")


def bench_overhead(dask: bool, small: int, large: int) -> None:
    print("\nper-task cost (wall / tasks; 'overhead' = what the backend adds per task beyond the work itself)")
    t_item = min(_wall(lambda: workitems.busy(0))[0] for _ in range(3))
    plain_small, _ = _wall(lambda: [workitems.echo(i) for i in range(small)])
    print(f"  plain loop: empty task {1e6 * plain_small / small:8.1f} µs; busy task {1000 * t_item:6.1f} ms")
    backends = {"local processes (2)": lambda: Executor("processes", workers=2)}
    if dask:
        backends["Dask LocalCluster (2)"] = _DaskCase
    for label, make in backends.items():
        with make() as ex:
            list(ex.map(workitems.echo, range(8)))  # warm the workers
            t_small, _ = _wall(lambda: list(ex.map(workitems.echo, range(small))))
            t_large, _ = _wall(lambda: list(ex.map(workitems.busy, range(large))))
        overhead_large = t_large * 2 / large - t_item  # two workers: each task had 2·wall/n of a core
        print(f"  {label:24s} empty tasks: {1e6 * t_small / small:8.1f} µs per task;  busy tasks: "
              f"{1000 * t_large / large:6.1f} ms per task (2 in parallel), overhead {1000 * overhead_large:+6.1f} ms "
              f"per task = {100 * overhead_large / t_item:+.0f} % of the work")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--images", type=int, default=48)
    parser.add_argument("--fingerprint-images", type=int, default=96,
                        help="images at 3 MP (smaller sizes get proportionally more, half the pixels in all)")
    parser.add_argument("--fingerprint-sizes", nargs="+", default=["2048x1536", "1024x768"])
    parser.add_argument("--small-tasks", type=int, default=2000)
    parser.add_argument("--large-tasks", type=int, default=100)
    parser.add_argument("--no-dask", action="store_true")
    parser.add_argument("--only", choices=["ageing", "fingerprint", "overhead"], default=None)
    args = parser.parse_args()
    print(f"machine: {os.cpu_count()} CPUs; load average before the run {os.getloadavg()[0]:.2f} "
          f"(1 min), {os.getloadavg()[1]:.2f} (5 min)")
    dask = not args.no_dask
    root = Path(tempfile.mkdtemp(prefix="bench-parallel-"))
    try:
        if args.only in (None, "ageing"):
            bench_ageing(root, args.images, dask)
        if args.only in (None, "fingerprint"):
            for size in args.fingerprint_sizes:
                w, h = (int(v) for v in size.split("x"))
                count = args.fingerprint_images * max(1, round(FP_SHAPE[0] * FP_SHAPE[1] / (w * h)) // 2) \
                    if (h, w) != FP_SHAPE else args.fingerprint_images
                bench_fingerprint(root, count, dask, (h, w))
        if args.only in (None, "overhead"):
            bench_overhead(dask, args.small_tasks, args.large_tasks)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    print(f"\nload average after the run {os.getloadavg()[0]:.2f} (1 min)")


if __name__ == "__main__":
    main()
