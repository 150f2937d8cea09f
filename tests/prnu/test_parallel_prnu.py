"""PRNU workloads on the execution layer: fingerprints, score matrices and the same-device test give the
same bits in this process, in worker processes and on a Dask cluster.

Data: two simulated devices (PRNU σ_k = 1 %, 64×64 8-bit PNG), 20 images each, written once per module:
20 images are two full chunks of 8 and a short one, so a build really is a sum of several work items.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from forensics._shared.errors import UsageError
from forensics._shared.parallel import Checkpoint, Executor
from forensics.demo.prnu import sensor_model, simulated_set
from forensics.io.dataset import open_dataset
from forensics.io.images import read_image, write_image
from forensics.prnu.fingerprint import (
    CHUNK_IMAGES,
    FingerprintBuilder,
    FingerprintJob,
    ImageSet,
    build_fingerprint,
    build_fingerprints,
)
from forensics.prnu.match import score_matrix
from forensics.prnu.samedevice import same_device

SIZE = (64, 64)
N = 20


@pytest.fixture(scope="module")
def cameras(tmp_path_factory) -> dict[str, list[Path]]:
    root = tmp_path_factory.mktemp("prnu_parallel")
    rng = np.random.default_rng(2024)
    model = sensor_model("A", SIZE)
    out = {}
    for k, name in enumerate(("cam1", "cam2")):
        device = model.realize(rng, [0.0])
        images = simulated_set(device, N, 0.0, 700 + k, name)
        folder = root / name
        folder.mkdir()
        for i in range(N):
            write_image(folder / f"{name}_{i:03d}.png", images.load(i))
        out[name] = sorted(folder.glob("*.png"))
    return out


@pytest.fixture(scope="module")
def processes():
    with Executor("processes", workers=2) as ex:
        yield ex


@pytest.fixture
def dask_executor(dask_cluster):
    with Executor("dask", scheduler=dask_cluster.scheduler_address) as ex:
        yield ex


def test_fingerprint_is_bit_identical_on_every_backend(cameras, processes, dask_executor):
    paths = cameras["cam1"]
    assert N > 2 * CHUNK_IMAGES  # several chunks, the last one short
    reference = build_fingerprint(paths, "full")
    # image by image, from arrays: the builder sums in the same chunks, so even this path agrees bit for bit
    builder = FingerprintBuilder("full")
    for p in paths:
        builder.add(read_image(p), source=str(p))
    assert np.array_equal(builder.result().K, reference.K)
    for ex in (processes, dask_executor):
        fp = build_fingerprint(paths, "full", executor=ex)
        assert np.array_equal(fp.K, reference.K), ex.backend
        assert fp.files == [str(p) for p in paths] and fp.n_images == N
        assert fp.parameters == reference.parameters


def test_several_fingerprints_are_set_chunk_items(cameras, processes):
    """Two sets (and a median-residual job) in one map: each equals the fingerprint built on its own."""
    from forensics.prnu.ageing import MedianFingerprintBuilder

    sets = {name: ImageSet.of(paths, name) for name, paths in cameras.items()}
    jobs = [FingerprintJob(FingerprintBuilder("center:32"), sets["cam1"], tuple(range(N))),
            FingerprintJob(FingerprintBuilder("center:32"), sets["cam2"], tuple(range(0, N, 2))),
            FingerprintJob(MedianFingerprintBuilder("center:32"), sets["cam1"], tuple(range(1, N, 2)))]
    seen = []

    def progress(iterable, total=None, desc=None):
        seen.append(total)
        return iterable

    together = build_fingerprints(jobs, executor=processes, progress=progress)
    assert seen == [3 + 2 + 2]  # one bar over every (set, chunk) item
    for job, fp in zip(jobs, together):
        alone = build_fingerprints([job])[0]
        assert np.array_equal(fp.K, alone.K) and fp.files == alone.files
    assert not np.array_equal(together[0].K, together[1].K)


def test_interrupted_build_resumes_to_the_same_fingerprint(cameras, tmp_path):
    paths = cameras["cam2"]
    config = {"test": "resume"}
    first = build_fingerprint(paths, "full", checkpoint=Checkpoint(tmp_path / "ck", config))
    items = sorted((tmp_path / "ck").glob("item-*.npz"))
    assert len(items) == 3
    items[1].unlink()  # as if the run had stopped before the second chunk finished
    resumed = build_fingerprint(paths, "full", checkpoint=Checkpoint(tmp_path / "ck", config))
    assert np.array_equal(resumed.K, first.K) and resumed.files == first.files


def test_score_matrix_is_identical_on_every_backend(cameras, processes, dask_executor):
    fps = [build_fingerprint(cameras[name], "full") for name in ("cam1", "cam2")]
    queries = cameras["cam1"][:3] + cameras["cam2"][:3]
    reference, details = score_matrix(fps, queries, details=True)
    assert reference.shape == (2, 6)
    # rows follow the fingerprints, columns the queries: each camera's images match its own fingerprint
    assert (reference[0, :3] > 60).all() and (reference[1, 3:] > 60).all()
    assert (reference[0, 3:] < 60).all() and (reference[1, :3] < 60).all()
    frames = open_dataset(cameras["cam1"][0].parent).frames[:3] + open_dataset(cameras["cam2"][0].parent).frames[:3]
    for ex in (processes, dask_executor):
        scores, got = score_matrix(fps, frames, details=True, executor=ex)
        assert np.array_equal(scores, reference), ex.backend
        assert got == details  # every MatchScore (NCC, p_FA, shift) too
    ncc = score_matrix(fps, queries, "ncc")
    assert np.array_equal(score_matrix(fps, queries, "ncc", executor=processes), ncc)


def test_parallel_scoring_needs_files_not_arrays(cameras, processes):
    fp = build_fingerprint(cameras["cam1"][:4], "full")
    arrays = [read_image(p) for p in cameras["cam1"][:2]]
    with pytest.raises(UsageError, match="paths or dataset frames"):
        score_matrix([fp], arrays, executor=processes)
    with pytest.raises(UsageError, match="iterator"):
        build_fingerprint((a for a in arrays), executor=processes)
    # in this process both are fine, and agree with their file-based twins
    assert np.array_equal(score_matrix([fp], arrays), score_matrix([fp], cameras["cam1"][:2]))


def test_same_device_is_identical_in_process_and_on_dask(cameras, dask_executor):
    a, b = (open_dataset(cameras[name][0].parent) for name in ("cam1", "cam2"))
    options = dict(fingerprint_images=8, score_images=12, region="full", n_boot=200, ageing_fingerprints=3,
                   ageing_images=5)
    reference = same_device(a, b, 5, **options)
    on_dask = same_device(a, b, 5, executor=dask_executor, **options)
    assert reference.eer.decision == "different"
    assert on_dask.eer.eer == reference.eer.eer and on_dask.eer.ci == reference.eer.ci
    assert np.array_equal(on_dask.genuine, reference.genuine) and np.array_equal(on_dask.impostor, reference.impostor)
    assert np.array_equal(on_dask.ageing.matrix, reference.ageing.matrix)
    assert on_dask.to_dict() == reference.to_dict()  # everything else too: plans, files, ageing table, verdict
    # the bootstrap draws from the seed alone: another seed moves the interval, the executor does not
    assert same_device(a, b, 6, **options).set_a.plan != reference.set_a.plan
