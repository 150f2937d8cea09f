"""Command-line tests of ``forensics fingerprint db add|list|remove``.

Fingerprints are small: 64×64 arrays saved directly, and two built from three 64×64 PNG
images each whose EXIF names the camera (make, model, body serial) and the capture dates.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from forensics.prnu.fingerprint import Fingerprint

SHAPE = (64, 64)


def _save(path: Path, seed: int, n_images: int = 4) -> Path:
    k = np.random.default_rng(seed).standard_normal(SHAPE).astype(np.float32)
    Fingerprint(K=k, region="full", sigma=3.0, files=[], n_images=n_images, frame_shape=SHAPE).save(path)
    return path


@pytest.fixture(scope="module")
def fps(tmp_path_factory) -> dict[str, Path]:
    """'a', 'b': bare fingerprints (no source files); 'sn1', 'sn2': built from images whose EXIF names the camera."""
    from forensics.io.images import write_image
    from forensics.prnu.fingerprint import build_fingerprint

    root = tmp_path_factory.mktemp("db_cli")
    out = {"a": _save(root / "a.npz", 1), "b": _save(root / "b.npz", 2)}
    rng = np.random.default_rng(8)
    for serial in ("SN1", "SN2"):
        images = [write_image(root / serial / f"{i}.png", rng.integers(50, 200, SHAPE, dtype=np.uint8),
                              metadata={"Make": "ACME", "Model": "Cam", "Exif:BodySerialNumber": serial,
                                        "Exif:DateTimeOriginal": f"2012:0{i + 1}:15 10:00:00"})
                  for i in range(3)]
        out[serial.lower()] = build_fingerprint(images).save(root / f"{serial}.npz")
    return out


def test_add_list_remove_json(cli_json, fps, tmp_path):
    db = tmp_path / "db"
    added = cli_json("fingerprint", "db", "add", db, fps["a"], "--device", "cam A", "--make", "ACME", "--serial", "1")
    assert added["n_devices"] == 1 and added["replaced"] == []
    entry = added["added"][0]
    assert entry["device_id"] == "cam A" and entry["make"] == "ACME" and entry["serial"] == "1"
    assert entry["provenance"]["fingerprint_file"] == str(fps["a"].resolve()) and (db / entry["file"]).is_file()
    cli_json("fingerprint", "db", "add", db, fps["b"], "--device", "cam B")
    listed = cli_json("fingerprint", "db", "list", db)
    assert listed["n_devices"] == 2 and [e["device_id"] for e in listed["entries"]] == ["cam A", "cam B"]
    assert listed["entries"][0] == entry  # list --json gives every entry's to_dict
    from forensics.prnu.database import FingerprintDatabase

    k = np.load(fps["b"])["K"]
    assert np.array_equal(FingerprintDatabase(db).load("cam B").K, k)
    removed = cli_json("fingerprint", "db", "remove", db, "cam A")
    assert removed["removed"]["device_id"] == "cam A" and removed["n_devices"] == 1
    assert [e["device_id"] for e in cli_json("fingerprint", "db", "list", db)["entries"]] == ["cam B"]


def test_ids_from_exif_several_files_and_the_table(cli, cli_json, fps, tmp_path):
    db = tmp_path / "db"
    out = cli_json("fingerprint", "db", "add", db, fps["sn1"], fps["sn2"])
    assert [e["device_id"] for e in out["added"]] == ["ACME Cam #SN1", "ACME Cam #SN2"]
    assert all(e["n_images"] == 3 and e["quality"] == pytest.approx(3.0) for e in out["added"])
    code, text, err = cli("fingerprint", "db", "list", db)
    assert code == 0, err
    lines = text.splitlines()
    assert lines[0].split() == ["device", "make", "model", "serial", "region", "size", "images", "captured", "quality"]
    assert "ACME Cam #SN1" in lines[1] and "SN1" in lines[1] and "64×64" in lines[1]
    assert "2012-01-15–2012-03-15" in lines[1]  # the capture-date range of the source images
    assert "2 device(s)" in lines[-1] and "higher is better" in lines[-1]


def test_duplicates_replace_and_all_or_nothing(cli, cli_json, fps, tmp_path):
    db = tmp_path / "db"
    cli_json("fingerprint", "db", "add", db, fps["a"], "--device", "cam")
    code, out, err = cli("fingerprint", "db", "add", db, fps["b"], "--device", "cam")
    assert code == 2 and "already in the database" in err and "--replace" in err and err.count("\n") == 1
    out = cli_json("fingerprint", "db", "add", db, fps["b"], "--device", "cam", "--replace")
    assert out["replaced"] == ["cam"] and out["n_devices"] == 1
    code, out, err = cli("fingerprint", "db", "add", db, fps["sn1"], fps["a"])  # 'a' has no device id: none added
    assert code == 2 and "--device" in err
    assert [e["device_id"] for e in cli_json("fingerprint", "db", "list", db)["entries"]] == ["cam"]


def test_bad_input_and_usage(cli, fps, tmp_path):
    db = tmp_path / "db"
    code, out, err = cli("fingerprint", "db", "add", db, fps["a"], fps["b"], "--device", "x")
    assert code == 2 and "one FP file" in err and not db.exists()
    code, out, err = cli("fingerprint", "db", "add", db, tmp_path / "missing.npz", "--device", "x")
    assert code == 3 and "missing.npz: no such fingerprint file" in err and not db.exists()
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a fingerprint")
    code, out, err = cli("fingerprint", "db", "add", db, bad, "--device", "x")
    assert code == 3 and "not a fingerprint file" in err
    code, out, err = cli("fingerprint", "db", "add", db, fps["a"])  # no device id: refused, and no database made
    assert code == 2 and "--device" in err
    assert not db.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["bad.npz"]  # nor any temporary
    code, out, err = cli("fingerprint", "db", "list", tmp_path / "nowhere")
    assert code == 3 and "nowhere: no such fingerprint database" in err
    code, out, err = cli("fingerprint", "db", "list", fps["a"].parent)  # a folder of other things
    assert code == 3 and "not a fingerprint database" in err
    code, out, err = cli("fingerprint", "db", "add", db, fps["a"], "--device", "x")
    assert code == 0
    code, out, err = cli("fingerprint", "db", "remove", db, "y")
    assert code == 2 and "no device 'y'" in err and "db list" in err
    code, out, err = cli("fingerprint", "db", "list", db)
    assert code == 0 and out.startswith("device")
    code, out, err = cli("fingerprint", "db", "remove", db, "x")
    assert code == 0 and "removed 'x'" in out
    code, out, err = cli("fingerprint", "db", "list", db)
    assert code == 0 and "no devices" in out
    code, out, err = cli("fingerprint", "db")
    assert code == 2


@pytest.mark.parametrize("what", ["add", "list", "remove"])
def test_help_has_an_example(cli, what):
    code, out, _ = cli("fingerprint", "db", what, "--help")
    assert code == 0 and f"example:\n  forensics fingerprint db {what} " in out and "--json" in out


def test_json_is_one_object(cli, fps, tmp_path):
    code, out, err = cli("fingerprint", "db", "add", tmp_path / "db", fps["a"], "--device", "x", "--json", "--quiet")
    assert code == 0 and err == "" and json.loads(out)["added"][0]["device_id"] == "x"
