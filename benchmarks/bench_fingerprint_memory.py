"""Peak memory and time of building a 6 MP fingerprint from many images, streamed.

Run::

    /work/main/.venv/bin/python benchmarks/bench_fingerprint_memory.py [--counts 50 200] [--naive 2 6]

Each measurement runs in a fresh child process (``--child``) that generates
3008×2000 RGB uint8 frames on the fly (smooth shading with random phase and
exposure × a 1 % PRNU, fresh noise per frame, all in reused buffers) and feeds them
one by one to :class:`forensics.prnu.fingerprint.FingerprintBuilder`.  The child
reports its peak resident set size (``resource.getrusage(...).ru_maxrss``), its
RSS before the first frame (interpreter, libraries, frame generator) and its time
per frame.  Target: peak ≤ 0.5 GB and the same for 50 and 200 frames.

For comparison, the plain float64 approach of the public NumPy port, which keeps
every residual and intensity in memory and applies the batch formula at the end,
is run for a few frames (``--naive``): its peak grows by ≈ 96 MB per 6 MP frame,
so 200 frames would need ≈ 19 GB.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np

SHAPE = (2000, 3008)


def frames(n: int, seed: int = 0):
    """n synthetic 6 MP frames, generated one at a time into the same buffers (≈ 80 MB in all).

    Each frame: a smooth shading with a random phase and exposure, times the
    sensor's (1 + k) with k ~ N(0, 1 %) (kept as float16), a colour tint per
    channel, plus N(0, 2) noise; rounded to uint8.
    """
    rng = np.random.default_rng(seed)
    h, w = SHAPE
    one_plus_k = (1 + rng.normal(0, 0.01, SHAPE)).astype(np.float16)
    y = np.arange(h, dtype=np.float32)[:, None]
    x = np.arange(w, dtype=np.float32)[None, :]
    scene = np.empty(SHAPE, np.float32)
    noise = np.empty(SHAPE, np.float32)
    frame = np.empty(SHAPE + (3,), np.uint8)
    tint = (0.9, 1.0, 0.8)
    for _ in range(n):
        phase = rng.uniform(0, 2 * np.pi, 2).astype(np.float32)
        np.multiply(np.sin(y / 300 + phase[0]), np.cos(x / 400 + phase[1]), out=scene)
        scene *= 25
        scene += np.float32(rng.uniform(100, 140))
        np.multiply(scene, one_plus_k, out=scene)
        for c in range(3):
            rng.standard_normal(out=noise, dtype=np.float32)
            noise *= np.float32(2.0 / tint[c])
            noise += scene
            noise *= np.float32(tint[c])
            np.rint(noise, out=noise)
            np.clip(noise, 0, 255, out=noise)
            frame[..., c] = noise
        yield frame


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kB


def child(mode: str, n: int, workers: int) -> dict:
    from forensics.prnu.fingerprint import FingerprintBuilder, postprocess, region_residual_and_intensity

    gen = frames(n)
    first = next(gen)
    before = rss_mb()
    elapsed = 0.0  # time in the estimator only, not in the frame generator
    if mode == "stream":
        builder = FingerprintBuilder(workers=workers)
        for f in [first] if n == 1 else _chain(first, gen):
            t0 = time.perf_counter()
            builder.add(f)
            elapsed += time.perf_counter() - t0
        t0 = time.perf_counter()
        k = builder.result().K
        final = time.perf_counter() - t0
    else:  # naive: keep everything in float64, batch formula at the end
        ws, is_ = [], []
        for f in _chain(first, gen):
            t0 = time.perf_counter()
            w, i = region_residual_and_intensity(f, "full", 3.0, workers=workers)
            ws.append(w.astype(np.float64))
            is_.append(i.astype(np.float64))
            elapsed += time.perf_counter() - t0
        t0 = time.perf_counter()
        w = np.stack(ws)
        i = np.stack(is_)
        k = postprocess((w * i).sum(0) / (i * i).sum(0), "full", SHAPE)
        final = time.perf_counter() - t0
    return {"mode": mode, "n": n, "rss_before_mb": before, "peak_mb": rss_mb(),
            "s_per_frame": elapsed / n, "final_s": final, "k_std": float(np.std(k))}


def _chain(first, rest):
    yield first
    yield from rest


def run_child(mode: str, n: int, workers: int) -> dict:
    out = subprocess.run([sys.executable, __file__, "--child", mode, str(n), str(workers)],
                         check=True, capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[50, 200])
    parser.add_argument("--naive", type=int, nargs="*", default=[2, 6])
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--child", nargs=3, metavar=("MODE", "N", "WORKERS"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        mode, n, workers = args.child
        print(json.dumps(child(mode, int(n), int(workers))))
        return
    print(f"# fingerprint memory benchmark: {SHAPE[1]}x{SHAPE[0]} RGB uint8 frames, workers={args.workers}, "
          f"load average {os.getloadavg()[0]:.2f}")
    print("\n| implementation | frames | RSS before 1st frame (MB) | peak RSS (MB) | growth (MB) | s/frame | final step s |")
    print("|---|---|---|---|---|---|---|")
    for mode, counts in (("stream", args.counts), ("naive", args.naive)):
        for n in counts:
            r = run_child(mode, n, args.workers)
            name = "FingerprintBuilder (streaming)" if mode == "stream" else "plain float64, all in memory"
            print(f"| {name} | {n} | {r['rss_before_mb']:.0f} | {r['peak_mb']:.0f} | "
                  f"{r['peak_mb'] - r['rss_before_mb']:.0f} | {r['s_per_frame']:.2f} | {r['final_s']:.2f} |", flush=True)
    print(f"\nload average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
