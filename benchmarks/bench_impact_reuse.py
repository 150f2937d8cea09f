"""The paper's full experiment on real eyes, projected from a measured subset: with and without reuse.

Run (the images stay in ../shared; research use only)::

    .venv/bin/python benchmarks/bench_impact_reuse.py [--data ../shared/data/iitd-iris-001-040] [--images 40]
        [--segmentation caht] [--seed 0] [--sensors A,B,C,D,E,F,G,H] [--algorithms masek,ko,qsw,dct,cr,cb]
        [--check]

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

* the reuse of comparison scores between byte-identical templates (:mod:`forensics.impact.reuse`): every
  distinct set of aged images is encoded by every algorithm and each template digested
  (:func:`~forensics.impact.reuse.score_digest`, as the run keys its scores: a built-in's code without its
  segmentation; its CPU time is measured too), then the run's own rule is
  replayed on the digests — each sensor's later distinct ages in age order, every (algorithm, protocol) starting
  from the stored scores leaving the fewest pairs (:func:`~forensics.impact.reuse.best_base`) — counting the
  matrix entries the run computes (:func:`~forensics.impact.reuse.upper_entries_computed`: ``fill_upper``'s
  own plan of ``compare_all`` calls).  At the paper's 2,240 images the measured images are drawn with
  replacement (seeded) so that each drawn image keeps its measured history of template changes over the ages
  and algorithms; the share of templates that change is what carries over, not the images themselves;
* the class bootstrap of one unit at the paper's size (224 classes × 10 images, 1,000 resamples).

Projected to the paper's scale (2,240 images, 8 sensors × 13 ages, six algorithms, both protocols; per protocol
the entries the experiment computes, ``experiment.upper_entries(2240)``: the pairs ``i < j`` in 8 bands of rows,
56 % of the full 2,240² matrix): the work without any reuse (104 (sensor, age) tasks), with the reuse of whole
tasks (the distinct tasks only, after the digest pass over all 104) and with the reuse of scores on top, in one
process and on 2 cores.  ``--check`` runs :func:`~forensics.impact.experiment.run_impact` itself on the measured
images (linked, not copied, into a temporary folder) and checks that its counts of computed and copied
comparisons equal the replay's at that size.
"""
from __future__ import annotations

import argparse
import csv
import hashlib
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

# The experiment's worker processes run BLAS on one thread each (forensics._shared.parallel); the projection to
# 2 workers assumes the same, so the matrix products are timed on one thread too (set before numpy loads BLAS).
for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import numpy as np  # noqa: E402

from forensics._shared.rng import keyed_generator
from forensics.impact.experiment import parse_sensors, run_impact, upper_band, upper_entries
from forensics.impact.matchers import compare_all, load_matchers
from forensics.impact.reuse import (
    ScoredPairs,
    band_untouched,
    best_base,
    segment_reusing,
    score_digest,
    template_digest,
    upper_entries_computed,
)
from forensics.impact.segment import normalise
from forensics.io.dataset import open_dataset
from forensics.sensor.simulate import aged_exposures
from forensics.stats.clustered import PairedScores, class_bootstrap_eer, class_weights

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "iitd-iris-001-040"
ALGORITHMS = ["masek", "ko", "qsw", "dct", "cr", "cb"]
PAPER = {"images": 2240, "classes": 224, "sensors": "A,B,C,D,E,F,G,H", "ages": [float(a) for a in range(0, 97, 8)],
         "protocols": ["same-age", "enrol-0"], "n_boot": 1000}


def pick_frames(frames, n: int) -> list:
    """The first two images of each class (manifest order) until ``n``: many eyes, and genuine pairs to score."""
    taken: dict[str, int] = {}
    out = []
    for f in frames:
        if len(out) < n and taken.get(str(f.subject), 0) < 2:
            taken[str(f.subject)] = taken.get(str(f.subject), 0) + 1
            out.append(f)
    return out


def aged_cells(images: list[np.ndarray], sensors, ages: list[float], seed: int):
    """Every (sensor, age)'s aged images as the experiment makes them, keyed by the digest of the whole set.

    Returns ``(digest of every (s, a), {digest: aged images}, CPU s per aged image digested)``; the aged images
    are kept once per distinct set (they are encoded later).
    """
    digests, sets = {}, {}
    t0 = time.process_time()
    for s_index, spec in enumerate(sensors):
        rng = keyed_generator(seed, 1, spec.stream_key())
        device = spec.model.realize(rng, [spec.model.t0 + a for a in ages])
        for a_index, age in enumerate(ages):
            ctx = device.context(spec.model.t0 + age)
            aged = [aged_exposures(device, image, [ctx], rng, index, first_step=a_index)[0]
                    for index, image in enumerate(images)]
            digest = hashlib.blake2b(digest_size=20)
            for a in aged:
                digest.update(f"{a.dtype.str}{a.shape}".encode())
                digest.update(np.ascontiguousarray(a).tobytes())
            key = digest.digest()
            digests[s_index, a_index] = key
            sets.setdefault(key, aged)
    cpu = (time.process_time() - t0) / (len(sensors) * len(ages) * len(images))
    return digests, sets, cpu


def run_structure(digests: dict, n_sensors: int, n_ages: int, lead: int = 0):
    """The run's representatives, first-age tasks and chains (``experiment._run_tasks`` with reuse, enrol-0).

    A task is computed when it is the first with its probe digest and its sensor's age-0 digest.
    """
    first, rep = {}, {}
    for s in range(n_sensors):
        for a in range(n_ages):
            rep[s, a] = first.setdefault((digests[s, a], digests[s, lead]), (s, a))
    computed = [t for t in rep if rep[t] == t]
    chains = {s: [a for t, a in computed if t == s and a != lead] for s in range(n_sensors)}
    return rep, [t for t in computed if t[1] == lead], {s: c for s, c in chains.items() if c}


def replay(versions: dict, digests: dict, structure, names: list[str], n: int, band: int) -> tuple[dict, dict]:
    """Matrix entries computed and pairs computed / copied per algorithm, and the entries of every computed task
    per algorithm, replaying the run's score reuse.

    ``versions[(digest, name)]`` are the template digests of a distinct set of aged images for one algorithm
    (already drawn to ``n`` images).  Mirrors ``experiment._score_cell``: per (algorithm, protocol) the stored
    scores leaving the fewest pairs are the base, the enrol-0 protocol may copy from the same age's same-age
    scores, a chain holds the scores of its previous computed age.
    """
    rep, first, chains = structure
    i, j = np.triu_indices(n, 1)
    out = {m: {"entries": 0, "computed": 0, "copied": 0} for m in names}
    per_task: dict[tuple[int, int], dict[str, int]] = {}

    def cell(task: tuple[int, int], key: bytes, enrol_key: bytes, bases: dict) -> dict:
        made, per_task[task] = {}, dict.fromkeys(names, 0)
        for m in names:
            probe, gallery0 = versions[key, m], versions[enrol_key, m]
            done: list[ScoredPairs] = []
            for protocol in PAPER["protocols"]:
                gallery = probe if protocol == "same-age" else gallery0
                base, rows, cols = best_base([*bases.get(m, ()), *done], gallery, probe, i, j)
                if base is None:
                    rows = cols = np.zeros(n, bool)
                entries = 0 if base is not None and rows[:-1].all() and cols[1:].all() else \
                    upper_entries_computed(rows, cols, band)
                needed = int((~(rows[i] & cols[j])).sum()) if base is not None else i.size
                out[m]["entries"] += entries
                per_task[task][m] += entries
                out[m]["computed"] += needed
                out[m]["copied"] += i.size - needed
                done.append(ScoredPairs(tuple(gallery), tuple(probe), np.empty(0)))
            made[m] = done
        return made

    starts = {t: cell(t, digests[t], digests[t], {}) for t in first}
    for s, ages in chains.items():
        bases = starts[rep[s, 0]]
        for a in ages:
            bases = cell((s, a), digests[s, a], digests[s, 0], bases)
    return out, per_task


def encodings(bands: dict, digests: dict, structure, names: list[str], n: int) -> dict:
    """Templates each computed task encodes per algorithm, replaying the run's template reuse: all ``n`` in a
    first-age task; in a chain, those whose band digest differs from the previous computed age's (the sensor's
    first age before the chain's first step: ``experiment._chain_task`` starts from ``job.firsts``)."""
    rep, first, chains = structure
    out = {t: dict.fromkeys(names, n) for t in first}
    for s, ages in chains.items():
        before = digests[rep[s, 0]]
        for a in ages:
            now = digests[s, a]
            out[s, a] = {m: sum(x is None or x != y for x, y in zip(bands[now, m], bands[before, m])) for m in names}
            before = now
    return out


def two_core_wall(first: list, chains: dict, cost: dict, workers: int = 2) -> float:
    """Wall time of the run's two stages on ``workers`` processes: the first-age tasks, then the sensors' chains
    longest first (as ``experiment._run_tasks`` submits them), each item to the first free worker."""
    total = 0.0
    longest_first = sorted(chains, key=lambda s: -len(chains[s]))
    for items in ([[t] for t in first], [[(s, a) for a in chains[s]] for s in longest_first]):
        free = [0.0] * workers
        for item in items:
            k = free.index(min(free))
            free[k] += sum(cost[t] for t in item)
        total += max(free)
    return total


def encode_cells(sets: dict, digests: dict, structure, matchers
                 ) -> tuple[dict, dict, float, float, dict, dict, dict]:
    """Template and band digests of every distinct set for every algorithm; CPU s per template and per band
    digested (the band: the texture, mask and segmentation the algorithm's template is encoded from); and per
    computed task the CPU s per image of its segmentation, the segmentation steps it reused and the share of
    its (image, band size) rubber sheets the run unwraps — all but those whose every band of that size is
    provably unchanged since the previous computed age (:func:`forensics.impact.reuse.band_untouched`).

    The sets are segmented as the run segments them (:func:`forensics.impact.reuse.segment_reusing`): every
    first-age task from scratch, then each sensor's chain in age order, every image starting from the steps of
    the same image at the chain's previous computed age (the first step from the sensor's first age).
    """
    rep, first, chains = structure
    versions, bands, hash_cpu, band_cpu, hashed = {}, {}, 0.0, 0.0, 0
    seg_task, steps_task, sheets_task, memo_of, segs_of = {}, {}, {}, {}, {}
    segmenter = matchers[0].segmenter
    sizes = sorted({(m.radial, m.angular) for m in matchers})
    order = [(t, None) for t in first] + [((s, a), prev) for s, ages in chains.items()
                                          for prev, a in zip([rep[s, 0], *[(s, b) for b in ages]], ages)]
    for task, prev in order:
        key = digests[task]
        aged = sets[key]
        digs = {m.name: [] for m in matchers}
        keys = {m.name: [] for m in matchers}
        seg_cpu, hits, memos, segs, unwrapped = 0.0, 0, [], [], 0
        for index, image in enumerate(aged):
            t0 = time.process_time()
            memo = segment_reusing(segmenter, image, memo_of[prev][index] if prev is not None else None)
            seg_cpu += time.process_time() - t0
            hits += memo.hits
            memos.append(memo.entries)
            if prev is None:
                unwrapped += len(sizes)
            else:
                earlier = sets[digests[prev]][index]
                kept = {(m.radial, m.angular) for m in matchers}
                for m in matchers:
                    if not band_untouched(m, image, earlier, segs_of[prev][index][m.name]):
                        kept.discard((m.radial, m.angular))
                unwrapped += len(sizes) - len(kept)
            segs.append({})
            for m in matchers:
                band = m.segmenter.unwrap(image, m.radial, m.angular)
                segs[-1][m.name] = band[2]
                t0 = time.process_time()
                keys[m.name].append(template_digest(band))
                band_cpu += time.process_time() - t0
                template = m.encode_texture(*band)
                t0 = time.process_time()
                digs[m.name].append(score_digest(m, template))
                hash_cpu += time.process_time() - t0
                hashed += 1
        memo_of[task], segs_of[task] = memos, segs
        seg_task[task], steps_task[task] = seg_cpu / len(aged), hits
        sheets_task[task] = unwrapped / (len(aged) * len(sizes))
        for name in digs:
            versions[key, name], bands[key, name] = digs[name], keys[name]
    return (versions, bands, hash_cpu / max(hashed, 1), band_cpu / max(hashed, 1), seg_task, steps_task,
            sheets_task)


def time_encoding(images, matchers) -> tuple[float, float, dict, dict]:
    """CPU s per image of the segmentation and of the rubber sheets (one per distinct size, as the shared
    segmenter unwraps them), of each algorithm's features from its sheet; compare CPU s per matrix entry."""
    n = len(images)
    segmenter = matchers[0].segmenter
    seg_cpu, sheet_cpu, compare_cpu = 0.0, 0.0, {}
    feature_cpu = dict.fromkeys([m.name for m in matchers], 0.0)
    templates: dict[str, list] = {m.name: [] for m in matchers}
    for image in images:
        t0 = time.process_time()
        seg = segmenter.segment(image)
        seg_cpu += (time.process_time() - t0) / n
        sheets = {}
        for m in matchers:
            size = (m.radial, m.angular)
            if size not in sheets:
                t0 = time.process_time()
                sheets[size] = normalise(image, seg, *size, **segmenter.normalise_params)
                sheet_cpu += (time.process_time() - t0) / n
            t0 = time.process_time()
            templates[m.name].append(m.encode_texture(*sheets[size], seg))
            feature_cpu[m.name] += (time.process_time() - t0) / n
    # Per-entry cost at the experiment's own call at 2,240 images: a band of upper_band(2240) = 280 rows against
    # the bands' mean width, 1,120 columns (the measured templates repeated; vectorised comparisons prepare
    # each row and column once per call, so a small matrix would overstate the cost per entry).
    rows, cols = upper_band(PAPER["images"]), PAPER["images"] // 2
    for m in matchers:
        many = templates[m.name] * -(-cols // n)
        t0 = time.process_time()
        compare_all(m, many[:rows], many[:cols])
        compare_cpu[m.name] = (time.process_time() - t0) / (rows * cols)
    return seg_cpu, sheet_cpu, feature_cpu, compare_cpu


def time_bootstrap(seed: int) -> float:
    """CPU s of one unit's class bootstrap at the paper's size (224 classes × 10 images, all pairs)."""
    labels = np.repeat(np.arange(PAPER["classes"]), PAPER["images"] // PAPER["classes"])
    i, j = np.triu_indices(labels.size, 1)
    rng = np.random.default_rng(seed)
    scores = rng.normal(0.45, 0.03, i.size) - 0.15 * (labels[i] == labels[j])
    weights = class_weights(PAPER["classes"], PAPER["n_boot"], rng)
    t0 = time.process_time()
    class_bootstrap_eer(PairedScores.of(scores, labels[i], labels[j], PAPER["classes"], higher_is_similar=False),
                        weights)
    return time.process_time() - t0


def check_against_run(frames, sensors_spec: str, ages, names, segmentation, seed, expected, reused: int,
                      steps: int) -> None:
    """Run the experiment on the measured images (symbolic links) and compare its counts of comparisons and of
    reused templates and segmentation steps with the replay's."""
    with tempfile.TemporaryDirectory(prefix="bench-reuse-") as tmp:
        root = Path(tmp)
        with open(root / "manifest.csv", "w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(["file", "subject"])
            for f in frames:
                (root / f.file).parent.mkdir(parents=True, exist_ok=True)
                (root / f.file).symlink_to(Path(f.path).resolve())
                writer.writerow([f.file, f.subject])
        source = open_dataset(root, allow_outside=True)    # the links lead to the shared folder
        sensors = parse_sensors(sensors_spec, source.shape()[:2], 8)
        result = run_impact(source, sensors, ages, load_matchers(names, segmentation=segmentation), rng=seed,
                            n_boot=100)
    got = (result.computed_pairs, result.copied_pairs, result.reused_templates, result.reused_steps)
    want = (sum(v["computed"] for v in expected.values()), sum(v["copied"] for v in expected.values()), reused,
            steps)
    print(f"check: run_impact on these {len(frames)} images computed {got[0]} and copied {got[1]} comparisons and "
          f"reused {got[2]} templates and {got[3]} segmentation steps; the replay: {want[0]}, {want[1]}, {want[2]} "
          f"and {want[3]} -> "
          f"{'EQUAL' if got == want else 'DIFFERENT'}")
    if got != want:
        raise SystemExit("bench_impact_reuse: the replay does not match the run")


def measure(images, sensors, ages, names, args) -> dict:
    """Every measurement the projection needs (the slow part: ageing, encoding, timing)."""
    digests, sets, digest_cpu = aged_cells(images, sensors, ages, args.seed)
    matchers = load_matchers(names, segmentation=args.segmentation)
    seg_cpu, sheet_cpu, feature_cpu, compare_cpu = time_encoding(images, matchers)
    structure = run_structure(digests, len(sensors), len(ages))
    versions, bands, hash_cpu, band_cpu, seg_task, steps_task, sheets_task = encode_cells(sets, digests, structure,
                                                                                         matchers)
    return {"digests": digests, "versions": versions, "bands": bands, "digest_cpu": digest_cpu, "seg_cpu": seg_cpu,
            "sheet_cpu": sheet_cpu, "feature_cpu": feature_cpu, "compare_cpu": compare_cpu, "hash_cpu": hash_cpu,
            "band_cpu": band_cpu, "seg_task": seg_task, "steps_task": steps_task, "sheets_task": sheets_task,
            "boot_cpu": time_bootstrap(args.seed), "made": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "load": os.getloadavg()[0]}


def save_measurements(path: Path, settings: dict, m: dict) -> None:
    """The measurements as JSON (digests in hex; no image data)."""
    hexed = {**m, "digests": [[s, a, d.hex()] for (s, a), d in m["digests"].items()],
             **{part: [[k.hex(), name, [v.hex() if v is not None else None for v in vs]]
                       for (k, name), vs in m[part].items()] for part in ("versions", "bands")},
             **{part: [[s, a, v] for (s, a), v in m[part].items()]
                for part in ("seg_task", "steps_task", "sheets_task")}}
    path.write_text(json.dumps({"settings": settings, "measurements": hexed}))


def load_measurements(path: Path, settings: dict) -> dict:
    stored = json.loads(path.read_text())
    if stored["settings"] != settings:
        raise SystemExit(f"{path}: measured with {stored['settings']}, not {settings}")
    m = stored["measurements"]
    m["digests"] = {(s, a): bytes.fromhex(d) for s, a, d in m["digests"]}
    for part in ("versions", "bands"):
        m[part] = {(bytes.fromhex(k), name): [bytes.fromhex(v) if v is not None else None for v in vs]
                   for k, name, vs in m[part]}
    for part in ("seg_task", "steps_task", "sheets_task"):
        m[part] = {(s, a): v for s, a, v in m[part]}
    return m


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--images", type=int, default=40,
                    help="images measured: the first two of each class, classes in the manifest's order")
    ap.add_argument("--segmentation", default="caht")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sensors", default=PAPER["sensors"])
    ap.add_argument("--algorithms", default=",".join(ALGORITHMS))
    ap.add_argument("--check", action="store_true", help="also run the experiment on the measured images")
    ap.add_argument("--measurements", type=Path,
                    help="JSON file keeping the measurements (timings, template digests): written when absent, "
                         "read when present, so that the projection can be redone without measuring again")
    args = ap.parse_args(argv)
    if not (args.data / "manifest.csv").is_file():
        print(f"bench_impact_reuse: no manifest.csv in {args.data}; give --data", file=sys.stderr)
        return 3
    frames = pick_frames(open_dataset(args.data).frames, args.images)
    images = [f.load() for f in frames]
    n, ages, names = len(images), PAPER["ages"], args.algorithms.split(",")
    print(f"# bench_impact_reuse on {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.1f}: {n} images of {args.data.name}, segmentation {args.segmentation}")
    sensors = parse_sensors(args.sensors, images[0].shape[:2], 8)
    t_start = time.process_time()
    settings = {k: str(getattr(args, k)) for k in ("images", "segmentation", "seed", "sensors", "algorithms")}
    settings["format"] = "5"       # scores keyed by score_digest (format 4: by the whole template)
    if args.measurements and args.measurements.is_file():
        m = load_measurements(args.measurements, settings)
        print(f"measurements read from {args.measurements} (made {m['made']})")
    else:
        m = measure(images, sensors, ages, names, args)
        if args.measurements:
            save_measurements(args.measurements, settings, m)
    digests, versions, bands = m["digests"], m["versions"], m["bands"]
    seg_cpu, sheet_cpu, feature_cpu, compare_cpu = m["seg_cpu"], m["sheet_cpu"], m["feature_cpu"], m["compare_cpu"]
    digest_cpu, hash_cpu, band_cpu, boot_cpu = m["digest_cpu"], m["hash_cpu"], m["band_cpu"], m["boot_cpu"]
    seg_task, steps_task, sheets_task = m["seg_task"], m["steps_task"], m["sheets_task"]
    structure = run_structure(digests, len(sensors), len(ages))
    rep, first, chains = structure
    tasks, distinct = len(rep), sum(1 for t in rep if rep[t] == t)
    per_sensor = {spec.name: len({digests[s, a] for a in range(len(ages))}) for s, spec in enumerate(sensors)}
    print(f"distinct aged-image sets per sensor over {len(ages)} ages: "
          + ", ".join(f"{k} {v}" for k, v in per_sensor.items())
          + f"; distinct (sensor, age) tasks {distinct} of {tasks}: {len(first)} first-age, "
            f"{sum(len(c) for c in chains.values())} in the sensors' chains")
    print(f"digest pass: {1e3 * digest_cpu:.2f} ms CPU per aged image")
    print(f"segmentation: {1e3 * seg_cpu:.1f} ms CPU per image, rubber sheets {1e3 * sheet_cpu:.1f} ms; template "
          f"digest {1e6 * hash_cpu:.0f} µs CPU per template, band digest {1e6 * band_cpu:.0f} µs; class bootstrap "
          f"of one unit at 2,240 images: {boot_cpu:.2f} s CPU")

    changed = {}
    for s_index, spec in enumerate(sensors):
        prev, steps = digests[s_index, 0], []
        for a_index in chains.get(s_index, []):
            now = digests[s_index, a_index]
            steps.append(np.mean([x is None or x != y for name in names
                                  for x, y in zip(versions[now, name], versions[prev, name])]))
            prev = now
        changed[spec.name] = f"{np.mean(steps):.0%} ({len(steps)} steps)" if steps else "-"
    print("codes changed per step of a chain (previous computed age to the next; mean over steps and "
          "algorithms): " + ", ".join(f"{k} {v}" for k, v in changed.items()))

    # The replay at the measured size (what --check compares with the run), then at the paper's.
    small, _ = replay(versions, digests, structure, names, n, upper_band(n))
    encoded_small = encodings(bands, digests, structure, names, n)
    if args.check:
        reused = sum(n * len(names) - sum(c.values()) for t, c in encoded_small.items() if t not in first)
        check_against_run(frames, args.sensors, ages, names, args.segmentation, args.seed, small, reused,
                          sum(steps_task.values()))
    big = PAPER["images"]
    draw = np.random.default_rng(args.seed).integers(n, size=big)
    drawn = {k: [v[d] for d in draw] for k, v in versions.items()}
    scaled, per_task = replay(drawn, digests, structure, names, big, upper_band(big))
    encoded = encodings({k: [v[d] for d in draw] for k, v in bands.items()}, digests, structure, names, big)
    kept = {}
    for s_index, spec in enumerate(sensors):
        steps = [sum(encoded_small[s_index, a].values()) / (n * len(names)) for a in chains.get(s_index, [])]
        kept[spec.name] = f"{1 - np.mean(steps):.0%}" if steps else "-"
    print("templates reused in a chain's step (band unchanged since the previous computed age; mean over steps "
          "and algorithms): " + ", ".join(f"{k} {v}" for k, v in kept.items()))
    seg_chain = {spec.name: np.mean([seg_task[s_index, a] for a in chains.get(s_index, [])])
                 for s_index, spec in enumerate(sensors) if chains.get(s_index)}
    first_seg = 1e3 * np.mean([seg_task[t] for t in first])
    unwrapped_chain = {spec.name: np.mean([sheets_task[s_index, a] for a in chains.get(s_index, [])])
                       for s_index, spec in enumerate(sensors) if chains.get(s_index)}
    print("rubber sheets unwrapped in a chain's step (the rest provably unchanged; mean over steps): "
          + ", ".join(f"{k} {v:.0%}" for k, v in unwrapped_chain.items()))
    print(f"segmentation with the step reuse, ms CPU per image: first age {first_seg:.1f}; a chain's step (mean "
          "over its steps): " + ", ".join(f"{k} {1e3 * v:.1f}" for k, v in seg_chain.items())
          + f"; steps reused at the measured size: {sum(steps_task.values())}")

    print("| algorithm | features ms/image | compare µs/entry | pairs copied (measured set) | entries computed at "
          "2,240, share of no score reuse |")
    print("|---|---:|---:|---:|---:|")
    full = len(PAPER["protocols"]) * upper_entries(big)
    for m in names:
        copied = small[m]["copied"] / (small[m]["copied"] + small[m]["computed"])
        print(f"| {m} | {1e3 * feature_cpu[m]:.1f} | {1e6 * compare_cpu[m]:.1f} | {copied:.1%} | "
              f"{scaled[m]['entries'] / (distinct * full):.1%} |")

    encode = big * (seg_cpu + sheet_cpu + sum(feature_cpu.values()))
    segment_only = big * seg_cpu
    compare_task = sum(full * compare_cpu[m] for m in names)
    digest_all = tasks * big * digest_cpu
    units = len(names) * len(PAPER["protocols"])
    boot = distinct * units * boot_cpu
    plain = tasks * (encode + compare_task + units * boot_cpu)
    whole = digest_all + distinct * (encode + compare_task) + boot
    compare_reused = sum(scaled[m]["entries"] * compare_cpu[m] for m in names)
    # Probe templates digested once per computed task, the enrolment gallery once more in each chain task.
    hashing = (distinct + sum(len(c) for c in chains.values())) * big * len(names) * hash_cpu
    scores = digest_all + distinct * encode + hashing + compare_reused + boot
    print(f"\nprojected, {big} images × {len(sensors)} sensors × {len(ages)} ages × {len(names)} algorithms × "
          f"{len(PAPER['protocols'])} protocols (CPU hours; 2 cores: half):")
    print(f"  per distinct (sensor, age) task without score reuse: encoding {encode / 3600:.2f} h "
          f"(segmentation {segment_only / 3600:.2f} h), comparisons {compare_task / 3600:.2f} h, bootstrap "
          f"{units * boot_cpu / 3600:.3f} h")
    print(f"  no reuse:              {tasks} tasks = {plain / 3600:.1f} h  (2 cores: {plain / 7200:.1f} h)")
    print(f"  whole-task reuse:      {distinct} tasks + digest pass {digest_all / 3600:.2f} h = {whole / 3600:.1f} h  "
          f"(2 cores: {whole / 7200:.1f} h)")
    print(f"  + score reuse:         comparisons {compare_reused / 3600:.2f} h instead of "
          f"{distinct * compare_task / 3600:.2f} h, template digests {hashing / 3600:.2f} h: {scores / 3600:.1f} h "
          f"(2 cores: {scores / 7200:.1f} h; {whole / scores:.2f}× faster than whole-task reuse alone)")
    # Template reuse: every task segments, unwraps and digests each algorithm's band; features only where the
    # band changed since the chain's previous computed age (every template of a first-age task).
    fixed = big * (seg_cpu + sheet_cpu + len(names) * band_cpu)
    features = {t: sum(c * feature_cpu[m] for m, c in encoded[t].items()) for t in encoded}
    templates = scores - distinct * encode + sum(fixed + f for f in features.values())
    print(f"  + template reuse:      features {sum(features.values()) / 3600:.2f} h instead of "
          f"{distinct * big * sum(feature_cpu.values()) / 3600:.2f} h, band digests "
          f"{distinct * big * len(names) * band_cpu / 3600:.2f} h: {templates / 3600:.1f} h (2 cores: "
          f"{templates / 7200:.1f} h)")
    # Segmentation steps: each task's segmentation costs what it measured per image with the run's step reuse
    # (a first-age task from scratch, a chain's image from the steps of its previous computed age).
    segmented = {t: big * seg_task[t] for t in encoded}
    stepped = templates - distinct * segment_only + sum(segmented.values())
    print(f"  + segmentation steps:  segmentation {sum(segmented.values()) / 3600:.2f} h instead of "
          f"{distinct * segment_only / 3600:.2f} h: {stepped / 3600:.1f} h (2 cores: {stepped / 7200:.1f} h)")
    # Untouched bands: the rubber sheets (and band digests) only of the (image, size) bands not provably unchanged
    # (the pixels the sheet reads and the segmentation equal the previous computed age's).
    unwrap_one = sheet_cpu + len(names) * band_cpu
    unwrapping = {t: big * sheets_task[t] * unwrap_one for t in encoded}
    untouched = stepped - distinct * big * unwrap_one + sum(unwrapping.values())
    print(f"  + untouched bands:     rubber sheets and band digests {sum(unwrapping.values()) / 3600:.2f} h instead "
          f"of {distinct * big * unwrap_one / 3600:.2f} h: {untouched / 3600:.1f} h (2 cores: "
          f"{untouched / 7200:.1f} h)")
    task_cost = {t: segmented[t] + unwrapping[t] + features[t]
                 + len(names) * big * hash_cpu * (1 if t in first else 2) + units * boot_cpu
                 + sum(e * compare_cpu[m] for m, e in entries.items()) for t, entries in per_task.items()}
    wall = digest_all / 2 + two_core_wall(first, chains, task_cost)
    print(f"  on 2 worker processes (the first-age tasks, then one item per sensor's chain, longest first; the "
          f"digest pass split): {wall / 3600:.1f} h (perfect halving: {untouched / 7200:.1f} h)")
    sheets = sum(big * sheets_task[t] * sheet_cpu for t in encoded)
    parts = {"segmentation": sum(segmented.values()), "rubber sheets": sheets,
             "features": sum(features.values()), "comparisons": compare_reused, "bootstrap": boot,
             "digests (images, templates, bands)": digest_all + hashing + sum(unwrapping.values()) - sheets}
    print("  shares of the remaining work: " + ", ".join(f"{k} {v / untouched:.0%}" for k, v in parts.items()))
    print(f"(benchmark CPU {time.process_time() - t_start:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
