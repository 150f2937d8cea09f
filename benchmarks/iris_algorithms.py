"""EER of the reference paper's six iris algorithms on the shared IITD eyes, with class-bootstrap intervals.

Run (from the repository; the images stay in ../shared, research use only)::

    .venv/bin/python benchmarks/iris_algorithms.py [--data ../shared/data/iitd-iris-001-040]
        [--matcher masek --matcher ko ...] [--boot 1000] [--seed 1] [--json OUT.json]

At age 0 (no sensor ageing): every image is segmented once (the built-ins' shared
:class:`~forensics.impact.segment.Segmenter`, whatever segmentation the checkout has) and encoded by every
matcher; all pairs ``i < j`` are compared (400 images: 79,800 comparisons, 1,126 of them genuine); the EER's
95 % interval resamples the classes (``subject`` = folder + eye; :mod:`forensics.stats.clustered`), the same
resamples for every matcher.  Printed per matcher: EER and interval, mean genuine and impostor scores,
feature extraction per image (after the segmentation, which is timed once for all; the first matcher of
each rubber-sheet size also pays for the sheet), and the all-against-all
comparison time per pair.  Segmentations the segmenter itself flags as unreliable are counted (and still
scored, as the experiment scores them).

Timings are CPU time of this process (``time.process_time``: the work is single-threaded numpy), which other
load on the machine inflates far less than wall time; still take them as indications.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from forensics._shared.jsonsafe import dumps
from forensics.impact.matchers import compare_all, load_matchers
from forensics.io.dataset import open_dataset
from forensics.stats.clustered import PairedScores, class_bootstrap_eer, class_weights

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "iitd-iris-001-040"
ALGORITHMS = ["masek", "ko", "qsw", "dct", "cr", "cb"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="IITD folder with manifest.csv")
    parser.add_argument("--matcher", action="append", help="matcher spec (repeatable); default: all six")
    parser.add_argument("--boot", type=int, default=1000, help="class resamples (default 1000)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--json", type=Path, help="also write the results as JSON to this file")
    args = parser.parse_args(argv)
    if not (args.data / "manifest.csv").is_file():
        print(f"iris_algorithms: no manifest.csv in {args.data}; give --data", file=sys.stderr)
        return 3
    ds = open_dataset(args.data)
    subjects = [str(f.subject) for f in ds.frames]
    names = sorted(set(subjects))
    labels = np.array([names.index(s) for s in subjects])
    matchers = load_matchers(args.matcher or ALGORITHMS)
    segmenter = matchers[0].segmenter
    print(f"# iris_algorithms on {platform.processor() or platform.machine()}, {os.cpu_count()} cores: "
          f"{len(ds.frames)} images, {len(names)} classes, {args.data}")

    # Encode: one segmentation per image (timed on its own), then every matcher's features.
    codes: dict[str, list] = {m.name: [] for m in matchers}
    extract = dict.fromkeys(codes, 0.0)
    seg_time, flagged = 0.0, 0
    for frame in ds.frames:
        image = frame.load()
        t0 = time.process_time()
        seg = segmenter.segment(image)
        seg_time += time.process_time() - t0
        flagged += not seg.ok
        for m in matchers:
            t0 = time.process_time()
            codes[m.name].append(m.encode(image))
            extract[m.name] += time.process_time() - t0
    n = len(ds.frames)
    print(f"segmentation: {1e3 * seg_time / n:.1f} ms per image; {flagged} of {n} flagged unreliable by the segmenter")

    i, j = np.triu_indices(n, 1)
    weights = class_weights(len(names), args.boot, args.seed)
    rows = []
    print("\n| matcher | EER % | 95 % interval | genuine | impostor | features ms/image | compare µs/pair |")
    print("|---|---:|---|---:|---:|---:|---:|")
    for m in matchers:
        t0 = time.process_time()
        matrix = compare_all(m, codes[m.name], codes[m.name])
        per_pair = (time.process_time() - t0) / (n * n)
        scores = matrix[i, j]
        pairs = PairedScores.of(scores, labels[i], labels[j], len(names), higher_is_similar=m.higher_is_similar)
        boot = class_bootstrap_eer(pairs, weights)
        genuine = labels[i] == labels[j]
        row = {"matcher": m.name, "eer": boot.estimate, "ci": list(boot.ci), "n_genuine": boot.n_genuine,
               "n_impostor": boot.n_impostor, "genuine_mean": float(scores[genuine].mean()),
               "impostor_mean": float(scores[~genuine].mean()), "higher_is_similar": bool(m.higher_is_similar),
               "features_ms": 1e3 * extract[m.name] / n, "compare_us": 1e6 * per_pair}
        rows.append(row)
        print(f"| {m.name} | {100 * boot.estimate:.2f} | [{100 * boot.ci[0]:.2f}, {100 * boot.ci[1]:.2f}] | "
              f"{row['genuine_mean']:.3f} | {row['impostor_mean']:.3f} | {row['features_ms']:.1f} | "
              f"{row['compare_us']:.1f} |")
    if args.json:
        from forensics._shared.atomic import write_text

        write_text(args.json, dumps({"data": str(args.data), "images": n, "classes": len(names),
                                     "segmentation_ms": 1e3 * seg_time / n, "flagged": flagged,
                                     "boot": args.boot, "seed": args.seed, "matchers": rows}, indent=2),
                   force=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
