"""Which fitted parameters the data determine, and their covariance.

A fit's Gauss–Newton (or Fisher) matrix ``H`` says how much the data tell about each parameter.  A parameter
the data say nothing about (a zero column: a black level when no frame is dark and nothing multiplies the
signal) or that trades off exactly against others (a near-null direction of ``H``) is *not identifiable*:
its value is whatever the fit started from, and a standard error from a pseudo-inverse would be meaningless
(zero, or "0 ± 1,070").  Such parameters are reported as not identifiable, naming what they trade off
against; the covariance of the others is the inverse of their own block of ``H`` (the unidentifiable
ones held fixed).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from forensics.check.params import unit
from forensics.check.result import ParamEstimate
from forensics.sensor.model import Effect

#: An eigenvalue of the scaled information matrix below this fraction of the largest is a null direction.
NULL_DIRECTION = 1e-9
#: A parameter loading a null direction more than this (unit eigenvector) is part of it.
LOADING = 0.1


@dataclass(frozen=True)
class Identification:
    """Covariance of the identifiable parameters and why the others are not."""

    cov: np.ndarray  #: (k, k), NaN in the rows and columns of unidentifiable parameters
    identifiable: np.ndarray  #: (k,) bool
    why: list[str]  #: per parameter, empty when identifiable

    def se(self, i: int) -> float | None:
        v = self.cov[i, i]
        return float(np.sqrt(max(v, 0.0))) if np.isfinite(v) else None


def identify(information: np.ndarray, names: Sequence[str]) -> Identification:
    """Split parameters into identifiable and not, from their information matrix ``H`` (k × k)."""
    H = np.asarray(information, float)
    k = len(names)
    why = [""] * k
    ok = np.ones(k, bool)
    diag = np.diag(H) if k else np.zeros(0)
    for i in range(k):
        if not np.isfinite(diag[i]) or diag[i] <= 0:
            ok[i] = False
            why[i] = "the data carry no information on it"
    idx = np.flatnonzero(ok)
    if idx.size > 1:
        scale = np.sqrt(diag[idx])
        C = H[np.ix_(idx, idx)] / np.outer(scale, scale)
        lam, vec = np.linalg.eigh(C)
        null = lam < NULL_DIRECTION * max(float(lam.max()), 1e-300)
        for j in np.flatnonzero(null):
            members = idx[np.abs(vec[:, j]) > LOADING]
            for m in members:
                others = [names[o] for o in members if o != m]
                ok[m] = False
                why[m] = ("not separable from " + ", ".join(others)) if others else "the data carry no information on it"
    cov = np.full((k, k), np.nan)
    idx = np.flatnonzero(ok)
    if idx.size:
        cov[np.ix_(idx, idx)] = np.linalg.inv(H[np.ix_(idx, idx)])
    return Identification(cov, ok, why)


def estimates(effects: Sequence[Effect], free: Sequence[tuple[int, str]], information: np.ndarray,
              converged: bool) -> list[ParamEstimate]:
    """Estimates of the ``free`` parameters ``(effect index, name)`` with standard errors from their information
    matrix; parameters the data do not determine are reported as not identifiable (:mod:`.identify`)."""
    names = [f"{effects[j].key}.{n}" for j, n in free]
    ident = identify(information, names)
    out = []
    for i, (j, n) in enumerate(free):
        value = float(getattr(effects[j], n))
        ok = bool(ident.identifiable[i]) and np.isfinite(value)
        note = ident.why[i] if not ok else ""
        if not converged:
            note = f"{names[i]} still moving when the fit stopped"
        out.append(ParamEstimate(effects[j].key, n, value, ident.se(i) if ok and converged else None,
                                 unit(effects[j], n), identifiable=ok, converged=converged, note=note))
    return out
