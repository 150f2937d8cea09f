"""The model check's reading of measurements leaves content-free frames out (D17 of issue 26).

All-black frames were read as 481 partially stuck pixels, all-white ones flagged prnu at ΔBIC 5.9·10⁸: a frame
clipped at the pixel type's floor or full scale (or constant) holds nothing of the sensor.  A dataset of only
such frames is refused, naming it and why; such frames among real ones are left out, and the measurements of
the rest are exactly those of the dataset without them.
"""
from __future__ import annotations

import csv
import shutil
from pathlib import Path

import numpy as np
import pytest

from forensics._shared.errors import InputError
from forensics.check.measurements import load_measurements
from forensics.fixtures.hidden import Design, make_hidden
from forensics.io.dataset import write_manifest
from forensics.io.images import write_image

DESIGN = Design(shape=(48, 48), ages=(0, 1))


def _constant_set(folder: Path, value: int) -> Path:
    folder.mkdir()
    rows = []
    for e, exposure in enumerate((0.01, 0.02)):
        for i in range(6):
            name = f"e{e}_{i}.png"
            write_image(folder / name, np.full((40, 40), value, np.uint8))
            rows.append({"file": name, "captured": "2010-01-01", "exposure_s": exposure, "iso": 100,
                         "temperature_c": 20})
    write_manifest(folder / "manifest.csv", rows)
    return folder


@pytest.mark.parametrize("value, why", [(0, "all black"), (255, "all saturated")])
def test_a_set_of_content_free_frames_is_refused(tmp_path, value, why):
    folder = _constant_set(tmp_path / f"v{value}", value)
    with pytest.raises(InputError, match=rf"v{value}: every one of its 12 frames is content-free.*{why}"):
        load_measurements(folder)


def _rows(folder: Path) -> list[dict[str, str]]:
    with open(folder / "manifest.csv", newline="") as handle:
        return list(csv.DictReader(handle))


def test_content_free_frames_are_left_out_and_the_rest_measured_as_without_them(tmp_path):
    """A condition of black frames (dropped) and one saturated frame inside a real condition (left out of it):
    every array of the measurements equals that of the dataset without those frames."""
    clean = tmp_path / "clean"
    make_hidden("none", clean, rng=1, design=DESIGN)
    dirty = tmp_path / "dirty"
    shutil.copytree(clean, dirty)
    rows = _rows(clean)
    probe = rows[2]  # a frame of a repeated flat condition
    full = float(2**16 - 1)
    shape = DESIGN.shape
    write_image(dirty / "saturated.png", np.full(shape, full, np.uint16))
    extra = [{**probe, "file": "saturated.png"}]
    for i in range(3):  # a condition of its own, all black
        write_image(dirty / f"black{i}.png", np.zeros(shape, np.uint16))
        extra.append({**probe, "file": f"black{i}.png", "exposure_s": "7.0"})
    write_manifest(dirty / "manifest.csv", rows + extra, force=True)
    a, b = load_measurements(clean), load_measurements(dirty)
    assert b.n_frames == a.n_frames == len(rows)
    assert [g.condition for g in b.groups] == [g.condition for g in a.groups]
    assert [g.n for g in b.groups] == [g.n for g in a.groups] and b.repeated == a.repeated
    for name in ("mean_all", "var_all", "lo", "hi", "mean_a", "mean_b", "n_a", "n_b", "var_resid", "scene_all"):
        np.testing.assert_array_equal(getattr(b, name), getattr(a, name), err_msg=name)
    note = next(n for n in b.notes if "content-free" in n)
    assert note.startswith("4 content-free frame(s) left out") and "1 condition(s)" in note
