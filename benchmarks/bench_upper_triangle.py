"""The experiment's upper-triangle scoring against the full matrix: CPU time and equality, per algorithm.

Run (the images stay in ../shared; research use only)::

    .venv/bin/python benchmarks/bench_upper_triangle.py [--data ../shared/data/iitd-iris-001-040] [--images 20]
        [--repeat 30] [--matcher masek --matcher ko ...]

The first ``--images`` shared eyes are encoded and their templates repeated ``--repeat`` times (n templates);
``compare_all`` of the whole n × n matrix and ``experiment._upper_scores`` (the pairs i < j in bands of rows,
``experiment.upper_entries(n)`` entries) are timed in CPU seconds and checked equal on the pairs i < j.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from forensics.impact.experiment import _upper_scores, upper_entries
from forensics.impact.matchers import compare_all, load_matchers
from forensics.io.dataset import open_dataset

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "iitd-iris-001-040"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--images", type=int, default=20)
    ap.add_argument("--repeat", type=int, default=30)
    ap.add_argument("--matcher", action="append")
    args = ap.parse_args(argv)
    if not (args.data / "manifest.csv").is_file():
        print(f"bench_upper_triangle: no manifest.csv in {args.data}; give --data", file=sys.stderr)
        return 3
    images = [f.load() for f in list(open_dataset(args.data).frames)[: args.images]]
    for m in load_matchers(args.matcher or ["masek", "ko", "dct", "cb"], segmentation="caht"):
        templates = [m.encode(image) for image in images] * args.repeat
        n = len(templates)
        t0 = time.process_time()
        full = compare_all(m, templates, templates)
        t_full = time.process_time() - t0
        t0 = time.process_time()
        upper = _upper_scores(m, templates, templates)
        t_upper = time.process_time() - t0
        i, j = np.triu_indices(n, 1)
        print(f"{m.name}: n = {n}: full matrix {t_full:.2f} s, upper triangle {t_upper:.2f} s CPU "
              f"({t_upper / t_full:.2f} of the full; {upper_entries(n) / n**2:.2f} of its entries); "
              f"equal on every pair i < j: {np.array_equal(full[i, j], upper)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
