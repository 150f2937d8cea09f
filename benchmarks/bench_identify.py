"""Benchmark of 1:N identification (forensics.prnu.identify): N queries against M fingerprints at ~1 MP.

Run::

    /work/main/.venv/bin/python benchmarks/bench_identify.py [--queries 1000] [--fingerprints 100]
        [--size 1024] [--workers 2] [--outside 0.2] [--runs full,prescreen]

Data (synthetic, nothing on disk): M devices with a PRNU pattern ``K ~ N(0, σ_k²)`` (σ_k = 0.5 %); each
fingerprint is ``K`` plus estimation noise of the size a ~20-image fingerprint has; each query is a smooth
scene times ``(1 + K)`` plus sensor noise, rendered by the worker that scores it (a picklable
``load()`` object, as a dataset frame would be), of a device in the set or — a fraction ``--outside`` —
of a device that is not.

Reported, for the full PCE against every fingerprint and for the pre-screen (sketch n/4, keep
max(10, 10 %)):

* wall time, queries per second, and the time per query per fingerprint;
* peak memory: this process (it holds the fingerprints) and the largest worker (``ru_maxrss``);
* attributions, false attributions (queries of devices outside the set), the true devices' PCE;
* the pre-screen's miss rate on the queries whose device is in the set, with its 95 % Clopper–Pearson
  interval (:func:`forensics.prnu.identify.prescreen_miss_rate`), measured, not assumed.
"""
from __future__ import annotations

import argparse
import os
import platform
import resource
import threading
import time
from dataclasses import dataclass
from typing import Self

import numpy as np
from scipy import ndimage

from forensics._shared.parallel import open_executor
from forensics.prnu.fingerprint import Fingerprint
from forensics.prnu.identify import Prescreen, identify, prescreen_miss_rate

SIGMA_K = 0.005
#: Estimation noise of the fingerprint relative to σ_k, and the queries' scene texture and noise: chosen so
#: that a matching 1 MP query has a PCE of about 250, typical of a natural photograph against a fingerprint
#: of 20–50 images (the Dresden natural images against 10-flat fingerprints: 27–7400, median ≈ 800).
ESTIMATION_NOISE = 4.0
SCENE_BLUR, SENSOR_NOISE = 1.5, 6.0


def pattern(device: int, shape: tuple[int, int]) -> np.ndarray:
    """Device ``device``'s PRNU (the truth)."""
    return np.random.default_rng([7, device]).normal(0.0, SIGMA_K, shape).astype(np.float32)


def fingerprint(device: int, shape: tuple[int, int]) -> Fingerprint:
    k = pattern(device, shape) + np.random.default_rng([8, device]).normal(0.0, ESTIMATION_NOISE * SIGMA_K, shape)
    return Fingerprint(k.astype(np.float32), "full", 3.0, [], 20, shape)


@dataclass(frozen=True)
class SimQuery:
    """A query image rendered on demand (like a dataset frame: picklable, read where it is scored)."""

    device: int
    index: int
    shape: tuple[int, int]

    @property
    def file(self) -> str:
        return f"device{self.device}_{self.index}"

    def load(self) -> np.ndarray:
        rng = np.random.default_rng([9, self.device, self.index])
        scene = ndimage.gaussian_filter(rng.normal(0.0, 1.0, self.shape), SCENE_BLUR)
        scene = 120 + 40 * scene / scene.std()
        image = scene * (1 + pattern(self.device, self.shape)) + rng.normal(0.0, SENSOR_NOISE, self.shape)
        return np.clip(np.rint(image), 0, 255).astype(np.uint8)


class MemorySampler:
    """Peak resident memory (MB) of the worker processes, sampled every 0.2 s while a run lasts.

    Workers are children of the fork server, not of this process, so ``RUSAGE_CHILDREN`` does not see
    them; ``psutil`` walks the process tree instead (none reported without psutil).
    """

    def __init__(self) -> None:
        self.peak = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        try:
            import psutil
        except ImportError:
            return
        me = psutil.Process()
        while not self._stop.wait(0.2):
            for child in me.children(recursive=True):
                try:
                    self.peak = max(self.peak, child.memory_info().rss / 2**20)
                except psutil.Error:
                    pass

    def __enter__(self) -> Self:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def driver_peak_mb() -> float:
    """Peak resident memory (MB) of this process (it holds the fingerprints)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--queries", type=int, default=1000)
    parser.add_argument("--fingerprints", type=int, default=100)
    parser.add_argument("--size", type=int, default=1024, help="side of the square frames (default 1024: 1 MP)")
    parser.add_argument("--workers", type=int, default=None, help="worker processes (default: every core)")
    parser.add_argument("--outside", type=float, default=0.2, help="fraction of queries from devices not in the set")
    parser.add_argument("--runs", default="full,prescreen",
                        help="comma-separated runs: full (PCE against every fingerprint), prescreen (sketch first)")
    args = parser.parse_args()
    runs = {"full": ("full PCE", None), "prescreen": ("pre-screen", Prescreen())}
    chosen = [r.strip() for r in args.runs.split(",") if r.strip()]
    if not chosen or any(r not in runs for r in chosen):
        parser.error(f"--runs {args.runs!r}: choose from {', '.join(runs)}")
    shape = (args.size, args.size)
    rng = np.random.default_rng(0)
    m, n = args.fingerprints, args.queries
    outside = rng.random(n) < args.outside
    devices = np.where(outside, m + np.arange(n), rng.integers(0, m, n))
    queries = [SimQuery(int(d), i, shape) for i, d in enumerate(devices)]
    truth = [None if o else f"dev{d:04d}" for d, o in zip(devices, outside)]
    t0 = time.perf_counter()
    fps = [(f"dev{j:04d}", fingerprint(j, shape)) for j in range(m)]
    t_fp = time.perf_counter() - t0
    print(f"# identification benchmark: {n} queries against {m} fingerprints of {shape[1]}x{shape[0]} "
          f"({shape[0] * shape[1] / 1e6:.2f} MP), {outside.sum()} queries of devices outside the set; "
          f"python {platform.python_version()}, numpy {np.__version__}, CPUs {os.cpu_count()}, "
          f"load average {os.getloadavg()[0]:.2f}; fingerprints made in {t_fp:.1f} s")
    print("| run | workers | wall s | queries/s | ms per query·fingerprint | attributed | false | "
          "median true PCE | peak MB (driver / worker) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for label, pre in (runs[r] for r in chosen):
        with open_executor(args.workers) as ex, MemorySampler() as memory:
            t0 = time.perf_counter()
            result = identify(queries, fps, prescreen=pre, executor=ex)
            wall = time.perf_counter() - t0
            workers = ex.workers if ex.backend != "in-process" else 1
        attributed = sum(q.attributed for q in result.queries)
        false = sum(q.attributed and q.device_id != t for q, t in zip(result.queries, truth))
        true_pce = [c.pce for q, t in zip(result.queries, truth) if t for c in q.top if c.device_id == t]
        print(f"| {label} | {workers} | {wall:.1f} | {n / wall:.2f} | {1000 * wall * workers / (n * m):.2f} | "
              f"{attributed} | {false} | {np.median(true_pce) if true_pce else float('nan'):.0f} | "
              f"{driver_peak_mb():.0f} / {memory.peak:.0f} |")
    inside = [q for q, t in zip(queries, truth) if t]
    with open_executor(args.workers) as ex:
        t0 = time.perf_counter()
        miss = prescreen_miss_rate(inside, [t for t in truth if t], fps, Prescreen(), executor=ex)
        wall = time.perf_counter() - t0
    print(f"\npre-screen (sketch length {miss.dim}, keep {miss.keep} of {miss.n_fingerprints}): true device dropped "
          f"for {miss.missed} of {miss.n} queries, miss rate {100 * miss.rate:.2f} % "
          f"[95 % CI {100 * miss.ci[0]:.2f}, {100 * miss.ci[1]:.2f}]; lowest true-device sketch z "
          f"{min(miss.scores):.1f}; sketch stage alone {wall:.1f} s")


if __name__ == "__main__":
    main()
