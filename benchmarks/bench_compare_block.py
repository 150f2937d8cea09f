"""The six iris algorithms' all-against-all comparison at the impact experiment's block, with the plain ways beside.

Run (the images stay in ../shared; research use only)::

    .venv/bin/python benchmarks/bench_compare_block.py [--data ../shared/data/iitd-iris-001-040] [--images 40]
        [--rows 280] [--cols 1120] [--repeat 2]

The measured eyes' templates are repeated to a block of ``--rows`` × ``--cols`` (the experiment's call at the
paper's 2,240 images: a band of ``upper_band(2240)`` = 280 rows against the bands' mean width, 1,120 columns) and
each matcher's ``compare_all`` is timed on it (CPU time of this process, one BLAS thread, ``--repeat`` rounds,
the best kept), side by side with:

* ``cb`` at other working-memory sizes per block (``CbMatcher(block_bytes=…)``; the default keeps a block's
  arrays in a core's cache);
* the Hamming matchers whose code has mask groups (Masek, ``qsw``, ``cr``) through the plain bit-packed loop
  over shifts (:func:`~forensics.impact.iriscode.hamming_all`) instead of the exact cross-correlation
  (:func:`~forensics.impact.iriscode.hamming_all_spectral`), on a block of a tenth of the rows.

Every variant's scores are checked equal to the default's (the same bits, not a tolerance).
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import numpy as np  # noqa: E402

from forensics.impact.cb import CbMatcher  # noqa: E402
from forensics.impact.iriscode import hamming_all  # noqa: E402
from forensics.impact.matchers import compare_all, load_matchers  # noqa: E402
from forensics.io.dataset import open_dataset  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "iitd-iris-001-040"
ALGORITHMS = ["masek", "ko", "qsw", "dct", "cr", "cb"]


def best_cpu(call, repeat: int) -> tuple[float, np.ndarray]:
    """The least CPU time of ``repeat`` calls, and the last result."""
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.process_time()
        out = call()
        best = min(best, time.process_time() - t0)
    return best, out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--images", type=int, default=40)
    ap.add_argument("--rows", type=int, default=280)
    ap.add_argument("--cols", type=int, default=1120)
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args(argv)
    if not (args.data / "manifest.csv").is_file():
        print(f"bench_compare_block: no manifest.csv in {args.data}; give --data", file=sys.stderr)
        return 3
    images = [f.load() for f in open_dataset(args.data).frames[:args.images]]
    print(f"# bench_compare_block on {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load "
          f"average {os.getloadavg()[0]:.1f}: {len(images)} eyes of {args.data.name}, block {args.rows} × {args.cols}")
    matchers = load_matchers(ALGORITHMS)
    print("| algorithm | variant | µs per entry | scores equal |")
    print("|---|---|---:|---|")
    for m in matchers:
        templates = [m.encode(im) for im in images]
        many = templates * -(-args.cols // len(templates))
        rows, cols = many[:args.rows], many[:args.cols]
        compare_all(m, rows[:8], cols[:32])                      # imports and first allocations
        cpu, want = best_cpu(lambda: compare_all(m, rows, cols), args.repeat)
        print(f"| {m.name} | default | {1e6 * cpu / want.size:.2f} | — |")
        if m.name == "cb":
            for mib in (32, 8, 2, 1):
                other = CbMatcher(m.segmenter, block_bytes=mib * 2**20)
                cpu, got = best_cpu(lambda o=other: o.compare_all(rows, cols), args.repeat)
                print(f"| cb | block_bytes {mib} MiB | {1e6 * cpu / got.size:.2f} | {np.array_equal(got, want)} |")
        if getattr(m, "mask_groups", lambda: None)() is not None:
            few = max(1, args.rows // 10)
            cpu, got = best_cpu(lambda: hamming_all(rows[:few], cols, m.max_shift, m._min_valid_bits(rows[0])), 1)
            print(f"| {m.name} | bit-packed loop over shifts (`hamming_all`) | {1e6 * cpu / got.size:.2f} | "
                  f"{np.array_equal(got, want[:few])} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
