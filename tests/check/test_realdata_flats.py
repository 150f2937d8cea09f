"""The model check on real flat fields: the shared Nikon flats (JPEG, demosaiced) and a synthetic null like them.

On the ten flat JPEGs of each of four Nikon cameras (``../shared/data/dresden-nikon/flat``) the check must find
PRNU, say how large it is with an interval, and say what JPEG and frame-to-frame level changes limit
(docs/CHECK_ON_JPEG_FLATS.md).  The synthetic null has what makes those frames hard — spatially correlated
temporal noise and per-frame level changes — and no PRNU: there prnu must not be flagged.
"""
from __future__ import annotations

import math
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import dresden_or_skip
from scipy import ndimage

from forensics.check import check
from forensics.check.measurements import central_region, load_measurements
from forensics.check.result import CheckResult
from forensics.io.dataset import open_dataset
from forensics.io.images import write_image

CAMERAS = ("Nikon_D70_0", "Nikon_D70_1", "Nikon_D70s_0", "Nikon_D70s_1")
#: "pattern σ 0.00182 ± 2.1e-05" in a fixed-pattern test's evidence (forensics.check.scoretests._pattern_test)
SIZE = re.compile(r"pattern σ ([0-9.eE+-]+) ± ([0-9.eE+-]+)")
IN_CAMERA = "σ_k is the effective in-camera value, not the sensor's raw PRNU"
LEVELS = "frame-to-frame level changes removed; they are not pixel noise"


def dataset(folder: Path, files: list[Path], device: str) -> Path:
    """A dataset folder (documented format: manifest.csv with file, device, subject) linking ``files``."""
    folder.mkdir(parents=True, exist_ok=True)
    rows = ["file,device,subject"]
    for f in files:
        target = folder / f.name
        try:
            os.symlink(f, target)
        except OSError:  # no symlinks here (e.g. some Windows setups): copy
            shutil.copy2(f, target)
        rows.append(f"{f.name},{device},flat")
    (folder / "manifest.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    return folder


@pytest.fixture(scope="module")
def flats(tmp_path_factory) -> dict[str, CheckResult]:
    """Per camera: the check with prnu added, its base check as ``baseline`` (512² centre region)."""
    src = dresden_or_skip() / "flat"
    if not src.is_dir():
        pytest.skip(f"no flat fields at {src}")
    out = {}
    root = tmp_path_factory.mktemp("flats")
    for cam in CAMERAS:
        files = sorted(src.glob(f"{cam}_*.JPG"))
        if len(files) < 4:
            pytest.skip(f"{src}: fewer than 4 flats of {cam}")
        folder = dataset(root / cam, files, cam)
        # the central 512² (the frames are 3008 × 2000: whole frames cost minutes per camera, and the centre
        # holds ~1,000 of the 16 × 16 tiles the split-half statistics need)
        ds = open_dataset(folder, allow_outside=True)  # the manifest names links to the shared data
        meas = load_measurements(ds, region=central_region(ds.shape(), 512))
        out[cam] = check(meas, add=["prnu"], rng=0)
    return out


def prnu_candidate(result: CheckResult):
    return next(c for c in result.candidates if c.effect == "prnu")


@pytest.mark.realdata
@pytest.mark.parametrize("cam", CAMERAS)
def test_prnu_is_found_with_its_size(flats, cam):
    base = flats[cam].baseline
    cand = prnu_candidate(base)
    assert cand.flagged, cand.evidence
    # the check finds ΔBIC of 400–2000 here; 100 keeps a wide margin above the flag (10) without being loose
    assert cand.delta_bic > 100, cand.evidence
    size = SIZE.search(cand.evidence)
    assert size, cand.evidence
    sigma, se = float(size.group(1)), float(size.group(2))
    # the investigation measured 0.16–0.22 % surviving the 7 × 7 scene estimate, which keeps 42–79 % of the
    # pattern's variance: the whole pattern is 0.1–0.4 % (a JPEG flat's effective PRNU), known to ≥ 10 se
    assert 1e-3 < sigma < 4e-3 and 0 < se < sigma / 10, (sigma, se)
    assert any(IN_CAMERA in w for w in base.warnings), base.warnings


@pytest.mark.realdata
def test_level_changes_are_named_where_the_frames_drift(flats):
    # frame means spread by 0.69 and 1.90 DN on D70_1 and D70s_1 (22 % and 67 % of a pixel's temporal variance),
    # by 0.06–0.08 DN (< 0.5 %) on the other two
    drifting = {cam for cam in CAMERAS if any(LEVELS in w for w in flats[cam].baseline.warnings)}
    assert drifting == {"Nikon_D70_1", "Nikon_D70s_1"}


def error_drop(result: CheckResult) -> tuple[float, float]:
    """The drop of the held-out Σ residual² (DN²) from the base model to the model with prnu, and its standard
    error from 16 × 16 tiles (the noise is spatially correlated; tiles are far larger than its reach)."""
    rb, ra = result.baseline.plots.residual_map, result.plots.residual_map
    ok = np.isfinite(rb) & np.isfinite(ra)
    diff = np.where(ok, rb**2 - ra**2, 0.0)
    h, w = (diff.shape[0] // 16) * 16, (diff.shape[1] // 16) * 16
    tiles = diff[:h, :w].reshape(h // 16, 16, w // 16, 16).sum(axis=(1, 3)).ravel()
    return float(tiles.sum()), float(tiles.std(ddof=1) * math.sqrt(tiles.size))


@pytest.mark.realdata
@pytest.mark.parametrize("cam", CAMERAS)
def test_adding_prnu_lowers_the_error_and_reports_sigma_k(flats, cam):
    after = flats[cam]
    before = after.baseline
    drop, se = error_drop(after)
    # one condition of 5 + 5 frames: the halves' residuals correlate by 0.1–0.2, so the best one can expect is a
    # drop of 1–4 % of error², judged against its own noise (3 se), not the 1.5× of the simulated sweeps
    assert after.error["pixel"] < before.error["pixel"]
    assert drop > 3 * se, (drop, se)
    # σ_k as the fitted pattern: its size in the frames with a standard error, the same range as the test above
    # (0.1–0.4 %, known to ≥ 10 se: the investigation measured se ≈ 1–5 % of σ)
    k = next(p for p in after.patterns if p.effect == "prnu")
    assert k.size is not None and k.size_se is not None, k
    assert 0.001 < k.size < 0.004 and 0 < k.size_se < k.size / 10, k


# ----------------------------------------------------------------------------------------- synthetic null
def correlated_flats(folder: Path, rng: np.random.Generator, n: int = 10, size: int = 160, level: float = 3000.0,
                     noise: float = 50.0, blur: float = 0.7, drift: float = 12.0, prnu: float = 0.0) -> Path:
    """Flat fields like demosaiced camera output: blurred white temporal noise (lag-1 ρ ≈ 0.6), a per-frame level
    change of ``drift`` DN rms, a vignetted scene, 16-bit PNG; a blurred PRNU of ``prnu`` (relative) if given."""
    folder.mkdir(parents=True, exist_ok=True)
    yy, xx = np.mgrid[0:size, 0:size].astype(float)
    c = (size - 1) / 2
    scene = level * (1 - 0.2 * ((xx - c) ** 2 + (yy - c) ** 2) / c**2)
    k = ndimage.gaussian_filter(rng.standard_normal((size, size)), blur)
    k *= prnu / k.std()
    rows = ["file,device,subject"]
    for i in range(n):
        frame = scene * (1 + k) + drift * rng.standard_normal() + ndimage.gaussian_filter(
            noise * rng.standard_normal((size, size)), blur)
        name = f"flat_{i:02d}.png"
        write_image(folder / name, np.clip(np.rint(frame), 0, 65535).astype(np.uint16))
        rows.append(f"{name},synthetic,flat")
    (folder / "manifest.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    return folder


@pytest.mark.parametrize("seed", [3, 4])
def test_correlated_noise_and_level_changes_are_not_prnu(tmp_path, seed):
    result = check(correlated_flats(tmp_path / "null", np.random.default_rng(seed)), rng=seed)
    cand = prnu_candidate(result)
    assert not cand.flagged, cand.evidence
    # what the data limit is said, from the data alone (16-bit PNG: the correlation is what names it)
    assert any(IN_CAMERA in w for w in result.warnings), result.warnings
    assert any(LEVELS in w for w in result.warnings), result.warnings


def test_correlated_prnu_is_found_and_sized(tmp_path):
    # the same frames with a 0.3 % blurred PRNU: found, and its size (as the frames show it) within 3 se, plus
    # the 2 % the wide scene estimate itself removes of a pattern correlated over neighbours (Σ_q w_q·ρ_q)
    truth_rng = np.random.default_rng(5)
    result = check(correlated_flats(tmp_path / "prnu", truth_rng, prnu=0.003), rng=5)
    cand = prnu_candidate(result)
    assert cand.flagged, cand.evidence
    size = SIZE.search(cand.evidence)
    assert size, cand.evidence
    sigma, se = float(size.group(1)), float(size.group(2))
    assert abs(sigma - 0.003) < 3 * se + 0.02 * 0.003, (sigma, se)
