"""A CCD's PRNU from its FITS flat fields: the ten flats of the real STL-1001E (../shared/data/sbig-stl1001e-2017),
split five and five, are one device; against flats of a simulated sensor of the same format they are not."""
from __future__ import annotations

from pathlib import Path

import pytest

from forensics.fixtures.darkseries import DarkSeriesDesign, make_dark_series
from forensics.io.dataset import open_dataset
from forensics.prnu.fingerprint import build_fingerprint
from forensics.prnu.match import PCE_THRESHOLD, match_set
from tests.conftest import shared_or_skip


@pytest.fixture(scope="module")
def flats(tmp_path_factory):
    source = shared_or_skip("sbig-stl1001e-2017")
    root = tmp_path_factory.mktemp("flats")
    halves = []
    for name, indices in (("a", range(0, 5)), ("b", range(5, 10))):
        folder = root / name
        folder.mkdir()
        for i in indices:  # links in a temporary folder: the frames are never copied
            path = source / f"flat-expos23s-Neg5-Vis.{i:08d}.FIT"
            (folder / path.name).symlink_to(path)
        halves.append(folder)
    other = root / "other"  # another sensor of the same format: 1024², 16-bit FITS, flat level and gain alike
    make_dark_series(other, 7, DarkSeriesDesign(shape=(1024, 1024), setpoints=(-5.0,), n_bias=0, exposures=(),
                                                n_flats=5, flat_level=18700.0, prnu=0.007, bias=992.0, gain=1.93))
    return halves[0], halves[1], other


def test_fingerprint_from_five_flats(flats):
    a, b, other = flats
    fp = build_fingerprint(open_dataset(a).frames, "center:512", 3.0)
    same = match_set(fp, open_dataset(b))
    assert all(row["match"] for row in same.scores)
    different = match_set(fp, open_dataset(other))
    assert not any(row["match"] for row in different.scores)
    assert max(row["score"] for row in different.scores) < PCE_THRESHOLD


def test_same_device_protocol_on_split_flats(flats, cli_json):
    a, b, other = flats
    same = cli_json("same-device", a, b, "--seed", "1", "--workers", "1", "--quiet")
    assert same["eer_ci"][0] <= 0.5 <= same["eer_ci"][1]  # cannot be told apart: one device
    consistency = same["ageing"]["consistency"]
    assert consistency["ci"][0] <= 1.0 <= consistency["ci"][1]
    different = cli_json("same-device", a, other, "--seed", "1", "--workers", "1", "--quiet")
    assert different["eer_ci"][1] < 0.1  # different devices
