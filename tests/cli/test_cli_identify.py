"""Command-line tests of ``forensics identify``.

Data: four simulated devices (sensor model, PRNU σ_k = 1 %, 160×192 8-bit PNG); fingerprints of three of
them in a database built through its API, and a set of their images — full frames, a quarter-turned
frame, a crop — plus one image of the fourth device, which is in no fingerprint.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from forensics.demo.prnu import sensor_model, simulated_set
from forensics.io.images import write_image
from forensics.prnu.fingerprint import build_fingerprint

SIZE = (160, 192)


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> dict[str, Path]:
    from forensics.prnu.database import FingerprintDatabase

    root = tmp_path_factory.mktemp("identify_cli")
    rng = np.random.default_rng(12)
    model = sensor_model("A", SIZE, sigma_k=0.01)
    devices = [model.realize(rng, [0.0]) for _ in range(4)]
    db = FingerprintDatabase(root / "db", create=True)
    for i, device in enumerate(devices[:3]):
        db.add(build_fingerprint(simulated_set(device, 8, 0.0, 100 + i, f"cam{i}")), f"cam{i}", make="Sim")
    photos = root / "photos"
    photos.mkdir()
    for i, device in enumerate(devices):
        image = simulated_set(device, 1, 0.0, 200 + i, "q").load(0)
        write_image(photos / f"{i}_full.png", image)
        if i == 0:
            write_image(photos / "0_turned.png", np.ascontiguousarray(np.rot90(image)))
        if i == 1:
            write_image(photos / "1_crop.png", image[30:150, 40:170])
    return {"root": root, "db": root / "db", "photos": photos}


def test_identify_json(cli_json, data):
    out = cli_json("identify", data["photos"], "--db", data["db"], "--workers", "1", "--top", "2")
    assert out["n_images"] == 6 and out["n_fingerprints"] == 3 and out["pfa"] == 0.001
    by_file = {q["source"]: q for q in out["queries"]}
    assert by_file["0_full.png"]["device_id"] == "cam0" and by_file["0_turned.png"]["device_id"] == "cam0"
    assert by_file["0_turned.png"]["best"]["rotation"] == 3
    assert by_file["1_crop.png"]["device_id"] == "cam1" and by_file["1_crop.png"]["best"]["offset"] == [30, 40]
    assert by_file["2_full.png"]["device_id"] == "cam2"
    assert by_file["3_full.png"]["decision"] == "unknown" and by_file["3_full.png"]["device_id"] is None
    for q in out["queries"]:
        assert len(q["top"]) == 2 and q["runner_up"] is not None and q["pce_threshold"] > 0
    assert out["counts"] == {"cam0": 2, "cam1": 2, "cam2": 1}
    assert out["devices"][0]["make"] == "Sim" and "Šidák" in out["correction"]
    assert out["database"] == str(data["db"]) and out["execution"]["backend"] == "in-process"


def test_identify_summary_and_report(cli, data, tmp_path):
    code, out, err = cli("identify", data["photos"], "--db", data["db"], "--workers", "2", "--quiet",
                         "--report", tmp_path / "rep", "--scales", "0.95:1.0", "--rotations", "all")
    assert code == 0, err
    lines = out.splitlines()
    assert lines[0].startswith("Identification of 6 images") and "p_FA ≤ 0.001" in lines[0]
    row = next(line for line in lines if line.startswith("1_crop.png"))
    assert "cam1" in row and "attributed" in row and "at (30, 40)" in row
    assert "unknown" in next(line for line in lines if line.startswith("3_full.png"))
    assert "5 attributed, 1 unknown" in out
    page = (tmp_path / "rep" / "index.html").read_text()
    assert "best_pce.png" in page and "1_crop.png" in page and (tmp_path / "rep" / "best_pce.png").stat().st_size > 0
    # the report is not overwritten without --force
    code, _, err = cli("identify", data["photos"], "--db", data["db"], "--workers", "1", "--report", tmp_path / "rep")
    assert code == 2 and "exists" in err


def test_identify_bad_input(cli, data, tmp_path):
    code, _, err = cli("identify", data["photos"], "--db", tmp_path / "nowhere", "--workers", "1")
    assert code == 3 and "nowhere" in err
    code, _, err = cli("identify", tmp_path / "no_photos", "--db", data["db"], "--workers", "1")
    assert code == 3 and "no_photos" in err
    code, _, err = cli("identify", data["photos"], "--db", data["db"], "--pfa", "2")
    assert code == 2 and "--pfa" in err
    code, _, err = cli("identify", data["photos"], "--db", data["db"], "--scales", "big", "--workers", "1")
    assert code == 2 and "scales" in err


def test_identify_help_has_an_example(cli):
    code, out, _ = cli("identify", "--help")
    assert code == 0 and "example:" in out and "--db" in out


def test_identify_json_is_strict(cli, data):
    code, out, err = cli("identify", data["photos"], "--db", data["db"], "--workers", "1", "--json")
    assert code == 0, err
    json.loads(out, parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"))
