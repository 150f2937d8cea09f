"""Frames larger than 512² are analysed whole (issue 9 item 8): no silent central crop.

The check used to crop every frame to its central 512 × 512 pixels.  Here a 600 × 720 dataset has a partially
stuck pixel and a stuck pixel near a corner, outside that central square: both must be found, and the
measurements must have the frame's shape.  A region is analysed only when asked for, and the notes say so.
"""
from __future__ import annotations

import numpy as np
import pytest

from forensics._shared.errors import InputError
from forensics.check.detection import detect_defects
from forensics.check.measurements import central_region, load_measurements
from forensics.check.scene import edge_estimates, plane_fill, scene_estimate
from forensics.io.images import write_image

SHAPE = (600, 720)
PARTIAL_AT = (9, 14)  # row, column: outside the old central crop (rows 44–555, columns 104–615)
STUCK_AT = (590, 705)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """Dark and vignetted flat frames, 3 of each, 16-bit PNG, with a partially stuck and a stuck pixel."""
    rng = np.random.default_rng(0)
    root = tmp_path_factory.mktemp("full")
    h, w = SHAPE
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    vignette = 1 - 0.3 * ((yy - h / 2) ** 2 + (xx - w / 2) ** 2) / ((h / 2) ** 2 + (w / 2) ** 2)
    rows = ["file,device,captured,exposure_s,iso,temperature_c,subject"]
    for subject, level in (("dark", 0.0), ("flat", 2000.0)):
        for i in range(3):
            frame = 100.0 + level * vignette + 3.0 * rng.standard_normal(SHAPE)
            frame[PARTIAL_AT] += 400.0
            frame[STUCK_AT] = 3000.0
            name = f"{subject}_{i}.png"
            write_image(root / name, np.clip(np.rint(frame), 0, 65535).astype(np.uint16))
            rows.append(f"{name},dev,2020-01-01T00:00:0{i},1,100,20,{subject}")
    (root / "manifest.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    return root


def test_frames_larger_than_512_are_measured_whole(folder):
    meas = load_measurements(folder)
    assert meas.shape == SHAPE and meas.mean_all.shape[1:] == SHAPE and meas.scene_all.shape[1:] == SHAPE
    assert not any("region" in n or "crop" in n for n in meas.notes), meas.notes
    found = detect_defects(meas, [[g.index for g in meas.groups]], common_threshold=True).catalogue
    sites = set(zip(found.y.tolist(), found.x.tolist()))
    assert PARTIAL_AT in sites and STUCK_AT in sites, sorted(sites)


def test_a_region_is_used_only_when_asked_for_and_said(folder):
    region = central_region(SHAPE, 512)
    assert region == (44, 104, 512, 512)
    meas = load_measurements(folder, region=region)
    assert meas.shape == (512, 512)
    assert any("only a region" in n and "512×512" in n for n in meas.notes), meas.notes
    with pytest.raises(InputError, match="not inside"):
        load_measurements(folder, region=(100, 300, 512, 512))


def test_scene_estimate_edges_and_fills_are_exact_for_planes_at_any_size():
    # the vectorised edge estimates and plane fills: exact for a plane wherever the window is cut by the edge
    h, w = 530, 610
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    plane = 500 + 0.7 * xx - 0.4 * yy
    est = plane.copy()
    edge_estimates(plane, est)
    np.testing.assert_allclose(est, plane, rtol=0, atol=1e-8)
    good = np.ones((h, w), bool)
    good[0:3, 0:3] = good[200, 300] = good[h - 1, 100:120] = False
    np.testing.assert_allclose(plane_fill(np.where(good, plane, 0.0), good), plane, rtol=0, atol=1e-8)
    np.testing.assert_allclose(scene_estimate(plane), plane, rtol=0, atol=1e-7)


def test_a_check_beyond_the_memory_limit_is_refused_before_the_fit_naming_the_region(cli, folder, monkeypatch,
                                                                                     tmp_path):
    """600 × 720 pixels × 2 fitted conditions at 2.2 KB each (the fit's measured peak per pixel and condition)
    is ≈ 1.8 GiB: under a 1 GiB limit the check says so in one line, names --region and writes no report; the
    same frames checked on a 64² region (≈ 17 MiB) run."""
    from forensics._shared.limits import MEMORY_ENV

    monkeypatch.setenv(MEMORY_ENV, "1G")
    code, _, err = cli("model", "check", folder, "--workers", "1", "--quiet", "--report", tmp_path / "r")
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert "720×600 pixels × 2 fitted conditions" in err and "--region" in err and MEMORY_ENV in err
    assert not (tmp_path / "r").exists()
    code, out, err = cli("model", "check", folder, "--region", "64", "--workers", "1", "--quiet", "--json")
    assert code == 0, err
