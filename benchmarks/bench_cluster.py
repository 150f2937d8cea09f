"""Benchmark: clustering N images of about 1 MP by camera (``forensics.prnu.cluster.cluster_images``).

A collection of N simulated 8-bit grey PNG images of 1024×1024 (the sensor model's cameras: preset A with
PRNU σ_k = 1 %, read and shot noise, smooth scenes) from D cameras, N/D images each, is written once; then
it is clustered (crop 1024², the default) with each worker count asked for, timing the two phases the
execution layer runs — residuals (one image per item: read, wavelet residual, ×I, crop; 4 MB back to the
driver) and similarity blocks (two blocks of vectors multiplied, plus the null samples) — and the
clustering itself.  Reported per run: wall seconds per phase, ms per image and per image pair, the peak
resident memory of the driver and of the workers, the size of the memory-mapped residual store
(rows × crop² × 4 bytes) and the recovery (purity, completeness, adjusted Rand index, clusters found).

Run:  .venv/bin/python benchmarks/bench_cluster.py --images 1000 --devices 50 --workers 1,2
      (the issue's figure: 1,000 images at 1 MP); --images 40 --devices 8 for a quick check.
"""
from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from forensics._shared.parallel import Executor
from forensics.demo.prnu import sensor_model, simulated_set
from forensics.io.images import write_image
from forensics.prnu.cluster import adjusted_rand_index, block_images, cluster_images, completeness, purity

SHAPE = (1024, 1024)


def make_collection(root: Path, n: int, devices: int, seed: int = 2024) -> tuple[list[Path], list[int]]:
    """Write ``n`` images of ``devices`` simulated cameras (as evenly as possible) as PNG files."""
    rng = np.random.default_rng(seed)
    model = sensor_model("A", SHAPE)
    counts = [n // devices + (1 if d < n % devices else 0) for d in range(devices)]
    paths, truth = [], []
    for d, count in enumerate(counts):
        shots = simulated_set(model.realize(rng, [0.0]), count, 0.0, int(rng.integers(2**31)), f"camera {d}")
        for i in range(count):
            paths.append(root / f"cam{d:03d}_{i:03d}.png")
            write_image(paths[-1], shots.load(i))
            truth.append(d)
    return paths, truth


class MemorySampler:
    """Peak resident memory of this process and of its descendants (the workers), sampled from /proc every
    0.2 s while a run lasts (``getrusage`` sees neither the fork server's children nor a per-run peak)."""

    def __init__(self) -> None:
        self.driver = 0.0
        self.worker = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def __enter__(self) -> MemorySampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def _loop(self) -> None:
        me = os.getpid()
        while True:
            parents = {}
            for entry in os.listdir("/proc"):
                if entry.isdigit():
                    try:
                        with open(f"/proc/{entry}/stat") as handle:
                            parents[int(entry)] = int(handle.read().rsplit(")", 1)[1].split()[1])
                    except (OSError, IndexError, ValueError):
                        continue
            for pid in parents:
                p = parents.get(pid)
                while p not in (None, 0, 1, me):
                    p = parents.get(p)
                if pid == me or p == me:
                    mb = _rss_mb(pid)
                    if pid == me:
                        self.driver = max(self.driver, mb)
                    else:
                        self.worker = max(self.worker, mb)
            if self._stop.wait(0.2):
                return


def _rss_mb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status") as handle:
            for line in handle:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def run(paths: list[Path], truth: list[int], workers: int, work: Path) -> dict[str, float]:
    executor = Executor("processes", workers=workers) if workers > 1 else Executor("in-process")
    with executor as ex, MemorySampler() as memory:
        start = time.perf_counter()
        result = cluster_images(paths, executor=ex, workdir=work)
        wall = time.perf_counter() - start
    seconds = result.parameters["seconds"]
    labels = result.labels
    return {"wall": wall, **seconds, "clusters": len(result.clusters), "unattributed": result.n_unattributed,
            "purity": purity(truth, labels), "completeness": completeness(truth, labels),
            "ari": adjusted_rand_index(truth, labels), "sigma_crop": result.groups[0].null.sigma * result.crop,
            "tau": result.groups[0].threshold_merge, "driver_mb": memory.driver, "worker_mb": memory.worker}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--images", type=int, default=1000)
    parser.add_argument("--devices", type=int, default=50)
    parser.add_argument("--workers", default="1,2", help="comma-separated worker counts (1 = in-process)")
    parser.add_argument("--dir", default=None, help="where to write the images (default: a temporary folder)")
    args = parser.parse_args()
    root = Path(args.dir) if args.dir else Path(tempfile.mkdtemp(prefix="bench-cluster-"))
    root.mkdir(parents=True, exist_ok=True)
    try:
        t0 = time.perf_counter()
        paths, truth = make_collection(root / "images", args.images, args.devices)
        n = len(paths)
        crop = SHAPE[0]
        print(f"{n} images of {SHAPE[1]}×{SHAPE[0]} from {args.devices} simulated cameras written in "
              f"{time.perf_counter() - t0:.1f} s; crop {crop}², blocks of {block_images(crop)} rows; residual store "
              f"{n * crop * crop * 4 / 2**30:.2f} GiB on disk (rows × crop² × 4 bytes)")
        print(f"{'workers':>7}  {'residuals s':>11}  {'ms/image':>8}  {'blocks s':>8}  {'µs/pair':>7}  "
              f"{'cluster s':>9}  {'wall s':>7}  {'driver MB':>9}  {'worker MB':>9}  clusters  unattr  purity  "
              "complete  ARI     σ·crop  τ")
        for workers in (int(w) for w in args.workers.split(",")):
            r = run(paths, truth, workers, root / f"work-{workers}")
            pairs = n * (n + 1) / 2
            print(f"{workers:>7}  {r['residuals']:>11.1f}  {1000 * r['residuals'] / n:>8.1f}  {r['similarity']:>8.1f}  "
                  f"{1e6 * r['similarity'] / pairs:>7.1f}  {r['clustering']:>9.2f}  {r['wall']:>7.1f}  "
                  f"{r['driver_mb']:>9.0f}  {r['worker_mb']:>9.0f}  "
                  f"{r['clusters']:>8}  {r['unattributed']:>6}  {r['purity']:>6.3f}  {r['completeness']:>8.3f}  "
                  f"{r['ari']:.3f}  {r['sigma_crop']:.3f}  {r['tau']:.2f}")
        print("memory: peak resident set during the run (driver: this process, with the blocks when in-process; "
              "worker: the largest worker process); mapped pages of the residual store count while read")
    finally:
        if not args.dir:
            shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
