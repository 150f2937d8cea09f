"""The noise law of partially stuck pixels near a bound is fitted by each variance's own precision.

Near a bound (dark frames whose normal pixels touch 0 DN) the partially stuck pixels read their noise from a
law fitted to their own temporal variances.  Their levels span decades — a hot pixel's dark charge, with its
own shot noise, from a few to thousands of DN — and each variance is of two frames (one degree of freedom,
standard deviation √2 σ²).  An ordinary least-squares line is then decided by the brightest pixels' noise; the
law must instead have the precision quasi-likelihood theory gives it, and be positive at every level it serves
(camera convention, ISO 200 darks, seed 3: OLS gave a = −1,015 DN², and six hot pixels at 260 DN were weighted as
if their noise were the rounding's only).
"""
from __future__ import annotations

import numpy as np

from forensics.check.pixels import _pooled_law

READ_VAR = 1600.0      # (40 DN)²: 20 DN read noise behind an ISO gain of 2
GAIN = 3.2             # DN of variance per DN of dark charge (shot noise behind the same gain)
N_PIX, N_COND = 600, 4  # 2,400 partially stuck pixel means in one gain pool, as on the camera's ISO 200 darks


def two_frame_variances(rng: np.random.Generator):
    """Levels and sample variances of two frames of hot pixels whose charge is exponential (mean 4,800 DN)."""
    d = rng.exponential(4800.0, (N_COND, N_PIX, 1, 1))          # (conditions, rows, columns, frames)
    frames = 48.0 + d + np.sqrt(READ_VAR + GAIN * d) * rng.standard_normal((N_COND, N_PIX, 1, 2))
    return frames.mean(axis=-1), frames.var(axis=-1, ddof=1)


def test_the_law_has_quasi_likelihood_precision_and_stays_positive():
    errors, bound = [], []
    for seed in range(60):
        level, var = two_frame_variances(np.random.default_rng(seed))
        mask = np.ones(level.shape, bool)
        a, b = _pooled_law(level, var, mask, [200.0] * N_COND, [1.0] * N_COND)[200.0]
        # positive wherever it is read: at every level of the pixels it serves
        assert a + b * level.min() > 0
        errors.append((a - (READ_VAR - GAIN * 48.0), b - GAIN))   # the truth in terms of the mean level
        # the Gamma GLM's covariance, φ (XᵀWX)⁻¹ with W = 1/μ² and φ = 2/df = 2
        x = np.stack([np.ones(level.size), level.ravel()], axis=1)
        mu = (READ_VAR - GAIN * 48.0) + GAIN * level.ravel()
        bound.append(np.sqrt(np.diag(2.0 * np.linalg.inv((x.T / mu**2) @ x))))
    rms = np.sqrt(np.mean(np.square(errors), axis=0))
    se = np.mean(bound, axis=0)
    # 60 seeds estimate an rms to ±9 % (1/√(2·60)); the fit drops the χ² tail beyond 10⁻⁶ and stops after a few
    # reweightings, so allow 1.3× the theoretical standard error.  OLS on the same data: 4–6× it (the brightest decide).
    assert np.all(rms <= 1.3 * se), (rms, se)
