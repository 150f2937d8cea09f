"""A parameter the pixel channel cannot see is held, not walked by the float32 rounding of its derivative.

The project convention's dark frames are veiled (a 64-DN pedestal of stray light, estimated from each pixel's
neighbours like any scene), so the dark signal's mean level — the dark current's offset μ_d0 and mean rate —
is absorbed by the scene estimates: their derivatives are zero up to the predictions' float32 rounding.  A
forward difference of 10⁻³ DN read that rounding as information ("a standard error of 100 DN"), and
Gauss–Newton walked the offset by thousands of DN; the shot noise's law, which takes μ_d0 as an electronic
offset (no shot noise), then failed, and forward selection ended with input_noise flagged (dark_current +
shot_noise hidden: 6 of 10 seeds).
"""
from __future__ import annotations

import numpy as np
import pytest

from forensics.check.pipeline import base_model, prepare, resolve_effects, run_check
from forensics.fixtures.hidden import make_hidden


@pytest.fixture(scope="module")
def veiled_dark(tmp_path_factory):
    data = tmp_path_factory.mktemp("veiled") / "data"
    make_hidden(["dark_current", "shot_noise"], data, rng=3)   # a seed that failed before
    return data


def test_an_absorbed_parameter_is_not_identifiable_and_the_noise_law_holds(veiled_dark):
    ev, _ = prepare(veiled_dark, [], 3, 199)
    res = run_check(ev, [*base_model(ev.black_level), *resolve_effects(["shot_noise", "dark_current"])])
    by = {(p.effect, p.name): p for p in res.params}
    offset = by[("dark_current", "offset")]
    assert not offset.identifiable and offset.value == 0.0     # held at its start, said so (before: 938 ± 1,572 DN)
    # the truth (hidden_params): read noise 2 DN, conversion gain 0.1 DN/e⁻; before: 4.63 and 0.296
    for key, truth in ((("read_noise", "sigma"), 2.0), (("shot_noise", "g"), 0.1)):
        est = by[key]
        assert abs(est.value - truth) <= 4 * est.se, (key, est.value, est.se)
    assert res.flagged == []                                  # before: input_noise (variance χ²/df 864)
    assert res.gof["variance"] >= 0.001
