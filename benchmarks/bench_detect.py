"""Detection streams images at close to reading speed.

    .venv/bin/python benchmarks/bench_detect.py --workdir /tmp/bench_detect [--small 1000] [--large 50]

Writes (once; reused when present) K = 1000 grey 8-bit PNGs of 640×480 and
K = 50 grey 16-bit TIFFs (zip) of 6000×4000 (24 MP), then measures in one run,
alternating, the time to read every image (Dataset.images, decode only) and the
time of `forensics.defects.detection.detect_dataset` on the same files (streaming stack
statistics with decoding in a background thread, then the q = 9 median, fit
and thresholds).  Each is measured twice after a warm-up read (files in the
page cache); the best times and their ratio are printed.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from forensics.io.dataset import open_dataset, write_manifest  # noqa: E402
from forensics.defects.detection import MaskSpec, detect_dataset  # noqa: E402
from forensics.io.images import write_image  # noqa: E402
from forensics.sensor.scenes import pink_texture  # noqa: E402


def make_set(folder: Path, n: int, shape: tuple[int, int], bits: int, ext: str) -> None:
    if (folder / "manifest.csv").exists():
        return
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    full = 2**bits - 1
    bases = [np.clip(0.5 + 0.15 * pink_texture(shape, rng), 0, 1) * full for _ in range(4)]
    rows = []
    for i in range(n):
        img = bases[i % 4] + rng.normal(0, full * 0.004, shape)
        img = np.clip(np.rint(img), 0, full).astype(np.uint8 if bits == 8 else np.uint16)
        name = f"img_{i:04d}{ext}"
        write_image(folder / name, img, force=True)
        rows.append({"file": name, "captured": 2010.0, "device": "bench"})
    write_manifest(folder / "manifest.csv", rows, force=True)


def read_all(ds) -> None:
    for _ in ds.images():
        pass


def cpu() -> float:
    import resource

    a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime


def measure(ds, repeat: int) -> tuple[float, float, float, float]:
    read_all(ds)  # warm the page cache
    reads, dets = [], []
    for _ in range(repeat):
        t, c = time.perf_counter(), cpu()
        read_all(ds)
        reads.append((time.perf_counter() - t, cpu() - c))
        t, c = time.perf_counter(), cpu()
        detect_dataset(ds, mask=MaskSpec("centre"))
        dets.append((time.perf_counter() - t, cpu() - c))
    r, d = min(reads), min(dets)
    return r[0], d[0], r[1], d[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workdir", default="/tmp/bench_detect")
    ap.add_argument("--small", type=int, default=1000)
    ap.add_argument("--large", type=int, default=50)
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    work = Path(args.workdir)
    print(f"cpus: {os.cpu_count()}, load average before: {os.getloadavg()[0]:.2f}")
    cases = []
    if args.small:
        make_set(work / "small", args.small, (480, 640), 8, ".png")
        cases.append((f"K = {args.small}, 640×480 8-bit PNG", work / "small"))
    if args.large:
        make_set(work / "large", args.large, (4000, 6000), 16, ".tif")
        cases.append((f"K = {args.large}, 6000×4000 (24 MP) 16-bit TIFF", work / "large"))
    for label, folder in cases:
        ds = open_dataset(folder)
        read, det, read_cpu, det_cpu = measure(ds, args.repeat)
        print(f"{label}: wall: read {read:.2f} s, detect {det:.2f} s, ratio {det / read:.2f}; "
              f"CPU: read {read_cpu:.2f} s, detect {det_cpu:.2f} s")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
