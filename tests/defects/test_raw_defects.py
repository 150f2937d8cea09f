"""Defect detection on real raw mosaics, one frame each (../shared/data/raw-samples), per CFA channel.

What one frame can show: the scene is still in it (a single frame's mean *is* the scene), so the test is what the
CFA lattices change — each colour channel is compared with its own neighbours and fitted on its own, so the
colour modulation of the mosaic does not widen d̂, and a defect stands out against its own colour.
"""
from __future__ import annotations

import numpy as np
import pytest

from forensics.defects.detection import MaskSpec, detect
from forensics.io.images import read_raw
from forensics.io.stack import stack_stats
from forensics.sensor.catalogue import PARTIAL
from tests.conftest import shared_or_skip

FILES = {"Blackmagic.dng": ("RGGB", ["R", "G1", "G2", "B"]), "RAW_KODAK_DC50.KDC": ("GRBG", ["G1", "R", "B", "G2"])}


@pytest.mark.parametrize("name", sorted(FILES))
def test_detection_per_cfa_channel_on_one_real_frame(name):
    raw = read_raw(shared_or_skip(f"raw-samples/{name}"))
    pattern, channels = FILES[name]
    assert raw.cfa_pattern == pattern
    stack = stack_stats([raw.mosaic])
    per_channel = detect(stack, mask=MaskSpec("all"), cfa=raw.cfa_pattern, keep_images=False)
    as_grey = detect(stack, mask=MaskSpec("all"), cfa=None, keep_images=False)
    assert [f.name for f in per_channel.fits] == channels
    # the grey treatment's median mixes colours, so the mosaic's colour modulation widens its d̂
    assert max(f.scale for f in per_channel.fits) < as_grey.fits[0].scale
    assert any("only 1 images" in w for w in per_channel.warnings)  # a single frame is said to be one

    # defects of 30 σ of their channel's d̂ at random sites, each in its own colour
    rng = np.random.default_rng(28)
    h, w = raw.mosaic.shape
    ys, xs = rng.integers(20, h - 20, 60), rng.integers(20, w - 20, 60)
    channel = (ys % 2) * 2 + xs % 2
    amplitude = np.array([30 * per_channel.fits[c].scale for c in channel])
    marked = raw.mosaic.astype(np.int64)
    marked[ys, xs] += np.rint(amplitude).astype(np.int64)
    found = detect(stack_stats([np.clip(marked, 0, 65535).astype(np.uint16)]), mask=MaskSpec("all"),
                   cfa=raw.cfa_pattern, keep_images=False)
    sites = {(x, y): c for x, y, c, k in zip(found.x.tolist(), found.y.tolist(), found.channel.tolist(),
                                             found.kind.tolist()) if k == PARTIAL}
    hits = [(x, y) in sites for x, y in zip(xs.tolist(), ys.tolist())]
    assert np.mean(hits) >= 0.95  # 30 σ: missed only where another injected site or a clipped highlight interferes
    assert all(sites[(x, y)] == c for x, y, c, hit in zip(xs.tolist(), ys.tolist(), channel.tolist(), hits) if hit)


def test_cli_detects_a_raw_folder_per_channel(tmp_path, cli_json):
    source = shared_or_skip("raw-samples/RAW_KODAK_DC50.KDC")
    folder = tmp_path / "kdc"
    folder.mkdir()
    (folder / source.name).symlink_to(source)  # a link in a temporary folder: the data are never copied
    out = cli_json("defects", "detect", folder, "--mask", "all", "--workers", "1", "--quiet")
    assert out["cfa"] == "GRBG" and [f["channel"] for f in out["fits"]] == ["G1", "R", "B", "G2"]
    assert out["n_images"] == 1 and out["shape"] == [512, 768]
