"""Command-line regressions of issue 26 for the PRNU commands: damaged fingerprint files, a damaged database
index, content-free image sets, one set given twice and bad option values each end in one line on stderr with
the documented exit code (3 bad input data, 2 usage), never a traceback, and nothing outside the database is
touched.

Data: two simulated devices (sensor model, PRNU σ_k = 1 %, 96×128 8-bit PNG), six images each; black and white
sets of constant frames; one fingerprint file and damaged copies of it.
"""
from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from forensics.demo.prnu import sensor_model, simulated_set
from forensics.io.images import write_image
from forensics.prnu.fingerprint import build_fingerprint

SIZE = (96, 128)


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("prnu_inputs")
    rng = np.random.default_rng(26)
    model = sensor_model("A", SIZE, sigma_k=0.01)
    out: dict[str, Path] = {"root": root}
    for k in range(2):
        images = simulated_set(model.realize(rng, [0.0]), 6, 0.0, 300 + k, f"cam{k}")
        folder = root / f"cam{k}"
        folder.mkdir()
        for i in range(6):
            write_image(folder / f"{i}.png", images.load(i))
        out[f"cam{k}"] = folder
    for name, value in (("black", 0), ("white", 255)):
        folder = root / name
        folder.mkdir()
        for i in range(6):
            write_image(folder / f"{i}.png", np.full(SIZE, value, np.uint8))
        out[name] = folder
    good = build_fingerprint(sorted(out["cam0"].glob("*.png"))).save(root / "cam0.npz")
    raw = good.read_bytes()
    (root / "truncated.npz").write_bytes(raw[: len(raw) // 2])
    with np.load(good) as npz:
        k, meta = npz["K"], json.loads(str(npz["meta"][()]))
    np.savez(root / "nokey.npz", K=k, meta=np.array(json.dumps({x: v for x, v in meta.items() if x != "frame_shape"})))
    np.savez(root / "wrongtype.npz", K=k, meta=np.array(json.dumps({**meta, "n_images": "six"})))
    np.savez(root / "nan.npz", K=np.full_like(k, np.nan), meta=np.array(json.dumps(meta)))
    out.update(good=good, truncated=root / "truncated.npz", nokey=root / "nokey.npz",
               wrongtype=root / "wrongtype.npz", nan=root / "nan.npz")
    return out


def _one_line_error(result: tuple[int, str, str], code: int, fragment: str) -> None:
    exit_code, _, err = result
    assert exit_code == code, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("forensics: error:") and fragment in lines[0], err
    assert "Traceback" not in err


@pytest.mark.parametrize("damaged", ["truncated", "nokey", "wrongtype", "nan"])
def test_damaged_fingerprint_files_exit_3_in_one_line(cli, data, tmp_path, damaged):
    """D20: db add, fingerprint match and identify (through a database entry) on a truncated .npz, metadata
    missing a key or of the wrong type, or an all-NaN K: one line naming the file, exit 3."""
    bad = data[damaged]
    name = bad.name
    _one_line_error(cli("fingerprint", "db", "add", tmp_path / "db", bad, "--device", "x"), 3, name)
    assert not (tmp_path / "db").exists()  # a failed first add leaves no database behind
    _one_line_error(cli("fingerprint", "match", bad, data["cam0"], "--workers", "1", "--quiet"), 3, name)
    # a database whose entry's file was damaged afterwards
    code, _, err = cli("fingerprint", "db", "add", tmp_path / "db2", data["good"], "--device", "cam0")
    assert code == 0, err
    stored = next((tmp_path / "db2" / "fingerprints").glob("*.npz"))
    stored.write_bytes(bad.read_bytes())
    _one_line_error(cli("identify", data["cam1"], "--db", tmp_path / "db2", "--workers", "1", "--quiet"), 3,
                    stored.name)


def test_a_damaged_index_deletes_nothing_outside_the_database(cli, data, tmp_path):
    """D03: index rows naming '../victim' or an absolute path make db remove and db add --replace exit 3 in one
    line, and the victim file survives."""
    db = tmp_path / "db"
    assert cli("fingerprint", "db", "add", db, data["good"], "--device", "camA")[0] == 0
    victim = tmp_path / "victim"
    victim.write_text("keep me")
    for planted in ("../victim", str(victim)):
        with sqlite3.connect(db / "index.sqlite") as con:
            con.execute("UPDATE devices SET file = ?", (planted,))
        con.close()
        _one_line_error(cli("fingerprint", "db", "remove", db, "camA"), 3, "the index is damaged")
        _one_line_error(cli("fingerprint", "db", "add", db, data["good"], "--device", "camA", "--replace"), 3,
                        "the index is damaged")
        assert victim.read_text() == "keep me"


def test_db_remove_strips_the_id_and_identical_fingerprints_are_refused(cli, data, tmp_path):
    """D21 and D16 at the command line."""
    db = tmp_path / "db"
    assert cli("fingerprint", "db", "add", db, data["good"], "--device", "camA")[0] == 0
    _one_line_error(cli("fingerprint", "db", "add", db, data["good"], "--device", "camB"), 2,
                    "identical to the fingerprint of device 'camA'")
    code, out, err = cli("fingerprint", "db", "remove", db, " camA ")
    assert code == 0 and "removed 'camA'" in out, err


def test_content_free_sets_are_refused_and_left_out(cli, cli_json, data, tmp_path):
    """D06/D07: a fingerprint of black frames, matching black frames, identifying them and same-device black
    against white are refused (exit 3, naming the set and why); a content-free frame among good ones is left
    out with a warning."""
    _one_line_error(cli("fingerprint", "build", data["black"], "-o", tmp_path / "b.npz", "--workers", "1",
                        "--quiet"), 3, "content-free")
    assert not (tmp_path / "b.npz").exists()
    _one_line_error(cli("fingerprint", "match", data["good"], data["black"], "--workers", "1", "--quiet"), 3,
                    "black: every one of its 6 frame(s) is content-free")
    db = tmp_path / "db"
    assert cli("fingerprint", "db", "add", db, data["good"], "--device", "cam0")[0] == 0
    _one_line_error(cli("identify", data["white"], "--db", db, "--workers", "1", "--quiet"), 3, "all saturated")
    _one_line_error(cli("same-device", data["black"], data["white"], "--region", "full", "--workers", "1", "--quiet",
                        "--ageing-fingerprints", "0"), 3, "all black")
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    for p in sorted(data["cam0"].glob("*.png")):
        (mixed / p.name).write_bytes(p.read_bytes())
    (mixed / "z_black.png").write_bytes((data["black"] / "0.png").read_bytes())
    code, out, err = cli("fingerprint", "match", data["good"], mixed, "--workers", "1", "--quiet")
    assert code == 0 and "z_black.png" in out and "content-free" in out, err
    assert "1 of 7 frames of" in err and "left out" in err
    ident = cli_json("identify", mixed, "--db", db, "--workers", "1", "--quiet")
    assert ident["n_excluded"] == 1 and ident["n_attributed"] == 6


def test_same_set_twice_and_bad_sigma_are_usage_errors(cli, data):
    """D20/D21: same-device X X and identify --sigma -1 (or nan) exit 2 before any work."""
    _one_line_error(cli("same-device", data["cam0"], data["cam0"], "--region", "full", "--workers", "1", "--quiet"),
                    2, "are the same 6 images")
    for value in ("-1", "nan", "0"):
        code, _, err = cli("identify", data["cam0"], "--db", data["root"], f"--sigma={value}")
        assert code == 2 and "argument --sigma" in err and "Traceback" not in err, err


def test_identify_reports_both_shares_of_the_budget(cli, cli_json, data, tmp_path):
    """D25: with a larger sensor in the database, --json and the summary give the aligned and the searched
    share, each with its count and threshold."""
    from forensics.prnu.fingerprint import Fingerprint

    db = tmp_path / "db"
    assert cli("fingerprint", "db", "add", db, data["good"], "--device", "cam0")[0] == 0
    k = np.random.default_rng(5).standard_normal((128, 160)).astype(np.float32)
    Fingerprint(k, "full", 3.0, [], 8, (128, 160)).save(tmp_path / "big.npz")
    assert cli("fingerprint", "db", "add", db, tmp_path / "big.npz", "--device", "big")[0] == 0
    out = cli_json("identify", data["cam0"], "--db", db, "--workers", "1", "--quiet")
    budget = out["queries"][0]["budget"]
    assert budget["aligned"]["n_tests"] == 1 and budget["searched"]["n_tests"] == 33 * 33
    assert budget["aligned"]["share"] == budget["searched"]["share"] == 0.5
    assert budget["aligned"]["pce_threshold"] < budget["searched"]["pce_threshold"]
    assert out["n_attributed"] == 6
    code, text, err = cli("identify", data["cam0"], "--db", db, "--workers", "1", "--quiet", "--report",
                          tmp_path / "report")
    assert code == 0 and "false-alarm budget (6 image(s)): aligned 50 % over 1 test(s)" in text, err
    assert "crop/scale search 50 % over 1,089 position(s)" in text
    page = (tmp_path / "report" / "index.html").read_text()
    assert "PCE needed aligned" in page and "PCE needed searched" in page
