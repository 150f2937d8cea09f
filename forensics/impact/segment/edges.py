"""Edge pixels and the eyelid margins, shared by the segmentations.

:func:`edges_and_gradient` gives Canny edge pixels and the smoothed gradient at them; :func:`find_eyelid` fits
an eyelid margin as a parabola with a small Hough transform.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from forensics.impact.segment.common import Circle, Parabola
from forensics.impact.segment.memo import StepMemo, remembered


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



def find_eyelid(ey, ex, gy, gx, pupil: Circle, iris: Circle, upper: bool, curvature: float,
                min_support: float, memo: StepMemo | None = None) -> Parabola | None:
    """The eyelid margin over the iris by a Hough transform for parabolas ``y = y0 + a (x − x0)²``.

    Masek fits lines to the eyelids (a horizontal cut at the line's lowest point then masks everything
    above); a parabola follows an arched lid closely without giving away the iris at its sides.  Voters are
    the near-horizontal edge pixels (``|g_y| ≥ |g_x|``) inside the limbus, on the lid's side of a line half
    a pupil radius below the pupil centre, and not on the pupil circle (whose top and bottom arcs are
    parabola-like too; the limbus is excluded by staying 2 px inside it).  The apex ``x0`` is searched within
    ±0.3 r of the iris centre, ``|a|`` within ``[0, curvature / r]``.  The best parabola is kept when the edges
    cover at least ``min_support`` of the columns it spans inside the iris.  The Hough transform depends on the
    voters alone (:func:`lid_hough`, reused through ``memo`` where they are byte-identical).
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
    return remembered(memo, lid_hough, ex[sel].astype(float), ey[sel].astype(float), iris, float(split), bool(upper),
                      float(curvature), float(min_support))


def lid_hough(x: np.ndarray, y: np.ndarray, iris: Circle, split: float, upper: bool, curvature: float,
              min_support: float) -> Parabola | None:
    """:func:`find_eyelid`'s parabola Hough transform of the voting edge pixels ``(x, y)``."""
    xi, yi, ri = iris
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

