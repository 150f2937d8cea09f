"""Per-pixel linear algebra of the pixel channel: least squares, projection, collinear and empty columns."""
from __future__ import annotations

import numpy as np

from forensics.check.local_solve import PixelProjector, shrink_local, solve_local


def _columns(rng, R=9, shape=(4, 5), k=3):
    return [rng.standard_normal((R, *shape)) for _ in range(k)], rng.uniform(0.5, 2.0, (R, *shape))


def test_solve_local_is_per_pixel_weighted_least_squares():
    rng = np.random.default_rng(0)
    X, w = _columns(rng)
    r = rng.standard_normal(X[0].shape)
    coef, var = solve_local(w, X, r)
    for y, x in [(0, 0), (2, 3), (3, 4)]:
        D = np.stack([c[:, y, x] for c in X], axis=1) * np.sqrt(w[:, y, x])[:, None]
        expected = np.linalg.lstsq(D, r[:, y, x] * np.sqrt(w[:, y, x]), rcond=None)[0]
        np.testing.assert_allclose(coef[:, y, x], expected, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(var[:, y, x], np.diag(np.linalg.inv(D.T @ D)), rtol=1e-9)


def test_collinear_columns_get_the_minimum_norm_split_and_no_variance():
    """A partially stuck pixel's own offset and the DSNU value there are the same column: the ridged inverse
    used to split their sum into ±10⁵; the pseudo-inverse splits it evenly (in the scaled columns) and the
    fitted values, which is all the data determine, are the least-squares ones."""
    rng = np.random.default_rng(1)
    X, w = _columns(rng, k=2)
    X.append(X[0] * 3.0 * (1 + 1e-10 * rng.standard_normal(X[0].shape)))  # same function of the conditions
    r = rng.standard_normal(X[0].shape)
    coef, var = solve_local(w, X, r)
    fitted = sum(c[None] * x for c, x in zip(coef, X))
    for y, x in [(0, 0), (1, 2), (3, 4)]:
        D = np.stack([c[:, y, x] for c in X], axis=1) * np.sqrt(w[:, y, x])[:, None]
        ls = np.linalg.lstsq(D[:, :2], r[:, y, x] * np.sqrt(w[:, y, x]), rcond=None)[0]
        np.testing.assert_allclose(fitted[:, y, x] * np.sqrt(w[:, y, x]), D[:, :2] @ ls, rtol=1e-6, atol=1e-9)
    assert np.all(np.abs(coef) < 100)  # no cancelling giants
    # equal split in scaled units: coefficient × column norm the same for the two collinear columns
    np.testing.assert_allclose(coef[0] * 1.0, coef[2] * 3.0, rtol=1e-4, atol=1e-9)
    assert np.all(np.isnan(var[0])) and np.all(np.isnan(var[2])) and np.all(np.isfinite(var[1]))


def test_dead_column_stays_zero():
    rng = np.random.default_rng(2)
    X, w = _columns(rng, k=2)
    X[1][:, 1, 1] = 0.0
    coef, var = solve_local(w, X, rng.standard_normal(X[0].shape))
    assert coef[1, 1, 1] == 0.0 and np.isnan(var[1, 1, 1])
    assert np.isfinite(var[1]).sum() == var[1].size - 1


def test_shrinkage_keeps_a_fixed_effect_without_data_and_zeroes_a_random_one():
    """A stuck pixel read at full scale is censored (weight 0 in every condition): its constant value is a fixed
    effect the data cannot move, so shrinking the random-effect patterns (PRNU) must leave it as detected —
    zeroing it let 16383 DN leak into its neighbours' predictions through the scene estimate's refill.  A random
    effect without data goes to its prior mean 0.  Elsewhere the one-column shrinkage is β̂·τ²/(τ² + s²)."""
    rng = np.random.default_rng(4)
    X, w = _columns(rng, k=2)
    w[:, 2, 3] = 0.0  # no data at all at this pixel
    coef = rng.standard_normal((2, *w.shape[1:])) + 5.0
    tau2 = 0.5
    out = shrink_local(w, X, coef, np.array([0.0, 1.0 / tau2]))
    assert out[0, 2, 3] == coef[0, 2, 3]  # fixed effect, no data: unchanged
    assert out[1, 2, 3] == 0.0  # random effect, no data: its prior mean
    one = shrink_local(w, X[1:], coef[1:], np.array([1.0 / tau2]))
    a = np.sum(w * X[1] ** 2, axis=0)
    expected = np.where(a > 0, coef[1] * tau2 / (tau2 + 1.0 / np.where(a > 0, a, 1.0)), 0.0)
    np.testing.assert_allclose(one[0], expected, rtol=1e-9, atol=1e-12)
    # two collinear fixed effects (a partially stuck pixel's offset and a per-pixel dark pattern with no prior):
    # their normal matrix is singular; the fitted values are kept, split by minimum norm
    Xc = [X[0], 2.0 * X[0], X[1]]
    split = shrink_local(w, Xc, np.stack([coef[0], np.zeros_like(coef[0]), coef[1]]), np.array([0.0, 0.0, 0.0]))
    fitted = sum(c[None] * x for c, x in zip(split, Xc))
    np.testing.assert_allclose(fitted * (w > 0), (coef[0][None] * X[0] + coef[1][None] * X[1]) * (w > 0),
                               rtol=1e-6, atol=1e-9)


def test_projection_is_orthogonal_and_idempotent_even_with_collinear_columns():
    rng = np.random.default_rng(3)
    X, _ = _columns(rng, k=2)
    X.append(2 * X[1])
    proj = PixelProjector(X)
    v = rng.standard_normal(X[0].shape)
    p = proj.project(v)
    for c in X:
        assert np.max(np.abs(np.einsum("r...,r...->...", c, p))) < 1e-9
    np.testing.assert_allclose(proj.project(p), p, atol=1e-9)
    # the residual of each pixel's least-squares fit on the two distinct columns
    D = np.stack([X[0][:, 2, 2], X[1][:, 2, 2]], axis=1)
    expected = v[:, 2, 2] - D @ np.linalg.lstsq(D, v[:, 2, 2], rcond=None)[0]
    np.testing.assert_allclose(p[:, 2, 2], expected, atol=1e-9)
