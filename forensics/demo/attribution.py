"""Demo section: which camera took these images?  Clustering an unlabelled collection, then 1:N identification.

A collection of simulated photographs from several cameras of one model (independent PRNU, the truth) and a
few single images of other cameras is written as anonymous PNG files.  :func:`forensics.prnu.cluster.cluster_images`
groups it by camera without being told how many there are; the clusters are written as a dataset, a fingerprint is
built from each and kept in a :class:`~forensics.prnu.database.FingerprintDatabase`; new images of the
cameras — whole, cropped at a random offset, turned by 90° — and images of cameras never seen are then
identified against the database (:func:`forensics.prnu.identify.identify`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from forensics._shared.parallel import Executor
from forensics._shared.progress import Progress
from forensics._shared.rng import RngLike, as_generator
from forensics.io.images import write_image
from forensics.prnu.cluster import adjusted_rand_index, cluster_images, completeness, purity, write_cluster_dataset
from forensics.prnu.database import FingerprintDatabase
from forensics.prnu.fingerprint import build_fingerprint
from forensics.prnu.identify import identify
from forensics.report.cluster import add_clusters
from forensics.report.html import Report
from forensics.report.identify import add_identification

from . import DemoSection
from .prnu import sensor_model, simulated_set

TITLE = "Which camera? Clustering an unlabelled collection, a fingerprint database, 1:N identification"
SIZE = (240, 320)  # landscape, so that a turned image needs the quarter-turn search
CAMERAS, PER_CAMERA, STRANGERS = 6, 6, 3
CROP = (160, 200)
PFA = 1e-3


def _collection(rng: np.random.Generator, folder: Path) -> tuple[list, list[Path], list[str]]:
    """Realise the cameras and write the shuffled, anonymous collection; its files and true cameras."""
    model = sensor_model("A", SIZE)
    cameras = [model.realize(rng, [0.0]) for _ in range(CAMERAS + 2 * STRANGERS)]
    shots = [(c, k) for c in range(CAMERAS) for k in range(PER_CAMERA)] + [(CAMERAS + s, 0) for s in range(STRANGERS)]
    order = rng.permutation(len(shots))
    seeds = rng.integers(0, 2**31, size=len(cameras))
    folder.mkdir(parents=True)
    paths, truth = [], []
    for position, shot in enumerate(order):
        camera, k = shots[shot]
        images = simulated_set(cameras[camera], PER_CAMERA, 0.0, int(seeds[camera]), f"camera {camera}")
        paths.append(write_image(folder / f"IMG_{position:04d}.png", images.load(k)))
        truth.append(f"camera {camera + 1}")
    return cameras, paths, truth


def _queries(cameras: list, rng: np.random.Generator) -> tuple[list[np.ndarray], list[str | None], list[str]]:
    """New images of the collection's cameras (whole, cropped, turned) and of cameras never seen."""
    queries, truth, kinds = [], [], []
    h, w = SIZE
    for c in range(CAMERAS):
        image = simulated_set(cameras[c], 3, 0.0, int(rng.integers(0, 2**31)), "new").load
        y, x = int(rng.integers(0, h - CROP[0] + 1)), int(rng.integers(0, w - CROP[1] + 1))
        for kind, query in (("whole", image(0)), ("crop", image(1)[y:y + CROP[0], x:x + CROP[1]]),
                            ("turned 90°", np.rot90(image(2)))):
            queries.append(np.ascontiguousarray(query))
            truth.append(f"camera {c + 1}")
            kinds.append(kind)
    for s in range(STRANGERS):  # cameras neither in the collection nor among its strangers
        queries.append(simulated_set(cameras[CAMERAS + STRANGERS + s], 1, 0.0, int(rng.integers(0, 2**31)),
                                     "unseen").load(0))
        truth.append(None)
        kinds.append("unseen camera")
    return queries, truth, kinds


def run(workdir: Path, rng: RngLike, progress: Progress, executor: Executor | None = None) -> DemoSection:
    """Cluster the collection, build the database from the clusters, identify the new images (≈ 5 s)."""
    rng = as_generator(rng)
    cameras, paths, truth = _collection(rng, workdir / "collection")
    clusters = cluster_images(paths, p_fa=PFA, crop=min(SIZE), executor=executor, workdir=workdir / "scratch",
                              progress=progress)
    labels = clusters.labels
    write_cluster_dataset(clusters, workdir / "clusters")

    # one fingerprint per cluster, named by the cluster; which camera each cluster is, by its majority
    db = FingerprintDatabase(workdir / "db", create=True)
    majority: dict[str, str] = {}
    for cluster in clusters.clusters:
        members = [i for i, label in enumerate(labels) if label == cluster.label]
        fp = build_fingerprint([str(paths[i]) for i in members], "full")
        db.add(fp, cluster.label)
        names, counts = np.unique([truth[i] for i in members], return_counts=True)
        majority[cluster.label] = str(names[np.argmax(counts)])
    queries, query_truth, kinds = _queries(cameras, rng)
    (workdir / "queries").mkdir()
    # as files: workers read their queries themselves (image bytes never pass through the executor)
    query_files = [str(write_image(workdir / "queries" / f"Q_{i:03d}.png", q)) for i, q in enumerate(queries)]
    found = identify(query_files, db, pfa=PFA, executor=executor, progress=progress)

    named = [majority.get(q.device_id) if q.device_id else None for q in found.queries]
    correct = sum(n == t for n, t in zip(named, query_truth) if t is not None)
    n_known = sum(t is not None for t in query_truth)
    false = sum(n is not None and n != t for n, t in zip(named, query_truth))
    scores = {"ari": adjusted_rand_index(truth, labels), "purity": purity(truth, labels),
              "completeness": completeness(truth, labels)}

    rep = Report(TITLE)
    rep.text(f"{len(paths)} anonymous {SIZE[1]}×{SIZE[0]} photographs: {PER_CAMERA} from each of {CAMERAS} cameras of one model "
             f"(independent PRNU, σ = 1 %) and one from each of {STRANGERS} other cameras, shuffled.  The number of "
             f"cameras is not given.  Clusters at p_FA = {PFA:g}: {len(clusters.clusters)} found, "
             f"{clusters.n_unattributed} images unattributed; against the truth purity {scores['purity']:.3f}, "
             f"completeness {scores['completeness']:.3f}, adjusted Rand index {scores['ari']:.3f}.  "
             "On real cameras use `forensics cluster PHOTOS -o CLUSTERS`.")
    add_clusters(clusters, rep, prefix="cluster_")
    rep.text(f"A fingerprint is built from each cluster and kept in a fingerprint database "
             f"(`forensics fingerprint db add`).  Then {len(queries)} new images are identified against it "
             f"(`forensics identify`): for each camera one whole image, one {CROP[1]}×{CROP[0]} crop at a random "
             f"offset and one turned by 90°, and {STRANGERS} images of cameras never seen.  "
             f"{correct}/{n_known} attributed to their camera's cluster, {false} false attributions.")
    add_identification(found, rep, prefix="identify_")
    summary = [
        f"which camera: {len(paths)} unlabelled images ({CAMERAS} cameras × {PER_CAMERA} + {STRANGERS} single images "
        f"of others) → {len(clusters.clusters)} cameras found, {clusters.n_unattributed} images unattributed, "
        f"ARI {scores['ari']:.3f}",
        f"which camera: identification against the clusters' fingerprints {correct}/{n_known} correct "
        f"(whole, cropped, turned), {false} false of {len(queries) - n_known} unseen cameras",
    ]
    data = {**scores, "images": len(paths), "clusters": len(clusters.clusters),
            "unattributed": clusters.n_unattributed, "identified": correct, "known_queries": n_known,
            "false_attributions": false, "queries": [{"kind": k, "truth": t, "attributed_to": n, "pce":
                                                      q.best.pce if q.best else None, "p_fa": q.p_fa}
                                                     for k, t, n, q in zip(kinds, query_truth, named, found.queries)]}
    return DemoSection(TITLE, rep, summary, data)
