"""Benchmark of the ageing-impact experiment's parts, and the projected time of the paper's full experiment.

Run::

    /work/main/.venv/bin/python benchmarks/bench_impact.py [--classes 60] [--samples 5] [--repeat 3]

Cases, each beside a plain implementation in the same run:

* encodes per second: segmentation alone, Masek (segmentation included), Ko after Masek on the same image
  (the shared Segmenter's cache), and Ko alone;
* all-against-all comparisons per second: the bit-packed ``compare_all`` against a plain loop of ``compare``
  over a sample of pairs (results checked equal);
* the class bootstrap of the EER at the paper's size (224 classes × 10 images: 10,080 genuine and 2,497,600
  impostor comparisons, 1,000 resamples) against the score-by-score bootstrap's cost per replicate;
* the projection: 2,240 images × 13 ages × 8 sensors × 2 matchers × 2 protocols on this machine.
"""
from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from _timing import timeit  # benchmarks/ is on sys.path when a script runs

from forensics.impact.irises import simulate_irises
from forensics.impact.matchers import KoMatcher, MasekMatcher, compare_all, load_matchers
from forensics.impact.segment import Segmenter
from forensics.io.dataset import open_dataset
from forensics.stats.clustered import PairedScores, class_bootstrap_eer, class_weights
from forensics.stats.scores import bootstrap_eer

PAPER = {"images": 2240, "classes": 224, "ages": 13, "sensors": 8, "matchers": 2, "protocols": 2}


def per_image(func, images) -> float:
    t0 = time.perf_counter()
    for im in images:
        func(im)
    return (time.perf_counter() - t0) / len(images)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--classes", type=int, default=60)
    parser.add_argument("--samples", type=int, default=5)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    print(f"# bench_impact on {platform.processor() or platform.machine()}, {os.cpu_count()} cores")
    with tempfile.TemporaryDirectory() as scratch:
        root = Path(scratch) / "irises"
        t0 = time.perf_counter()
        simulate_irises(root, args.classes, args.samples, rng=1)
        n = args.classes * args.samples
        print(f"simulate irises: {n} images in {time.perf_counter() - t0:.2f} s "
              f"({1e3 * (time.perf_counter() - t0) / n:.1f} ms per image, PNG writing included)")
        images = [f.load() for f in open_dataset(root).frames]

    # Encodes.  Every timing uses fresh objects so that no cache from an earlier case helps.
    seg_s = min(per_image(Segmenter().segment, images) for _ in range(args.repeat))
    masek_s = min(per_image(MasekMatcher().encode, images) for _ in range(args.repeat))
    ko_alone_s = min(per_image(KoMatcher().encode, images) for _ in range(args.repeat))

    def both(im, pair=None):
        pair[0].encode(im)
        pair[1].encode(im)

    shared = []
    for _ in range(args.repeat):
        pair = load_matchers(["masek", "ko"])
        shared.append(per_image(lambda im, p=pair: both(im, p), images))
    both_s = min(shared)
    print(f"\nencode (per image, best of {args.repeat}):")
    print(f"  segmentation alone                 {1e3 * seg_s:7.1f} ms  ({1 / seg_s:6.1f} /s)")
    print(f"  masek (segmentation included)      {1e3 * masek_s:7.1f} ms  ({1 / masek_s:6.1f} /s)")
    print(f"  ko alone (segmentation included)   {1e3 * ko_alone_s:7.1f} ms  ({1 / ko_alone_s:6.1f} /s)")
    print(f"  masek + ko, one shared Segmenter   {1e3 * both_s:7.1f} ms  (plain: {1e3 * (masek_s + ko_alone_s):.1f} ms, "
          f"{(masek_s + ko_alone_s) / both_s:.2f}× faster)")

    # All-against-all against the plain loop.
    rates = {}
    print(f"\nall-against-all, {n}×{n} templates:")
    for matcher in (MasekMatcher(), KoMatcher()):
        templates = [matcher.encode(im) for im in images]
        best, _, matrix = timeit(lambda m=matcher, t=templates: compare_all(m, t, t), args.repeat)
        rng = np.random.default_rng(0)
        a, b = rng.integers(0, n, 2000), rng.integers(0, n, 2000)
        t0 = time.perf_counter()
        loop = np.array([matcher.compare(templates[i], templates[j]) for i, j in zip(a, b)])
        loop_s = (time.perf_counter() - t0) / a.size
        assert np.array_equal(np.asarray(matrix)[a, b], loop)
        rate = n * n / best
        rates[matcher.name] = rate
        print(f"  {matcher.name:6s} compare_all {best:6.2f} s = {rate / 1e6:6.2f} M comparisons/s; plain loop "
              f"{1e6 * loop_s:6.1f} µs per pair = {1 / loop_s / 1e6:6.3f} M/s ({rate * loop_s:.0f}× faster; equal)")

    # Class bootstrap at the paper's size.
    rng = np.random.default_rng(0)
    labels = np.repeat(np.arange(224), 10)
    q, z = rng.normal(0, 0.03, 224), rng.normal(0, 0.02, labels.size)
    i, j = np.triu_indices(labels.size, 1)
    genuine = labels[i] == labels[j]
    d = np.where(genuine, 0.3 + q[labels[i]] + z[i] + z[j] + rng.normal(0, 0.04, i.size),
                 0.46 + rng.normal(0, 0.015, i.size))
    pairs = PairedScores.of(d, labels[i], labels[j], 224, higher_is_similar=False)
    weights = class_weights(224, 1000, 1)
    boot_s, _, _ = timeit(lambda: class_bootstrap_eer(pairs, weights), args.repeat)
    t0 = time.perf_counter()
    bootstrap_eer(-d[genuine], -d[~genuine], rng, n_boot=20)
    iid_per_rep = (time.perf_counter() - t0) / 20
    print(f"\nclass bootstrap, 10,080 + 2,497,600 comparisons, 1,000 resamples: {boot_s:.2f} s "
          f"(score-by-score bootstrap: {iid_per_rep:.3f} s per replicate = {1000 * iid_per_rep:.0f} s for 1,000)")

    # Projection of the paper's experiment.
    aged = PAPER["images"] * PAPER["ages"] * PAPER["sensors"]
    encode_h = aged * both_s / 3600
    units = PAPER["ages"] * PAPER["sensors"]
    matrices = units * PAPER["protocols"]
    compare_h = matrices * PAPER["images"] ** 2 * sum(1 / r for r in rates.values()) / 3600
    boot_h = units * PAPER["matchers"] * PAPER["protocols"] * boot_s / 3600
    print(f"\nprojected, the paper's experiment ({PAPER['images']:,} images × {PAPER['ages']} ages × "
          f"{PAPER['sensors']} sensors = {aged:,} aged images; 2 matchers; 2 protocols) on this machine, one process:")
    print(f"  encoding     {encode_h:6.2f} h")
    print(f"  comparisons  {compare_h:6.2f} h ({matrices} full {PAPER['images']}² matrices per matcher)")
    print(f"  bootstrap    {boot_h:6.2f} h ({units * 4} EERs with 1,000 class resamples)")
    print(f"  total        {encode_h + compare_h + boot_h:6.2f} h")


if __name__ == "__main__":
    main()
