"""Dark series as other years' runs of one camera may write them: header spellings, biases with a recorded
exposure, no biases at all.  Synthetic FITS (fixtures.darkseries, 48 × 64) of known truth; what each test protects
is in its docstring."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

fits = pytest.importorskip("astropy.io.fits")

from forensics.defects.darkdetect import series_frames  # noqa: E402
from forensics.defects.darkseries import fit_dark_series, plan_series  # noqa: E402
from forensics.fixtures.darkseries import DarkSeriesDesign, make_dark_series  # noqa: E402
from forensics.io.dataset import open_dataset  # noqa: E402

SMALL = DarkSeriesDesign(shape=(48, 64), setpoints=(-10.0,), exposures=(10.0, 30.0, 100.0, 300.0), n_bias=6,
                         cosmic_rate=0.0, temperature_wander=0.02)


def _frames(folder: Path):
    return [(Path(f.path).stem, f.frame_type, f.exposure_s, f.temperature_c, f.set_temperature_c, f.captured)
            for f in series_frames(open_dataset(folder))]


@pytest.mark.parametrize("spelling", [
    {"exposure_key": "EXPOSURE"},
    {"type_words": (("bias", "BIAS"), ("dark", "DARK"))},
    {"type_words": (("bias", "zero"), ("dark", "dark"))},
    {"date_style": "seconds"},
    {"date_style": "split"},
    {"suffix": ".FIT"},
    {"suffix": ".fts"},
    {"binning": 2},
])
def test_header_spellings_of_other_programs_give_the_same_series(tmp_path, spelling):
    """EXPOSURE for EXPTIME, 'DARK'/'dark'/'zero' for 'Dark Frame'/'Bias Frame', DATE-OBS to the second or split into
    DATE-OBS + TIME-OBS, .FIT/.fts files and XBINNING: every frame's type, exposure, temperatures and date read as
    from the 2017 spelling (dates to the second the whole-second forms keep)."""
    design = replace(SMALL, n_bias=2, exposures=(10.0, 30.0))
    make_dark_series(tmp_path / "ref", 0, design)
    make_dark_series(tmp_path / "var", 0, replace(design, **spelling))
    ref, var = _frames(tmp_path / "ref"), _frames(tmp_path / "var")
    assert len(ref) == len(var) == 4
    second = 1 / (365.25 * 86400)
    for a, b in zip(ref, var):
        assert a[:5] == b[:5]
        assert abs(a[5] - b[5]) < 1.01 * second


def test_biases_with_a_recorded_exposure_are_still_biases(tmp_path):
    """Some cameras write their shortest exposure (0.12 s) into a bias's EXPTIME.  A bias is a bias by its IMAGETYP:
    the read noise and the offset jitter come from the biases (before, a bias was 'exposure 0' only, so these
    series had no biases: the read noise came from the darks' scatter, 8 % high with their shot noise, the jitter
    was unknown, and frames were named off the line for their ordinary jitter)."""
    make_dark_series(tmp_path, 3, SMALL)
    for path in tmp_path.glob("bias*.fits"):
        with fits.open(path, mode="update") as hdul:
            hdul[0].header["EXPTIME"] = 0.12
    plan = plan_series(series_frames(open_dataset(tmp_path)))
    fit = fit_dark_series(plan)
    group = fit.groups[0]
    assert group.n_bias == SMALL.n_bias
    # read noise from 6 biases × 3072 pixels (median of s², ν = 5): relative SE ≈ 1 %; 4 % covers the quantisation
    assert group.read_noise == pytest.approx(SMALL.read_noise, rel=0.04)
    # σ_o from 6 bias levels: the truth 0.3 ADU plus the median's own sampling (≈ 0.15 ADU); within a factor of 3
    assert 0.1 < group.offset_jitter < 0.9
    assert not any("median level" in p for f in fit.frames for p in f.problems)


def test_without_biases_no_frame_is_named_for_an_unknown_jitter_or_an_upper_bound_of_the_noise(tmp_path):
    """Without biases the offset jitter is unknown and the read noise comes from the darks' scatter (an upper bound,
    their shot noise included): frames are not named off the line (the warning says none can be) nor quieter than
    that bound — but a frame noisier than the model still is."""
    design = replace(SMALL, n_bias=0, exposures=(10.0, 20.0, 30.0, 60.0, 100.0, 150.0, 200.0, 300.0))
    make_dark_series(tmp_path, 5, design)
    noisy = sorted(tmp_path.glob("dark*.fits"))[3]
    with fits.open(noisy, mode="update") as hdul:  # read noise doubled in one frame
        data = hdul[0].data.astype(float)
        hdul[0].data = np.rint(data + np.random.default_rng(1).normal(0, 2 * design.read_noise, data.shape)
                               ).astype(np.uint16)
    fit = fit_dark_series(plan_series(series_frames(open_dataset(tmp_path))))
    assert fit.groups[0].offset_jitter == 0.0 and fit.groups[0].read_noise > design.read_noise
    named = {f.name: f.problems for f in fit.frames if f.problems}
    assert set(named) == {noisy.name}
    assert all(p.startswith("noise") for p in named[noisy.name])
