"""The paper's full experiment on real eyes, projected from a measured subset: with and without reuse.

Run (the images stay in ../shared; research use only)::

    .venv/bin/python benchmarks/bench_impact_reuse.py [--data ../shared/data/iitd-iris-001-040] [--images 40]
        [--segmentation caht] [--seed 0]

Measured on ``--images`` images of the shared IITD eyes, in this process (CPU time, ``time.process_time``, so
that other programs on a shared machine inflate it less than wall time):

* how many distinct sets of aged images each paper sensor A–H gives over the paper's 13 ages (0–96 years in
  8-year steps), found as the experiment finds them (:func:`forensics.impact.experiment.run_impact`'s digest
  pass: every image aged and hashed); sensor defects sit at fixed pixels, so one image's distinct count is the
  set's — checked on all the measured images;
* the CPU time of that digest pass per aged image;
* the CPU time per aged image of the segmentation and of each of the six algorithms' features (its own
  rubber sheet included);
* each algorithm's all-against-all comparison time per matrix entry (on the templates repeated to ~200, so
  that the vectorised comparisons' per-call overhead is not charged to a tiny matrix).

Projected to the paper's scale (2,240 images, 8 sensors × 13 ages, six algorithms, both protocols; per protocol
the entries the experiment computes, ``experiment.upper_entries(2240)``: the pairs ``i < j`` in 8 bands of rows,
56 % of the full 2,240² matrix, against the full matrix before): the work without reuse (104 (sensor, age)
tasks) and with it (the distinct tasks only, after the digest pass over all 104), in one process and on 2
cores.
"""
from __future__ import annotations

import argparse
import hashlib
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from forensics._shared.rng import keyed_generator
from forensics.impact.experiment import parse_sensors, upper_entries
from forensics.impact.matchers import compare_all, load_matchers
from forensics.impact.segment import normalise
from forensics.io.dataset import open_dataset
from forensics.sensor.simulate import aged_exposures

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "iitd-iris-001-040"
ALGORITHMS = ["masek", "ko", "qsw", "dct", "cr", "cb"]
PAPER = {"images": 2240, "sensors": "A,B,C,D,E,F,G,H", "ages": [float(a) for a in range(0, 97, 8)], "protocols": 2}


def distinct_sets(images: list[np.ndarray], sensors, ages: list[float], seed: int) -> tuple[dict[str, int], int, float]:
    """Distinct aged-image sets per sensor, distinct (sensor, age) tasks overall, CPU s per aged image hashed."""
    groups: dict[bytes, tuple[str, float]] = {}
    per_sensor: dict[str, int] = {}
    t0 = time.process_time()
    for spec in sensors:
        rng = keyed_generator(seed, 1, spec.stream_key())
        device = spec.model.realize(rng, [spec.model.t0 + a for a in ages])
        seen = set()
        for k, age in enumerate(ages):
            ctx = device.context(spec.model.t0 + age)
            digest = hashlib.blake2b(digest_size=20)
            for index, image in enumerate(images):
                digest.update(aged_exposures(device, image, [ctx], rng, index, first_step=k)[0].tobytes())
            key = digest.digest()
            seen.add(key)
            groups.setdefault(key, (spec.name, age))
        per_sensor[spec.name] = len(seen)
    cpu = (time.process_time() - t0) / (len(sensors) * len(ages) * len(images))
    return per_sensor, len(groups), cpu


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--images", type=int, default=40, help="images measured (the first N of the manifest)")
    ap.add_argument("--segmentation", default="caht")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if not (args.data / "manifest.csv").is_file():
        print(f"bench_impact_reuse: no manifest.csv in {args.data}; give --data", file=sys.stderr)
        return 3
    frames = list(open_dataset(args.data).frames)[: args.images]
    images = [f.load() for f in frames]
    n = len(images)
    print(f"# bench_impact_reuse on {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.1f}: {n} images of {args.data.name}, segmentation {args.segmentation}")
    sensors = parse_sensors(PAPER["sensors"], images[0].shape[:2], 8)
    per_sensor, distinct, digest_cpu = distinct_sets(images, sensors, PAPER["ages"], args.seed)
    tasks = len(sensors) * len(PAPER["ages"])
    print(f"distinct aged-image sets per sensor over {len(PAPER['ages'])} ages: "
          + ", ".join(f"{k} {v}" for k, v in per_sensor.items())
          + f"; distinct (sensor, age) tasks {distinct} of {tasks} (age 0 shared by the noiseless sensors)")
    print(f"digest pass: {1e3 * digest_cpu:.2f} ms CPU per aged image")

    matchers = load_matchers(ALGORITHMS, segmentation=args.segmentation)
    segmenter = matchers[0].segmenter
    seg_cpu, feature_cpu, compare_cpu = 0.0, dict.fromkeys(ALGORITHMS, 0.0), {}
    templates: dict[str, list] = {m.name: [] for m in matchers}
    for image in images:
        t0 = time.process_time()
        seg = segmenter.segment(image)
        seg_cpu += (time.process_time() - t0) / n
        for m in matchers:        # each its own rubber sheet (normalisation counted with the features)
            t0 = time.process_time()
            texture, mask = normalise(image, seg, m.radial, m.angular, **segmenter.normalise_params)
            templates[m.name].append(m.encode_texture(texture, mask, seg))
            feature_cpu[m.name] += (time.process_time() - t0) / n
    # Per-pair cost at a realistic matrix size: the templates repeated to about 200 (vectorised comparisons
    # have a per-call overhead that a 20 × 20 matrix would charge to each pair).
    reps = max(1, -(-200 // n))
    for m in matchers:
        many = templates[m.name] * reps
        t0 = time.process_time()
        compare_all(m, many, many)
        compare_cpu[m.name] = (time.process_time() - t0) / len(many) ** 2
    print(f"segmentation: {1e3 * seg_cpu:.1f} ms CPU per image")
    print("| algorithm | features ms/image | compare µs/entry |")
    print("|---|---:|---:|")
    for m in matchers:
        print(f"| {m.name} | {1e3 * feature_cpu[m.name]:.1f} | {1e6 * compare_cpu[m.name]:.1f} |")

    big = PAPER["images"]
    encode = big * (seg_cpu + sum(feature_cpu.values()))
    compare = PAPER["protocols"] * upper_entries(big) * sum(compare_cpu.values())
    before = PAPER["protocols"] * big * big * sum(compare_cpu.values())
    digest_all = tasks * big * digest_cpu
    plain = tasks * (encode + compare)
    reused = digest_all + distinct * (encode + compare)
    print(f"\nprojected, {big} images × {len(sensors)} sensors × {len(PAPER['ages'])} ages × {len(matchers)} "
          f"algorithms × {PAPER['protocols']} protocols (CPU hours; 2 cores: half):")
    print(f"  per (sensor, age) task: encoding {encode / 3600:.2f} h, comparisons {compare / 3600:.2f} h "
          f"(the full matrix: {before / 3600:.2f} h)")
    print(f"  without reuse: {tasks} tasks = {plain / 3600:.1f} h  (2 cores: {plain / 7200:.1f} h)")
    print(f"  with reuse:    {distinct} tasks + digest pass {digest_all / 3600:.2f} h = {reused / 3600:.1f} h  "
          f"(2 cores: {reused / 7200:.1f} h; {plain / reused:.2f}× faster)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
