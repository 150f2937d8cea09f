"""Hot pixels that fill their full well in the long darks: found, censored, and the fit converges."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from forensics.fixtures.darkseries import DarkSeriesDesign, make_dark_series
from forensics.check.measurements import full_well_level, load_measurements
from forensics.check.pipeline import base_model, prepare, run_check

SBIG = Path(__file__).resolve().parents[3] / "shared" / "data" / "sbig-stl1001e-2017"
#: a well of 40,000 e⁻ at 2 e⁻/ADU: 20,000 ADU above the bias, reached at 300 s by pixels above ≈ 43 ADU/s at −5 °C
WELL = DarkSeriesDesign(hot_max=200.0, full_well=40000.0)


@pytest.mark.parametrize("seed", [1, 2])
def test_the_full_well_is_found_where_the_wells_are(tmp_path, seed):
    make_dark_series(tmp_path, seed, WELL)
    level = load_measurements(tmp_path).saturation
    d = WELL
    # the lowest stalled reading: a saturated pixel's bias (990 ± 3 column pattern, ≤ 4σ) plus its well (1 %
    # spread: the lowest of a few dozen wells lies within 4σ below the nominal) in ADU, ± 5σ of read noise
    well = d.full_well / d.gain
    assert d.bias - 4 * d.column_pattern + well * (1 - 4 * d.full_well_spread) - 5 * d.read_noise <= level
    assert level <= d.bias + 4 * d.column_pattern + well * (1 + d.full_well_spread) + 5 * d.read_noise


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_no_full_well_without_one(tmp_path, seed):
    # cosmic-ray hits (single frames), 3 % hot pixels up to 200 ADU/s and nothing saturating: no level
    make_dark_series(tmp_path, seed, DarkSeriesDesign(hot_max=200.0, cosmic_rate=2e-5))
    assert load_measurements(tmp_path).saturation is None


def test_censoring_the_full_well_lets_the_fit_converge_between_the_doublings(tmp_path):
    make_dark_series(tmp_path, 1, WELL)
    ev, extra = prepare(tmp_path, ["shot_noise", "dark_current"], np.random.default_rng(0), 19)
    assert ev.meas.saturation is not None
    result = run_check(ev, [*base_model(ev.black_level), *extra])
    assert all(p.converged for p in result.params)
    t_d = {p.label: p for p in result.params}["dark_current.t_double"]
    # one doubling temperature for a bulk doubling every 5 °C and hot pixels every 8 °C lies between them (with the
    # stalled readings fitted as dark signal it came out at 10.8 °C: the saturated pixels seem to double slowly)
    assert WELL.doubling_bulk < t_d.value < WELL.doubling_hot


@pytest.mark.skipif(not SBIG.is_dir(), reason=f"the real STL-1001E series is not at {SBIG} (../shared/data)")
def test_the_stl1001e_hot_pixel_saturates_at_its_full_well():
    # the tile around frame pixel (495, 198), whose darks read 47,318 ADU (10 s at −10 °C) and then 61,773–63,345 ADU
    # whatever the exposure (by inspection; over the whole frame the stalled readings lie at 61,005–65,224 ADU and
    # the level is 61,005 — the whole series takes 30 s to reduce, the tile 3 s)
    meas = load_measurements(SBIG, region=(381, 125, 134, 134))
    assert 61_773 <= meas.saturation <= 63_345
    assert meas.saturation == full_well_level(meas.mean_all, meas.groups, meas.interior)
