"""Clustering an unlabelled collection by camera (:mod:`forensics.prnu.cluster`).

Simulated collections: the sensor model's cameras (preset A with PRNU σ_k = 1 %, read and shot noise,
8-bit; :func:`forensics.demo.prnu.sensor_model`) imaging smooth scenes, each camera with its own PRNU
pattern, so the true device of every image is known.  Real data: the Dresden Nikons (skipped where absent).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from forensics._shared.errors import InputError, UsageError
from forensics.demo.prnu import sensor_model, simulated_set
from forensics.prnu.cluster import (
    adjusted_rand_index,
    block_images,
    cluster_images,
    comparison_residual,
    completeness,
    null_shifts,
    purity,
    write_cluster_dataset,
)

SIZE = (256, 256)


def collection(seed: int, devices: int, per_device: int, singles: int = 0, size: tuple[int, int] = SIZE,
               turns: dict[int, int] | None = None) -> tuple[list[np.ndarray], list[int]]:
    """``devices`` cameras with ``per_device`` images each, then ``singles`` cameras with one image each.

    ``turns`` maps an image's position to the ``np.rot90`` quarter turns it is stored with (portrait copies).
    Returns the images (uint8) and each one's true device.
    """
    rng = np.random.default_rng(seed)
    model = sensor_model("A", size)
    images, truth = [], []
    for d in range(devices + singles):
        device = model.realize(rng, [0.0])
        n = per_device if d < devices else 1
        shots = simulated_set(device, n, 0.0, int(rng.integers(2**31)), f"device {d}")
        for i in range(n):
            images.append(shots.load(i))
            truth.append(d)
    for position, k in (turns or {}).items():
        images[position] = np.ascontiguousarray(np.rot90(images[position], k))
    return images, truth


# ----------------------------------------------------------------------------- label agreement


def test_agreement_measures_on_hand_counted_examples():
    truth = ["a", "a", "a", "b", "b", "c"]
    assert purity(truth, truth) == completeness(truth, truth) == adjusted_rand_index(truth, truth) == 1.0
    # one 'a' left unattributed: clusters stay pure, completeness loses that image
    labels = ["x", "x", None, "y", "y", None]
    assert purity(truth, labels) == 1.0
    assert completeness(truth, labels) == pytest.approx(5 / 6)
    # everything in one cluster: complete, purity = share of the largest class
    one = ["x"] * 6
    assert completeness(truth, one) == 1.0 and purity(truth, one) == pytest.approx(3 / 6)
    assert adjusted_rand_index(truth, one) == pytest.approx(0.0)
    # a hand-computed ARI: truth {0,1,2}{3,4,5}, clusters {0,1}{2,3}{4,5}: index 2, expected 6·3/15, max 4.5
    ari = adjusted_rand_index([0, 0, 0, 1, 1, 1], ["p", "p", "q", "q", "r", "r"])
    assert ari == pytest.approx((2 - 6 * 3 / 15) / (4.5 - 6 * 3 / 15))
    with pytest.raises(UsageError):
        purity([1, 2], [1])


# ----------------------------------------------------------------------------- residuals and geometry


def test_comparison_residual_is_unit_norm_without_the_block_pattern():
    images, _ = collection(1, 1, 1, size=(96, 128))
    v = comparison_residual(images[0], 64)
    assert v.shape == (64, 64) and v.dtype == np.float32
    assert float(np.square(v, dtype=np.float64).sum()) == pytest.approx(1.0, rel=1e-5)
    # the 8×8-periodic mean (shared by cameras that compress alike) is gone, and with it the mean
    periodic = v.reshape(8, 8, 8, 8).mean(axis=(0, 2))
    assert np.abs(periodic).max() < 1e-6
    blank = comparison_residual(np.full((96, 128), 255, np.uint8), 64)  # fully saturated: nothing to compare
    assert not blank.any()
    with pytest.raises(UsageError):
        comparison_residual(images[0], 60)


def test_block_size_depends_on_the_crop_only():
    assert block_images(1024) == (384 << 20) // (12 * 1024 * 1024) == 32
    assert block_images(8192) == 1
    assert null_shifts(1024) == ((512, 512), (512, 0), (0, 512))
    assert all(s % 8 == 0 for shift in null_shifts(200) for s in shift)  # JPEG and CFA grids stay aligned


# ----------------------------------------------------------------------------- simulated collections


@pytest.mark.parametrize("seed", range(10))
def test_simulated_collection_of_20_devices_is_recovered(seed):
    """20 cameras × 3 images + 5 cameras with one image each (65 images, 256²), 10 seeds (about 1 s each)."""
    images, truth = collection(seed, 20, 3, singles=5)
    result = cluster_images(images)
    labels = result.labels
    assert purity(truth, labels) >= 0.95
    assert completeness(truth, labels) >= 0.95
    # a camera with a single image has nothing to match: it stays unattributed
    singles = [i for i, d in enumerate(truth) if d >= 20]
    assert all(labels[i] is None for i in singles)
    assert result.p_fa == 1e-3 and result.groups[0].crop == 256  # the largest crop that fits, stated
    null = result.groups[0].null
    # 6,000 null samples of 65 images: σ known to a few per cent (jackknife), the one-sided bound inside
    assert null.sigma_ci[0] < null.sigma < null.sigma_upper < null.sigma_ci[1] < 1.1 * null.sigma


def test_null_collection_gives_no_clusters_beyond_the_stated_rate():
    """Every image from a different camera (30 images, 128²), 20 collections.

    At p_fa = 0.5 the share of collections with any attribution must be consistent with at most 0.5 (the
    bound is conservative: Šidák over every comparison, σ at its upper bound); at the default 1e-3 none may
    have one.  The pairwise z themselves must follow the Gaussian null the thresholds assume.
    """
    hits_half, hits_default, pair_z = 0, 0, []
    for seed in range(20):
        images, _ = collection(100 + seed, 30, 1, size=(128, 128))
        loose = cluster_images(images, p_fa=0.5)
        hits_half += loose.n_unattributed < len(images)
        hits_default += cluster_images(images).n_unattributed < len(images)
        pair_z.append(loose.similarity[0][np.triu_indices(len(images), 1)])
    assert hits_default == 0
    assert hits_half <= stats.binom.ppf(0.999, 20, 0.5)
    z = np.concatenate(pair_z)  # 8,700 pairs
    assert abs(z.mean()) < 0.05 and 0.93 < z.std() < 1.07
    # the upper tail: P(z > 3) = 0.00135; 99.9 % binomial bound on 8,700 pairs
    assert np.count_nonzero(z > 3) <= stats.binom.ppf(0.999, z.size, stats.norm.sf(3))


def test_portrait_images_are_turned_back_either_way():
    turns = {1: 1, 2: 3, 5: 3, 9: 1, 10: 1}  # device 0: images 1 and 2; device 1: 5; device 3: 9, 10 (of 0..11)
    images, truth = collection(7, 4, 3, size=(192, 256), turns=turns)
    result = cluster_images(images)
    assert adjusted_rand_index(truth, result.labels) == 1.0
    assert result.groups[0].frame == (192, 256) and result.groups[0].n_rotated == len(turns)
    for i, k in turns.items():
        assert result.images[i].rotation == (4 - k) % 4  # the quarter turn that undoes it
    assert result.groups[0].n_comparisons == 2 * (len(images) - 1) ** 2  # two orientations tried


def test_other_frame_sizes_form_their_own_groups_with_a_warning():
    a, truth_a = collection(11, 3, 3)
    b, truth_b = collection(12, 2, 4, size=(256, 320))
    result = cluster_images(a + b, crop=256)
    truth = truth_a + [10 + d for d in truth_b]
    assert adjusted_rand_index(truth, result.labels) == 1.0
    assert len(result.groups) == 2 and any("2 frame sizes" in w for w in result.warnings)
    assert {result.images[i].group for i in range(len(a))} == {0}
    assert {result.images[i].group for i in range(len(a), len(a) + len(b))} == {1}
    for cluster in result.clusters:  # no cluster mixes sizes
        assert len({result.images[i].group for i in cluster.members}) == 1


def test_too_few_images_and_bad_arguments_are_refused():
    images, _ = collection(3, 2, 2, size=(64, 64))
    with pytest.raises(InputError, match="at least 5 images"):
        cluster_images(images)
    with pytest.raises(UsageError):
        cluster_images(images, p_fa=0)
    with pytest.raises(UsageError):
        cluster_images(images, crop=32)


# ----------------------------------------------------------------------------- execution layer and output


@pytest.fixture(scope="module")
def png_collection(tmp_path_factory) -> tuple[list[Path], list[int]]:
    """6 cameras × 4 images + 2 single-image cameras, 128×128 PNG files."""
    from forensics.io.images import write_image

    root = tmp_path_factory.mktemp("cluster_set")
    images, truth = collection(21, 6, 4, singles=2, size=(128, 128))
    paths = []
    for i, image in enumerate(images):
        paths.append(root / f"img_{i:03d}.png")
        write_image(paths[-1], image)
    return paths, truth


def test_workers_and_blocks_do_not_change_the_result(png_collection, tmp_path):
    from forensics._shared.parallel import Executor

    paths, truth = png_collection
    reference = cluster_images(paths, crop=128)
    assert purity(truth, reference.labels) == 1.0 and completeness(truth, reference.labels) >= 0.9
    with Executor("processes", workers=2) as ex:
        parallel = cluster_images(paths, crop=128, executor=ex, workdir=tmp_path / "work")
    assert parallel.labels == reference.labels
    # the same blocks on every backend: the same numbers (BLAS threads may change the last bits only)
    np.testing.assert_allclose(parallel.similarity[0], reference.similarity[0], rtol=1e-5, atol=1e-5)
    assert not list((tmp_path / "work").glob("residuals-*.npy"))  # the store is removed
    # smaller blocks: the same Gram matrix, fewer null samples (three shifts on diagonal blocks only)
    small = cluster_images(paths, crop=128, block=5)
    assert small.labels == reference.labels
    lo, hi = reference.groups[0].null.sigma_ci
    assert lo < small.groups[0].null.sigma < hi
    assert small.groups[0].null.n_samples < reference.groups[0].null.n_samples


def test_a_dask_cluster_gives_the_same_clusters(png_collection, dask_cluster, tmp_path):
    from forensics._shared.parallel import Executor

    paths, _ = png_collection
    reference = cluster_images(paths, crop=128)
    with Executor("dask", scheduler=dask_cluster.scheduler_address) as ex:
        result = cluster_images(paths, crop=128, executor=ex, workdir=tmp_path / "work")
    assert result.labels == reference.labels
    np.testing.assert_allclose(result.similarity[0], reference.similarity[0], rtol=1e-5, atol=1e-5)


def test_written_dataset_feeds_the_other_commands(png_collection, tmp_path):
    from forensics.io.dataset import open_dataset

    paths, _ = png_collection
    result = cluster_images(paths, crop=128, names=[p.name for p in paths])
    before = [p.stat().st_mtime_ns for p in paths]
    out = tmp_path / "by_camera"
    written = write_cluster_dataset(result, out, captured=[2020.5] * len(paths))
    assert written["linked"] + written["copied"] == len(paths)
    ds = open_dataset(out)  # refuses links leaving the folder: none are written
    assert len(ds) == len(paths)
    devices = [f.device for f in ds.frames]
    assert sorted({d for d in devices if d}) == sorted(c.label for c in result.clusters)
    assert devices.count(None) == result.n_unattributed  # unattributed images have an empty device
    assert all(f.captured == pytest.approx(2020.5) for f in ds.frames)
    assert not any(p.is_symlink() for p in out.rglob("*"))
    first = result.clusters[0]
    sub = open_dataset(out / first.label)  # each device folder is a dataset of its own
    assert len(sub) == first.size and {f.device for f in sub.frames} == {first.label}
    assert (out / "clusters.json").is_file() and (out / "similarity.npz").is_file()
    assert [p.stat().st_mtime_ns for p in paths] == before  # inputs untouched
    with pytest.raises(UsageError):
        write_cluster_dataset(result, out)  # exists, no force
    with pytest.raises(UsageError, match="holds the input"):
        write_cluster_dataset(result, paths[0].parent, force=True)


def test_result_to_dict_is_complete_and_json_safe(png_collection):
    import json

    paths, _ = png_collection
    result = cluster_images(paths, crop=128)
    payload = json.loads(json.dumps(result.to_dict(), allow_nan=False))
    assert payload["n_images"] == len(paths) and len(payload["images"]) == len(paths)
    assert payload["groups"][0]["null"]["sigma_ci"][0] < payload["groups"][0]["null"]["sigma"]
    assert all(set(img) >= {"file", "cluster", "best_z", "best_match", "passed", "cluster_z"}
               for img in payload["images"])
    for img in payload["images"]:
        assert img["passed"] == (img["cluster"] is not None)


# ----------------------------------------------------------------------------- real cameras


@pytest.mark.realdata
def test_dresden_nikons_are_recovered():
    """All 54 Dresden images (40 flat, 14 natural; four Nikons, two D70 and two D70s), 2000×2000 centre crops
    (the largest square that fits in 3008×2000; about 25 s in one process).

    Measured: ARI 0.975, one natural image (D70_1_20891, z 3.8 against its camera's cluster, threshold 3.95)
    unattributed; at 1024² crops ARI 0.951 with two left out.
    """
    from conftest import dresden_or_skip

    root = dresden_or_skip()
    paths = sorted((root / "flat").glob("*.JPG")) + sorted((root / "natural").glob("*.JPG"))
    truth = [p.stem.rsplit("_", 1)[0] for p in paths]
    result = cluster_images(paths, crop=2000)
    labels = result.labels
    assert adjusted_rand_index(truth, labels) >= 0.95
    assert purity(truth, labels) == 1.0
    # no natural image of one camera in another camera's cluster
    for c in result.clusters:
        assert len({truth[i] for i in c.members}) == 1
    assert len(result.clusters) == 4
