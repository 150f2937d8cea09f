"""Per-pixel linear algebra of the pixel channel: projection off per-pixel nuisance directions, and
per-pixel weighted least squares."""
from __future__ import annotations

import numpy as np


def normal_matrix(X: list[np.ndarray], weight: np.ndarray | None = None) -> np.ndarray:
    """Per pixel, the (weighted) Gram matrix Σ_r X_i·w·X_j of the columns ``X`` (each ``(R, H, W)``):
    ``(H, W, k, k)``."""
    k = len(X)
    A = np.empty((*X[0].shape[1:], k, k))
    for i in range(k):
        xi = X[i] if weight is None else X[i] * weight
        for j in range(i, k):
            A[..., i, j] = A[..., j, i] = np.einsum("r...,r...->...", xi, X[j])
    return A


#: Per pixel, an eigenvalue of the scaled (unit-diagonal) normal matrix below this is a direction the data do
#: not determine.  The columns are finite-difference derivatives of a float prediction, so two columns that
#: are the same function of the conditions (a defect's offset and the DSNU value at its pixel) come out
#: correlated to ~1 − 1e-9, not exactly 1; a pair this close to collinear is not separable by any data.
LOCAL_NULL = 1e-7


def scaled_pinv(A: np.ndarray, null: float = LOCAL_NULL,
                dead: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the pseudo-inverse of a normal matrix ``A`` (…, k, k), computed on its unit-diagonal scaling
    with null directions (eigenvalues below ``null`` times the largest) dropped, and which columns it leaves
    undetermined (…, k).  ``dead``: columns without information (default :func:`dead_columns`).

    Why not ``inv(A + ridge)``: where two columns are collinear at a pixel (a partially stuck pixel's own
    offset and the per-pixel DSNU), the ridged inverse splits their common value into ±10⁵ that cancel; kept
    in float32 patterns, the cancellation is noise in every later prediction.  The pseudo-inverse gives the
    minimum-norm split, and the prediction is the same.
    """
    diag = np.einsum("...ii->...i", A)
    dead = dead_columns(A) if dead is None else dead
    scale = np.sqrt(np.where(dead, 1.0, diag))
    S = A / (scale[..., :, None] * scale[..., None, :])
    live = ~dead
    S = np.where(live[..., :, None] & live[..., None, :], S, 0.0)
    lam, vec = np.linalg.eigh(S)
    keep = lam > null * np.maximum(lam[..., -1:], 1e-300)
    inv_lam = np.where(keep, 1.0 / np.where(keep, lam, 1.0), 0.0)
    inv = np.einsum("...ik,...k,...jk->...ij", vec, inv_lam, vec)
    inv /= scale[..., :, None] * scale[..., None, :]
    undetermined = np.einsum("...ik,...k->...i", vec**2, (~keep).astype(float)) > 1e-6
    return inv, undetermined | dead


def dead_columns(A: np.ndarray) -> np.ndarray:
    """Per pixel, the columns of a normal matrix ``(H, W, k, k)`` that carry no information ``(H, W, k)``."""
    diag = np.einsum("...ii->...i", A)
    return diag <= 1e-12 * (diag.max() if diag.size else 1.0)


def common_mode(inv: np.ndarray, coef: np.ndarray, centred: np.ndarray,
                gram: tuple[np.ndarray, np.ndarray] | None = None,
                members: np.ndarray | None = None) -> np.ndarray | None:
    """The per-pixel change of least-squares coefficients that makes the ``centred`` columns' coefficients
    sum to zero over the pixels (the constrained least-squares solution): ``− A⁺[:, C]·G⁻¹·Σ_p β_C`` with
    ``G = Σ_p A⁺[C, C]``.  ``inv`` (…, k, k) the per-pixel pseudo-inverses, ``coef`` (…, k) the coefficients.

    Why: a random-effect pattern (PRNU, DSNU, DCNU) has zero mean by definition, and its mean is collinear
    with a global parameter (the DSNU's mean with a dark offset, the DCNU's with the mean dark rate).
    Unconstrained, the split between the two is arbitrary, and the global parameter is then fitted from
    whatever else touches it — the neighbours' scene estimates — and comes out biased.

    ``gram``: :func:`common_mode_gram` of ``inv`` and ``centred``, when the caller applies one ``inv`` to many
    coefficients (the joint solve's preconditioner, once per iteration: building it was a tenth of that solve).
    ``members``: the pixels ``(…)`` over which the sums run (default all); the others' coefficients are free and
    keep their unconstrained values (the fit's never-scored border, whose mean is not the pattern's:
    :func:`~forensics.check.pixelfit.recentre`).
    """
    cols = np.flatnonzero(centred)
    if cols.size == 0:
        return None
    inv_c, G = common_mode_gram(inv, centred, members) if gram is None else gram
    if members is not None:
        coef = coef[members]
    total = coef.reshape(-1, coef.shape[-1])[:, cols].sum(axis=0)
    lam = np.linalg.lstsq(G, total, rcond=None)[0]
    return -np.einsum("...ic,c->...i", inv_c, lam)


def common_mode_gram(inv: np.ndarray, centred: np.ndarray,
                     members: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """What :func:`common_mode` needs of the pseudo-inverses ``inv`` alone: their ``centred`` columns
    ``A⁺[:, C]`` (…, k, c), zero outside ``members`` where given, and ``G = Σ_p A⁺[C, C]`` (c, c) over them."""
    cols = np.flatnonzero(centred)
    inv_c = inv[..., :, cols]
    if members is None:
        flat_inv = inv.reshape(-1, *inv.shape[-2:])
        return inv_c, flat_inv[:, cols][:, :, cols].sum(axis=0)
    return inv_c * members[..., None, None], inv[members][:, cols][:, :, cols].sum(axis=0)


class PixelProjector:
    """Projection, pixel by pixel, off the span of per-pixel nuisance directions (weighted).

    ``columns`` are arrays ``(R, H, W)`` already multiplied by √weight; for each pixel the projection acts on the
    vector over conditions.  Columns flagged ``centred`` (random-effect patterns) have coefficients that sum to
    zero over the pixels (:func:`common_mode`): their common mode is not a nuisance direction, so it stays.
    """

    def __init__(self, columns: list[np.ndarray], centred: list[bool] | None = None):
        self.cols = columns
        k = len(columns)
        self.centred = np.zeros(k, bool) if centred is None else np.asarray(centred, bool)
        if k == 0:
            self.inv = None
            return
        self.inv = scaled_pinv(normal_matrix(columns))[0]

    def project(self, x: np.ndarray, keep_common: bool = True) -> np.ndarray:
        """``x`` off the nuisance directions; ``keep_common=False`` projects off the centred columns' common
        mode too — for a candidate random-effect pattern, whose own mean is 0 as well: its common mode is not
        part of its signature (kept, it read as a pattern of no size, and dsnu looked infinitely strong on a
        flat of one light level, where it is prnu's column)."""
        if self.inv is None:
            return x
        k = len(self.cols)
        b = np.stack([np.einsum("r...,r...->...", c, x) for c in self.cols], axis=-1)
        coef = np.einsum("...ij,...j->...i", self.inv, b)
        shift = common_mode(self.inv, coef, self.centred) if keep_common else None
        if shift is not None:
            coef += shift
        out = x.copy()
        for j in range(k):
            out -= coef[..., j][None] * self.cols[j]
        return out

    def leverage(self) -> np.ndarray | None:
        if self.inv is None:
            return None
        k = len(self.cols)
        h = np.zeros(self.cols[0].shape)
        for i in range(k):
            for j in range(k):
                h += self.cols[i] * self.cols[j] * self.inv[..., i, j][None]
        return h


def solve_local(weight: np.ndarray, X: list[np.ndarray], r: np.ndarray,
                centred: list[bool] | None = None, members: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel weighted least squares of ``r`` on the columns ``X``: (coefficients (k,H,W), their variances).

    Where columns are collinear at a pixel the coefficients are the minimum-norm solution and their variances
    NaN (not determined there), as for a column without information (:func:`scaled_pinv`).  The coefficients
    of ``centred`` columns sum to zero over the pixels (:func:`common_mode`); the variances are the
    unconstrained ones (one constraint over many pixels changes them by ~1/n); ``members``: the pixels the sum
    runs over (:func:`common_mode`)."""
    w = weight
    k = len(X)
    A = normal_matrix(X, w)
    b = np.stack([np.einsum("r...,r...->...", X[i] * w, r) for i in range(k)], axis=-1)
    inv, undetermined = scaled_pinv(A)
    coef = np.einsum("...ij,...j->...i", inv, b)
    shift = common_mode(inv, coef, np.zeros(k, bool) if centred is None else np.asarray(centred, bool),
                        members=members)
    if shift is not None:
        coef += shift
    var = np.einsum("...ii->...i", inv).copy()
    var[undetermined] = np.nan
    return np.moveaxis(coef, -1, 0), np.moveaxis(var, -1, 0)


def shrink_local(weight: np.ndarray, X: list[np.ndarray], coef: np.ndarray, precision: np.ndarray) -> np.ndarray:
    """Per pixel, least-squares coefficients ``coef`` (k, H, W) moved to the mixed-model solution in which
    column j has a zero-mean prior of precision ``precision[j]`` (1/τ²; 0 for a fixed effect, ``inf`` to fix
    it at 0): β = (A + P)⁻¹·A·β̂ with A the weighted normal matrix (Henderson's equations at the least-squares
    point).

    With one column this is the familiar shrinkage β̂·τ²/(τ² + s²); with several, fixed effects that are
    collinear with a random one (a defect's offset and the per-pixel dark-rate pattern) take over what the
    random one gives up instead of both being shrunk.  A column without information at a pixel keeps its
    value if it is a fixed effect (nothing in the data moves it: a stuck pixel read at full scale, whose censored
    means are not used, keeps its detected value) and goes to its prior mean 0 if it is a random effect.
    """
    A = normal_matrix(X, weight)
    prec = np.asarray(precision, float)
    beta = np.moveaxis(coef, 0, -1)
    # a dead column or one fixed at 0 is pinned: β_i = β̂_i (a fixed effect without data) or 0 (a random
    # effect's prior mean, or fixed at 0); the others solve (A + P)β = A·β̂ less the pinned columns' share
    pinned = dead_columns(A) | np.isinf(prec)
    fixed = np.where(pinned & (prec == 0), beta, 0.0)
    rhs = np.einsum("...ij,...j->...i", A, beta - fixed)
    M = A + np.diag(np.where(np.isfinite(prec), prec, 0.0))
    # collinear fixed effects (a defect's offset and a per-pixel dark pattern with no prior) leave M singular:
    # the pseudo-inverse's minimum-norm split, as in :func:`solve_local`
    inv, _ = scaled_pinv(M, dead=pinned)
    return np.moveaxis(np.einsum("...ij,...j->...i", inv, rhs) + fixed, -1, 0)
