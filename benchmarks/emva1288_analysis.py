#!/usr/bin/env python3
"""emva1288's own analysis (``emva1288.process``) of one EMVA 1288 series, timed as a whole process.

Runs in an environment of its own: emva1288 1.0.2's analysis calls ``np.asfarray``, removed in NumPy 2, so it
needs NumPy < 2 (``python3 -m venv /work/venv-emva && /work/venv-emva/bin/pip install "numpy<2" emva1288``).
It imports nothing of this project.  Prints one JSON object: the quantities both tools compute and the seconds
from the start of the interpreter to the end of the analysis (parse, load every image, reduce, fit).

Usage::

    /work/venv-emva/bin/python benchmarks/emva1288_analysis.py DESCRIPTOR        # an EMVA1288descriptor.txt
    /work/venv-emva/bin/python benchmarks/emva1288_analysis.py --images IMAGES.json   # {temporal, spatial} dict
"""
import time

STARTED = time.perf_counter()

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import math  # noqa: E402
import os  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("descriptor", nargs="?", help="EMVA1288descriptor.txt")
    parser.add_argument("--images", help="a JSON file with emva1288's images dict (exposures in ns, photons)")
    args = parser.parse_args()
    from emva1288.process import Data1288, LoadImageData, ParseEmvaDescriptorFile, Results1288

    if args.images:
        with open(args.images) as f:
            raw = json.load(f)
        images = {kind: {float(t): {float(p): paths for p, paths in d.items()} for t, d in raw[kind].items()}
                  for kind in ("temporal", "spatial")}
        path = ""
    else:
        parsed = ParseEmvaDescriptorFile(args.descriptor, loglevel=logging.ERROR)
        images, path = parsed.images, ""
    loaded = LoadImageData(images, path=path, loglevel=logging.ERROR)
    res = Results1288(Data1288(loaded.data, loglevel=logging.ERROR).data, loglevel=logging.ERROR)

    def number(value):
        try:
            value = float(value() if callable(value) else value)
        except Exception:  # noqa: BLE001 - a quantity emva1288 cannot compute on these data
            return None
        return value if math.isfinite(value) else None

    out = {
        "K": number(res.K),  # DN/e-
        "sigma_y_dark": number(res.sigma_y_dark),  # DN, temporal dark noise
        "sigma_d": number(res.sigma_d),  # e-
        "DSNU1288_DN": number(res.DSNU1288_DN),  # DN
        "DSNU1288": number(res.DSNU1288),  # e-
        "PRNU1288": number(res.PRNU1288),  # %
        "u_I_mean_DN": number(res.u_I_mean_DN),  # DN/s, dark current from the mean
        "u_I_var_DN": number(res.u_I_var_DN),  # DN/s, dark current from the variance
        "seconds": time.perf_counter() - STARTED,
        "pid": os.getpid(),
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
