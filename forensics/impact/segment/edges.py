"""Edge pixels, the local circle refinement and the eyelid margins, shared by the segmentations.

:func:`edges_and_gradient` gives Canny edge pixels and the smoothed gradient at them; :func:`refine_circle`
is a local vote at full resolution that counts only edge pixels whose gradient points outwards (dark inside,
bright outside); :func:`find_eyelid` fits an eyelid margin as a parabola with a small Hough transform.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from forensics.impact.segment.common import Circle, Parabola


def edges_and_gradient(img: np.ndarray, sigma: float, quantiles: tuple[float, float]):
    """Canny edge coordinates and the smoothed gradient at them: ``(ey, ex, gy, gx)``."""
    from skimage.feature import canny

    if float(img.max()) - float(img.min()) < 1e-6:  # flat image: no edges at all
        empty = np.zeros(0)
        return empty.astype(np.intp), empty.astype(np.intp), empty, empty
    # Smooth once and let canny skip its own Gaussian: the same smoothed image gives the gradients below.
    smooth = ndimage.gaussian_filter(img, sigma)
    edges = canny(smooth, sigma=0.0, low_threshold=quantiles[0], high_threshold=quantiles[1],
                  use_quantiles=True)
    ey, ex = np.nonzero(edges)
    gy = ndimage.sobel(smooth, axis=0)[ey, ex]
    gx = ndimage.sobel(smooth, axis=1)[ey, ex]
    return ey, ex, gy, gx



def refine_circle(ey, ex, gy, gx, centre: tuple[float, float], radius: float, window: int, radius_window: int,
            sides_only: bool, cos_min: float = 0.7) -> tuple[float, float, float, float]:
    """Local circular vote at full resolution around a coarse circle.

    Every integer centre within ``±window`` px and radius within ``±radius_window`` px is scored by the number
    of edge pixels at that (rounded) distance whose gradient points outwards within ``acos(cos_min)`` of the
    radial direction, divided by the length of the perimeter considered.  ``sides_only`` counts only the
    left and right thirds of the circle (|cos θ| ≥ 0.5), as Masek weights vertical edges for the limbus so that
    eyelids do not vote.  Returns ``(x, y, r, support)``.
    """
    cx0, cy0 = round(centre[0]), round(centre[1])
    r0 = round(radius)
    rmin, rmax = max(r0 - radius_window, 2), r0 + radius_window
    if ey.size == 0:
        return float(cx0), float(cy0), float(r0), 0.0
    # Only edges in the band that can matter (cheap pre-selection).
    d0 = np.hypot(ex - cx0, ey - cy0)
    keep = np.abs(d0 - r0) <= radius_window + window * 1.5 + 1
    ex, ey, gx, gy = ex[keep], ey[keep], gx[keep], gy[keep]
    offs = np.arange(-window, window + 1)
    cxs = (cx0 + offs)[:, None].repeat(offs.size, 1).ravel()
    cys = (cy0 + offs)[None, :].repeat(offs.size, 0).ravel()
    nr = rmax - rmin + 1
    if ex.size == 0:
        return float(cx0), float(cy0), float(r0), 0.0
    dx = ex[None, :] - cxs[:, None]
    dy = ey[None, :] - cys[:, None]
    d = np.hypot(dx, dy)
    gnorm = np.hypot(gx, gy)[None, :]
    good = (dx * gx[None, :] + dy * gy[None, :]) >= cos_min * gnorm * np.maximum(d, 1e-9)
    if sides_only:
        good &= np.abs(dx) >= 0.5 * d
    ri = np.rint(d).astype(np.int64) - rmin
    good &= (ri >= 0) & (ri < nr)
    idx = (np.arange(cxs.size)[:, None] * nr + ri)[good]
    counts = np.bincount(idx, minlength=cxs.size * nr).reshape(cxs.size, nr).astype(float)
    # A 1-px-wide ring of radius r holds about 2πr pixels; canny lines are thinner, so support rarely reaches 1.
    perim = 2 * np.pi * np.arange(rmin, rmax + 1) * (2 / 3 if sides_only else 1.0)
    support = counts / perim[None, :]
    # Ties (common with integer votes) go to the candidate nearest the coarse estimate.
    penalty = (np.abs(cxs - cx0) + np.abs(cys - cy0))[:, None] * 1e-6 + np.abs(np.arange(rmin, rmax + 1) - r0) * 1e-6
    k = int(np.argmax(support - penalty))
    c, r = divmod(k, nr)
    return float(cxs[c]), float(cys[c]), float(rmin + r), float(support[c, r])



def find_eyelid(ey, ex, gy, gx, pupil: Circle, iris: Circle, upper: bool, curvature: float,
                 min_support: float) -> Parabola | None:
    """The eyelid margin over the iris by a Hough transform for parabolas ``y = y0 + a (x − x0)²``.

    Masek fits lines to the eyelids (a horizontal cut at the line's lowest point then masks everything
    above); a parabola follows an arched lid closely without giving away the iris at its sides.  Voters are
    the near-horizontal edge pixels (``|g_y| ≥ |g_x|``) inside the limbus, on the lid's side of a line half
    a pupil radius below the pupil centre, and not on the pupil circle (whose top and bottom arcs are
    parabola-like too; the limbus is excluded by staying 2 px inside it).  The apex ``x0`` is searched within
    ±0.3 r of the iris centre, ``|a|`` within ``[0, curvature / r]``.  The best parabola is kept when the edges
    cover at least ``min_support`` of the columns it spans inside the iris.
    """
    xp, yp, rp = pupil
    xi, yi, ri = iris
    if ey.size == 0 or ri <= 0:
        return None
    d_iris = np.hypot(ex - xi, ey - yi)
    d_pupil = np.hypot(ex - xp, ey - yp)
    # The upper lid often comes down to the pupil, the lower one rarely up to it: split at half a pupil
    # radius below the pupil centre so that no edge can vote for both lids.
    split = yp + 0.5 * rp
    side = ey < split if upper else ey > split
    # Edges inside the pupil count: a lid that comes down over the pupil makes its margin there.
    sel = (np.abs(gy) >= np.abs(gx)) & side & (d_iris < ri - 2) & (np.abs(d_pupil - rp) > 3)
    if not sel.any():
        return None
    x, y = ex[sel].astype(float), ey[sel].astype(float)
    sign = 1.0 if upper else -1.0
    x0s = xi + ri * np.array([-0.3, -0.15, 0.0, 0.15, 0.3])
    As = sign * np.linspace(0.0, curvature / ri, 11)
    y_lo = math.floor(yi - ri) - 1
    n_y = math.ceil(2 * ri) + 3
    # Votes: (x0, a) × y0 bins, one per edge pixel per (x0, a).
    y0 = np.rint(y[None, None, :] - As[None, :, None] * (x[None, None, :] - x0s[:, None, None]) ** 2) - y_lo
    ok = (y0 >= 0) & (y0 < n_y)
    combo = np.arange(x0s.size * As.size).reshape(x0s.size, As.size, 1)
    idx = (combo * n_y + y0.astype(np.int64))[ok]
    votes = np.bincount(idx, minlength=x0s.size * As.size * n_y).reshape(x0s.size, As.size, n_y).astype(float)
    # Normalise by the number of columns over which a parabola runs inside the iris (its visible length):
    # computed for the 24 most voted parabolas only (the best-supported long one is among them in practice).
    cols = np.arange(math.floor(xi - ri), math.ceil(xi + ri) + 1, dtype=float)
    half = np.sqrt(np.maximum(ri ** 2 - (cols - xi) ** 2, 0.0))
    flat = votes.ravel()
    top = np.argpartition(flat, flat.size - 24)[flat.size - 24:] if flat.size > 24 else np.arange(flat.size)
    best, best_support = None, 0.0
    for t in top:
        if flat[t] <= 0:
            continue
        i, j, k = np.unravel_index(int(t), votes.shape)
        yy = k + y_lo + As[j] * (cols - x0s[i]) ** 2
        inside = (np.abs(yy - yi) < half - 2) & ((yy < split) if upper else (yy > split))
        length = float(inside.sum())
        if length < 0.25 * ri:  # a parabola grazing the iris: nothing to mask, nothing to trust
            continue
        support = flat[t] / length
        if support > best_support:
            best, best_support = (float(x0s[i]), float(k + y_lo), float(As[j])), support
    return best if best_support >= min_support else None

