#!/usr/bin/env python3
"""The model check's two inner kernels, side by side with the scipy calls they replace (issue 27, eighteenth session).

* the scene kernel (the 7 × 7 leave-one-out quadratic, :data:`forensics.check.scene.KERNEL`):
  ``scipy.ndimage.correlate`` against :func:`forensics.check.scene.correlate_kernel` (box and squared-offset sums
  along each axis), on frames of a tile (134²), the EMVA 1288 series (240 × 320) and 1 MP;
* the truncated readout mean's checked table: scipy's splines (``make_interp_spline``, ``RectBivariateSpline.ev``)
  against :func:`forensics.stats.censored.uniform_cubic` / :func:`~forensics.stats.censored.uniform_bicubic` on the
  same uniform grid, 76,800 values (one dark frame of the standard series).

Each pair is timed in the same process, best of several repeats, after the allocator has settled as it has in a
running check: glibc serves blocks above its mmap threshold (128 KB at first) by fresh mappings and trims its heap
above twice that, so in a fresh process every new temporary of a few hundred KB is page-faulted in again; freeing one
large array (16 MB; as the check does at once: its per-condition arrays are tens of MB) raises both thresholds for good
(:func:`settle_allocator`).  Without that step the sums measure the page faults (0.9–1.6× scipy, which allocates
nothing but its output).  The largest difference between the pair is printed beside the times.

Usage::

    .venv/bin/python benchmarks/bench_scene_kernel.py
"""
from __future__ import annotations

import sys
import timeit
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.interpolate import RectBivariateSpline, make_interp_spline

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from forensics.check.scene import KERNEL, correlate_kernel  # noqa: E402
from forensics.stats.censored import TABLE_STEP, readout_moments, uniform_bicubic, uniform_cubic  # noqa: E402


def settle_allocator() -> None:
    """Allocate and free one 16 MB array: glibc's dynamic mmap threshold rises to its size (a freed mapping above
    its cap of 32 MB would not move it) and the trim threshold to twice that, as in a running model check."""
    big = np.ones(2 * 2**20)
    big.sum()
    del big


def best(fn, number: int = 20, repeat: int = 7) -> float:
    """Best time of one call (s) over ``repeat`` runs of ``number`` calls."""
    return min(timeit.repeat(fn, number=number, repeat=repeat)) / number


def kernel_rows() -> list[str]:
    rows = []
    rng = np.random.default_rng(0)
    for shape in [(134, 134), (240, 320), (1000, 1000)]:
        img = rng.normal(1000.0, 30.0, shape)
        for mode in ("reflect", "constant"):
            want = ndimage.correlate(img, KERNEL, mode=mode)
            got = correlate_kernel(img, mode)
            n = 3 if shape[0] > 500 else 20
            for _ in range(2):  # warm-up: the allocator keeps the temporaries' pages
                correlate_kernel(img, mode), ndimage.correlate(img, KERNEL, mode=mode)
            t_scipy = best(lambda: ndimage.correlate(img, KERNEL, mode=mode), n)
            t_ours = best(lambda: correlate_kernel(img, mode), n)
            rows.append(f"| {shape[0]} × {shape[1]} | {mode} | {t_scipy * 1e3:.3f} | {t_ours * 1e3:.3f} | "
                        f"{t_scipy / t_ours:.2f}× | {np.max(np.abs(got - want)):.1e} |")
    return rows


def table_rows() -> list[str]:
    rows = []
    rng = np.random.default_rng(1)
    n = 76_800
    mu = rng.uniform(1.0, 3.0, n)
    for label, sigma in (("one σ", np.full(n, 0.45)), ("σ 0.43–0.52", rng.uniform(0.43, 0.52, n))):
        s_lo, s_hi = float(sigma.min()), float(sigma.max())
        h = TABLE_STEP * s_lo  # the grid tabulated_truncated_mean builds
        grid = np.arange(float(mu.min()) - 2 * h, float(mu.max()) + 3 * h, h)
        if s_hi - s_lo < 1e-9:
            table = readout_moments(grid, s_lo, 0, 4095, truncate=True, closed_form=False)[0]
            spline = make_interp_spline(grid, table, k=3)
            t_scipy = best(lambda: spline(mu))
            t_ours = best(lambda: uniform_cubic(float(grid[0]), h, table, mu))
            diff = np.max(np.abs(spline(mu) - uniform_cubic(float(grid[0]), h, table, mu)))
        else:
            k = max(int(np.ceil((s_hi - s_lo) / h)) + 1, 4)
            hs = (s_hi - s_lo) / (k - 1)
            gs = s_lo + hs * np.arange(-1, k + 1)
            table = readout_moments(grid[:, None], gs[None, :], 0, 4095, truncate=True, closed_form=False)[0]
            spline = RectBivariateSpline(grid, gs, table, kx=3, ky=3, s=0)
            t_scipy = best(lambda: spline.ev(mu, sigma))
            t_ours = best(lambda: uniform_bicubic((float(grid[0]), float(gs[0])), (h, hs), table, mu, sigma))
            diff = np.max(np.abs(spline.ev(mu, sigma)
                                 - uniform_bicubic((float(grid[0]), float(gs[0])), (h, hs), table, mu, sigma)))
        rows.append(f"| {label} | {t_scipy * 1e3:.3f} | {t_ours * 1e3:.3f} | {t_scipy / t_ours:.2f}× | {diff:.1e} |")
    return rows


def main() -> None:
    settle_allocator()
    print("| frame | mode | ndimage.correlate ms | correlate_kernel ms | speed-up | max difference |")
    print("|---|---|---|---|---|---|")
    print("\n".join(kernel_rows()))
    print()
    print("| 76,800 values, table of the truncated mean | scipy spline ms | local cubic ms | speed-up "
          "| max difference DN |")
    print("|---|---|---|---|---|")
    print("\n".join(table_rows()))


if __name__ == "__main__":
    main()
