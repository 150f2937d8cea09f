"""``--dark`` on the real STL-1001E series of 2017 (../shared/data/sbig-stl1001e-2017; skipped where absent).

The published flats were dark-subtracted when they were taken (CCDSoft's auto-dark: the hottest pixels, 48–1,634
ADU/s, which add 1,100–37,600 ADU to a raw 23 s frame, show nothing in them), so ``--dark`` refuses them, naming the
frame, and ``--dark-scale fit`` scales the pattern to the ≈ 0 they show; the repeated 60 s darks, which the master
does not use, show the whole predicted pattern.  With this camera's own dark pattern added back (measured on frames
the master does not use), the flats are raw again, and the calibration removes the pattern: the fingerprint's NCC
with the dark pattern of the −10 °C frames (same hot pixels and bias structure, noise independent of every −5 °C
frame; winsorised at its 99.9 % quantile, or the hottest pixel alone would make the NCC) falls from far beyond its
null spread σ₀ (see ``test_dark_calibration.py``) to within it.  ``benchmarks/bench_ccd_dark.py`` measures the same
with PCE.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from forensics._shared.errors import InputError
from forensics.io.dataset import open_dataset
from forensics.io.fits import read_fits
from forensics.prnu.calibration import dark_calibration, dark_pattern_share
from forensics.prnu.fingerprint import build_fingerprint
from tests.conftest import shared_or_skip
from tests.prnu.test_dark_calibration import _ncc

PEDESTAL = 100.0  # CCDSoft's BIAS keyword: the pedestal its auto-dark subtraction adds


def _link(folder: Path, paths: list[Path]) -> Path:
    folder.mkdir()
    for p in paths:  # links in a temporary folder: the frames are never copied
        os.symlink(p, folder / p.name)
    return folder


@pytest.fixture(scope="module")
def real(tmp_path_factory):
    source = shared_or_skip("sbig-stl1001e-2017")
    root = tmp_path_factory.mktemp("stl")
    pick = lambda pattern: sorted(source.glob(pattern))  # noqa: E731
    b5 = pick("biases-Neg5-*")
    # the master: both temperatures' biases (but the −5 °C biases 0–4) and the single darks of 10–300 s
    darks = _link(root / "darks", pick("bias-Neg10-*") + b5[5:] + pick("darks-expos*s-*"))
    return source, root, dark_calibration(darks), pick("flat-*"), pick("darks-expos1-*"), b5[:5]


def test_the_published_flats_are_dark_subtracted_already(real):
    source, root, cal, flats, darks60, _ = real
    warm = 1 if cal.groups[1].set_temperature_c == -5.0 else 0
    for path in flats:
        share, se, n = dark_pattern_share(read_fits(path).data, cal.groups[warm],
                                          cal.plan(str(path), 23.0, None, -5.0), cal.white_level)
        assert n > 200 and abs(share) < 0.05  # measured −0.023 … −0.007, SE ≤ 0.003
    for path in darks60:
        share, se, n = dark_pattern_share(read_fits(path).data, cal.groups[warm],
                                          cal.plan(str(path), 60.0, None, -5.0), cal.white_level)
        assert abs(share - 1.0) < 0.05  # measured 1.009 … 1.017, SE ≤ 0.001
    with pytest.raises(InputError, match=r"flat-expos23s-Neg5-Vis\.00000000\.FIT: shows .* dark-subtracted already"):
        build_fingerprint(open_dataset(_link(root / "flats", flats)), "full", 3.0, dark=cal)


def test_the_calibration_removes_this_cameras_dark_pattern(real):
    from astropy.io import fits

    source, root, cal, flats, darks60, biases = real
    bias = np.median([read_fits(p).data.astype(np.float32) for p in biases], axis=0)
    dark60 = np.median([read_fits(p).data.astype(np.float32) for p in darks60], axis=0)
    pattern = bias + (dark60 - bias) * np.float32(23.0 / 60.0)  # a 23 s frame's, from frames the master leaves out
    folder = root / "redarkened"
    folder.mkdir()
    for p in flats:
        with fits.open(p) as hdul:
            data = np.clip(np.rint(hdul[0].data + pattern - PEDESTAL), 0, 65535).astype(np.uint16)
            hdu = fits.PrimaryHDU(data)
            for key in ("EXPTIME", "SET-TEMP", "CCD-TEMP", "IMAGETYP", "INSTRUME", "DATE-OBS"):
                hdu.header[key] = hdul[0].header[key]
        hdu.writeto(folder / p.name)
    reference = _reference(cal)
    raw = build_fingerprint(open_dataset(folder).frames, "full", 3.0)
    calibrated = build_fingerprint(open_dataset(folder), "full", 3.0, dark=cal)
    r_value, r_sd = _ncc(raw.K, reference)
    c_value, c_sd = _ncc(calibrated.K, reference)
    assert r_value > 5 * r_sd  # measured 0.20, σ₀ 0.007
    assert abs(c_value) < 4 * c_sd  # measured −0.011, σ₀ 0.009


def _reference(cal) -> np.ndarray:
    """The −10 °C group's dark pattern of a 23 s frame, high-passed (minus its 5 × 5 mean) and winsorised."""
    from scipy import ndimage

    cold = next(g for g in cal.groups if g.set_temperature_c == -10.0)
    pattern = (cold.offset + np.float32(23.0) * cold.rate).astype(np.float64)
    high = pattern - ndimage.uniform_filter(pattern, 5)
    cap = float(np.quantile(np.abs(high), 0.999))
    return np.clip(high, -cap, cap)


def test_a_fitted_scale_leaves_the_published_flats_as_they_are(real):
    from dataclasses import replace

    source, root, cal, flats, _, _ = real
    folder = root / "flats" if (root / "flats").exists() else _link(root / "flats", flats)
    fp = build_fingerprint(open_dataset(folder), "center:512", 3.0, dark=replace(cal, scale="fit"))
    scales = [f["scale"] for f in fp.parameters["dark_calibration"]["frames"]]
    assert len(scales) == 10 and all(abs(x) < 0.05 for x in scales)  # measured −0.023 … −0.007
