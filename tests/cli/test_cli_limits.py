"""D12 and D20: a request is bounded before anything is allocated or written, and a value is refused where it
is parsed.

Options are checked by argparse (exit 2, naming the option); files are input data (a growth model: exit 3,
naming the file and the field).  Memory is estimated from the arguments and the images' headers and refused
above ``FORENSICS_MEMORY_LIMIT``; the number of ages (one folder each) above ``FORENSICS_MAX_AGES``.  Each
refusal is checked to come fast and to leave nothing behind.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from forensics._shared.limits import AGES_ENV, DEFAULT_MAX_AGES, MEMORY_ENV


def one_line(err: str) -> bool:
    return err.count("\n") == 1 and err.startswith("forensics: error: ") and "Traceback" not in err


@pytest.fixture(scope="module")
def images(tmp_path_factory) -> Path:
    from forensics.io.images import write_image

    root = tmp_path_factory.mktemp("limits")
    rng = np.random.default_rng(3)
    for name, shape in (("small", (48, 64)), ("large", (512, 768))):
        for i in range(3):
            write_image(root / name / f"img_{i}.png", rng.integers(20, 230, shape, dtype=np.uint8))
    return root


@pytest.fixture(scope="module")
def growth_model(tmp_path_factory) -> dict:
    """A growth model written by 'forensics defects growth -o' from a simulated device."""
    from forensics.cli.main import main
    from forensics.sensor.presets import preset
    from forensics.sensor.simulate import age_dataset, make_scenes

    root = tmp_path_factory.mktemp("model")
    src = make_scenes(root / "scenes", 10, (48, 64), 0, bit_depth=16, kind="texture")
    age_dataset(src, root / "aged", preset("G", (48, 64), bit_depth=16, rate_scale=2000), [0, 4, 8], rng=1,
                start_year=2000.0, sensor_name="G")
    sets = [str(root / "aged" / f"year_{a:03d}") for a in (0, 4, 8)]
    assert main(["defects", "growth", *sets, "-o", str(root / "m.json"), "--workers", "1", "--quiet"]) == 0
    return json.loads((root / "m.json").read_text())


# ----------------------------------------------------------------------------- D12: bounded requests
def test_a_million_ages_is_refused_at_once(cli, images, tmp_path):
    start = time.perf_counter()
    code, _, err = cli("simulate", "age", images / "small", tmp_path / "aged", "--years", "0:1e6:1")
    assert code == 2 and "1,000,001 ages" in err and AGES_ENV in err
    assert time.perf_counter() - start < 5
    assert list(tmp_path.iterdir()) == []  # no output, no .partial


def test_the_age_limit_can_be_raised(monkeypatch):
    from forensics.sensor.simulate import parse_years

    assert len(parse_years(f"0:{DEFAULT_MAX_AGES - 1}:1")) == DEFAULT_MAX_AGES
    monkeypatch.setenv(AGES_ENV, "5000")
    assert len(parse_years("0:1500:1")) == 1501


def test_the_detection_window_is_bounded_by_the_frame_and_memory(cli, images, monkeypatch, tmp_path):
    code, _, err = cli("defects", "detect", images / "small", "--q", "99999", "--report", tmp_path / "r")
    assert code == 2 and one_line(err) and "--q 99999" in err and "whole 64×48 frame" in err
    monkeypatch.setenv(MEMORY_ENV, "8M")  # a 768×512 set needs about 30 MiB
    start = time.perf_counter()
    code, _, err = cli("defects", "detect", images / "large", "--q", "9", "--report", tmp_path / "r")
    assert code == 2 and one_line(err) and "more than the limit" in err and MEMORY_ENV in err
    assert time.perf_counter() - start < 5
    assert not (tmp_path / "r").exists()
    monkeypatch.setenv(MEMORY_ENV, "64M")
    code, _, err = cli("defects", "detect", images / "large", "--q", "9", "--workers", "1", "--quiet")
    assert code == 0, err


def test_detection_memory_estimate_is_above_what_is_used():
    """The estimate (per pixel, per channel, per set) bounds what was measured (peak RSS: grey 69–80 bytes per
    pixel, RGB 175, about 10 more per further set), so the limit refuses before the kernel would."""
    from forensics.defects.detection import BYTES_PER_PIXEL, BYTES_PER_PIXEL_CHANNEL, BYTES_PER_PIXEL_SET

    assert BYTES_PER_PIXEL_CHANNEL + BYTES_PER_PIXEL >= 80
    assert 3 * BYTES_PER_PIXEL_CHANNEL + BYTES_PER_PIXEL >= 175
    assert BYTES_PER_PIXEL_SET >= 10


@pytest.mark.parametrize("argv", [
    ["simulate", "scenes", "{out}", "--size", "100000x100000"],
    ["simulate", "irises", "{out}", "--size", "100000x100000"],
    ["validate", "defects", "--size", "100000x100000", "--trials", "1", "--report", "{out}"],
    ["simulate", "age", "{small}", "{out}", "--rate-scale", "1e12"],
    ["impact", "{small}", "--sensors", "H*1e12", "--years", "0,96", "--report", "{out}"],
])
def test_enormous_requests_are_refused_before_anything_is_written(cli, images, tmp_path, argv):
    start = time.perf_counter()
    code, _, err = cli(*(a.format(out=tmp_path / "out", small=images / "small") for a in argv))
    assert code == 2 and one_line(err) and "of memory, more than the limit" in err and MEMORY_ENV in err, err
    assert time.perf_counter() - start < 10
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- D20: values refused where parsed
@pytest.mark.parametrize("argv, option", [
    (["simulate", "age", "{small}", "{out}", "--years", "nan"], "--years"),
    (["simulate", "age", "{small}", "{out}", "--years", "0,8,8"], "--years"),
    (["simulate", "age", "{small}", "{out}", "--years", "0,0.11,0.14"], "--years"),  # one folder name
    (["simulate", "age", "{small}", "{out}", "--years", "0:inf:1"], "--years"),
    (["simulate", "age", "{small}", "{out}", "--rate-scale", "nan"], "--rate-scale"),
    (["simulate", "age", "{small}", "{out}", "--start", "inf"], "--start"),
    (["impact", "{small}", "--years", "0,nan"], "--years"),
    (["defects", "detect", "{small}", "--tau", "-1"], "--tau"),
    (["defects", "detect", "{small}", "--tau", "nan"], "--tau"),
    (["defects", "detect", "{small}", "--sigma", "nan"], "--sigma"),
    (["defects", "detect", "{small}", "--sigma", "0"], "--sigma"),
    (["defects", "detect", "{small}", "--q", "8"], "--q"),
    (["defects", "detect", "{small}", "--stuck-tolerance", "-1"], "--stuck-tolerance"),
    (["date", "{small}", "--model", "m.json", "--q", "nan"], "--q"),
    (["fingerprint", "match", "fp.npz", "{small}", "--threshold", "nan"], "--threshold"),
    (["fingerprint", "match", "fp.npz", "{small}", "--sigma", "nan"], "--sigma"),
    (["fingerprint", "build", "{small}", "-o", "{out}", "--sigma", "-inf"], "--sigma"),
    (["identify", "{small}", "--db", "db", "--sigma", "nan"], "--sigma"),
    (["cluster", "{small}", "-o", "{out}", "--sigma", "0"], "--sigma"),
    (["validate", "defects", "--read-noise", "nan"], "--read-noise"),
])
def test_option_values_are_refused_where_they_are_parsed(cli, images, tmp_path, argv, option):
    code, _, err = cli(*(a.format(out=tmp_path / "out", small=images / "small") for a in argv))
    assert code == 2 and f"argument {option}" in err and "Traceback" not in err, err
    assert list(tmp_path.iterdir()) == []


def test_a_rate_factor_must_be_finite(cli, images):
    code, _, err = cli("impact", images / "small", "--sensors", "H*nan", "--years", "0,8")
    assert code == 2 and one_line(err) and "--sensors 'H*nan'" in err


def _broken(model: dict, change: str) -> object:
    m = json.loads(json.dumps(model))
    if change == "reversed dates":
        m["dates"] = m["dates"][::-1]
    elif change == "equal dates":
        m["dates"][1] = m["dates"][0]
    elif change == "a NaN date":
        m["dates"][1] = float("nan")
    elif change == "a JSON list":
        m = [m]
    elif change == "no counts":
        del m["counts"]
    elif change == "counts of the wrong length":
        m["counts"]["partial"] = m["counts"]["partial"][:1]
    elif change == "a defect outside the frame":
        m["catalogue"][0]["x"] = 10**6
    elif change == "an unknown defect kind":
        m["catalogue"][0]["kind"] = "broken"
    elif change == "an epoch out of range":
        m["catalogue"][0]["first_epoch"] = 9
    elif change == "an even q":
        m["detection"]["q"] = 8
    elif change == "a negative sigma":
        m["detection"]["sigma"] = -5
    elif change == "a zero-pixel frame":
        m["shape"] = [0, 64]
    return m


@pytest.mark.parametrize("change", ["reversed dates", "equal dates", "a NaN date", "a JSON list", "no counts",
                                    "counts of the wrong length", "a defect outside the frame",
                                    "an unknown defect kind", "an epoch out of range", "an even q",
                                    "a negative sigma", "a zero-pixel frame"])
def test_a_damaged_growth_model_is_bad_input(cli, images, tmp_path, growth_model, change):
    assert growth_model["catalogue"], "the simulated device must have catalogued defects"
    path = tmp_path / "model.json"
    path.write_text(json.dumps(_broken(growth_model, change)))  # NaN written as the token NaN on purpose
    code, _, err = cli("date", images / "small", "--model", path)
    assert code == 3 and one_line(err) and "model.json" in err, (change, err)


def test_the_intact_growth_model_loads(tmp_path, growth_model):
    from forensics.defects.growth import GrowthModel

    path = tmp_path / "model.json"
    path.write_text(json.dumps(growth_model))
    model = GrowthModel.load(path)
    assert model.dates == sorted(model.dates) and len(model.catalogue) == len(growth_model["catalogue"])
