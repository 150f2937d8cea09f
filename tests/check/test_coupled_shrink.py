"""The coupled mixed-model shrinkage (:func:`forensics.check.joint_solve.coupled_shrink`) against a dense solve."""
import numpy as np

from forensics.check.joint_solve import coupled_shrink, operator_blocks
from forensics.check.local_solve import shrink_local


def _problem(rng, shape=(16, 16)):
    R = 6
    dark = np.array([1, 1, 0, 0, 0, 0], bool)
    w = rng.uniform(0.5, 2.0, (R, *shape))
    w[dark] *= rng.random((int(dark.sum()), *shape)) < 0.2  # most dark means censored
    X = [np.ones((R, *shape)), rng.uniform(0.5, 1.5, (R, *shape))]
    Z = [np.where(dark[:, None, None], 0.0, 1.0) * np.ones((R, *shape)), np.zeros((R, *shape))]
    F = np.where(dark[:, None, None], 0.0, -1.0) * np.ones((R, *shape))
    return X, Z, F, w, dark


def _dense(X, Z, F, w):
    k, (h, wd) = len(X), X[0].shape[1:]
    coupled = [r for r in range(F.shape[0]) if np.any(F[r])]
    blocks = operator_blocks(X, Z, F, w, coupled)
    n = k * h * wd
    A = np.empty((n, n))
    for i in range(n):
        e = np.zeros(n)
        e[i] = 1.0
        A[:, i] = blocks.apply(e.reshape(k, h, wd)).ravel()
    return A


def test_coupled_shrink_is_the_dense_mixed_model_solution():
    rng = np.random.default_rng(3)
    X, Z, F, w, _ = _problem(rng)
    coef = rng.normal(0, 1, (2, 16, 16))
    precision = np.array([4.0, 0.0])  # a random effect beside a fixed one
    A = _dense(X, Z, F, w)
    P = np.diag(np.repeat(precision, 256))
    want = np.linalg.solve(A + P, A @ coef.ravel()).reshape(coef.shape)
    got = coupled_shrink(X, Z, F, w, coef, precision)
    # CG to a residual of 1e-6 of the right-hand side, condition number ≈ 50: within 1e-4 of the values' scale
    assert np.max(np.abs(got - want)) < 1e-4 * np.max(np.abs(want))


def test_without_coupling_it_is_the_local_shrinkage():
    rng = np.random.default_rng(4)
    X, Z, F, w, _ = _problem(rng)
    coef = rng.normal(0, 1, (2, 16, 16))
    precision = np.array([4.0, 0.0])
    got = coupled_shrink(X, [np.zeros_like(z) for z in Z], np.zeros_like(F), w, coef, precision)
    want = shrink_local(w, X, coef, precision)
    assert np.max(np.abs(got - want)) < 1e-4 * np.max(np.abs(want))


def test_smooth_modes_shrink_more_than_the_local_solution_says():
    # one additive random pattern, dark frames mostly censored: the local shrinkage treats the light frames'
    # information as the pixel's own; coupled, a smooth (constant-free) mode keeps only the dark frames'
    rng = np.random.default_rng(5)
    X, Z, F, w, _ = _problem(rng, (32, 32))
    X, Z = X[:1], Z[:1]
    yy, xx = np.mgrid[:32, :32]
    smooth = np.cos(2 * np.pi * xx / 32)[None]  # one period across the image
    rough = np.where((xx + yy) % 2 == 0, 1.0, -1.0)[None]  # the checkerboard: K averages it away
    prec = np.array([25.0])
    kept = {n: float(np.sum(coupled_shrink(X, Z, F, w, m, prec) * m) / np.sum(m * m)) for n, m in
            (("smooth", smooth), ("rough", rough))}
    local = float(np.sum(shrink_local(w, X, smooth, prec) * smooth) / np.sum(smooth * smooth))
    assert kept["smooth"] < 0.8 * local
    assert kept["rough"] > kept["smooth"]
