"""A fixed pattern is flagged only when both halves of the repeats show it (``diagnosis.flag_rule``).

The pixel channel tests a pattern by the first half's random-effect likelihood ratio, calibrated by the split
halves.  That ratio also grows with structure in one half's residuals the other does not share; on the sweep's
14-bit DSNU, seed 2 (no PRNU in the truth), it reached 44.6 (÷ 1.19) with a split-half z of only +1.78, and prnu
was flagged after ``dsnu`` (ΔBIC 31).  A pattern the model lacks is in both halves, so the candidate must also
clear the bar with every pattern counted as far as the split-half z² shows it.
"""
import math

import numpy as np
import pytest

from forensics.check.diagnosis import FLAG_DBIC, flag_rule
from forensics.check.pipeline import base_model, prepare, resolve_effects, run_check
from forensics.check.scoretests import pattern_statistic, tile_index
from forensics.fixtures.hidden import convention, make_hidden


def test_a_pattern_shared_by_the_halves_clears_both_bars():
    # a PRNU-like pattern (variance 0.1 per unit weight) under unit noise, block weights varying 4×, 128 × 128
    n = 128 * 128
    tile = tile_index((128, 128)).ravel()
    penalty = math.log(n)
    for seed in range(10):
        rng = np.random.default_rng(seed)
        ab = rng.uniform(0.5, 2.0, n)
        pattern = math.sqrt(0.1) * rng.standard_normal(n)
        ua = np.sqrt(ab) * rng.standard_normal(n) + ab * pattern
        ub = np.sqrt(ab) * rng.standard_normal(n) + ab * pattern
        stat = pattern_statistic(ua, ub, ab, tile)
        # the split-half z ≈ t / se(t) with se(t) ≈ 0.0065 over the 64 tiles (measured): z ≈ 15, z² ≈ 230, and the
        # one-half ratio ≈ 100; both far above the bar 10 + ln n ≈ 19.7
        assert flag_rule(stat.lm - penalty, min(stat.lm, stat.confirmed) - penalty, 1e-9)
        # the gate costs a shared pattern nothing: the cross-product of two halves sees it at least as well
        assert stat.confirmed >= stat.lm


def test_the_bar_needs_both_statistics():
    assert flag_rule(FLAG_DBIC + 5, None, 1e-6)          # no pattern tested: ΔBIC and p decide
    assert not flag_rule(FLAG_DBIC + 5, FLAG_DBIC - 1, 1e-6)  # the halves do not agree enough
    assert not flag_rule(FLAG_DBIC - 1, FLAG_DBIC + 5, 1e-6)
    assert not flag_rule(FLAG_DBIC + 5, FLAG_DBIC + 5, 0.5)


@pytest.mark.slow
def test_no_prnu_flag_after_dsnu_without_prnu(tmp_path):
    make_hidden("dsnu", tmp_path / "data", rng=2, design=convention("14bit"))
    ev, _ = prepare(tmp_path / "data", ["gain"], 2, 199)  # the convention's ISO amplifier, known to the user
    result = run_check(ev, [*base_model(ev.black_level), *resolve_effects(["gain", "dsnu"])])
    prnu = next(c for c in result.candidates if c.effect == "prnu")
    # before the rule: flagged on the first half's ratio alone (ΔBIC 31, split-half z +1.78)
    assert not prnu.flagged
    assert prnu.delta_bic_confirmed is not None and prnu.delta_bic_confirmed < FLAG_DBIC
    assert result.flagged == []
