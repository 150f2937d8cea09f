"""PRNU residuals of real raw mosaics, one frame each (../shared/data/raw-samples), per CFA channel.

A mosaic denoised as one grey image leaks the scene's colour modulation into the residual as a 2×2-periodic
pattern that follows the scene; channel by channel it does not.  Measured as the variance of the four CFA
phases' means in 16×16 blocks, relative to the residual's variance: white noise gives ¾·1/64 ≈ 1.2 %.
"""
from __future__ import annotations

import numpy as np
import pytest

from forensics.io.images import read_raw
from forensics.prnu.fingerprint import FingerprintBuilder, raw_options
from forensics.prnu.residual import cfa_residual_and_grey, residual_and_grey
from tests.conftest import shared_or_skip

NAMES = ["Blackmagic.dng", "RAW_KODAK_DC50.KDC"]


def phase_energy(residual: np.ndarray, block: int = 16) -> float:
    """Variance of the 2×2 phases' means within blocks, relative to the residual's variance."""
    h, w = (residual.shape[0] // block) * block, (residual.shape[1] // block) * block
    r = np.asarray(residual[:h, :w], np.float64).reshape(h // block, block, w // block, block)
    phases = np.stack([r[:, dy::2, :, dx::2].mean(axis=(1, 3)) for dy in (0, 1) for dx in (0, 1)])
    return float(phases.var(axis=0).mean() / r.var())


@pytest.mark.parametrize("name", NAMES)
def test_residual_per_channel_has_no_colour_modulation(name):
    raw = read_raw(shared_or_skip(f"raw-samples/{name}"))
    per_channel, grey = cfa_residual_and_grey(raw.mosaic, 3.0, white_level=raw.white_level, workers=1)
    whole, _ = residual_and_grey(raw.mosaic, 3.0, white_level=raw.white_level, workers=1)
    assert grey.shape == raw.mosaic.shape and np.array_equal(grey, raw.mosaic.astype(np.float32))
    assert phase_energy(per_channel) < 0.02  # at white noise's ≈ 1.2 % or below
    assert phase_energy(whole) > 5 * 0.02  # measured 17 % (DNG) and 20 % (KDC)


def test_fingerprint_builder_takes_a_raw_frame_per_channel():
    path = shared_or_skip("raw-samples/RAW_KODAK_DC50.KDC")
    options = raw_options(path)
    assert options == {"cfa": True, "black_level": [0.0, 0.0, 0.0, 0.0], "white_level": 16383.0}
    builder = FingerprintBuilder("full", 3.0, workers=1, **options)
    builder.add(read_raw(path).mosaic, source=str(path))
    fp = builder.result()
    assert fp.K.shape == (512, 768) and np.isfinite(fp.K).all()
    assert fp.parameters["residual"]["cfa_channels"] is True and fp.parameters["white_level"] == 16383.0
    assert phase_energy(fp.K) < 0.02
