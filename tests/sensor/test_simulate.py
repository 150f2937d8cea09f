"""The ageing simulation end to end: per-step datasets, ground truth, determinism, bad input, CLI."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from forensics.io.dataset import open_dataset
from forensics._shared.errors import InputError, UsageError
from forensics.io.images import read_image, write_image
from forensics.sensor.catalogue import STUCK
from forensics.sensor.presets import preset
from forensics.sensor.simulate import age_dataset, make_scenes, parse_years, read_catalogue


@pytest.fixture
def tiff16(tmp_path):
    """A folder of 16-bit grey TIFF scenes."""
    return make_scenes(tmp_path / "src", 4, (60, 80), rng=3, bit_depth=16, ext=".tif", kind="texture")


def test_parse_years():
    assert parse_years("0:96:8") == [8.0 * i for i in range(13)]
    assert parse_years("0,4,2.5") == [0.0, 2.5, 4.0]
    # malformed, not finite, negative, repeated (also in the folder names, one decimal), too many ages
    for bad in ("0:96", "0:96:0", "a:b:c", "5:1:1", "-1,2", "nan", "0,nan", "0:inf:1", "0:8:nan", "0,8,8",
                "0,0.11,0.14", "0:1e6:1", "0:1:1e-320"):
        with pytest.raises(UsageError, match="--years"):
            parse_years(bad)


def test_ageing_16bit_tiffs_satisfies_the_invariants(tiff16, tmp_path):
    ages = parse_years("0:96:24")
    model = preset("H", (60, 80), bit_depth=16, rate_scale=20.0)
    result = age_dataset(tiff16, tmp_path / "aged", model, ages, rng=9, start_year=2001.0, sensor_name="H")
    sensor = json.loads((tmp_path / "aged" / "sensor.json").read_text())
    assert sensor["seed"] == 9 and sensor["size"] == {"width": 80, "height": 60, "channels": 1}
    assert sensor["model"]["effects"][0]["params"]["rate_partial"] == pytest.approx(8 * 0.6659 * 20)
    catalogue = read_catalogue(tmp_path / "aged" / "defects.csv")
    assert len(catalogue) > 20
    sources = [f.load().astype(np.int64) for f in tiff16]
    previous_defective = None
    for age, step in zip(ages, result.steps):
        ds = open_dataset(step)
        assert len(ds) == len(tiff16)
        assert [f.captured for f in ds] == pytest.approx([2001.0 + age] * len(ds))
        eff = catalogue.effective(2001.0 + age)
        defective = set(zip(eff.y.tolist(), eff.x.tolist()))
        if previous_defective is not None:
            assert previous_defective <= defective  # once defective, always defective
        previous_defective = defective
        for frame, src in zip(ds, sources):
            image = frame.load()
            assert image.dtype == np.uint16
            changed = set(zip(*np.nonzero(image.astype(np.int64) != src)))
            assert changed <= defective  # only defect sites differ from the source
            for x, y, kind, amp in zip(eff.x, eff.y, eff.kind, eff.amplitude):
                want = amp if kind == STUCK else src[y, x] + amp
                assert image[y, x] == np.clip(np.rint(np.float32(want)), 0, 65535)
    assert result.counts["partial"][0] == 0 and result.counts["stuck"][0] == 0


def test_rgb_8bit_and_determinism(tmp_path):
    src = make_scenes(tmp_path / "src", 2, (40, 50), rng=1, channels=3)
    model = preset("G", (40, 50), rate_scale=200.0)
    for name in ("a", "b"):
        age_dataset(src, tmp_path / name, model, [0.0, 10.0], rng=5, start_year=2000.0)
    assert (tmp_path / "a" / "defects.csv").read_text() == (tmp_path / "b" / "defects.csv").read_text()
    for f in ("year_010/scene_0000.png", "year_010/scene_0001.png"):
        a, b = (open_dataset(tmp_path / n / "year_010") for n in "ab")
        np.testing.assert_array_equal(a[0].load(), b[0].load())
        assert a[0].load().shape == (40, 50, 3)
    age_dataset(src, tmp_path / "c", model, [0.0, 10.0], rng=6, start_year=2000.0)
    assert (tmp_path / "c" / "defects.csv").read_text() != (tmp_path / "a" / "defects.csv").read_text()


def test_defects_csv_columns(tmp_path):
    src = make_scenes(tmp_path / "src", 1, (30, 30), rng=1)
    age_dataset(src, tmp_path / "aged", preset("B", (30, 30), rate_scale=1000.0), [0.0, 5.0], rng=1)
    with open(tmp_path / "aged" / "defects.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert rows and set(rows[0]) >= {"x", "y", "kind", "amplitude", "onset_year"}
    assert {r["kind"] for r in rows} <= {"partial", "stuck"}


def test_mixed_sizes_fail_before_writing(tmp_path):
    make_scenes(tmp_path / "src", 2, (30, 30), rng=1)
    write_image(tmp_path / "src" / "odd.png", np.zeros((31, 30), np.uint8))
    (tmp_path / "src" / "manifest.csv").unlink()
    with pytest.raises(InputError, match=r"odd\.png: size"):
        age_dataset(open_dataset(tmp_path / "src"), tmp_path / "out", preset("A", (30, 30)), [0.0, 1.0], rng=1)
    assert not (tmp_path / "out").exists()


def test_corrupt_file_leaves_nothing_half_written(tmp_path):
    make_scenes(tmp_path / "src", 3, (30, 30), rng=1)
    bad = tmp_path / "src" / "scene_0002.png"
    bad.write_bytes(bad.read_bytes()[:200])
    with pytest.raises(InputError, match="scene_0002.png"):
        age_dataset(open_dataset(tmp_path / "src"), tmp_path / "out", preset("A", (30, 30)), [0.0, 1.0], rng=1)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]  # no output, no temporary folder


# ----------------------------------------------------------------------------- command line
def test_cli_simulate_scenes_and_age(cli, cli_json, tmp_path):
    out = cli_json("simulate", "scenes", tmp_path / "sc", "--count", "3", "--size", "48x32", "--bits", "16",
                   "--format", "tif")
    assert out["count"] == 3
    res = cli_json("simulate", "age", tmp_path / "sc", tmp_path / "aged", "--sensor", "h", "--years", "0:20:10",
                   "--seed", "4", "--rate-scale", "500")
    assert res["ages"] == [0.0, 10.0, 20.0] and res["counts"]["partial"][0] == 0
    assert res["counts"]["partial"][-1] >= res["counts"]["partial"][1]
    code, out, err = cli("simulate", "age", tmp_path / "sc", tmp_path / "aged")
    assert code == 2 and "already exists" in err and "--force" in err
    code, out, err = cli("simulate", "age", tmp_path / "sc", tmp_path / "aged", "--force", "--years", "0:4:2")
    assert code == 0 and "age (years)" in out


@pytest.mark.parametrize("setup, match", [
    ("empty", "no images found"),
    ("missing", "does not exist"),
    ("baddate", "field 'captured'"),
    ("truncated", "cannot read the image"),
])
def test_cli_bad_input_exit_3_one_line_nothing_written(cli, tmp_path, setup, match):
    src = tmp_path / "src"
    src.mkdir()
    if setup != "empty":
        for i in range(2):
            write_image(src / f"a{i}.png", np.full((16, 16), 100, np.uint8))
    if setup == "missing":
        (src / "manifest.csv").write_text("file\na0.png\ngone.png\n")
    if setup == "baddate":
        (src / "manifest.csv").write_text("file,captured\na0.png,2009-02-30\n")
    if setup == "truncated":
        data = (src / "a1.png").read_bytes()
        (src / "a1.png").write_bytes(data[: len(data) // 2])
    code, out, err = cli("simulate", "age", src, tmp_path / "out")
    assert code == 3, err
    assert match in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out")]


def test_cli_usage_errors_exit_2(cli, tmp_path):
    code, _, err = cli("simulate", "age", tmp_path, tmp_path / "o", "--sensor", "Q")
    assert code in (2, 3)
    code, _, err = cli("simulate", "age")
    assert code == 2
    code, out, _ = cli("simulate", "age", "--help")
    assert code == 0 and "example:" in out


# ----------------------------------------------------------------------------- the rng convention


def test_age_dataset_int_seed_equals_its_generator(tmp_path):
    src = make_scenes(tmp_path / "src", 2, (30, 30), rng=1)
    model = preset("B", (30, 30), rate_scale=1000.0)
    r_int = age_dataset(src, tmp_path / "a", model, [0.0, 5.0], rng=4)
    r_gen = age_dataset(src, tmp_path / "b", model, [0.0, 5.0], rng=np.random.default_rng(4))
    assert r_int.counts == r_gen.counts and r_int.sensor["seed"] == 4
    assert r_gen.sensor["seed"] == {"entropy": 4, "spawn_key": []}
    for name in ("year_000", "year_005"):
        for f in sorted((tmp_path / "a" / name).glob("*.png")):
            np.testing.assert_array_equal(read_image(f), read_image(tmp_path / "b" / name / f.name))
