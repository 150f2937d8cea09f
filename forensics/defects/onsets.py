"""When did a defect first appear?  The one onset look-back of the toolkit.

A defect is detected at the first epoch where it clears the detection threshold, but a defect near the
threshold may have been there before, just under it.  Looking back, a site first detected at epoch e
counts as present at an earlier epoch j where it still *shows* (a lower bar: z above ``z_recheck``), so
that noise around the threshold does not make old defects look new (*once defective, always defective*).

:func:`look_back` is the look-back itself, on a presence matrix (epochs × sites) that each caller builds
with its own presence test:

* defect growth and dating (:mod:`forensics.defects.growth`): a partially stuck site shows at an epoch
  when its z there exceeds ``z_recheck`` (:func:`z_at`), a stuck site when it was detected stuck; the onset
  is the earliest epoch at which the site shows (:func:`first_epochs`).
* the model check (:mod:`forensics.check.detection`): a partially stuck site shows when its offset d̂
  there exceeds ``z`` σ *and* agrees with its detected amplitude within as much; the onset walks back
  only over consecutive epochs at which it shows (``contiguous=True``), because the checker's onsets
  define each pixel's class at every epoch in between — a pixel classed partially stuck at an epoch
  must read as one there.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from forensics.sensor.catalogue import PARTIAL, STUCK

if TYPE_CHECKING:
    from forensics.defects.detection import DetectionResult
    from forensics.defects.growth import Epoch

#: z above which a site already counts as present when looking back for a defect's first epoch.
Z_RECHECK = 3.0


def look_back(first: np.ndarray, present: np.ndarray, contiguous: bool = False,
              observed: np.ndarray | None = None) -> np.ndarray:
    """Onset epoch of every site, given the epoch ``first`` it was first detected at.

    Parameters
    ----------
    first
        ``(n,)`` epoch index of each site's first detection.
    present
        ``(epochs, n)`` booleans: the site shows the defect at that epoch (the caller's presence test).
    contiguous
        False: the onset is the earliest epoch before ``first`` at which the site shows.  True: walk back
        from ``first − 1`` and stop at the first epoch at which it does not show.
    observed
        ``(epochs,)`` booleans; unobserved epochs are skipped (neither onset nor a break of the walk).

    Returns
    -------
    ``(n,)`` onset epochs (≤ ``first``).
    """
    first = np.asarray(first, np.int64)
    onset = first.copy()
    present = np.asarray(present, bool)
    n_epochs = present.shape[0] if present.ndim == 2 else 0
    seen = np.ones(n_epochs, bool) if observed is None else np.asarray(observed, bool)
    if not contiguous:
        for j in range(n_epochs):
            if seen[j]:
                onset[(onset > j) & present[j]] = j
        return onset
    alive = np.ones(len(first), bool)
    for j in range(n_epochs - 1, -1, -1):
        if not seen[j]:
            continue
        before = j < first
        alive &= ~before | present[j]
        onset[before & alive] = j
    return onset


def z_at(detection: "DetectionResult", xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """z of d̂ at the given sites (−inf where the epoch kept no d̂ image or the site is outside its region)."""
    if detection.d_hat is None:
        return np.full(len(xs), -np.inf)
    z = np.full(len(xs), -np.inf)
    for fit_index, fit in enumerate(detection.fits):
        if detection.cfa:
            sel = ((ys % 2) * 2 + (xs % 2)) == fit_index
        else:
            sel = np.ones(len(xs), bool)
        z[sel] = (detection.d_hat[ys[sel], xs[sel]] - fit.center) / fit.scale
    if detection.mask is not None:
        z[~detection.mask[ys, xs]] = -np.inf
    return z


def shows(detection: "DetectionResult", sites: np.ndarray, kind: int, z_recheck: float = Z_RECHECK) -> np.ndarray:
    """Whether each ``(x, y)`` site shows a defect of ``kind`` in one epoch's detection (partially stuck:
    z > ``z_recheck``; stuck: detected stuck)."""
    if kind == PARTIAL:
        return z_at(detection, sites[:, 0], sites[:, 1]) > z_recheck
    found = detection.sites(STUCK)
    return np.array([s in found for s in zip(sites[:, 0].tolist(), sites[:, 1].tolist())], bool)


def first_epochs(epochs: Sequence["Epoch"], kind: int, z_recheck: float = Z_RECHECK) -> dict[tuple[int, int], int]:
    """For every site detected (as ``kind``) at some epoch, the first epoch at which it is present.

    A site first detected at epoch i counts as present at an earlier epoch j
    when its z there exceeds ``z_recheck`` (for stuck sites: when it was
    constant there), so noise around τ does not make old defects look new.
    """
    first: dict[tuple[int, int], int] = {}
    for i, ep in enumerate(epochs):
        for site in ep.detection.sites(kind):
            if site not in first:
                first[site] = i
    if not first:
        return first
    sites = np.array(list(first), dtype=np.int64)
    present = np.stack([shows(ep.detection, sites, kind, z_recheck) for ep in epochs])
    onset = look_back(np.array(list(first.values())), present)
    return {tuple(s): int(e) for s, e in zip(sites.tolist(), onset)}


def presence_matrix(epochs: Sequence["Epoch"], sites: list[tuple[int, int]], kind: int,
                    z_recheck: float = Z_RECHECK) -> np.ndarray:
    """(epochs × sites) booleans: the site shows the defect at that epoch (detected, or z > z_recheck; stuck: constant)."""
    out = np.zeros((len(epochs), len(sites)), bool)
    if not sites:
        return out
    arr = np.array(sites, dtype=np.int64)
    for j, ep in enumerate(epochs):
        found = ep.detection.sites(kind)
        out[j] = [s in found for s in sites]
        if kind == PARTIAL:
            out[j] |= z_at(ep.detection, arr[:, 0], arr[:, 1]) > z_recheck
    return out
