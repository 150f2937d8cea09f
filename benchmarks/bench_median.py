"""The exact q×q median on a 24 MP mean image: the comparator network vs scipy.ndimage.median_filter.

    .venv/bin/python benchmarks/bench_median.py [--q 9] [--repeat 3]

Checks that the network equals scipy exactly (on a crop, and on the full image
at --full), then times it on the whole 4000×6000 float32 image with 1 and 2
threads, and scipy on a quarter of the image (extrapolated ×4).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from forensics._shared.filters import median_filter  # noqa: E402


def mean_like(shape, rng):
    """A mean image: smooth scene + noise of the mean of K frames, quantised to 1/K."""
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float32)
    img = 2000 + 800 * np.sin(xx / 700) * np.cos(yy / 500) + rng.normal(0, 3, shape).astype(np.float32)
    return (np.rint(img * 50) / 50).astype(np.float32)


def cpu() -> float:
    """CPU seconds of this process, its threads and its waited-for children."""
    import resource

    a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime


def best(fn, repeat):
    times, cpus = [], []
    for _ in range(repeat):
        t, c = time.perf_counter(), cpu()
        fn()
        times.append(time.perf_counter() - t)
        cpus.append(cpu() - c)
    i = int(np.argmin(times))
    return times[i], times, cpus[i]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--q", type=int, default=9)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--full", action="store_true", help="also compare with scipy on the full image (slow)")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    img = mean_like((4000, 6000), rng)
    crop = img[:500, :700]
    assert np.array_equal(median_filter(crop, args.q), ndimage.median_filter(crop, args.q, mode="reflect"))
    print(f"cpus: {os.cpu_count()}, load average before: {os.getloadavg()[0]:.2f}")
    print(f"q = {args.q}, image 4000×6000 float32 (24 MP); network == scipy on a 500×700 crop: True")
    for workers in (1, 2):
        t, all_t, c = best(lambda: median_filter(img, args.q, threads=workers), args.repeat)
        print(f"network, {workers} worker(s): best {t:.2f} s wall of {[round(x, 2) for x in all_t]}, "
              f"{c:.2f} s CPU")
    quarter = img[:1000]
    t, _, _ = best(lambda: ndimage.median_filter(quarter, args.q, mode="reflect"), 1)
    print(f"scipy.ndimage.median_filter on 1000×6000: {t:.2f} s → ≈ {4 * t:.1f} s for 24 MP")
    if args.full:
        same = np.array_equal(median_filter(img, args.q), ndimage.median_filter(img, args.q, mode="reflect"))
        print(f"network == scipy on the full 24 MP image: {same}")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
