"""Interval coverage of the model check on cameras simulated by the EMVA 1288 reference implementation
(issue 9 item 5): conversion gain, read noise, dark current and its doubling temperature, ISO exponent,
black level, dark offset.

Each camera is a photon-transfer series from ``emva1288.camera.Camera`` (:func:`forensics.fixtures.emva.
make_emva_series`; its own DSNU and PRNU maps and noise seed), checked with the effects the simulator has
(``dark_current gain shot_noise input_noise dsnu prnu``).  A parameter's 95 % interval is value ± 1.96 SE;
its coverage is the fraction of cameras whose interval holds the truth (:func:`forensics.fixtures.emva.
model_truth`).  With 50 cameras a true 95 % coverage reads 0.90–0.99 with probability 0.95.

Run::

    .venv/bin/python benchmarks/coverage_emva.py --cameras 50 --shape 48x64 --out benchmarks/coverage_emva.json
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from forensics.check import check
from forensics.fixtures.emva import EmvaDesign, make_emva_series, model_truth

EFFECTS = ["dark_current", "gain", "shot_noise", "input_noise", "dsnu", "prnu"]
COMPARED = ["shot_noise.g", "input_noise.sigma_in", "dark_current.rate", "dark_current.t_double", "gain.exponent",
            "black_level.level", "dark_current.offset"]


def camera_estimates(seed: int, design: EmvaDesign, work: Path) -> dict[str, dict[str, float | None]]:
    """Check one simulated camera; the compared parameters' values and standard errors."""
    data = make_emva_series(work / f"cam{seed}", rng=seed, design=design)
    result = check(data, add=EFFECTS, rng=seed, baseline=False)
    out = {}
    for p in result.params:
        if p.label in COMPARED:
            out[p.label] = {"value": float(p.value), "se": p.se, "converged": bool(p.converged)}
    err = result.error.get("pixel")
    out["_error_pixel"] = {"value": None if err is None else float(err)}
    out["_flagged"] = {"value": ",".join(result.flagged)}
    return out


def coverage(rows: list[dict], truth: dict[str, float], z: float = 1.959964) -> dict[str, dict[str, float]]:
    """Per parameter: cameras with an interval, the fraction covering the truth, mean (value − truth)/SE."""
    out = {}
    for name in COMPARED:
        zs = [(r[name]["value"] - truth[name]) / r[name]["se"] for r in rows
              if name in r and r[name]["se"] and r[name]["converged"]]
        if zs:
            zs_a = np.array(zs)
            out[name] = {"n": len(zs), "coverage": float(np.mean(np.abs(zs_a) <= z)), "mean_z": float(zs_a.mean()),
                         "sd_z": float(zs_a.std(ddof=1)) if len(zs) > 1 else math.nan}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cameras", type=int, default=50)
    ap.add_argument("--shape", default="48x64", help="HEIGHTxWIDTH of the frames")
    ap.add_argument("--out", type=Path, default=None, help="write the per-camera rows and the coverage as JSON")
    args = ap.parse_args(argv)
    h, w = (int(v) for v in args.shape.split("x"))
    design = replace(EmvaDesign(), shape=(h, w))
    truth = model_truth(design)
    rows = []
    t0 = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.cameras):
            rows.append(camera_estimates(seed, design, Path(tmp)))
            print(f"camera {seed}: {time.time() - t0:.0f} s", file=sys.stderr, flush=True)
    cov = coverage(rows, truth)
    print(f"{args.cameras} cameras of {h}×{w}, {time.time() - t0:.0f} s")
    print(f"{'parameter':<24}{'truth':>10}{'n':>5}{'coverage':>10}{'mean z':>9}{'sd z':>7}")
    for name, c in cov.items():
        print(f"{name:<24}{truth[name]:>10.4g}{c['n']:>5}{c['coverage']:>10.2f}{c['mean_z']:>9.2f}{c['sd_z']:>7.2f}")
    if args.out:
        args.out.write_text(json.dumps({"truth": truth, "coverage": cov, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
