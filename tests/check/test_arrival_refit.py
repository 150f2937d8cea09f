"""The growth channel's fit started at its own optimum is converged (sweep_check's camera dark_current, seed 2).

After the first fit with a fixed pattern, pixels are detected again and the model refitted; when the defect
counts do not change, the arrival fit starts exactly at its optimum, L-BFGS-B's line search cannot decrease the
objective and it reports an abnormal termination.  That was read as "growth.rate_partial, growth.rate_stuck still
moving", and the whole check reported no result (camera convention, 320 × 240, dark_current seed 2).
"""
import dataclasses

import numpy as np
from scipy import optimize

import forensics.check.fit as fit_module
from forensics.check.fit import fit_arrivals, stationary
from forensics.check.pipeline import base_model, prepare
from forensics.fixtures.hidden import convention, make_hidden
from forensics.sensor.model import Stage


def test_lbfgsb_restarted_at_a_poisson_optimum_can_report_failure():
    # the situation itself (scipy's L-BFGS-B): a Poisson likelihood of two log-rates minimised, then restarted from
    # the point found, twice; with scipy 1.17 the third run cannot decrease the objective and reports failure
    # at the optimum.  Whatever a scipy version reports, every run must end where the fit counts as settled.
    counts = np.array([5000.0, 3.0])

    def nll(t: np.ndarray) -> float:
        return float(np.sum(np.exp(t) - counts * t))

    x = np.log(counts)
    for _ in range(3):
        r = optimize.minimize(nll, x, method="L-BFGS-B", bounds=[(-25.0, 25.0)] * 2)
        x = r.x
        assert r.success or stationary(nll, x, [(-25.0, 25.0)] * 2), r.message
    assert stationary(nll, x, [(-25.0, 25.0)] * 2)


def test_arrival_fit_stopped_at_its_optimum_is_converged(tmp_path, monkeypatch):
    design = dataclasses.replace(convention("project"), shape=(48, 64))
    make_hidden("none", tmp_path / "data", rng=3, design=design)
    ev, _ = prepare(tmp_path / "data", [], 3, 199)
    arrivals = [e for e in base_model(ev.black_level) if e.stage == Stage.ARRIVAL]
    first = fit_arrivals(ev, ev.defects, arrivals)
    assert first.params and all(p.converged for p in first.params)

    # an optimiser that stops where it started without claiming success, as L-BFGS-B does at its optimum
    def stops_at_start(fun, x0, **kwargs):
        return optimize.OptimizeResult(x=np.asarray(x0, float), fun=fun(x0), success=False, message="ABNORMAL")

    monkeypatch.setattr(fit_module.optimize, "minimize", stops_at_start)
    again = fit_arrivals(ev, ev.defects, first.effects)
    assert all(p.converged for p in again.params), [p.label for p in again.params if not p.converged]
    # started away from the optimum, the same optimiser is rightly not converged
    moved = [dataclasses.replace(e, rate_partial=2.0 * e.rate_partial) if hasattr(e, "rate_partial") else e
             for e in first.effects]
    assert not all(p.converged for p in fit_arrivals(ev, ev.defects, moved).params)


def test_stationary_tells_an_optimum_from_a_point_before_it():
    def nll(t: np.ndarray) -> float:  # a Poisson negative log-likelihood on log rates, 40 and 7 counts
        m = np.exp(t)
        return float(np.sum(m - np.array([40.0, 7.0]) * t))

    at = np.log([40.0, 7.0])
    assert stationary(nll, at, [(-25.0, 25.0)] * 2)
    # one count's worth off (Δθ = 1/40): the Newton step would still gain ≈ 40·(1/40)²/2 = 0.0125 ≫ 1e-6
    assert not stationary(nll, at + np.array([1 / 40, 0.0]), [(-25.0, 25.0)] * 2)
    # on the upper bound with the optimum beyond it: stationary in the box
    assert stationary(nll, np.array([np.log(20.0), np.log(7.0)]), [(-25.0, np.log(20.0)), (-25.0, 25.0)])
