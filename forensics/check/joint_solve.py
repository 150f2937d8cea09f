"""The pixel-local patterns solved jointly over the image, with their neighbours' scene estimates.

A pixel's additive fixed pattern (DSNU, the per-pixel dark rate) also enters every neighbour's scene
estimate: a light frame's prediction of pixel p moves with the neighbours' values through the scene kernel K
(:meth:`~forensics.check.prediction.Predictor.scene_shift`).  Solved pixel by pixel with that term frozen and
updated between solves, the patterns converge by the light frames' share of the information per update —
slowly for the smooth modes, on which (I − K) is nearly 0 and only dark frames speak — and the fixed point is
not the least-squares solution: χ² rose from cycle to cycle and the global parameters collinear with a
pattern's mean (the black level with the DSNU's) drifted with it (16-bit data, 20 DN read noise, DSNU).

Here one Gauss–Newton step of all pixels' patterns is solved jointly: the linearised prediction is

    μ_r(θ + Δ) ≈ μ_r + Σ_j X_rj·Δ_j + F_r ∘ K(Σ_j Z_rj·Δ_j),

with X the derivatives by a pixel's own values (neighbour term frozen), Z the derivatives of the pixels'
deviation at zero light (what the neighbour term averages) and F the prediction's derivative by that term.
The weighted normal equations are solved by conjugate gradients preconditioned with each pixel's own block of
them (exact when nothing couples), on the subspace where the random-effect patterns keep a zero mean.
"""
from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy import sparse

from forensics.check.local_solve import (common_mode, common_mode_gram, dead_columns, normal_matrix, scaled_pinv,
                                        shrink_local)
from forensics.check.scene import SCENE_SIZE, kernel_columns, kernel_estimate, kernel_transpose

#: Conjugate gradients stop when the preconditioned residual's squared norm fell by this factor: the step is
#: then as good as exact for one Gauss–Newton cycle (the next cycle starts from the new gradient).
RELATIVE_TOLERANCE = 1e-4
#: At most this many iterations (16-bit frames with a DSNU of 48 DN on a 48 DN black level, a fifth of the
#: dark pixels at 0: 20–40).
MAX_ITERATIONS = 100


@dataclass
class CoupledStep:
    """One joint Gauss–Newton step of the pixel-local patterns."""

    delta: np.ndarray  #: (k, H, W) change of each pattern's value at each pixel
    iterations: int  #: conjugate-gradient iterations used
    converged: bool  #: the residual fell by :data:`RELATIVE_TOLERANCE`


def coupled_forward(X: list[np.ndarray], Z: list[np.ndarray], F: np.ndarray, delta: np.ndarray,
                    kernel: Callable[[np.ndarray], np.ndarray] = kernel_estimate,
                    cache: dict | None = None) -> np.ndarray:
    """The linearised model's change of the prediction ``(R, H, W)`` for pattern changes ``delta`` (k, H, W).
    ``cache``: the cycle's, as for :func:`coupled_step` (its :class:`FactoredCoupling` is reused)."""
    out = sum(x * delta[j][None] for j, x in enumerate(X))
    coupled = _coupled_frames(Z, F)
    factored = _factored(X, Z, F, coupled, cache) if kernel is kernel_estimate else None
    if factored is not None:
        if coupled:
            out[coupled] += F[coupled] * factored.spread(delta)
        return out
    for r in range(F.shape[0]):
        if np.any(F[r]):
            moved = sum(z[r] * delta[j] for j, z in enumerate(Z))
            if np.any(moved):
                out[r] += F[r] * kernel(moved)
    return out


@dataclass
class FactoredCoupling:
    """Each pattern's Z over the coupled frames C as a common profile times a factor per frame plus what differs
    from it at a few pixels: Z_rj = c_rj·z_j + e_rj, e_rj nonzero only on ``support``.

    What differs between frames is the scene estimate's excluded outliers and the refill at defects; elsewhere
    the deviation at zero light scales with the frame (exposure, temperature, gain).  With it, Σ_r Z_rj·Kᵀ(u_r)
    is z_j·Kᵀ(Σ_r c_rj·u_r) plus Σ_r e_rj·Kᵀ(u_r) on the support, and K(Σ_j Z_rj·Δ_j) likewise: k kernels
    instead of one per frame, the rest from K's columns at the support (:func:`~forensics.check.scene.kernel_columns`).
    The same numbers to rounding (residuals below :data:`FACTOR_RESIDUAL` of the largest |Z| are left out)."""

    profiles: list[np.ndarray]  #: per pattern, z_j (H, W)
    factors: np.ndarray  #: (|C|, k): c_rj
    support: np.ndarray  #: flat pixel indices where some e_rj is not 0
    residuals: np.ndarray  #: (k, |C|, len(support)): e_rj there
    _columns: dict = field(default_factory=dict)

    def columns(self, power: int) -> sparse.csr_array:
        """K's columns at the support (weights to ``power``), made once."""
        if power not in self._columns:
            self._columns[power] = kernel_columns(self.profiles[0].shape, self.support, power)
        return self._columns[power]

    def gather(self, u: np.ndarray) -> np.ndarray:
        """Σ over the coupled frames of Z_rj·Kᵀ(u_r) for ``u`` (|C|, H, W): (k, H, W)."""
        out = np.stack([z * kernel_transpose(np.tensordot(self.factors[:, j], u, 1))
                        for j, z in enumerate(self.profiles)])
        if self.support.size:
            back = self.columns(1) @ u.reshape(len(u), -1).T  # (m, |C|): Kᵀ(u_r) at the support
            for j in range(len(out)):
                out[j].flat[self.support] += np.einsum("rm,mr->m", self.residuals[j], back)
        return out

    def spread(self, delta: np.ndarray) -> np.ndarray:
        """K(Σ_j Z_rj·Δ_j) in every coupled frame: (|C|, H, W)."""
        common = np.stack([kernel_estimate(z * d) for z, d in zip(self.profiles, delta)])
        out = np.tensordot(self.factors, common, 1)
        if self.support.size:
            moved = np.einsum("jrm,jm->mr", self.residuals, delta.reshape(len(delta), -1)[:, self.support])
            out += (self.columns(1).T @ moved).T.reshape(out.shape)
        return out

    def pair_sums(self, u: np.ndarray) -> np.ndarray:
        """Σ over the coupled frames of Z_ri·Z_rj·Kᵀ²(u_r) for ``u`` (|C|, H, W): (k, k, H, W) (the preconditioner's
        coupling term)."""
        k = len(self.profiles)
        out = np.empty((k, k, *self.profiles[0].shape))
        back = self.columns(2) @ u.reshape(len(u), -1).T if self.support.size else None  # (m, |C|)
        for i in range(k):
            for j in range(i, k):
                cc = self.factors[:, i] * self.factors[:, j]
                out[i, j] = self.profiles[i] * self.profiles[j] * kernel_transpose(np.tensordot(cc, u, 1), 2)
                if back is not None:
                    zi = self.factors[:, i][:, None] * self.profiles[i].flat[self.support][None] + self.residuals[i]
                    zj = self.factors[:, j][:, None] * self.profiles[j].flat[self.support][None] + self.residuals[j]
                    extra = zi * zj - cc[:, None] * (self.profiles[i].flat[self.support]
                                                     * self.profiles[j].flat[self.support])[None]
                    out[i, j].flat[self.support] += np.einsum("rm,mr->m", extra, back)
                out[j, i] = out[i, j]
        return out


#: A pattern's Z in a frame is taken to differ from its profile times the frame's factor where it does by more than
#: this share of its largest |Z| (below: the factors' rounding).
FACTOR_RESIDUAL = 1e-12
#: The factored form is used while its support is at most this share of the pixels (beyond, per-frame kernels).
FACTOR_SUPPORT = 0.25


def profiles_and_factors(Z: list[np.ndarray], coupled: list[int],
                         exact_scale: bool = False) -> tuple[list[np.ndarray], np.ndarray]:
    """Per pattern, the common profile z_j (its Z in the coupled frame where it is largest) and each coupled
    frame's factor c_rj: ``(profiles, factors (|C|, k))``.  The factor is the least-squares one (what the normal
    operator's approximation is best with), or with ``exact_scale`` the median ratio of the frame's Z to the
    profile: the frames differ from the profile at a few pixels (excluded outliers, defects' refills), a
    least-squares factor takes a share of those and leaves a small residual at every pixel, the median ratio is
    the exact scale of all the others (:class:`FactoredCoupling` needs the residual sparse)."""
    profiles, factors = [], []
    for zj in Z:
        norms = np.array([float(np.sum(zj[r] ** 2)) for r in coupled])
        ref = zj[coupled[int(np.argmax(norms))]]
        profiles.append(ref)
        if exact_scale:
            on = np.abs(ref) > 1e-6 * float(np.max(np.abs(ref)))
            factors.append(np.array([float(np.median(zj[r][on] / ref[on])) if on.any() else 0.0 for r in coupled]))
        else:
            den = float(np.sum(ref * ref))
            factors.append(np.array([float(np.sum(zj[r] * ref)) / den if den > 0 else 0.0 for r in coupled]))
    return profiles, np.stack(factors, axis=1)


def factor_coupling(Z: list[np.ndarray], coupled: list[int]) -> FactoredCoupling | None:
    """The :class:`FactoredCoupling` of ``Z`` over the ``coupled`` frames; None where it would not pay (a support
    over :data:`FACTOR_SUPPORT` of the pixels) or the image is too small for :func:`kernel_columns`."""
    H, W = Z[0].shape[1:]
    if not coupled or H <= SCENE_SIZE or W <= SCENE_SIZE:
        return None
    profiles, factors = profiles_and_factors(Z, coupled, exact_scale=True)
    residuals = [zj[coupled] - factors[:, j, None, None] * profiles[j][None] for j, zj in enumerate(Z)]
    off = np.zeros((H, W), bool)
    for zj, e in zip(Z, residuals):
        off |= np.any(np.abs(e) > FACTOR_RESIDUAL * float(np.max(np.abs(zj[coupled]))), axis=0)
    support = np.flatnonzero(off)
    if support.size > FACTOR_SUPPORT * H * W:
        return None
    kept = np.stack([e.reshape(len(coupled), -1)[:, support] for e in residuals])
    return FactoredCoupling(profiles, factors, support, kept)


def _coupled_frames(Z: list[np.ndarray], F: np.ndarray) -> list[int]:
    """The frames where the neighbour term acts (F) and some pattern moves it (Z)."""
    return [r for r in range(F.shape[0]) if np.any(F[r]) and any(np.any(z[r]) for z in Z)]


def _cycle_cache(X: list[np.ndarray], Z: list[np.ndarray], F: np.ndarray, cache: dict) -> dict:
    """``cache``, emptied when it was kept for other ``X``, ``Z``, ``F`` (other objects)."""
    held = cache.get("operands")
    if held is None or not (len(held[0]) == len(X) and all(a is b for a, b in zip(held[0], X))
                            and len(held[1]) == len(Z) and all(a is b for a, b in zip(held[1], Z)) and held[2] is F):
        cache.clear()
        cache["operands"] = (list(X), list(Z), F)
    return cache


def _factored(X: list[np.ndarray], Z: list[np.ndarray], F: np.ndarray, coupled: list[int],
              cache: dict | None) -> FactoredCoupling | None:
    """:func:`factor_coupling`, made once per cycle in ``cache``."""
    if cache is None:
        return factor_coupling(Z, coupled)
    cache = _cycle_cache(X, Z, F, cache)
    if "factored" not in cache:
        cache["factored"] = factor_coupling(Z, coupled)
    return cache["factored"]


def coupled_step(X: list[np.ndarray], Z: list[np.ndarray], F: np.ndarray, weight: np.ndarray, residual: np.ndarray,
                 centred: list[bool], kernel: Callable[[np.ndarray], np.ndarray] = kernel_estimate,
                 kernel_t: Callable[..., np.ndarray] = kernel_transpose,
                 tol: float = RELATIVE_TOLERANCE, max_iter: int = MAX_ITERATIONS,
                 cache: dict | None = None, members: np.ndarray | None = None) -> CoupledStep:
    """The weighted least-squares step Δ of the linearised model above.

    Parameters
    ----------
    X, Z
        Per pattern, ``(R, H, W)``: the prediction's derivative by the pixel's own value, and the derivative of
        the pixel's deviation at zero light (0 in dark frames and for patterns that do not add a signal).
    F
        ``(R, H, W)``: the prediction's derivative by the neighbour term (0 where it does not act).
    weight, residual
        ``(R, H, W)``: weights and data less prediction.
    centred
        Per pattern: its values keep a zero sum over the pixels (random effects).
    kernel, kernel_t
        The scene kernel K and its transpose on one image (``kernel_t(u, 2)``: with the squared weights).
    cache
        A dict kept by the caller for one set of ``X``, ``Z``, ``F`` (a fit cycle): the preconditioner is built
        once per content of ``weight`` in it (:func:`_preconditioner`).
    members
        ``(H, W)``: the pixels whose ``centred`` values keep the zero sum (default all; the others are free).
    """
    k = len(X)
    shape = X[0].shape[1:]
    coupled = _coupled_frames(Z, F)
    factored = _factored(X, Z, F, coupled, cache) if kernel_t is kernel_transpose else None
    held = _cached_operands(X, Z, F, weight, coupled, kernel_t, cache, factored)
    inv = held.inverse
    centred_mask = np.asarray(centred, bool)
    gram = common_mode_gram(inv, centred_mask, members) if centred_mask.any() else None

    def precondition(g: np.ndarray) -> np.ndarray:
        z = np.einsum("...ij,...j->...i", inv, np.moveaxis(g, 0, -1))
        shift = common_mode(inv, z, centred_mask, gram, members)
        if shift is not None:
            z = z + shift
        return np.moveaxis(z, -1, 0)

    # the gradient with the exact coupling (one transposed kernel per frame): the step's fixed point is the
    # least-squares solution itself
    v = weight * residual
    g = np.stack([np.einsum("r...,r...->...", x, v) for x in X])
    if factored is not None:
        g += factored.gather(F[coupled] * v[coupled])
    else:
        for r in coupled:
            back = kernel_t(F[r] * v[r])
            for j, z in enumerate(Z):
                g[j] += z[r] * back
    z = precondition(g)
    rz = float(np.sum(g * z))
    if not coupled or rz <= 0.0:  # the per-pixel solve is exact
        return CoupledStep(z, 0, True)
    blocks = held.blocks()
    rz0 = rz
    delta = np.zeros((k, *shape))
    p = z.copy()
    for it in range(1, max_iter + 1):
        q = blocks.apply(p, kernel, kernel_t)  # AᵀWA·p
        pq = float(np.sum(p * q))
        if pq <= 0.0:
            return CoupledStep(delta, it, False)
        alpha = rz / pq
        delta += alpha * p
        g -= alpha * q
        z = precondition(g)
        rz_new = float(np.sum(g * z))
        if rz_new <= tol * rz0:
            return CoupledStep(delta, it, True)
        p = z + (rz_new / rz) * p
        rz = rz_new
    return CoupledStep(delta, max_iter, False)


@dataclass
class OperatorBlocks:
    """The normal operator AᵀWA of :func:`coupled_step` reduced to per-pixel blocks over the frames.

    The operator is built with each pattern's Z factored as c_r·z(p) (``profiles`` z, ``factors`` c over the
    coupled frames C: what differs between frames is the scene estimate's excluded outliers, a few pixels) —
    one kernel and one transpose per pattern and iteration instead of one per frame; an approximate Hessian only
    slows the iterations, the fixed point stays exact.  With S_j = K(z_j·Δ_j) it is

        (AᵀWA·Δ)_i = Σ_j own_ij·Δ_j + Σ_j cross_ij·S_j + z_i·Kᵀ(Σ_j cross_ji·Δ_j + Σ_j spread_ij·S_j),

    own_ij = Σ_r X_ri·w_r·X_rj, cross_ij = Σ_{r∈C} X_ri·w_r·F_r·c_rj, spread_ij = Σ_{r∈C} c_ri·c_rj·F_r²·w_r.
    Why: applied frame by frame the operator cost O(k·R) image passes per iteration, and it was a quarter of
    the check's time on the camera convention (R ≈ 100 conditions); these sums over the frames are made once per
    weights and cost O(k²) passes per iteration.  The same numbers up to rounding."""

    own: np.ndarray  #: (k, k, H, W)
    cross: np.ndarray  #: (k, k, H, W)
    spread: np.ndarray  #: (k, k, H, W)
    profiles: list[np.ndarray]  #: per pattern, (H, W)

    def apply(self, d: np.ndarray, kernel: Callable[[np.ndarray], np.ndarray] = kernel_estimate,
              kernel_t: Callable[..., np.ndarray] = kernel_transpose) -> np.ndarray:
        """AᵀWA·``d`` for pattern changes ``d`` (k, H, W)."""
        spread = np.stack([kernel(z * dj) for z, dj in zip(self.profiles, d)])
        out = np.einsum("ij...,j...->i...", self.own, d) + np.einsum("ij...,j...->i...", self.cross, spread)
        into = np.einsum("ji...,j...->i...", self.cross, d) + np.einsum("ij...,j...->i...", self.spread, spread)
        for j, z in enumerate(self.profiles):
            out[j] += z * kernel_t(into[j])
        return out


def operator_blocks(X: list[np.ndarray], Z: list[np.ndarray], F: np.ndarray, weight: np.ndarray,
                    coupled: list[int], own: np.ndarray | None = None) -> OperatorBlocks:
    """The :class:`OperatorBlocks` of the linearised model (``own``: its :func:`normal_matrix`, if made)."""
    k = len(X)
    own = normal_matrix(X, weight) if own is None else own
    profiles, c = profiles_and_factors(Z, coupled)  # c: (|C|, k)
    fw = F[coupled] * weight[coupled]
    cross = np.stack([np.einsum("r...,rj->j...", X[i][coupled] * fw, c) for i in range(k)])
    spread = np.einsum("ri,rj,r...->ij...", c, c, fw * F[coupled])
    return OperatorBlocks(np.moveaxis(own, (-2, -1), (0, 1)), cross, spread, profiles)


@dataclass
class _Operands:
    """What :func:`coupled_step` builds once per weights: the preconditioner, and the operator's blocks when
    conjugate gradients need them."""

    inverse: np.ndarray
    build: Callable[[], OperatorBlocks]
    _blocks: OperatorBlocks | None = None

    def blocks(self) -> OperatorBlocks:
        if self._blocks is None:
            self._blocks = self.build()
        return self._blocks


def _cached_operands(X: list[np.ndarray], Z: list[np.ndarray], F: np.ndarray, weight: np.ndarray,
                     coupled: list[int], kernel_t: Callable[..., np.ndarray], cache: dict | None,
                     factored: FactoredCoupling | None = None) -> _Operands:
    """The preconditioner and operator blocks, from ``cache`` when they were built there for the same ``X``,
    ``Z``, ``F`` (the same objects) and the same values of ``weight`` (a digest of its bytes, O(n) against the
    build's O(k²·R·n)).

    Why: a fit cycle solves with one (X, Z, F) once per pattern refit and once per global parameter's column;
    building the per-pixel blocks anew each time was most of the coupled solve (30 % of the EMVA standard
    series' check on a 160 × 120 region).  The weights may change within a cycle (misfitting border pixels
    dropped), hence the digest."""
    def build() -> _Operands:
        own = normal_matrix(X, weight)
        return _Operands(_preconditioner(X, Z, F, weight, coupled, kernel_t, own.copy(), factored),
                         lambda: operator_blocks(X, Z, F, weight, coupled, own))

    if cache is None:
        return build()
    key = hashlib.blake2b(np.ascontiguousarray(weight).view(np.uint8).data, digest_size=16).digest()
    cache = _cycle_cache(X, Z, F, cache)
    if key not in cache:
        cache[key] = build()
    return cache[key]


def _preconditioner(X: list[np.ndarray], Z: list[np.ndarray], F: np.ndarray, weight: np.ndarray,
                    coupled: list[int], kernel_t: Callable[..., np.ndarray], A: np.ndarray | None = None,
                    factored: FactoredCoupling | None = None) -> np.ndarray:
    """Per pixel, the inverse of the normal matrix's own block — the pixel's own frames plus what its values do
    to its neighbours' estimates (Σ_q K_qp²·F²·w: a border pixel seen only in dark frames is otherwise read as
    far less determined than it is, and conjugate gradients took 140 iterations, not 40)."""
    k = len(X)
    A = normal_matrix(X, weight) if A is None else A  # (changed in place: pass a copy)
    own = ~dead_columns(A)  # a value without information of its own is not solved for (it stays)
    if factored is not None and coupled:
        pairs = factored.pair_sums(F[coupled] ** 2 * weight[coupled])
        for i in range(k):
            for j in range(i, k):
                A[..., i, j] += np.where(own[..., i] & own[..., j], pairs[i, j], 0.0)
                A[..., j, i] = A[..., i, j]
        coupled = []
    for r in coupled:
        spread = kernel_t(F[r] ** 2 * weight[r], 2)
        for i in range(k):
            for j in range(i, k):
                A[..., i, j] += np.where(own[..., i] & own[..., j], Z[i][r] * Z[j][r] * spread, 0.0)
                if j != i:
                    A[..., j, i] = A[..., i, j]
    inv, _ = scaled_pinv(A)
    return inv


def coupled_shrink(X: list[np.ndarray], Z: list[np.ndarray], F: np.ndarray, weight: np.ndarray, coef: np.ndarray,
                   precision: np.ndarray, residual: np.ndarray | None = None, tol: float = 1e-12,
                   max_iter: int = 4 * MAX_ITERATIONS) -> np.ndarray:
    """:func:`~forensics.check.local_solve.shrink_local` with the neighbours' scene term: least-squares values
    ``coef`` (k, H, W) moved to the mixed-model solution β = (A + P)⁻¹·A·β̂, A the *coupled* normal operator of
    :func:`coupled_step` (each pixel's own frames and what its values do to its neighbours' scene estimates),
    P = diag(``precision``) (1/τ² of a random effect, 0 for a fixed one, ``inf`` to fix it at 0).  Values
    without information of their own keep β̂ (fixed effects) or go to 0 (random ones), as there.

    Why: an additive pattern's smooth modes are what the scene estimates absorb — on them (I − K) is nearly 0,
    and only the dark frames speak.  Per pixel the information looks like the light frames' and the dark
    frames' together, so the local shrinkage leaves the smooth modes' noise almost whole; where the dark
    frames say little (8-bit frames at a black level of 0 DN, most dark means censored) that noise is most of
    the fitted values' error, and the held-out half's prediction, which carries it, shares it with the first
    half's residuals (a pattern "in both halves" that is the fit's own error).  Solved with the coupling, each
    mode is shrunk by its own information.  Conjugate gradients on the free values, preconditioned by each
    pixel's own block plus P, until the preconditioned residual's squared norm fell by ``tol`` (10⁻¹²: a
    residual of 10⁻⁶ of the right-hand side's, well below the values' own noise)."""
    k = len(X)
    prec = np.asarray(precision, float)
    coupled = _coupled_frames(Z, F)
    if not coupled:
        return shrink_local(weight, X, coef, prec)
    own = normal_matrix(X, weight)
    pinned = np.moveaxis(dead_columns(own) | np.isinf(prec), -1, 0)  # (k, H, W)
    beta = np.asarray(coef, float)
    fixed = np.where(pinned & (prec == 0)[:, None, None], beta, 0.0)
    free = ~pinned
    finite = np.where(np.isfinite(prec), prec, 0.0)[:, None, None]
    blocks = operator_blocks(X, Z, F, weight, coupled, own.copy())
    aug = own.copy()
    aug[..., np.arange(k), np.arange(k)] += finite[:, 0, 0]
    inv = _preconditioner(X, Z, F, weight, coupled, kernel_transpose, aug)

    def apply(d: np.ndarray) -> np.ndarray:
        return free * (blocks.apply(free * d) + finite * d)

    def precondition(g: np.ndarray) -> np.ndarray:
        return free * np.moveaxis(np.einsum("...ij,...j->...i", inv, np.moveaxis(free * g, 0, -1)), -1, 0)

    # the right-hand side A·(β̂ − pinned values) + Jᵀ·W·r, on the free values: Henderson's equations hold at any
    # β̂, not only at the least-squares point — the fit's conjugate gradients stop at a relative tolerance, and
    # the modes the data hardly determine (the smooth ones) are the last to converge and the first left behind
    g = blocks.apply(beta - fixed)
    if residual is not None:
        v = np.where(weight > 0, weight * residual, 0.0)  # (no weight: no residual, NaN or not)
        g += np.stack([np.einsum("r...,r...->...", x, v) for x in X])
        for r in coupled:
            back = kernel_transpose(F[r] * v[r])
            for j, zj in enumerate(Z):
                g[j] += zj[r] * back
    g = free * g
    x = precondition(g)
    r = g - apply(x)
    z = precondition(r)
    rz = float(np.sum(r * z))
    rz0 = float(np.sum(g * precondition(g)))
    p = z.copy()
    for _ in range(max_iter):
        if rz <= tol * rz0:
            break
        q = apply(p)
        pq = float(np.sum(p * q))
        if pq <= 0.0:
            break
        alpha = rz / pq
        x += alpha * p
        r -= alpha * q
        z = precondition(r)
        rz_new = float(np.sum(r * z))
        p = z + (rz_new / rz) * p
        rz = rz_new
    return free * x + fixed
