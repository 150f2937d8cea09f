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


def dead_columns(A: np.ndarray) -> np.ndarray:
    """Per pixel, the columns of a normal matrix ``(H, W, k, k)`` that carry no information ``(H, W, k)``."""
    diag = np.einsum("...ii->...i", A)
    return diag <= 1e-12 * (diag.max() if diag.size else 1.0)


class PixelProjector:
    """Projection, pixel by pixel, off the span of per-pixel nuisance directions (weighted).

    ``columns`` are arrays ``(R, H, W)`` already multiplied by √weight; for each pixel the projection acts on the
    vector over conditions.
    """

    def __init__(self, columns: list[np.ndarray]):
        self.cols = columns
        k = len(columns)
        if k == 0:
            self.inv = None
            return
        gram = normal_matrix(columns)
        diag = np.einsum("...ii->...i", gram)
        scale = np.where(diag > 0, diag, 1.0)
        norm = np.sqrt(scale[..., :, None] * scale[..., None, :])
        g = gram / norm
        for i in range(k):
            g[..., i, i] = np.where(diag[..., i] > 0, g[..., i, i] + 1e-10, 1.0)
        self.inv = np.linalg.inv(g) / norm

    def project(self, x: np.ndarray) -> np.ndarray:
        if self.inv is None:
            return x
        k = len(self.cols)
        b = np.stack([np.einsum("r...,r...->...", c, x) for c in self.cols], axis=-1)
        coef = np.einsum("...ij,...j->...i", self.inv, b)
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


def solve_local(weight: np.ndarray, X: list[np.ndarray], r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel weighted least squares of ``r`` on the columns ``X``: (coefficients (k,H,W), their variances)."""
    w = weight
    k = len(X)
    A = normal_matrix(X, w)
    b = np.stack([np.einsum("r...,r...->...", X[i] * w, r) for i in range(k)], axis=-1)
    dead = dead_columns(A)
    for i in range(k):
        A[..., i, i] = np.where(dead[..., i], 1.0, A[..., i, i] * (1 + 1e-10))
        b[..., i] = np.where(dead[..., i], 0.0, b[..., i])
        for j in range(k):
            if i != j:
                A[..., i, j] = np.where(dead[..., i] | dead[..., j], 0.0, A[..., i, j])
    inv = np.linalg.inv(A)
    coef = np.einsum("...ij,...j->...i", inv, b)
    var = np.einsum("...ii->...i", inv).copy()
    var[dead] = np.nan
    return np.moveaxis(coef, -1, 0), np.moveaxis(var, -1, 0)


def shrink_local(weight: np.ndarray, X: list[np.ndarray], coef: np.ndarray, precision: np.ndarray) -> np.ndarray:
    """Per pixel, least-squares coefficients ``coef`` (k, H, W) moved to the mixed-model solution in which
    column j has a zero-mean prior of precision ``precision[j]`` (1/τ²; 0 for a fixed effect, ``inf`` to fix
    it at 0): β = (A + P)⁻¹·A·β̂ with A the weighted normal matrix (Henderson's equations at the least-squares
    point).

    With one column this is the familiar shrinkage β̂·τ²/(τ² + s²); with several, fixed effects that are
    collinear with a random one (a defect's offset and the per-pixel dark-rate pattern) take over what the
    random one gives up instead of both being shrunk.  Columns without information at a pixel stay 0.
    """
    A = normal_matrix(X, weight)
    k = len(X)
    prec = np.asarray(precision, float)
    dead = dead_columns(A)
    beta = np.moveaxis(coef, 0, -1)
    rhs = np.einsum("...ij,...j->...i", A, beta)
    M = A + np.diag(np.where(np.isfinite(prec), prec, 0.0))
    for i in range(k):
        # a dead column or one fixed at 0: the row becomes β_i = 0 (its column then multiplies 0)
        zero = dead[..., i] | bool(np.isinf(prec[i]))
        M[..., i, :] = np.where(zero[..., None], 0.0, M[..., i, :])
        M[..., i, i] = np.where(zero, 1.0, M[..., i, i])
        rhs[..., i] = np.where(zero, 0.0, rhs[..., i])
    return np.moveaxis(np.linalg.solve(M, rhs[..., None])[..., 0], -1, 0)
