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
from dataclasses import dataclass

import numpy as np

from forensics.check.local_solve import common_mode, common_mode_gram, dead_columns, normal_matrix, scaled_pinv
from forensics.check.scene import kernel_estimate, kernel_transpose

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
                    kernel: Callable[[np.ndarray], np.ndarray] = kernel_estimate) -> np.ndarray:
    """The linearised model's change of the prediction ``(R, H, W)`` for pattern changes ``delta`` (k, H, W)."""
    out = sum(x * delta[j][None] for j, x in enumerate(X))
    for r in range(F.shape[0]):
        if np.any(F[r]):
            moved = sum(z[r] * delta[j] for j, z in enumerate(Z))
            if np.any(moved):
                out[r] += F[r] * kernel(moved)
    return out


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
    coupled = [r for r in range(F.shape[0]) if np.any(F[r]) and any(np.any(z[r]) for z in Z)]
    held = _cached_operands(X, Z, F, weight, coupled, kernel_t, cache)
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
    profiles, factors = [], []
    for zj in Z:
        norms = np.array([float(np.sum(zj[r] ** 2)) for r in coupled])
        ref = zj[coupled[int(np.argmax(norms))]]
        den = float(np.sum(ref * ref))
        profiles.append(ref)
        factors.append(np.array([float(np.sum(zj[r] * ref)) / den if den > 0 else 0.0 for r in coupled]))
    c = np.stack(factors, axis=1)  # (|C|, k)
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
                     coupled: list[int], kernel_t: Callable[..., np.ndarray], cache: dict | None) -> _Operands:
    """The preconditioner and operator blocks, from ``cache`` when they were built there for the same ``X``,
    ``Z``, ``F`` (the same objects) and the same values of ``weight`` (a digest of its bytes, O(n) against the
    build's O(k²·R·n)).

    Why: a fit cycle solves with one (X, Z, F) once per pattern refit and once per global parameter's column;
    building the per-pixel blocks anew each time was most of the coupled solve (30 % of the EMVA standard
    series' check on a 160 × 120 region).  The weights may change within a cycle (misfitting border pixels
    dropped), hence the digest."""
    def build() -> _Operands:
        own = normal_matrix(X, weight)
        return _Operands(_preconditioner(X, Z, F, weight, coupled, kernel_t, own.copy()),
                         lambda: operator_blocks(X, Z, F, weight, coupled, own))

    if cache is None:
        return build()
    key = hashlib.blake2b(np.ascontiguousarray(weight).view(np.uint8).data, digest_size=16).digest()
    held = cache.get("operands")
    if held is None or not (len(held[0]) == len(X) and all(a is b for a, b in zip(held[0], X))
                            and len(held[1]) == len(Z) and all(a is b for a, b in zip(held[1], Z)) and held[2] is F):
        cache.clear()
        cache["operands"] = (list(X), list(Z), F)
    if key not in cache:
        cache[key] = build()
    return cache[key]


def _preconditioner(X: list[np.ndarray], Z: list[np.ndarray], F: np.ndarray, weight: np.ndarray,
                    coupled: list[int], kernel_t: Callable[..., np.ndarray], A: np.ndarray | None = None) -> np.ndarray:
    """Per pixel, the inverse of the normal matrix's own block — the pixel's own frames plus what its values do
    to its neighbours' estimates (Σ_q K_qp²·F²·w: a border pixel seen only in dark frames is otherwise read as
    far less determined than it is, and conjugate gradients took 140 iterations, not 40)."""
    k = len(X)
    A = normal_matrix(X, weight) if A is None else A  # (changed in place: pass a copy)
    own = ~dead_columns(A)  # a value without information of its own is not solved for (it stays)
    for r in coupled:
        spread = kernel_t(F[r] ** 2 * weight[r], 2)
        for i in range(k):
            for j in range(i, k):
                A[..., i, j] += np.where(own[..., i] & own[..., j], Z[i][r] * Z[j][r] * spread, 0.0)
                if j != i:
                    A[..., j, i] = A[..., i, j]
    inv, _ = scaled_pinv(A)
    return inv
