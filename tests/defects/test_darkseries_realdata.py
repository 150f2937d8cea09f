"""The real SBIG STL-1001E series of 2017 (../shared/data/sbig-stl1001e-2017): the fitted figures against the
independent ones of issue 28, and hot-pixel counts from the −10 °C and −5 °C series alone, normalised to one
temperature at one threshold.

Independent figures (simple per-pixel regressions made outside the project): median dark rate 0.35 ADU/s at −5 °C
and 0.17 at −10 °C, bias ≈ 992 ADU, read noise 6.3–7.3 ADU, conversion gain ≈ 1.9 e⁻/ADU from a flat pair (EGAIN
2.06 in the header).  They are quoted to two figures, so they are read as ± half their last digit.
Nothing here is tuned to this series: the same camera measured in later years is the check.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from forensics.defects.darkdetect import DarkSettings, compare_counts, detect_dark, series_frames
from forensics.defects.darklaw import fit_temperature_law
from forensics.defects.darkseries import fit_dark_series, plan_series
from forensics.io.dataset import open_dataset
from tests.conftest import shared_or_skip


@pytest.fixture(scope="module")
def fit():
    return fit_dark_series(plan_series(series_frames(open_dataset(shared_or_skip("sbig-stl1001e-2017")))))


def test_every_frame_used(fit):
    assert fit.n_frames == 42 and not fit.named_frames()  # 20 biases and 22 darks; the flats give the gain
    assert [g.set_temperature_c for g in fit.groups] == [-10.0, -5.0]


def test_figures_against_the_independent_ones(fit):
    cold, warm = fit.groups
    # the regressions behind the independent figures carry no temperature correction: compare at the groups'
    # effective (measured) temperatures, −10.20 and −5.21 °C
    for group, independent in ((cold, 0.17), (warm, 0.35)):
        lo, hi = group.median_rate_ci()
        assert lo - 0.005 <= independent <= hi + 0.005
        assert abs(group.bias_level - 992) <= 1.5  # 991.2 and 992.5: the bias moved with the temperature
        assert 6.3 <= group.read_noise <= 7.3
    flat = fit.gain["flat_pairs"]
    assert abs(flat["gain_e_per_adu"] - 1.9) <= 0.05
    # the dark signal's shot noise, an estimate without light, agrees with the flat pairs; both put the gain
    # below the maker's EGAIN 2.06
    dark = fit.gain["dark_shot_noise"]
    assert dark["ci"][0] <= flat["ci"][1] and flat["ci"][0] <= dark["ci"][1]
    assert max(flat["ci"][1], dark["ci"][1]) < fit.gain["header_e_per_adu"]


def test_hot_pixels_double_more_slowly_than_the_bulk(fit):
    law = fit_temperature_law(fit.groups)
    lo, hi = law.bulk.doubling_ci()
    assert 4.0 < lo and hi < 6.5  # the bulk doubles every ≈ 5 °C
    hot = [c for c in law.classes if c.rate > 2.0]
    assert hot and all(c.doubling_ci()[0] > hi for c in hot)


@pytest.mark.parametrize("threshold", [1.0, 2.0, 5.0])
def test_counts_from_each_temperature_alone_agree_after_normalisation(fit, threshold):
    # the law is fitted on even columns and the hot pixels counted on odd ones, so it has not seen them
    columns = np.indices(fit.shape)[1]
    law = fit_temperature_law(fit.groups, pixels=(columns % 2 == 0).ravel())
    settings = DarkSettings(threshold=threshold, t_ref=-10.0, law=law)
    cold = detect_dark(replace(fit, groups=[fit.groups[0]]), settings)
    warm = detect_dark(replace(fit, groups=[fit.groups[1]]), settings)
    comparison = compare_counts(cold, warm, ("−10 °C alone", "−5 °C alone"), pixels=columns % 2 == 1)
    assert comparison.overlap, comparison.to_dict()
