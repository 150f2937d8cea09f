"""Per-pixel linear algebra of the pixel channel: projection off per-pixel nuisance directions, and
per-pixel weighted least squares."""
from __future__ import annotations

import numpy as np


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
        gram = np.empty((*columns[0].shape[1:], k, k))
        for i in range(k):
            for j in range(i, k):
                gram[..., i, j] = gram[..., j, i] = np.einsum("r...,r...->...", columns[i], columns[j])
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
    shape = w.shape[1:]
    A = np.empty((*shape, k, k))
    b = np.empty((*shape, k))
    for i in range(k):
        b[..., i] = np.einsum("r...,r...->...", X[i] * w, r)
        for j in range(i, k):
            A[..., i, j] = A[..., j, i] = np.einsum("r...,r...->...", X[i] * w, X[j])
    diag = np.einsum("...ii->...i", A).copy()
    dead = diag <= 1e-12 * (diag.max() if diag.size else 1.0)
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
