"""Benchmark: age N images of 640×480 8-bit over 13 time steps, against the I/O floor.

The I/O floor reads every source image once and writes it 13 times unchanged
(exactly the I/O the ageing must do).  The plain implementation follows the
paper's pseudo-code literally: dense D and C matrices per step, updated
defect by defect, then ``np.where`` over the whole image.

Run:  .venv/bin/python benchmarks/bench_ageing.py --images 1000
"""
from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from forensics.io.dataset import open_dataset
from forensics.io.images import read_image, write_image
from forensics.sensor.presets import preset
from forensics.sensor.simulate import age_dataset, make_scenes, parse_years

SHAPE = (480, 640)


def io_floor(src, out: Path, steps: int) -> float:
    start = time.perf_counter()
    for s in range(steps):
        (out / f"s{s}").mkdir(parents=True)
    for frame in src:
        image = read_image(frame.path)
        for s in range(steps):
            write_image(out / f"s{s}" / frame.file, image)
    return time.perf_counter() - start


def plain_ageing(src, out: Path, ages, lam_ps: float, a_ps: float, seed: int) -> float:
    """The paper's AGEDIMAGESEQUENCE, written as plainly as possible (deterministic counts)."""
    start = time.perf_counter()
    rng = np.random.default_rng(seed)
    h, w = SHAPE
    mp = h * w / 1e6
    D = [np.zeros(SHAPE)]
    C = [np.zeros(SHAPE)]
    for i in range(1, len(ages)):
        dn = round(lam_ps * mp * ages[i]) - round(lam_ps * mp * ages[i - 1])
        d = D[-1].copy()
        for _ in range(dn):
            d[rng.integers(h), rng.integers(w)] = rng.random() * a_ps
        D.append(d)
        C.append(C[-1].copy())
    for i in range(len(ages)):
        (out / f"s{i}").mkdir(parents=True)
    for frame in src:
        y0 = read_image(frame.path).astype(float)
        for i in range(len(ages)):
            y = np.where(C[i] != 0, C[i], y0 + D[i])
            write_image(out / f"s{i}" / frame.file, np.clip(np.rint(y), 0, 255).astype(np.uint8))
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--images", type=int, default=1000)
    parser.add_argument("--sensor", default="A")
    args = parser.parse_args()
    ages = parse_years("0:96:8")
    with tempfile.TemporaryDirectory(prefix="bench-ageing-") as tmp:
        tmp = Path(tmp)
        print(f"generating {args.images} source images of {SHAPE[1]}×{SHAPE[0]} …", flush=True)
        src = make_scenes(tmp / "src", args.images, SHAPE, rng=1, kind="texture")
        src = open_dataset(tmp / "src")
        n_out = args.images * len(ages)
        t_floor = io_floor(src, tmp / "floor", len(ages))
        shutil.rmtree(tmp / "floor")
        model = preset(args.sensor, SHAPE)
        start = time.perf_counter()
        age_dataset(src, tmp / "aged", model, ages, rng=2, start_year=2000.0, sensor_name=args.sensor)
        t_age = time.perf_counter() - start
        shutil.rmtree(tmp / "aged")
        growth = model.effect("growth")
        t_plain = plain_ageing(src, tmp / "plain", ages, growth.rate_partial, growth.amp_partial, seed=2)
    print(f"\n{args.images} images × {len(ages)} steps = {n_out} images written")
    print(f"{'':24} {'seconds':>8} {'images/s':>9} {'× I/O floor':>12}")
    for name, t in (("I/O floor (read+write)", t_floor), ("forensics age_dataset", t_age), ("plain (paper literal)", t_plain)):
        print(f"{name:24} {t:8.1f} {n_out / t:9.0f} {t / t_floor:12.2f}")


if __name__ == "__main__":
    main()
