"""Command-line tests of ``forensics fingerprint build|match`` and ``forensics same-device``.

Data: two simulated devices (PRNU σ_k = 1 %, 128×128 8-bit PNG, smooth scenes),
24 images each, written once per module.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from forensics.demo.prnu import sensor_model, simulated_set
from forensics.io.images import write_image

SIZE = (128, 128)
N = 24


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("prnu_cli")
    rng = np.random.default_rng(99)
    model = sensor_model("A", SIZE)
    out = {}
    for k, name in enumerate(("cam1", "cam2")):
        device = model.realize(rng, [0.0])
        images = simulated_set(device, N, 0.0, 500 + k, name)
        folder = root / name
        folder.mkdir()
        for i in range(N):
            write_image(folder / f"{name}_{i:03d}.png", images.load(i))
        out[name] = folder
    out["root"] = root
    return out


@pytest.fixture(scope="module")
def fingerprint(data) -> Path:
    """A fingerprint of cam1 built through the command."""
    from forensics.cli.main import main

    path = data["root"] / "cam1.npz"
    assert main(["fingerprint", "build", str(data["cam1"]), "-o", str(path), "--quiet"]) == 0
    return path


def test_build_json(cli_json, data, tmp_path):
    out = cli_json("fingerprint", "build", data["cam2"], "-o", tmp_path / "fp.npz", "--region", "center:64",
                   "--sigma", "3")
    assert out["n_images"] == N and out["region"] == "center:64" and out["shape"] == [64, 64]
    assert out["frame_shape"] == [128, 128] and len(out["files"]) == N
    assert (tmp_path / "fp.npz").is_file()
    from forensics.prnu.fingerprint import Fingerprint

    assert Fingerprint.load(tmp_path / "fp.npz").K.shape == (64, 64)


def test_build_summary_and_refusal(cli, data, fingerprint):
    code, out, err = cli("fingerprint", "build", data["cam1"], "-o", fingerprint, "--quiet")
    assert code == 2 and "already exists" in err and err.count("\n") == 1
    code, out, err = cli("fingerprint", "build", data["cam1"], "-o", fingerprint, "--quiet", "--force")
    assert code == 0 and f"Fingerprint of {N} images" in out and "next: forensics fingerprint match" in out


def test_build_on_two_workers_writes_the_same_fingerprint(cli_json, data, tmp_path):
    from forensics.prnu.fingerprint import Fingerprint

    one = cli_json("fingerprint", "build", data["cam1"], "-o", tmp_path / "one.npz", "--workers", "1")
    two = cli_json("fingerprint", "build", data["cam1"], "-o", tmp_path / "two.npz", "--workers", "2")
    assert one["execution"]["backend"] == "in-process"
    assert two["execution"]["backend"] == "processes" and two["execution"]["workers"] == 2
    fp1, fp2 = Fingerprint.load(tmp_path / "one.npz"), Fingerprint.load(tmp_path / "two.npz")
    assert np.array_equal(fp1.K, fp2.K) and fp1.files == fp2.files and fp1.n_images == N
    assert sorted(p.name for p in tmp_path.iterdir()) == ["one.npz", "two.npz"]  # no checkpoint left behind


def test_build_refuses_another_runs_checkpoint(cli, data, tmp_path):
    """A working folder left by a build with other settings is never mixed in: refused, or replaced with --force."""
    stale = tmp_path / ".fp.npz.partial"
    stale.mkdir()
    (stale / "config.json").write_text('{"command": "fingerprint build", "files": []}')
    code, _, err = cli("fingerprint", "build", data["cam2"], "-o", tmp_path / "fp.npz", "--quiet", "--workers", "1")
    assert code == 2 and "other settings" in err and stale.is_dir()
    code, _, err = cli("fingerprint", "build", data["cam2"], "-o", tmp_path / "fp.npz", "--quiet", "--workers", "1",
                       "--force")
    assert code == 0, err
    assert not stale.exists() and (tmp_path / "fp.npz").is_file()


def test_match_pce_json_decides(cli_json, data, fingerprint):
    own = cli_json("fingerprint", "match", fingerprint, data["cam1"])
    other = cli_json("fingerprint", "match", fingerprint, data["cam2"])
    assert own["metric"] == "pce" and own["threshold"] == 60 and own["shift_search"] == "zero shift"
    # the fingerprint's own images are scored too (in-sample: they match strongly); cam2's never do
    assert own["n_match"] == N and all(r["pce"]["p_fa"] < 1e-10 for r in own["scores"])
    assert other["n_match"] == 0 and max(r["score"] for r in other["scores"]) < 30
    assert {r["file"] for r in other["scores"]} == {f"cam2_{i:03d}.png" for i in range(N)}
    # one query per work item on two workers: the same scores, in the same order
    two = cli_json("fingerprint", "match", fingerprint, data["cam2"], "--workers", "2")
    one = cli_json("fingerprint", "match", fingerprint, data["cam2"], "--workers", "1")
    assert two["execution"]["backend"] == "processes" and one["execution"]["backend"] == "in-process"
    assert two["scores"] == one["scores"] == other["scores"]


def test_match_table_and_report(cli, data, fingerprint, tmp_path):
    code, out, err = cli("fingerprint", "match", fingerprint, data["cam2"], "--quiet", "--report", tmp_path / "rep",
                         "--shift-range", "3")
    assert code == 0, err
    assert "cam2_000.png" in out and "no match" in out and f"0 of {N} images reach the threshold 60" in out
    assert "shifts up to ±3" in out
    assert (tmp_path / "rep" / "index.html").is_file() and (tmp_path / "rep" / "scores.png").is_file()


def test_match_ncc_needs_a_threshold_for_decisions(cli, cli_json, data, fingerprint):
    out = cli_json("fingerprint", "match", fingerprint, data["cam2"], "--metric", "ncc")
    assert out["threshold"] is None and all(r["match"] is None for r in out["scores"])
    code, text, _ = cli("fingerprint", "match", fingerprint, data["cam2"], "--metric", "ncc", "--quiet")
    assert code == 0 and "no decisions" in text
    out = cli_json("fingerprint", "match", fingerprint, data["cam1"], "--metric", "ncc", "--threshold", "0.05")
    assert out["n_match"] == N
    code, _, err = cli("fingerprint", "match", fingerprint, data["cam2"], "--metric", "ncc", "--shift-range", "2")
    assert code == 2 and "PCE only" in err


def test_same_device_json_different_devices(cli_json, data):
    out = cli_json("same-device", data["cam1"], data["cam2"], "--region", "full", "--fingerprint-images", "8",
                   "--score-images", "16", "--bootstrap", "300", "--ageing-fingerprints", "4", "--ageing-images", "6",
                   "--seed", "3")
    assert out["decision"] == "different" and out["eer"] <= 0.05
    assert len(out["eer_ci"]) == 2 and out["eer_ci"][1] < 0.1
    assert "different devices" in out["verdict"]
    a = out["ageing"]
    assert a["n_fingerprints"] == [4, 4] and a["images_per_fingerprint"] == [6, 6]
    assert a["inter"]["mean"] < 0.5 * min(a["intra_a"]["mean"], a["intra_b"]["mean"])
    assert a["consistency"]["ci"][0] <= 0 <= a["consistency"]["ci"][1] and "share no detectable pattern" in a["verdict"]
    assert out["parameters"]["seed"] == 3 and out["sets"]["a"]["n_score"] == 16
    assert out["warnings"] == []  # every count as asked: nothing reduced
    assert out["execution"]["backend"] in ("processes", "in-process")  # all cores by default


def test_same_device_summary_report_and_power_warning(cli, data, tmp_path):
    half = tmp_path / "cam1_half"
    half.mkdir()
    for p in sorted(data["cam1"].glob("*.png"))[::2]:
        (half / p.name).symlink_to(p)
    code, out, err = cli("same-device", half, data["cam1"], "--region", "corners:32", "--bootstrap", "300",
                         "--ageing-fingerprints", "4", "--ageing-images", "3", "--quiet",
                         "--report", tmp_path / "rep")
    assert code == 0, err
    assert "Same-device test (NCC on region corners:32" in out and "EER" in out and "verdict:" in out
    assert "Fingerprint ageing (median residual" in out and "consistency" in out
    # 12 and 24 images: fewer than the defaults, so the statistical-power warning appears on stderr
    assert "warning: statistical power" in err and "points wide" in err
    for name in ("index.html", "histograms.png", "ageing.png"):
        assert (tmp_path / "rep" / name).is_file()
    html = (tmp_path / "rep" / "index.html").read_text()
    assert "forensics same-device" in html and "consistency" in html


def test_same_device_report_has_det_curve(cli, data, tmp_path):
    """Two sets of one camera overlap, so the DET curve has points to draw."""
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir(), b.mkdir()
    for n, p in enumerate(sorted(data["cam1"].glob("*.png"))):
        ((a if n % 2 else b) / p.name).symlink_to(p)
    code, out, err = cli("same-device", a, b, "--region", "full", "--bootstrap", "300", "--ageing-fingerprints", "0",
                         "--json", "--report", tmp_path / "rep")
    assert code == 0, err
    res = json.loads(out)
    assert res["eer_ci"][0] <= 0.5 <= res["eer_ci"][1] and res["decision"] == "indistinguishable"
    assert res["ageing"] is None
    assert (tmp_path / "rep" / "det.png").is_file()


@pytest.mark.parametrize("argv, fragment", [
    (["same-device", "{missing}", "{cam1}"], "missing: does not exist"),
    (["fingerprint", "build", "{empty}", "-o", "{tmp}/x.npz"], "no images found"),
    (["fingerprint", "match", "{cam1}/cam1_000.png", "{cam2}"], "not a fingerprint file"),
    (["fingerprint", "match", "{tmp}/none.npz", "{cam2}"], "no such fingerprint file"),
    (["same-device", "{cam1}", "{cam2}"], "do not fit"),  # default corners:128 on 128×128 frames
])
def test_bad_input_exit_3_one_line(cli, data, tmp_path, argv, fragment):
    empty = tmp_path / "empty"
    empty.mkdir()
    fill = {"missing": tmp_path / "missing", "cam1": data["cam1"], "cam2": data["cam2"], "empty": empty,
            "tmp": tmp_path}
    code, out, err = cli(*(a.format(**fill) for a in argv), "--quiet")
    assert code == 3, err
    assert err.startswith("forensics: error:") and err.count("\n") == 1 and fragment in err
    assert out == ""


@pytest.mark.parametrize("argv", [["same-device"], ["fingerprint", "build"], ["fingerprint", "match"]])
def test_help_has_an_example(cli, argv):
    code, out, _ = cli(*argv, "--help")
    assert code == 0 and "example:" in out and "forensics " + " ".join(argv) in out
