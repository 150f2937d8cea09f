"""EER of the reference paper's six iris algorithms on the shared IITD eyes, with class-bootstrap intervals.

Run (from the repository; the images stay in ../shared, research use only)::

    .venv/bin/python benchmarks/iris_algorithms.py [--data ../shared/data/iitd-iris-001-040]
        [--matcher masek --matcher ko ...] [--segmentation caht|wahet] [--circles MARKS.csv] [--boot 1000]
        [--seed 1] [--json OUT.json]

At age 0 (no sensor ageing): every image is segmented once (the built-ins' shared
:class:`~forensics.impact.segment.Segmenter`, whatever segmentation the checkout has) and encoded by every
matcher; all pairs ``i < j`` are compared (400 images: 79,800 comparisons, 1,126 of them genuine); the EER's
95 % interval resamples the classes (``subject`` = folder + eye; :mod:`forensics.stats.clustered`), the same
resamples for every matcher.  Printed per matcher: EER and interval, mean genuine and impostor scores,
feature extraction per image (after the segmentation, which is timed once for all; the first matcher of
each rubber-sheet size also pays for the sheet), and the all-against-all comparison time per pair.
Segmentations the segmenter itself flags as unreliable are counted (and still scored, as the experiment
scores them).

``--circles`` takes a CSV of given circles (columns ``file``, ``pupil_x``, ``pupil_y``, ``pupil_r``,
``iris_x``, ``iris_y``, ``iris_r``, e.g. hand-checked marks) and measures the algorithms on those images with
those circles instead of the segmentation: what the feature extraction and comparison achieve on their own.
It needs matchers with ``encode_texture(texture, mask)`` and ``radial``/``angular`` (all six built-ins).

Timings are CPU time of this process (``time.process_time``: the work is single-threaded numpy), which other
load on the machine inflates far less than wall time; still take them as indications.
"""
from __future__ import annotations

import argparse
import csv
import os
import platform
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from forensics._shared.atomic import write_text
from forensics._shared.jsonsafe import dumps
from forensics.impact.matchers import Matcher, compare_all, load_matchers
from forensics.impact.segment import DEFAULT_SEGMENTATION, SEGMENTATIONS, Segmentation, normalise
from forensics.io.dataset import Frame, open_dataset
from forensics.stats.clustered import PairedScores, class_bootstrap_eer, class_weights

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "iitd-iris-001-040"
ALGORITHMS = ["masek", "ko", "qsw", "dct", "cr", "cb"]


def read_circles(path: Path) -> dict[str, Segmentation]:
    """Given circles by file name."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return {r["file"]: Segmentation(pupil=(float(r["pupil_x"]), float(r["pupil_y"]), float(r["pupil_r"])),
                                    iris=(float(r["iris_x"]), float(r["iris_y"]), float(r["iris_r"])))
            for r in rows}


def encode_all(frames: Sequence[Frame], matchers: Sequence[Matcher],
               circles: dict[str, Segmentation] | None) -> tuple[dict[str, list], dict[str, float], float, int]:
    """Templates per matcher, feature CPU seconds per matcher, segmentation CPU seconds, flagged segmentations."""
    segmenter = matchers[0].segmenter
    codes: dict[str, list] = {m.name: [] for m in matchers}
    extract = dict.fromkeys(codes, 0.0)
    seg_time, flagged = 0.0, 0
    for frame in frames:
        image = frame.load()
        t0 = time.process_time()
        seg = circles[frame.file] if circles else segmenter.segment(image)
        seg_time += time.process_time() - t0
        flagged += not seg.ok
        for m in matchers:
            t0 = time.process_time()
            if circles:
                texture, mask = normalise(image, seg, m.radial, m.angular, **segmenter.normalise_params)
                codes[m.name].append(m.encode_texture(texture, mask, seg))
            else:
                codes[m.name].append(m.encode(image))
            extract[m.name] += time.process_time() - t0
    return codes, extract, seg_time, flagged


def score(matcher: Matcher, templates: list, labels: np.ndarray, weights: np.ndarray) -> dict[str, Any]:
    """EER with its class-bootstrap interval, score means and the comparison time of one matcher."""
    n = len(templates)
    i, j = np.triu_indices(n, 1)
    t0 = time.process_time()
    matrix = compare_all(matcher, templates, templates)
    per_pair = (time.process_time() - t0) / (n * n)
    scores = matrix[i, j]
    pairs = PairedScores.of(scores, labels[i], labels[j], weights.shape[1], higher_is_similar=matcher.higher_is_similar)
    boot = class_bootstrap_eer(pairs, weights)
    genuine = labels[i] == labels[j]
    return {"matcher": matcher.name, "eer": boot.estimate, "ci": list(boot.ci), "n_genuine": boot.n_genuine,
            "n_impostor": boot.n_impostor, "genuine_mean": float(scores[genuine].mean()),
            "impostor_mean": float(scores[~genuine].mean()), "higher_is_similar": bool(matcher.higher_is_similar),
            "compare_us": 1e6 * per_pair}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="IITD folder with manifest.csv")
    parser.add_argument("--matcher", action="append", help="matcher spec (repeatable); default: all six")
    parser.add_argument("--circles", type=Path, help="CSV of given circles: use them instead of the segmentation")
    parser.add_argument("--segmentation", choices=sorted(SEGMENTATIONS), default=DEFAULT_SEGMENTATION,
                        help=f"the built-ins' segmentation (default {DEFAULT_SEGMENTATION})")
    parser.add_argument("--boot", type=int, default=1000, help="class resamples (default 1000)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--json", type=Path, help="also write the results as JSON to this file")
    args = parser.parse_args(argv)
    if not (args.data / "manifest.csv").is_file():
        print(f"iris_algorithms: no manifest.csv in {args.data}; give --data", file=sys.stderr)
        return 3
    frames = list(open_dataset(args.data).frames)
    circles = read_circles(args.circles) if args.circles else None
    if circles is not None:
        frames = [f for f in frames if f.file in circles]
    subjects = [str(f.subject) for f in frames]
    names = sorted(set(subjects))
    labels = np.array([names.index(s) for s in subjects])
    matchers = load_matchers(args.matcher or ALGORITHMS, segmentation=args.segmentation)
    source = f"given circles from {args.circles}" if circles else f"segmentation {args.segmentation}"
    print(f"# iris_algorithms on {platform.processor() or platform.machine()}, {os.cpu_count()} cores: "
          f"{len(frames)} images, {len(names)} classes, {args.data}; {source}")
    codes, extract, seg_time, flagged = encode_all(frames, matchers, circles)
    n = len(frames)
    if not circles:
        print(f"segmentation: {1e3 * seg_time / n:.1f} ms per image; {flagged} of {n} flagged unreliable by the "
              "segmenter")
    weights = class_weights(len(names), args.boot, args.seed)
    rows = []
    print("\n| matcher | EER % | 95 % interval | genuine | impostor | features ms/image | compare µs/pair |")
    print("|---|---:|---|---:|---:|---:|---:|")
    for m in matchers:
        row = score(m, codes[m.name], labels, weights) | {"features_ms": 1e3 * extract[m.name] / n}
        rows.append(row)
        print(f"| {m.name} | {100 * row['eer']:.2f} | [{100 * row['ci'][0]:.2f}, {100 * row['ci'][1]:.2f}] | "
              f"{row['genuine_mean']:.3f} | {row['impostor_mean']:.3f} | {row['features_ms']:.1f} | "
              f"{row['compare_us']:.1f} |")
    if args.json:
        write_text(args.json, dumps({"data": str(args.data), "circles": str(args.circles) if circles else None,
                                     "images": n, "classes": len(names), "segmentation_ms": 1e3 * seg_time / n,
                                     "flagged": flagged, "boot": args.boot, "seed": args.seed, "matchers": rows},
                                    indent=2), force=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
