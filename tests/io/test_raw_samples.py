"""Two real raw files (../shared/data/raw-samples): size, CFA pattern, black and white levels as LibRaw reads them,
checked against what the files themselves say (the DNG's tags) where they say it."""
from __future__ import annotations

import numpy as np
import pytest

from forensics.io.images import read_info, read_raw
from tests.conftest import shared_or_skip


def test_blackmagic_cinema_dng():
    path = shared_or_skip("raw-samples/Blackmagic.dng")
    raw = read_raw(path)
    assert raw.mosaic.shape == (2176, 4128) and raw.mosaic.dtype == np.uint16
    assert raw.cfa_pattern == "RGGB"
    assert raw.black_level == (512.0, 512.0, 512.0, 512.0)
    assert raw.white_level == 65535.0
    assert read_info(path).shape == (2176, 4128)
    # the DNG itself: 12-bit samples through a 4,096-entry linearisation table onto 0…65,472, BlackLevel 512 in the
    # linearised units (DNG spec: black is subtracted after linearisation), CFAPattern 0 1 1 2 (R G G B)
    tifffile = pytest.importorskip("tifffile")
    with tifffile.TiffFile(path) as tif:
        tags = tif.pages[0].tags
        assert tags["BitsPerSample"].value == 12
        assert list(tags["CFAPattern"].value) == [0, 1, 1, 2]
        assert tags["BlackLevel"].value == 512
        table = np.asarray(tags["LinearizationTable"].value)
    assert table.size == 4096 and table.max() == 65472
    # LibRaw hands over linearised values: the mosaic never exceeds the table's top
    assert raw.mosaic.max() <= table.max()


def test_kodak_dc50_kdc():
    path = shared_or_skip("raw-samples/RAW_KODAK_DC50.KDC")
    raw = read_raw(path)
    assert raw.mosaic.shape == (512, 768)
    assert raw.cfa_pattern == "GRBG"
    assert raw.black_level == (0.0, 0.0, 0.0, 0.0)  # LibRaw's Kodak DC50 decoder subtracts nothing
    assert raw.white_level == 16383.0
    assert 0 < int(raw.mosaic.min()) and int(raw.mosaic.max()) <= 16383
