"""The variance channel's score test: a signature in the span of the fitted noise parameters is absorbed, not
tested along the finite differences' rounding; a signature that leaves that span is tested as before.

The case it comes from: on the 8-bit DSNU series of seed 2 (no analog gain) ``input_noise`` is ``read_noise``;
2.6 × 10⁻⁹ of its signature survived the projection off read noise's column, and the LM statistic — which does not
depend on a signature's scale — read the near-0-DN bins' residuals along that sliver: LM 19.5, flagged.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from scipy import stats

from forensics.check.diagnosis import FLAG_DBIC
from forensics.check.pixels import log_variance
from forensics.check.scoretests import ABSORBED_SHARE, score_variance
from forensics.check.signatures import Signature


def _fitted(rng: np.random.Generator, bins: int = 120):
    """Binned variances at levels 0 … 200 DN with 50 degrees of freedom each: a read-noise model (σ = 0.7 DN)
    whose residuals carry a misfit of 0.3 in log variance in the 10 bins next to 0 DN (what the censored variance
    law leaves there)."""
    level = np.linspace(0.0, 200.0, bins)
    df = np.full(bins, 50.0)
    pred = np.full(bins, 0.49 + 1 / 12)
    misfit = np.where(level < 17.0, 0.3, 0.0)
    observed = pred * np.exp(misfit + rng.standard_normal(bins) * np.sqrt(2 / df))
    read_noise_column = np.full(bins, 2 / 0.7 * 0.49 / pred[0])       # d log var / d σ_read
    fitted = SimpleNamespace(pixels=SimpleNamespace(bins=SimpleNamespace(observed=observed, df=df)),
                             variance_pred=pred, variance_jac=read_noise_column[None, :])
    return fitted, level, misfit


def test_a_signature_in_the_noise_parameters_span_is_absorbed_not_tested():
    fitted, _, misfit = _fitted(np.random.default_rng(1))
    # input noise without an analog gain: read noise's column up to a finite difference's rounding, which here
    # points along the misfit (the worst case: the old statistic read the misfit in full)
    sliver = 1e-9 * misfit
    x = 1e-3 * fitted.variance_jac[0] + sliver
    (test,) = score_variance(None, fitted, [Signature("variance", "input_noise.sigma_in", x)])
    assert test.absorbed and test.lm == 0.0 and test.df == 0
    assert "absorbed by the fitted noise parameters" in test.detail
    # what it replaced: the scale-free LM of the sliver alone is the misfit's own χ², a flag (ΔBIC = LM − ln n)
    w = fitted.pixels.bins.df / 2
    e = np.log(fitted.pixels.bins.observed) - np.log(fitted.variance_pred)
    old_lm = float((sliver * w @ e) ** 2 / (sliver * w @ sliver))
    assert old_lm - np.log(len(e)) > FLAG_DBIC and stats.chi2.sf(old_lm, 1) < 1e-3


def test_a_signature_that_leaves_the_span_is_tested_on_what_survives():
    fitted, level, _ = _fitted(np.random.default_rng(2))
    shot = level / (0.49 + 1 / 12)              # shot noise at its null g = 0: d log var / d g = level / var
    (test,) = score_variance(None, fitted, [Signature("variance", "shot_noise.g", shot)])
    assert not test.absorbed and test.df == 1
    w = fitted.pixels.bins.df / 2
    e = log_variance(fitted.pixels.bins.observed, fitted.pixels.bins.df) - np.log(fitted.variance_pred)
    j = fitted.variance_jac[0]
    p = shot - (j * w @ shot) / (j * w @ j) * j
    assert (p * w @ p) / (shot * w @ shot) >= ABSORBED_SHARE
    assert abs(test.lm - (p * w @ e) ** 2 / (p * w @ p)) <= 1e-9 * test.lm


def test_a_zero_signature_gives_no_test():
    fitted, _, _ = _fitted(np.random.default_rng(3))
    assert score_variance(None, fitted, [Signature("variance", "x.y", np.zeros(120))]) == []
