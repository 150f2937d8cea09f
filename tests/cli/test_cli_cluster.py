"""Command-line tests of ``forensics cluster``.

Data: 4 simulated cameras × 3 images and 2 cameras with one image each (PRNU σ_k = 1 %, 256×256 8-bit PNG,
smooth scenes), written once per module in a folder without a manifest.
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from forensics.demo.prnu import sensor_model, simulated_set
from forensics.io.images import write_image

SIZE = (256, 256)


@pytest.fixture(scope="module")
def collection(tmp_path_factory) -> tuple[Path, dict[str, int]]:
    root = tmp_path_factory.mktemp("cluster_cli")
    folder = root / "photos"
    folder.mkdir()
    rng = np.random.default_rng(4242)
    model = sensor_model("A", SIZE)
    truth = {}
    for d, n in enumerate([3, 3, 3, 3, 1, 1]):
        shots = simulated_set(model.realize(rng, [0.0]), n, 0.0, 900 + d, f"cam{d}")
        for i in range(n):
            name = f"shot_{d}{i}.png"  # the name says nothing the clustering could use: it reads pixels only
            write_image(folder / name, shots.load(i))
            truth[name] = d
    return folder, truth


def _manifest(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def test_cluster_writes_a_dataset_with_a_device_column(cli, collection, tmp_path):
    from forensics.io.dataset import open_dataset

    folder, truth = collection
    out = tmp_path / "by_camera"
    code, stdout, stderr = cli("cluster", folder, "-o", out, "--workers", "1", "--quiet")
    assert code == 0, stderr
    assert "→ 4 devices, 2 unattributed" in stdout and "cluster-01" in stdout and "next: forensics fingerprint" in stdout
    ds = open_dataset(out)
    assert len(ds) == len(truth)
    by_device: dict[str, set[int]] = {}
    for frame, row in zip(ds.frames, _manifest(out / "manifest.csv")):
        assert set(row) >= {"file", "device", "source_file"}
        source = Path(row["source_file"])
        assert source.parent == folder and (out / row["file"]).is_file()
        if frame.device:
            by_device.setdefault(frame.device, set()).add(truth[source.name])
        else:
            assert truth[source.name] >= 4  # only the single-image cameras are unattributed
    assert len(by_device) == 4 and all(len(v) == 1 for v in by_device.values())
    assert len(open_dataset(out / "cluster-01")) == 3  # a device folder is a dataset for 'fingerprint build'


def test_cluster_json_and_report(cli_json, collection, tmp_path):
    folder, truth = collection
    payload = cli_json("cluster", folder, "-o", tmp_path / "out", "--workers", "2", "--report", tmp_path / "rep",
                       "--pfa", "1e-2", "--crop", "200")
    assert payload["n_images"] == len(truth) and payload["n_clusters"] == 4 and payload["n_unattributed"] == 2
    assert payload["p_fa"] == 1e-2 and payload["execution"]["workers"] == 2
    group = payload["groups"][0]
    assert group["crop"] == 200 and group["null"]["sigma_ci"][0] < group["null"]["sigma"] < group["null"]["sigma_ci"][1]
    assert group["threshold_merge_z"] > 3 and len(payload["images"]) == len(truth)
    assert payload["linked"] + payload["copied"] == len(truth)
    assert (tmp_path / "rep" / "index.html").is_file() and (tmp_path / "rep" / "similarity_0.png").is_file()
    assert (tmp_path / "out" / "clusters.json").is_file()


def test_cluster_refuses_bad_input_and_existing_output(cli, collection, tmp_path):
    folder, _ = collection
    code, _, err = cli("cluster", tmp_path / "missing", "-o", tmp_path / "out")
    assert code == 3 and "missing: does not exist" in err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert cli("cluster", empty, "-o", tmp_path / "out")[0] == 3
    few = tmp_path / "few"
    few.mkdir()
    for name in sorted(p.name for p in folder.iterdir())[:3]:
        (few / name).write_bytes((folder / name).read_bytes())
    code, _, err = cli("cluster", few, "-o", tmp_path / "out", "--workers", "1")
    assert code == 3 and "at least 5 images" in err
    (tmp_path / "taken").mkdir()
    code, _, err = cli("cluster", folder, "-o", tmp_path / "taken", "--workers", "1")
    assert code == 2 and "--force" in err
    code, _, err = cli("cluster", folder, "-o", folder / "inside", "--workers", "1")
    assert code == 2 and "input" in err
    assert cli("cluster", folder, "-o", tmp_path / "x", "--pfa", "2")[0] == 2
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out*"))  # nothing half-written
