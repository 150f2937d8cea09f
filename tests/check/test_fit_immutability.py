"""Fitting never mutates effects; the rng convention; the onset look-back shared with defect growth."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from forensics.check import Evidence, base_model, check, fit_model, load_measurements
from forensics.defects.onsets import look_back
from forensics.fixtures.hidden import Design, make_hidden
from forensics.sensor.model import make_effect

SMALL = Design(shape=(48, 48), ages=(0, 1, 2, 3, 4))


@pytest.fixture(scope="module")
def evidence(tmp_path_factory):
    data = make_hidden("nonlinearity", tmp_path_factory.mktemp("imm") / "d", rng=3, design=SMALL)
    return Evidence(load_measurements(data.out), rng=3, n_sim=19)


def _params(effects):
    return [(e.key, dataclasses.asdict(e)) for e in effects]


def test_fitting_leaves_the_callers_effects_unchanged(evidence):
    effects = [*base_model(), make_effect("nonlinearity"), make_effect("prnu")]
    before = _params(effects)
    fitted = fit_model(evidence, effects)
    assert _params(effects) == before  # the caller's objects are untouched
    assert not any(f is e for f in fitted.effects for e in effects)  # the fit returns new effect objects
    fitted_values = {e.key: e.params() for e in fitted.effects}
    assert fitted_values["nonlinearity"]["beta"] != make_effect("nonlinearity").beta  # … carrying the fitted values
    assert fitted_values["growth"]["amp_partial"] != base_model()[0].amp_partial
    assert [e.key for e in fitted.device.model.effects] == [e.key for e in fitted.effects]
    # a model once fitted does not change when the same evidence is fitted again
    snapshot = _params(fitted.effects)
    fit_model(evidence, fitted.effects)
    assert _params(fitted.effects) == snapshot


def test_an_effect_with_an_in_place_fit_is_fitted_on_a_copy(evidence):
    class InPlace(type(make_effect("accelerating_growth"))):
        def fit(self, ev):  # the older interface: set attributes, return None
            self.amplitude = ev.amplitude_max(0, self.amplitude)

    effect = InPlace()
    amplitude = effect.amplitude
    fitted = fit_model(evidence, [*base_model(), effect])
    assert effect.amplitude == amplitude
    assert next(e for e in fitted.effects if isinstance(e, InPlace)).amplitude != amplitude


def test_integer_seed_and_generator_give_the_same_check(evidence):
    a = check(evidence.meas, rng=3, n_sim=19)
    b = check(evidence.meas, rng=np.random.default_rng(3), n_sim=19)
    assert a.to_dict() == b.to_dict()


def test_look_back_earliest_and_contiguous():
    first = np.array([3, 3, 2, 0])
    present = np.array([[1, 0, 1, 0],
                        [0, 1, 1, 0],
                        [1, 1, 0, 0],
                        [0, 0, 0, 0]], bool)
    np.testing.assert_array_equal(look_back(first, present), [0, 1, 0, 0])  # earliest epoch shown at
    np.testing.assert_array_equal(look_back(first, present, contiguous=True), [2, 1, 0, 0])  # stops at a gap
    observed = np.array([True, True, False, True])
    np.testing.assert_array_equal(look_back(first, present, contiguous=True, observed=observed), [3, 1, 0, 0])
