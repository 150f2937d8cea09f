"""Light frames dark-subtracted before they reached the check (a capture program's auto-dark) are named.

A synthetic cooled-CCD series (``fixtures.darkseries``) with four flats, written raw and written with their dark
signal subtracted (``auto_dark``, as the 2017 STL-1001E flats were).  The share of the predicted dark pattern the
flats carry is 1 for raw frames and 0 for reduced ones; its standard error is the robust scatter of the flats'
excess at the hot pixels (PRNU 1 % of 5,000 ADU and shot noise, ≈ 60 ADU) over √Σδ² of the hot pixels' predicted
dark pattern (30 pixels of 3–30 ADU/s at −10 °C, 23 s at −5 °C: δ ≈ 140–1,400 ADU), a few hundredths.
"""
from __future__ import annotations

import dataclasses
import json

import pytest

from forensics._shared.jsonsafe import dumps
from forensics.check.fit import fit_model
from forensics.check.pipeline import base_model, prepare, resolve_effects, run_check
from forensics.check.reduced import dark_pattern_shares, reduced_frame_warnings
from forensics.fixtures.darkseries import DarkSeriesDesign, make_dark_series

DESIGN = DarkSeriesDesign(shape=(48, 64), temperature_wander=0.0, offset_jitter=0.0, readout_s=0.0,
                          column_pattern=0.0, doubling_hot=5.0, hot_fraction=0.01, hot_min=3.0, hot_max=30.0,
                          n_repeat_dark=6, cosmic_rate=0.0, n_flats=4, flat_level=5000.0)


def _fitted(folder):
    ev, _ = prepare(folder, [], 1, 19)
    return ev, fit_model(ev, [*base_model(ev.black_level), *resolve_effects(["shot_noise", "dark_current"])])


@pytest.fixture(scope="module")
def raw_and_reduced(tmp_path_factory):
    raw, reduced = tmp_path_factory.mktemp("raw"), tmp_path_factory.mktemp("reduced")
    make_dark_series(raw, 4, DESIGN)
    make_dark_series(reduced, 4, dataclasses.replace(DESIGN, auto_dark=True))
    return _fitted(raw), _fitted(reduced)


def test_raw_flats_carry_the_whole_dark_pattern_and_are_not_named(raw_and_reduced):
    (ev, fitted), _ = raw_and_reduced
    assert not fitted.not_converged
    (share,) = dark_pattern_shares(ev, fitted)  # one light condition: the flats
    assert share.pixels >= 20 and share.se < 0.1
    assert abs(share.share - 1.0) < 4 * share.se + 0.05  # + the fitted pattern's own error (a few %)
    assert reduced_frame_warnings([share]) == []


def test_dark_subtracted_flats_carry_none_of_it_and_are_named(raw_and_reduced):
    _, (ev, fitted) = raw_and_reduced
    assert not fitted.not_converged
    (share,) = dark_pattern_shares(ev, fitted)
    assert share.se < 0.1
    assert abs(share.share) < 4 * share.se + 0.05
    (warning,) = reduced_frame_warnings([share])
    assert "dark-subtracted" in warning and "flat" in warning


def test_the_check_reports_the_shares_in_its_data_and_names_the_reduced_flats(raw_and_reduced):
    _, (ev, fitted) = raw_and_reduced
    result = run_check(ev, fitted.effects)
    (entry,) = result.data["dark_pattern_share"]
    assert set(entry) == {"label", "share", "se", "pixels"} and "flat" in entry["label"]
    assert abs(entry["share"]) < 4 * entry["se"] + 0.05
    assert sum("dark-subtracted" in w for w in result.warnings) == 1
    json.loads(dumps(result.to_dict()))  # standard JSON, as --json writes it
