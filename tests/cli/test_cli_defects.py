"""The commands: forensics defects detect|growth, forensics date, forensics validate (on disk, simulated)."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from forensics.cli.main import main
from forensics.sensor.presets import preset
from forensics.sensor.simulate import age_dataset, make_scenes

SHAPE = (96, 128)


@pytest.fixture(scope="module")
def aged(tmp_path_factory):
    root = tmp_path_factory.mktemp("defects")
    src = make_scenes(root / "scenes", 12, SHAPE, 0, bit_depth=16)
    model = preset("G", SHAPE, bit_depth=16, rate_scale=300)
    age_dataset(src, root / "aged", model, [0, 4, 8, 12], rng=1, start_year=2000.0, sensor_name="G")
    return root


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_help_has_examples(capsys):
    for argv in (["defects", "detect", "--help"], ["defects", "growth", "--help"], ["date", "--help"],
                 ["validate", "--help"]):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 0
        out = capsys.readouterr().out
        assert "example:" in out and "forensics " in out.split("example:")[1]


def test_detect_json_and_report(aged, capsys, tmp_path):
    code, out, err = run(capsys, "defects", "detect", str(aged / "aged" / "year_008"), "--json", "--report",
                         str(tmp_path / "rep"))
    assert code == 0
    d = json.loads(out)
    assert d["counts"]["partial"] >= 10
    assert {"x", "y", "kind", "amplitude", "z"} <= set(d["defects"][0])
    assert d["threshold"]["sigma"] == 5.0 and d["threshold"]["q"] == 9
    assert (tmp_path / "rep" / "index.html").exists()
    assert (tmp_path / "rep" / "accumulated_histogram.png").exists()
    assert (tmp_path / "rep" / "defect_map.png").exists()
    code, out, _ = run(capsys, "defects", "detect", str(aged / "aged" / "year_008"), "--tau", "5000", "--mask", "all",
                       "--q", "5")
    assert code == 0 and "partially stuck" in out and "τ = 5000" in out


def test_growth_then_date(aged, capsys, tmp_path):
    sets = [str(aged / "aged" / f"year_{a:03d}") for a in (0, 4, 8)]
    model = tmp_path / "model.json"
    code, out, _ = run(capsys, "defects", "growth", *sets, "-o", str(model), "--json", "--report", str(tmp_path / "g"))
    assert code == 0
    d = json.loads(out)
    lo, hi = d["rate_partial_ci"]
    assert lo <= d["rate_partial"] <= hi and d["rate_units"] == "defects/MP/year"
    assert d["threshold"]["sigma"] == 5.0 and len(d["epochs"]) == 3
    assert model.exists() and (tmp_path / "g" / "growth_counts.png").exists()
    # a later set, dated from the saved model
    code, out, _ = run(capsys, "date", str(aged / "aged" / "year_012"), "--model", str(model), "--json",
                       "--report", str(tmp_path / "d"))
    assert code == 0
    r = json.loads(out)
    assert r["query"] == "set" and r["interval"][0] <= r["estimate"] <= r["interval"][1]
    assert (tmp_path / "d" / "set_dating.png").exists()
    # a single image, dated from reference sets
    code, out, _ = run(capsys, "date", str(aged / "aged" / "year_008" / "scene_0003.png"), "--reference", *sets,
                       "--report", str(tmp_path / "i"))
    assert code == 0 and "estimated capture date" in out
    assert (tmp_path / "i" / "dating_likelihood.png").exists()
    # refusing to overwrite without --force
    code, _, err = run(capsys, "defects", "growth", *sets, "-o", str(model))
    assert code == 2 and "already exists" in err


def test_bad_input(aged, capsys, tmp_path):
    few = make_scenes(tmp_path / "few", 5, SHAPE, 3, bit_depth=16, start_year=2001.0)
    code, _, err = run(capsys, "defects", "detect", str(few.root))
    assert code == 0 and "fewer than 10" in err and "false" in err
    nodate = make_scenes(tmp_path / "nodate", 10, SHAPE, 4, bit_depth=16)
    code, _, err = run(capsys, "defects", "growth", str(aged / "aged" / "year_000"), str(nodate.root))
    assert code == 3 and "'captured'" in err
    other = make_scenes(tmp_path / "other", 10, (96, 120), 5, bit_depth=16, start_year=2010.0)
    code, _, err = run(capsys, "defects", "growth", str(aged / "aged" / "year_000"), str(other.root))
    assert code == 3 and "same size" in err
    dev = make_scenes(tmp_path / "dev", 10, SHAPE, 6, bit_depth=16, start_year=2010.0, device="someone-else")
    code, _, err = run(capsys, "defects", "growth", str(aged / "aged" / "year_000"), str(dev.root))
    assert code == 3 and "device" in err
    code, _, err = run(capsys, "defects", "growth", str(aged / "aged" / "year_000"))
    assert code == 2 and "at least two" in err
    code, _, err = run(capsys, "date", str(tmp_path / "missing"), "--model", "x.json")
    assert code == 3


def test_validate_command(capsys, tmp_path):
    code, out, _ = run(capsys, "validate", "defects", "--sensor", "F", "--trials", "3", "--size", "64x64",
                       "--json", "--report", str(tmp_path / "v"))
    d = json.loads(out)
    assert d["what"] == "defects" and d["trials"] == 3 and code in (0, 1)
    assert any(m["name"].startswith("detection recall") for m in d["metrics"])
    assert (tmp_path / "v" / "coverage.png").exists() and (tmp_path / "v" / "recall.png").exists()
    code, out, _ = run(capsys, "validate", "dating", "--trials", "2", "--size", "64x64")
    assert "set dating" in out and code in (0, 1)
    code, _, err = run(capsys, "validate", "defects", "--sensor", "Z", "--trials", "2")
    assert code == 2


REAL = Path(__file__).resolve().parents[2].parent / "shared/data/dresden-nikon"


@pytest.mark.realdata
@pytest.mark.skipif(not (REAL / "flat").is_dir(), reason=f"real images not found at {REAL}")
def test_detect_on_real_flat_fields(capsys, tmp_path):
    """Ten JPEG flat fields of one Nikon D70: few outliers, a tight d̂ distribution, JSON as documented."""
    folder = tmp_path / "d70"
    folder.mkdir()
    for f in sorted((REAL / "flat").glob("Nikon_D70_0_*.JPG")):
        (folder / f.name).symlink_to(f)
    code, out, err = run(capsys, "defects", "detect", str(folder), "--mask", "all", "--json")
    assert code == 0
    d = json.loads(out)
    assert d["shape"] == [2000, 3008] and d["n_images"] == 10
    assert d["fits"][0]["scale"] < 2.0  # flat fields: d̂ is sensor noise and PRNU, not scene
    assert 0 < d["counts"]["partial"] < 1000
    # flat fields hardly change between frames: with a loose tolerance the stuck test is refused, with a warning
    code, out, err = run(capsys, "defects", "detect", str(folder), "--mask", "all", "--stuck-tolerance", "3")
    assert code == 0 and "stuck test cannot" in err and "0 stuck" in out


def test_workers_do_not_change_the_results(aged, capsys, monkeypatch):
    """detect, growth and date with two worker processes print the JSON of one process, bit for bit."""
    import forensics.io.stack

    monkeypatch.setattr(forensics.io.stack, "STACK_CHUNK", 5)  # 12 frames a set: three chunks merged per set
    sets = [str(aged / "aged" / f"year_{a:03d}") for a in (0, 4, 8)]
    commands = (["defects", "detect", sets[2]], ["defects", "growth", *sets],
                ["date", str(aged / "aged" / "year_012"), "--reference", *sets])
    for argv in commands:
        outputs = {}
        for workers in ("1", "2"):
            code, out, err = run(capsys, *argv, "--json", "--workers", workers)
            assert code == 0, err
            outputs[workers] = json.loads(out)
        assert outputs["1"].pop("execution")["backend"] == "in-process"
        assert outputs["2"].pop("execution") == {"backend": "processes", "workers": 2, "scheduler": None,
                                                 "dashboard": None}
        assert outputs["1"] == outputs["2"], argv
