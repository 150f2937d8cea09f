"""Dark calibration of raw CCD flats before the fingerprint (``--dark``): synthetic FITS series written with astropy
(``fixtures.darkseries``) with a known PRNU and a strong known dark pattern (3 % hot pixels up to 90 ADU/s at −5 °C,
a 23 s flat: up to ≈ 2,200 ADU of dark signal against a PRNU of 1 % of 15,000 ADU).

Tolerances.  Under the null "K does not follow the dark pattern D", NCC(K, D) = Σ K·D / (‖K‖‖D‖) (both zero-mean)
has mean 0 and standard deviation σ₀ = √(Σ K²D²) / (‖K‖‖D‖) whatever the pixels' variances (a sum of terms of
random sign; its plug-in estimate is used): "correlates" is NCC > 5 σ₀, "does not" is |NCC| < 4 σ₀.  An NCC
estimated from N pixels moves by ≈ 1/√N between two noisy estimates of one pattern, so a gain of the PRNU's NCC is
asserted beyond 5/√N.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from forensics._shared.errors import InputError
from forensics.fixtures.darkseries import DarkSeriesDesign, make_dark_series
from forensics.io.dataset import open_dataset
from forensics.io.fits import read_fits
from forensics.prnu.calibration import FrameCalibration, dark_calibration, dark_pattern_share
from forensics.prnu.fingerprint import Fingerprint, build_fingerprint

SHAPE = (128, 128)
BASE = DarkSeriesDesign(shape=SHAPE, setpoints=(-5.0,), exposures=(10.0, 20.0, 30.0, 60.0, 150.0, 300.0),
                        n_bias=10, hot_fraction=0.03, hot_max=60.0)
FLATS = DarkSeriesDesign(**{**BASE.__dict__, "n_bias": 0, "exposures": (), "n_flats": 10})


def _ncc(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """NCC and its null standard deviation σ₀ (module notes)."""
    a = a.astype(np.float64) - a.mean()
    b = b.astype(np.float64) - b.mean()
    norm = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / norm), float(np.sqrt(((a * b) ** 2).sum()) / norm)


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    root = tmp_path_factory.mktemp("ccd")
    truth = make_dark_series(root / "darks", 1, BASE)
    flats = make_dark_series(root / "flats", 2, FLATS, sensor=truth)
    # the dark pattern a 23 s flat at −5 °C carries: offset (bias + read-out charge) and dark charge
    pattern = truth.bias_map + truth.rate_at(-5.0) * (FLATS.flat_exposure + FLATS.readout_s)
    return root, flats.prnu_map, pattern, dark_calibration(root / "darks"), truth


def test_calibration_removes_the_dark_pattern_and_sharpens_the_prnu(series):
    root, prnu, pattern, cal, _ = series
    flats = open_dataset(root / "flats")
    raw = build_fingerprint(flats.frames, "full", 3.0)
    calibrated = build_fingerprint(flats, "full", 3.0, dark=cal)
    r_dark, r_sd = _ncc(raw.K, pattern)
    c_dark, c_sd = _ncc(calibrated.K, pattern)
    assert r_dark > 5 * r_sd  # without --dark the "PRNU" follows the dark pattern (measured 0.57, σ₀ 0.06)
    assert abs(c_dark) < 4 * c_sd  # with it, not beyond the noise (measured −0.008, σ₀ 0.008)
    gain = _ncc(calibrated.K, prnu)[0] - _ncc(raw.K, prnu)[0]
    assert gain > 5 / np.sqrt(prnu.size)  # measured 0.78 → 0.96
    assert calibrated.parameters["dark_calibration"]["groups"][0]["set_temperature_c"] == -5.0


def test_the_master_is_the_dark_series_fit(series):
    """offset ≈ bias + read-out charge and rate ≈ the true rate, within the fit's noise: the line through 16 frames."""
    root, _, pattern, cal, _ = series
    group = cal.groups[0]
    predicted = group.offset + group.rate * np.float32(FLATS.flat_exposure)
    error = predicted - pattern
    # read noise 6.5 ADU over 16 frames, and shot noise of the dark charge: a few ADU; hot pixels' rates err by
    # their shot noise × 23 s / lever arm — the 99th percentile stays far below the pattern's own spread
    assert np.percentile(np.abs(error), 99) < 0.1 * np.percentile(np.abs(pattern - np.median(pattern)), 99.9)
    assert abs(float(np.median(error))) < 1.0  # the bias level, to the offset jitter (0.3 ADU)


def test_dark_pattern_share_tells_raw_frames_from_dark_subtracted_ones(series):
    root, _, pattern, cal, _ = series
    path = sorted((root / "flats").glob("*.fits"))[0]
    raw = read_fits(path).data
    how = FrameCalibration(FLATS.flat_exposure, 0, 1.0)
    share, se, n = dark_pattern_share(raw, cal.groups[0], how, cal.white_level)
    assert n > 200 and se < 0.05
    assert abs(share - 1.0) < 4 * se  # measured 0.984 ± 0.013
    subtracted = np.clip(np.rint(raw - pattern + 100.0), 0, 65535).astype(np.uint16)  # an auto-dark's output
    share0, se0, _ = dark_pattern_share(subtracted, cal.groups[0], how, cal.white_level)
    assert abs(share0) < 4 * se0
    with pytest.raises(InputError, match="dark-subtracted already"):
        cal.measure(subtracted, how, str(path))
    assert cal.measure(raw, how, str(path)).scale == 1.0  # a raw frame passes, calibrated by its exposure


def test_darks_of_another_temperature_are_refused(series, tmp_path):
    root, *_, truth = series
    make_dark_series(tmp_path / "cold", 3, DarkSeriesDesign(**{**BASE.__dict__, "setpoints": (-10.0,)}), sensor=truth)
    with pytest.raises(InputError, match=r"flat-.*nearest dark group is at -10\.\d\d °C.*--dark-doubling"):
        dark_calibration(tmp_path / "cold").calibrated_set(open_dataset(root / "flats"))


def test_a_doubling_temperature_scales_darks_of_another_temperature(series, tmp_path):
    """Darks of the flats' sensor at −10 °C, carried to −5 °C with the hot pixels' T_d (8 °C; they dominate the
    pattern): the pattern is removed as with darks at −5 °C."""
    root, _, pattern, _, truth = series
    make_dark_series(tmp_path / "cold", 3, DarkSeriesDesign(**{**BASE.__dict__, "setpoints": (-10.0,)}), sensor=truth)
    cal = dark_calibration(tmp_path / "cold", doubling_c=BASE.doubling_hot)
    fp = build_fingerprint(open_dataset(root / "flats"), "full", 3.0, dark=cal)
    value, sd = _ncc(fp.K, pattern)
    assert abs(value) < 4 * sd
    assert fp.parameters["dark_calibration"]["doubling_c"] == BASE.doubling_hot


# ----------------------------------------------------------------------------- the command line

def test_cli_build_and_match_with_dark(series, tmp_path, cli_json, cli):
    root, *_ = series
    out = tmp_path / "fp.npz"
    built = cli_json("fingerprint", "build", root / "flats", "-o", out, "--dark", root / "darks", "--workers", "1",
                     "--quiet")
    assert built["parameters"]["dark_calibration"]["source"] == str(root / "darks")
    assert Fingerprint.load(out).parameters["dark_calibration"]["groups"][0]["label"] == "set point -5.0 °C"
    matched = cli_json("fingerprint", "match", out, root / "flats", "--dark", root / "darks", "--workers", "1",
                       "--quiet")
    assert matched["n_match"] == 10
    code, _, err = cli("fingerprint", "match", out, root / "flats", "--workers", "1", "--quiet", "--json")
    assert code == 0 and "give --dark for them too" in err


def _one_line_error(cli, *argv) -> str:
    code, out, err = cli(*argv, "--quiet")
    assert code == 3, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


def test_cli_refuses_darks_of_another_size(series, tmp_path, cli):
    root, *_ = series
    make_dark_series(tmp_path / "small", 5, DarkSeriesDesign(**{**BASE.__dict__, "shape": (64, 96)}))
    out = tmp_path / "fp.npz"
    line = _one_line_error(cli, "fingerprint", "build", root / "flats", "-o", out, "--dark", tmp_path / "small",
                           "--workers", "1")
    assert "flat-" in line and "128×128" in line and "96×64" in line and "same size" in line
    assert not out.exists() and not list(tmp_path.glob(".fp.npz*"))


def test_cli_refuses_a_flat_without_exposure_time(series, tmp_path, cli):
    from astropy.io import fits

    root, *_ = series
    folder = tmp_path / "flats"
    folder.mkdir()
    for path in sorted((root / "flats").glob("*.fits"))[:3]:
        (folder / path.name).write_bytes(path.read_bytes())
    bad = sorted(folder.glob("*.fits"))[1]
    fits.delval(bad, "EXPTIME")
    line = _one_line_error(cli, "fingerprint", "build", folder, "-o", tmp_path / "fp.npz", "--dark", root / "darks",
                           "--workers", "1")
    assert bad.name in line and "exposure" in line and "EXPTIME" in line


def test_cli_refuses_a_dark_without_exposure_time(series, tmp_path, cli):
    from astropy.io import fits

    root, *_ = series
    folder = tmp_path / "darks"
    folder.mkdir()
    for path in sorted((root / "darks").glob("*.fits")):
        (folder / path.name).write_bytes(path.read_bytes())
    bad = sorted(folder.glob("dark-*.fits"))[0]
    fits.delval(bad, "EXPTIME")
    line = _one_line_error(cli, "fingerprint", "build", root / "flats", "-o", tmp_path / "fp.npz", "--dark", folder,
                           "--workers", "1")
    assert bad.name in line and "EXPTIME" in line


def test_cli_refuses_flats_already_dark_subtracted(series, tmp_path, cli):
    from astropy.io import fits

    root, _, pattern, *_ = series
    folder = tmp_path / "subtracted"
    folder.mkdir()
    for path in sorted((root / "flats").glob("*.fits"))[:3]:
        with fits.open(path) as hdul:
            data = np.clip(np.rint(hdul[0].data - pattern + 100.0), 0, 65535).astype(np.uint16)
            hdu = fits.PrimaryHDU(data, header=hdul[0].header)
        hdu.writeto(folder / path.name)
    line = _one_line_error(cli, "fingerprint", "build", folder, "-o", tmp_path / "fp.npz", "--dark", root / "darks",
                           "--workers", "1")
    assert "dark-subtracted already" in line and "leave out --dark" in line and ".fits" in line
    assert not (tmp_path / "fp.npz").exists()


def test_fitted_scale_follows_what_each_frame_shows(series, tmp_path):
    """``scale='fit'``: raw flats get ≈ 1 (the exposure's calibration), flats reduced already ≈ 0 (left as they are),
    each within 4 standard errors of its share; the fingerprints are then free of the pattern either way."""
    from astropy.io import fits

    root, _, pattern, _, _ = series
    cal = dark_calibration(root / "darks", scale="fit")
    folder = tmp_path / "subtracted"
    folder.mkdir()
    for path in sorted((root / "flats").glob("*.fits")):
        with fits.open(path) as hdul:
            data = np.clip(np.rint(hdul[0].data - pattern + 100.0), 0, 65535).astype(np.uint16)
            fits.PrimaryHDU(data, header=hdul[0].header).writeto(folder / path.name)
    for source, expected in ((root / "flats", 1.0), (folder, 0.0)):
        fp = build_fingerprint(open_dataset(source), "full", 3.0, dark=cal)
        for frame in fp.parameters["dark_calibration"]["frames"]:
            assert abs(frame["scale"] - expected) < 4 * frame["dark_share_se"]
        value, sd = _ncc(fp.K, pattern)
        assert abs(value) < 4 * sd


def test_same_device_with_dark(series, tmp_path, cli_json):
    root, *_ = series
    halves = []
    for name, files in (("a", slice(0, 5)), ("b", slice(5, 10))):
        folder = tmp_path / name
        folder.mkdir()
        for path in sorted((root / "flats").glob("*.fits"))[files]:
            (folder / path.name).symlink_to(path)
        halves.append(folder)
    result = cli_json("same-device", *halves, "--dark", root / "darks", "--seed", "1", "--workers", "1",
                      "--region", "full", "--ageing-fingerprints", "0", "--quiet")
    calibrations = result["parameters"]["dark_calibration"]
    assert len(calibrations) == 2 and all(c["source"] == str(root / "darks") for c in calibrations)
    assert result["eer_ci"][0] <= 0.5 <= result["eer_ci"][1]  # one sensor: the halves cannot be told apart
    json.dumps(result, allow_nan=False)
