"""Dark charge collected during the read-out: named by the check, added, and measured."""
from __future__ import annotations

import numpy as np
import pytest

from forensics.fixtures.darkseries import DarkSeriesDesign, make_dark_series
from forensics.check.pipeline import base_model, prepare, run_check

#: the fixture's CCD integrates 1 s more during its read-out; hot pixels double as the bulk does (the model's law),
#: so that the read-out time is the only effect the model lacks
DESIGN = DarkSeriesDesign(readout_s=1.0, doubling_hot=5.0)
ADD = ["shot_noise", "dark_current", "dsnu"]


def _check(folder, add):
    ev, extra = prepare(folder, add, np.random.default_rng(0), 19)
    return run_check(ev, [*base_model(ev.black_level), *extra])


@pytest.mark.parametrize("seed", [1, 2])
def test_readout_dark_is_named_then_measured(tmp_path, seed):
    make_dark_series(tmp_path, seed, DESIGN)
    without = _check(tmp_path, ADD)
    top = without.candidates[0]
    assert top.effect == "readout_dark" and top.flagged  # hot pixels brighter in the warmer biases: p < 1e-100
    with_it = _check(tmp_path, [*ADD, "readout_dark"])
    t_read = {p.label: p for p in with_it.params}["readout_dark.t_read"]
    # within 3 standard errors of the truth (measured over seeds 1–3: 0.998 ± 0.018, 0.980 ± 0.015, 0.996 ± 0.016)
    assert abs(t_read.value - DESIGN.readout_s) < 3 * t_read.se
    # the hot pixels' held-out misfit goes: error 4.7 / 1.7 → 1.23 / 1.37 on seeds 1 / 2 (1.40 on seed 3; the
    # noise floor is 1): the bound is the largest measured, plus its margin to the next-largest
    assert with_it.error["pixel"] < without.error["pixel"]
    assert with_it.error["pixel"] < 1.6
    assert "readout_dark" not in with_it.flagged


def test_no_readout_dark_without_one(tmp_path):
    make_dark_series(tmp_path, 1, DarkSeriesDesign(readout_s=0.0, doubling_hot=5.0))
    result = _check(tmp_path, ADD)
    assert "readout_dark" not in result.flagged
