"""Benchmark of PCE on a 6 MP pair (forensics.prnu.match.pce) against a plain float64 implementation.

Run::

    /work/main/.venv/bin/python benchmarks/bench_pce.py [--repeat N]

Cases, all on 2000×3008 float32 arrays (a residual with a weak copy of the
reference in it, so that there is a real peak):

* ``pce(a, b)`` zero shift (the default), 1 and 2 threads: real FFTs
  (``scipy.fft.rfft2``/``irfft2``) in float32, energy summed in float64;
* ``pce(a, b, shift_range=None)``: search over every circular shift (same FFTs,
  plus the arg-max);
* one reference spectrum reused for many fingerprints (what ``score_matrix`` does
  per query): the marginal cost of one more pair;
* ``score_query`` on a 6 MP RGB image: residual (σ = 2, full pipeline) + I·K + PCE;
* the plain float64 implementation: ``numpy.fft.fft2`` complex, ``ifft2``, real part,
  PCE at zero shift with an 11×11 exclusion.

Target: PCE of one 6 MP pair ≤ 0.5 s.
"""
from __future__ import annotations

import argparse
import os
import platform

import numpy as np

from _timing import timeit  # benchmarks/ is on sys.path when a script runs

from forensics.prnu.fingerprint import Fingerprint
from forensics.prnu.match import _pce_with, _Spectrum, pce, score_query

SHAPE = (2000, 3008)


def plain_pce(a: np.ndarray, b: np.ndarray, exclusion: int = 11) -> float:
    a = a.astype(np.float64) - a.mean()
    b = b.astype(np.float64) - b.mean()
    c = np.real(np.fft.ifft2(np.fft.fft2(a) * np.conj(np.fft.fft2(b))))
    r = exclusion // 2
    mask = np.ones(c.shape, bool)
    rows = np.arange(-r, r + 1) % c.shape[0]
    cols = np.arange(-r, r + 1) % c.shape[1]
    mask[np.ix_(rows, cols)] = False
    return float(np.sign(c[0, 0]) * c[0, 0] ** 2 / np.mean(c[mask] ** 2))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=7)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    b = rng.standard_normal(SHAPE, dtype=np.float32)
    a = 0.01 * b + rng.standard_normal(SHAPE, dtype=np.float32)
    mp = a.size / 1e6
    print(f"# PCE benchmark: {SHAPE[1]}x{SHAPE[0]} float32 pair = {mp:.2f} MP; python {platform.python_version()}, "
          f"numpy {np.__version__}, CPUs {os.cpu_count()}, load average {os.getloadavg()[0]:.2f}")
    rows = []
    results = {}
    for workers in (1, 2):
        best, med, r = timeit(lambda: pce(a, b, workers=workers), args.repeat)
        rows.append(("pce, zero shift", workers, best, med))
        results["fast"] = r
        best, med, r = timeit(lambda: pce(a, b, shift_range=None, workers=workers), args.repeat)
        rows.append(("pce, all circular shifts", workers, best, med))
        spectrum = _Spectrum(a, workers)
        best, med, _ = timeit(lambda: _pce_with(spectrum, b, 0, 11), args.repeat)
        rows.append(("pce with the query spectrum cached (score_matrix)", workers, best, med))
    best, med, slow = timeit(lambda: plain_pce(a, b), max(2, args.repeat // 3))
    rows.append(("plain float64 (numpy.fft complex)", 1, best, med))

    # score_query on a 6 MP RGB frame against a 6 MP fingerprint
    k = rng.normal(0, 0.01, SHAPE).astype(np.float32)
    scene = (110 + 40 * np.sin(np.arange(SHAPE[1]) / 200.0))[None, :] * np.ones((SHAPE[0], 1))
    grey = scene * (1 + k) + rng.normal(0, 2, SHAPE)
    image = np.clip(np.rint(np.stack([grey] * 3, axis=-1)), 0, 255).astype(np.uint8)
    fp = Fingerprint(K=k, region="full", sigma=3.0, files=[], n_images=0, frame_shape=SHAPE)
    for workers in (1, 2):
        best, med, score = timeit(lambda: score_query(fp, image, workers=workers), max(2, args.repeat // 2))
        rows.append(("score_query: residual + I·K + PCE (RGB frame)", workers, best, med))

    print("\n| case | threads | best s | median s |")
    print("|---|---|---|---|")
    for name, workers, best, med in rows:
        print(f"| {name} | {workers} | {best:.3f} | {med:.3f} |")
    print(f"\nPCE fast {results['fast'].pce:.4f} vs plain float64 {slow:.4f} "
          f"(relative difference {abs(results['fast'].pce - slow) / abs(slow):.1e}); "
          f"score_query PCE on the synthetic frame {score.value:.0f}")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
