#!/usr/bin/env python3
"""The issue-27 row "24 MP × 20 frames runs whole, memory as at 12 MP", with frames the EMVA simulator can make.

emva1288's ``Camera`` keeps a per-pixel spectral quantum efficiency (≈ 1 KB per pixel), so simulating a 24 MP
frame needs ≈ 24 GB: on this 24 GiB machine ``bench_check_emva.py --sizes 24MP`` was killed by the kernel's OOM
killer at 24.3 GB while writing the first frame.  Here the 24 MP frames (3000 × 8000) are the 12 MP simulator
frames (``bench_check_emva.py --sizes 12MP`` writes them) beside their own mirror image: every pixel is a real
simulator pixel, but the right half repeats the left one, so the combined estimates' standard errors are
optimistic by √2 — this run measures time and memory, not accuracy.  The 20 frames: every frame at 20 °C (3
exposures × dark + 2 flats × 2 repeats) and the two darks of the shortest exposure at 36 °C.

    .venv/bin/python benchmarks/large_24mp_stitched.py --source /tmp/bce/large-12MP --out /tmp/bce/large-24MP-stitched
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def stitch(source: Path, out: Path) -> int:
    from forensics.io.images import read_image, write_image

    out.mkdir(parents=True, exist_ok=False)
    with open(source / "manifest.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    t_min = min(float(r["exposure_s"]) for r in rows)
    keep = [r for r in rows if float(r["temperature_c"]) == 20.0
            or (r["subject"] == "dark" and float(r["exposure_s"]) == t_min)]
    for r in keep:
        frame = read_image(source / r["file"])
        write_image(out / r["file"], np.ascontiguousarray(np.concatenate([frame, frame[:, ::-1]], axis=1)))
    with open(out / "manifest.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(keep)
    return len(keep)


def main() -> int:
    from bench_check_emva import forensics_auto, path_summary

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--source", type=Path, required=True, help="the 12 MP folder of bench_check_emva.py")
    parser.add_argument("--out", type=Path, required=True, help="the 24 MP folder to write (must not exist)")
    parser.add_argument("--tiles", type=int, default=128)
    parser.add_argument("--timeout", type=float, default=5400.0)
    parser.add_argument("--json", help="also write the run's figures to this file")
    args = parser.parse_args()
    n = stitch(args.source, args.out)
    run = forensics_auto(args.out, args.timeout, ["--tiles", str(args.tiles)])
    print(f"| 24 MP (3000 × 8000, stitched) × {n}, --auto --tiles {args.tiles} | wall {run['wall']:.0f} s | "
          f"peak {run['rss_mb']:.0f} MB (check and workers) | load {run['load_before']:.1f} → {run['load_after']:.1f} | "
          f"{path_summary(run['result'])} |")
    if args.json:
        Path(args.json).write_text(json.dumps(run, default=str))
    return 0 if run["rc"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
