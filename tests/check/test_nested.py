"""Adding an effect nests the smaller model: the fit starts from the effect's null values, so its error is never
worse than the smaller model's by more than the noise of the extra fitted parameters (issue 9, item 2)."""
from __future__ import annotations

import math

from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from forensics.check.evidence import Evidence
from forensics.check.fit import at_null
from forensics.check.measurements import load_measurements
from forensics.check.pipeline import base_model, run_check
from forensics.fixtures.hidden import Design, make_hidden
from forensics.sensor.model import make_effect

PIXEL_CANDIDATES = ("prnu", "dsnu", "dark_current", "gain", "nonlinearity")
SMALL = Design(shape=(48, 48), ages=(0, 2, 4), exposures=(0.5, 1.0), temperatures=(20.0, 35.0))


def test_fits_start_from_the_null_values():
    for name in PIXEL_CANDIDATES + ("shot_noise", "input_noise"):
        effect = at_null(make_effect(name))
        nulls = effect.null_values()
        assert all(getattr(effect, n) == nulls[n] for n in effect.free_params() if n in nulls), name


# no shrinking: each example is a whole simulated dataset and two fits; the failing example is reported as is
@settings(max_examples=4, deadline=None, derandomize=True, phases=[Phase.explicit, Phase.generate],
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(hidden=st.sampled_from(("none",) + PIXEL_CANDIDATES), added=st.sampled_from(PIXEL_CANDIDATES),
       seed=st.integers(1, 10_000))
def test_adding_an_effect_never_makes_the_error_worse(tmp_path_factory, hidden, added, seed):
    out = tmp_path_factory.mktemp("nested") / "data"
    make_hidden(hidden, out, rng=seed, design=SMALL)
    ev = Evidence(load_measurements(out), rng=seed, n_sim=19)
    before = run_check(ev, base_model())
    after = run_check(ev, [*base_model(), make_effect(added)])
    assert after.error["pixel"] is not None, after.warnings  # the fit converged
    # held-out error² = mean z² over the n usable pixel means of a class: its sampling noise is √(2/n) relative
    # (4 σ; n of the class that sets error.pixel after adding); each extra per-pixel parameter fitted on one
    # half costs at most 1/(conditions per pixel) on the other half (3 such parameters at most)
    worst_class = max((k for k, v in after.error["classes"].items() if v is not None),
                      key=lambda k: after.error["classes"][k])
    n = next(int(c.statistic.split(", ")[1].split()[0]) for c in after.checks
             if c.statistic.startswith(f"pixel: held-out error² ({worst_class},"))
    worst = before.error["pixel"] ** 2 * (1 + 4 * math.sqrt(2 / n)) + 3.0 / len(ev.rep)
    assert after.error["pixel"] ** 2 <= worst, (hidden, added, n, before.error, after.error)
