"""The joint solve of the pixel-local patterns with the scene kernel's coupling (forensics.check.joint_solve)."""
import numpy as np

from forensics.check.joint_solve import coupled_step
from forensics.check.scene import kernel_estimate, kernel_transpose


def _dense_solution(X, Z, F, w, res, centred):
    """The same weighted least squares, built as a dense matrix (one column per pixel and pattern), with the
    centred patterns' sums held at zero by a Lagrange multiplier."""
    k = len(X)
    R, H, W = X[0].shape
    n = H * W
    cols = []
    for j in range(k):
        for q in range(n):
            d = np.zeros((k, H, W))
            d[j].flat[q] = 1.0
            col = sum(x * d[i][None] for i, x in enumerate(X))
            for r in range(R):
                col[r] += F[r] * kernel_estimate(sum(z[r] * d[i] for i, z in enumerate(Z)))
            cols.append(col.ravel())
    A = np.array(cols).T
    sw = np.sqrt(w.ravel())
    M = (A * sw[:, None]).T @ (A * sw[:, None])
    b = (A * sw[:, None]).T @ (sw * res.ravel())
    C = np.zeros((sum(centred), k * n))
    for m, j in enumerate([j for j in range(k) if centred[j]]):
        C[m, j * n:(j + 1) * n] = 1.0
    kkt = np.block([[M, C.T], [C, np.zeros((len(C), len(C)))]])
    sol = np.linalg.solve(kkt, np.concatenate([b, np.zeros(len(C))]))
    return sol[:k * n].reshape(k, H, W)


def _two_pattern_problem(rng: np.random.Generator):
    """Two patterns (the first centred), two dark and four light frames, Z proportional between frames (the case
    the solver's operator factors exactly), uneven weights: (X, Z, F, w), arrays of (6, 11, 12)."""
    R, H, W = 6, 11, 12
    dark = np.array([1, 1, 0, 0, 0, 0], bool)
    X = [np.ones((R, H, W)), rng.uniform(0.5, 2.0, (R, H, W))]
    scale = np.array([0, 0, 1.0, 2.0, 1.0, 0.5])
    Z = [scale[:, None, None] * np.ones((R, H, W)), np.zeros((R, H, W))]
    F = np.where(dark[:, None, None], 0.0, -rng.uniform(0.8, 1.2, (R, H, W)))
    w = rng.uniform(0.5, 1.5, (R, H, W))
    return X, Z, F, w


def test_coupled_step_equals_dense_least_squares():
    """With Z proportional between frames (the case the solver's operator factors exactly), the step is the
    dense constrained least-squares solution; two patterns (one centred), dark and light frames, uneven
    weights.  Tolerance: the solver runs to a squared residual 1e-20 of the start, so the solution's
    relative error is ~1e-5 times the condition number."""
    rng = np.random.default_rng(3)
    X, Z, F, w = _two_pattern_problem(rng)
    R, H, W = w.shape
    w[0, 3, 4] = w[1, 3, 4] = 0.0  # a pixel without dark information
    res = rng.standard_normal((R, H, W))
    step = coupled_step(X, Z, F, w, res, [True, False], tol=1e-20, max_iter=500)
    want = _dense_solution(X, Z, F, w, res, [True, False])
    assert step.iterations > 1
    np.testing.assert_allclose(step.delta, want, atol=1e-6 * np.max(np.abs(want)))
    assert abs(step.delta[0].sum()) < 1e-8 * np.abs(step.delta[0]).sum()


def test_cached_preconditioner_gives_the_same_step_and_follows_the_weights():
    """A cycle's cache (one X, Z, F) gives bit for bit the step computed without it, for every residual, and a
    change of the weights' values in place (misfitting pixels dropped) builds the preconditioner anew."""
    rng = np.random.default_rng(6)
    X, Z, F, w = _two_pattern_problem(rng)
    R, H, W = w.shape
    cache: dict = {}
    for _ in range(2):
        res = rng.standard_normal((R, H, W))
        cached = coupled_step(X, Z, F, w, res, [True, False], cache=cache)
        plain = coupled_step(X, Z, F, w, res, [True, False])
        assert np.array_equal(cached.delta, plain.delta) and cached.iterations == plain.iterations
    def built() -> int:  # preconditioners built (one per content of the weights), besides the cycle's own entries
        return sum(isinstance(key, bytes) for key in cache)

    assert built() == 1
    w[:, 3, 4] = 0.0
    cached = coupled_step(X, Z, F, w, res, [True, False], cache=cache)
    assert np.array_equal(cached.delta, coupled_step(X, Z, F, w, res, [True, False]).delta)
    assert built() == 2


def test_uncoupled_step_is_the_per_pixel_solve():
    """Without coupling (no frame where both F and Z act) the answer comes in one preconditioner application."""
    rng = np.random.default_rng(4)
    R, H, W = 5, 9, 10
    X = [np.ones((R, H, W))]
    res = rng.standard_normal((R, H, W))
    step = coupled_step(X, [np.zeros((R, H, W))], np.ones((R, H, W)), np.ones((R, H, W)), res, [False])
    assert step.iterations == 0 and step.converged
    np.testing.assert_allclose(step.delta[0], res.mean(axis=0), atol=1e-12)


def test_kernel_transpose_is_the_adjoint():
    """⟨K·x, y⟩ = ⟨x, Kᵀ·y⟩ to rounding, with the edge band (large images) and without it (small ones)."""
    rng = np.random.default_rng(5)
    for shape in [(40, 53), (9, 11), (6, 7)]:
        x, y = rng.standard_normal(shape), rng.standard_normal(shape)
        lhs = float(np.sum(kernel_estimate(x) * y))
        rhs = float(np.sum(x * kernel_transpose(y)))
        assert abs(lhs - rhs) <= 1e-12 * (np.abs(x).sum() * np.abs(y).sum()) ** 0.5 * 10


def test_operator_blocks_equal_the_frame_by_frame_operator():
    """The normal operator from per-pixel blocks (sums over the frames made once per weights) gives what the
    factored operator applied frame by frame gives, to rounding: three patterns, Z not proportional between
    frames (the factoring approximate), uneven weights, F zero in some frames."""
    from forensics.check.joint_solve import operator_blocks

    rng = np.random.default_rng(8)
    R, H, W, k = 7, 13, 17, 3
    X = [rng.uniform(0.2, 2.0, (R, H, W)) for _ in range(k)]
    Z = [rng.uniform(0.0, 1.5, (R, H, W)) for _ in range(k)]
    F = -rng.uniform(0.5, 1.5, (R, H, W))
    F[:2] = 0.0
    w = rng.uniform(0.1, 2.0, (R, H, W))
    coupled = list(range(2, R))
    blocks = operator_blocks(X, Z, F, w, coupled)
    d = rng.standard_normal((k, H, W))

    # frame by frame, the factored operator as written before the blocks (the reference)
    from forensics.check.joint_solve import profiles_and_factors

    _, c = profiles_and_factors(Z, coupled)
    factors = list(c.T)
    spread = [kernel_estimate(blocks.profiles[j] * d[j]) for j in range(k)]
    u = sum(x * d[j][None] for j, x in enumerate(X))
    u[coupled] += F[coupled] * sum(c[:, None, None] * s[None] for c, s in zip(factors, spread))
    u *= w
    want = np.stack([np.einsum("r...,r...->...", x, u) for x in X])
    fu = F[coupled] * u[coupled]
    for j in range(k):
        want[j] += blocks.profiles[j] * kernel_transpose(np.einsum("r,r...->...", factors[j], fu))

    got = blocks.apply(d, kernel_estimate, kernel_transpose)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10 * np.abs(want).max())


def test_factored_coupling_gives_the_per_frame_step():
    """Z that scales with the frame except at a few pixels per frame (a scene estimate's excluded outliers, the
    refill at a defect): the factored form (common profile × factor, residuals at the support, K's columns there)
    gives the per-frame kernels' gradient, preconditioner and step, and the same linearised forward model, to
    rounding.  The per-frame path is forced by passing kernels that are not the default objects."""
    from forensics.check.joint_solve import coupled_forward, factor_coupling

    rng = np.random.default_rng(11)
    R, H, W = 8, 23, 29
    dark = np.array([1, 1, 0, 0, 0, 0, 0, 0], bool)
    X = [np.ones((R, H, W)), rng.uniform(0.5, 2.0, (R, H, W))]
    scale = np.array([0, 0, 1.0, 2.0, 1.0, 0.5, 3.0, 1.5])
    base = [rng.standard_normal((H, W)), np.where(rng.uniform(size=(H, W)) < 0.05, 1.0, 0.0)]
    Z = [scale[:, None, None] * b[None] for b in base]
    for r in range(2, R):  # a few pixels per frame off the profile, on the edge band too
        for z in Z:
            idx = rng.choice(H * W, 4, replace=False)
            z[r].flat[idx] += rng.standard_normal(4)
    F = np.where(dark[:, None, None], 0.0, -rng.uniform(0.8, 1.2, (R, H, W)))
    w = rng.uniform(0.5, 1.5, (R, H, W))
    res = rng.standard_normal((R, H, W))
    coupled = list(range(2, R))
    fac = factor_coupling(Z, coupled)
    assert fac is not None and 0 < fac.support.size <= 2 * 4 * len(coupled)

    # the three sums the solver takes over the coupled frames, against the per-frame kernels: to rounding
    u = rng.standard_normal((len(coupled), H, W))
    scale_u = np.abs(u).sum(axis=0).max() * max(np.abs(z).max() for z in Z) ** 2
    want = np.stack([sum(z[r] * kernel_transpose(u[n]) for n, r in enumerate(coupled)) for z in Z])
    np.testing.assert_allclose(fac.gather(u), want, rtol=0, atol=1e-13 * scale_u)
    pairs = fac.pair_sums(u)
    for i in range(2):
        for j in range(2):
            want = sum(Z[i][r] * Z[j][r] * kernel_transpose(u[n], 2) for n, r in enumerate(coupled))
            np.testing.assert_allclose(pairs[i, j], want, rtol=0, atol=1e-13 * scale_u)
    delta = rng.standard_normal((2, H, W))
    want = np.stack([kernel_estimate(sum(z[r] * delta[j] for j, z in enumerate(Z))) for r in coupled])
    np.testing.assert_allclose(fac.spread(delta), want, rtol=0, atol=1e-13 * scale_u)

    # and the whole step (the same iterations; the solutions agree within what the stopping rule leaves, as for
    # the dense solution above) and the forward model, with the per-frame path forced by kernels that are not
    # the default objects
    def plain_t(u, power=1):
        return kernel_transpose(u, power)

    def plain_k(u):
        return kernel_estimate(u)

    fast = coupled_step(X, Z, F, w, res, [True, False], tol=1e-20, max_iter=500)
    slow = coupled_step(X, Z, F, w, res, [True, False], kernel=plain_k, kernel_t=plain_t, tol=1e-20, max_iter=500)
    np.testing.assert_allclose(fast.delta, slow.delta, rtol=0, atol=1e-6 * np.abs(slow.delta).max())
    np.testing.assert_allclose(coupled_forward(X, Z, F, delta), coupled_forward(X, Z, F, delta, kernel=plain_k),
                               rtol=0, atol=1e-13 * scale_u)
