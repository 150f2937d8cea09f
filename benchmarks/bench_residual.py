"""Benchmark of the PRNU noise residual (forensics.prnu.residual.wavelet_residual) on a 6 MP image.

Run::

    /work/main/.venv/bin/python benchmarks/bench_residual.py [--repeat N] [--oracle-repeat M]

A synthetic 3008×2000 RGB uint8 image (shading, edges, fine texture, 1 % PRNU,
noise) goes through

* the fast pipeline, stage by stage and whole, with 1 and 2 threads;
* the plain float64 implementation of the same algorithm (the test oracle in
  ``tests/test_residual.py``: ``pywt.wavedec2``, ``ndimage.uniform_filter``,
  complex ``fft2``), which is what the public NumPy port does.

Times are wall clock (``time.perf_counter``), best and median of the repeats;
the machine's load average is printed because other processes share the CPUs.
Target: ≤ 0.15 s per megapixel on 2 cores.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

import numpy as np

from _timing import timeit  # benchmarks/ is on sys.path when a script runs
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "prnu"))
from test_residual import oracle_residual  # noqa: E402  (the float64 oracle)

from forensics.prnu import residual as R  # noqa: E402
from forensics._shared.arrays import grey_luma  # noqa: E402

SHAPE = (2000, 3008)


def make_image(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    h, w = SHAPE
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    scene = 110 + 50 * np.sin(xx / 137.0) * np.cos(yy / 83.0) + 25 * ((xx // 240 + yy // 180) % 2)
    scene += ndimage.gaussian_filter(rng.normal(0, 20, SHAPE).astype(np.float32), 1.5)
    k = rng.normal(0, 0.01, SHAPE).astype(np.float32)
    grey = scene * (1 + k)
    rgb = np.stack([0.9 * grey, grey, 0.8 * grey], axis=-1) + rng.normal(0, 2, (h, w, 3)).astype(np.float32)
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--oracle-repeat", type=int, default=2)
    args = parser.parse_args()

    image = make_image()
    mp = image.shape[0] * image.shape[1] / 1e6
    print(f"# residual benchmark: {image.shape[1]}x{image.shape[0]} RGB uint8 = {mp:.2f} MP; "
          f"python {platform.python_version()}, numpy {np.__version__}, CPUs {os.cpu_count()}, "
          f"load average {os.getloadavg()[0]:.2f}")
    rows = []
    for workers in (1, 2):
        h, w = SHAPE
        top, bottom = R._pad_sizes(h, 16)
        left, right = R._pad_sizes(w, 16)
        buf = np.empty((h + top + bottom, w + left + right), np.float32)

        def grey_pad() -> np.ndarray:
            grey_luma(image, out=buf[top : top + h, left : left + w])
            R._mirror_edges(buf, top, bottom, left, right)
            return buf

        b, m, _ = timeit(grey_pad, args.repeat)
        rows.append((f"grey + mirror pad", workers, b, m))
        b, m, noise = timeit(lambda: R.wavelet_noise(buf, 3.0, workers=workers), args.repeat)
        rows.append(("wavelet denoising (db4, 4 levels, Mihcak)", workers, b, m))
        crop = np.ascontiguousarray(noise[top : top + h, left : left + w])
        b, m, _ = timeit(lambda: R.zero_mean_cfa(crop), args.repeat)
        rows.append(("zero mean (4 CFA sub-lattices)", workers, b, m))
        b, m, _ = timeit(lambda: R.wiener_dft(crop, workers=workers), args.repeat)
        rows.append(("Wiener filter in the DFT domain", workers, b, m))
        b, m, fast = timeit(lambda: R.wavelet_residual(image, 3.0, workers=workers), args.repeat)
        rows.append(("whole wavelet_residual", workers, b, m))
    b, m, slow = timeit(lambda: oracle_residual(image, 3.0), args.oracle_repeat)
    rows.append(("plain float64 implementation (oracle)", 1, b, m))

    print(f"\n| stage | threads | best s | median s | best s/MP |")
    print("|---|---|---|---|---|")
    for name, workers, best, med in rows:
        print(f"| {name} | {workers} | {best:.3f} | {med:.3f} | {best / mp:.3f} |")
    a = fast.astype(np.float64).ravel()
    c = slow.ravel()
    a -= a.mean()
    c = c - c.mean()
    r = float(a @ c / np.sqrt((a @ a) * (c @ c)))
    print(f"\ncorrelation fast vs float64 oracle: {r:.9f}; max |diff| / max |oracle|: "
          f"{np.abs(fast - slow).max() / np.abs(slow).max():.2e}")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
