"""Boundary tools on radial profiles: edge points along rays, the consensus circle, band contrast.

A boundary of the eye (pupil margin, limbus) is dark inside and bright outside; along a ray from a point inside,
its position is the steepest rise of the smoothed grey level.  These tools turn rays into circles:

* :func:`polar_fit` — among all circles within a window of a start, the one along which the rays' own
  strongest rises are best met: a smooth score searched exhaustively, so that any start within the window gives
  the same circle, which a boundary seen only on its lateral arcs needs (its vertical position is loosely held).
  The limbus marks of the IITD ground truth (``tests/impact/data``) were checked against it;
* :func:`fit_rays` — each ray's steepest rise near a circle and a robust (Tukey) circle fit, repeated with a
  shrinking window: sharp boundaries such as the pupil's;
* :func:`band_contrast` — how much brighter a band outside a circle is than a band inside (the limbus has the
  sclera outside; rings within the iris do not).

Angles are degrees counter-clockwise from +x with y up on screen (``x = xc + r cos θ``, ``y = yc − r sin θ``).
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from forensics.impact.segment.common import Circle
from forensics.impact.segment.memo import StepMemo, remembered

Arcs = tuple[tuple[float, float], ...]


def ray_angles(arcs: Arcs, step: float) -> np.ndarray:
    """Angles (radians) every ``step`` degrees over the arcs (each arc ``(start, end)`` in degrees, inclusive)."""
    return np.deg2rad(np.concatenate([np.arange(a, b + 1e-9, step) for a, b in arcs]))


def profiles(smooth: np.ndarray, xs, ys, r_lo: float, r_hi: float, ang: np.ndarray, dr: float = 0.5):
    """Grey-level profiles along rays: ``(radii, values (centres, rays, radii), inside (centres, rays))``.

    ``inside`` is True for rays that stay within the image over the whole radius range.
    """
    xs, ys = np.atleast_1d(np.asarray(xs, float)), np.atleast_1d(np.asarray(ys, float))
    rs = np.arange(r_lo, r_hi + 1e-9, dr)
    cos, sin = np.cos(ang), np.sin(ang)
    px = xs[:, None, None] + rs[None, None, :] * cos[None, :, None]
    py = ys[:, None, None] - rs[None, None, :] * sin[None, :, None]
    h, w = smooth.shape
    inside = ((px >= 0) & (px <= w - 1) & (py >= 0) & (py <= h - 1)).all(axis=2)
    values = ndimage.map_coordinates(smooth, [py.ravel(), px.ravel()], order=1, mode="nearest").reshape(px.shape)
    return rs, values, inside


def fit_circle(x: np.ndarray, y: np.ndarray) -> Circle | None:
    """Least-squares (Kåsa) circle through points, or None if they do not determine one."""
    a = np.column_stack([x, y, np.ones_like(x)])
    b = -(x * x + y * y)
    try:
        d, e, f = np.linalg.lstsq(a, b, rcond=None)[0]
    except np.linalg.LinAlgError:
        return None
    cx, cy = -d / 2, -e / 2
    r2 = cx * cx + cy * cy - f
    if not (np.isfinite(r2) and r2 > 0):
        return None
    return float(cx), float(cy), float(np.sqrt(r2))


def band_contrast(smooth: np.ndarray, circle: Circle, arcs: Arcs, width: float = 0.1, gap: float = 0.02,
                  step: float = 3.0) -> float:
    """How much brighter the image is just outside ``circle`` than just inside, over ``arcs``.

    The median over rays inside the image of the mean grey level in a band of ``width`` × the radius outside
    the circle minus the same inside, leaving ``gap`` × the radius on either side (the edge itself).  The
    limbus separates the iris from the much brighter sclera; rings inside the iris (collarette, a dark outer
    ring) have iris on both sides and a smaller step.  ``-inf`` when fewer than 5 rays are inside the image.
    """
    cx, cy, r = circle
    ang = ray_angles(arcs, step)
    rs, prof, inside = profiles(smooth, cx, cy, r * (1 - gap - width), r * (1 + gap + width), ang)
    prof = prof[0][inside[0]]
    if prof.shape[0] < 5:
        return -np.inf
    outer = prof[:, rs >= r * (1 + gap)].mean(axis=1)
    inner = prof[:, rs <= r * (1 - gap)].mean(axis=1)
    return float(np.median(outer - inner))


def polar_fit(smooth: np.ndarray, start: Circle, arcs: Arcs, window: float = 0.08, step: float = 2.0,
              sigma: float = 1.0, coarse: int = 6, memo: StepMemo | None = None) -> tuple[Circle, float]:
    """The circle near ``start`` along which the rays' own strongest rises are best met: ``(circle, score)``.

    Around ``start``'s centre the image is resampled on rays every ``step`` degrees over ``arcs`` (0.5-px radial
    steps, ``r0 (1 ± 2 window)``); the radial derivative (Gaussian, ``sigma`` px) is divided by each ray's own
    maximum and clipped at 0, so that every ray scores at most 1 and a lash or lid crossing it cannot outvote
    the others.  Every circle with its centre within ``window`` × ``r0`` (1-px grid) and radius within
    ``r0 (1 ± window)`` (0.5-px grid) is scored by the mean of that normalised rise where it crosses the rays
    (exactly: the ray from ``s`` in direction ``d`` meets the circle of centre ``s + o`` at
    ``ρ = d·o + √((d·o)² − |o|² + r²)``), and the best is refined on a 0.25-px grid.  Because the score is a
    smooth function of the circle that does not depend on where the search starts, any start within the
    window gives the same circle.  ``score`` (0–1) is the mean normalised rise on the result.

    ``coarse`` > 0 searches the grid coarse-to-fine from that many coarse circles (:func:`_grid_argmax`; about
    six times faster), 0 exhaustively.  With a ``memo`` (:class:`~forensics.impact.segment.memo.StepMemo`) the
    search is reused where the sampled profiles are byte-identical to those of an earlier fit: the search reads
    nothing else.
    """
    x0, y0, r0 = start
    ang = ray_angles(arcs, step)
    dr = 0.5
    rs, prof, inside = profiles(smooth, x0, y0, r0 * (1 - 2 * window), r0 * (1 + 2 * window), ang, dr)
    prof = prof[0][inside[0]]
    ang = ang[inside[0]]
    if ang.size < 5:
        return (float(x0), float(y0), float(r0)), 0.0
    return remembered(memo, _polar_search, prof, ang, rs, dr, (x0, y0, r0), window, sigma, coarse)


def _polar_search(prof: np.ndarray, ang: np.ndarray, rs: np.ndarray, dr: float, start: Circle, window: float,
                  sigma: float, coarse: int) -> tuple[Circle, float]:
    """:func:`polar_fit`'s search on the sampled profiles ``prof`` (rays ``ang`` × radii ``rs``, ``dr`` apart)."""
    x0, y0, r0 = start
    deriv = ndimage.gaussian_filter1d(prof, sigma / dr, axis=1, order=1)
    top = deriv.max(axis=1, keepdims=True)
    norm = np.clip(deriv / np.where(top > 0, top, np.inf), 0.0, 1.0)
    cos, sin = np.cos(ang), np.sin(ang)
    flat = norm.ravel()
    row0 = (np.arange(ang.size) * rs.size)[None, :, None]

    def score(dxs: np.ndarray, dys: np.ndarray, radii: np.ndarray) -> np.ndarray:
        # The operations of ρ = d·o + √((d·o)² − |o|² + r²), the position on the ray and the linear
        # interpolation, in place on few buffers (the same operations in the same order: the same bits).
        proj = dxs[:, None] * cos[None, :] - dys[:, None] * sin[None, :]                 # (centres, rays)
        base = proj * proj - (dxs * dxs + dys * dys)[:, None]
        pos = np.add(base[:, :, None], (radii * radii)[None, None, :])                   # (centres, rays, radii)
        np.maximum(pos, 0.0, out=pos)
        np.sqrt(pos, out=pos)
        np.add(proj[:, :, None], pos, out=pos)
        pos -= rs[0]
        pos /= dr
        i0 = np.floor(pos).astype(np.int64)
        np.clip(i0, 0, rs.size - 2, out=i0)
        frac = np.subtract(pos, i0)
        np.clip(frac, 0.0, 1.0, out=frac)
        i0 += row0
        val = np.multiply(np.take(flat, i0), np.subtract(1, frac))                       # float32 × float64
        i0 += 1
        val += np.multiply(np.take(flat, i0), frac, out=frac)
        val[(pos < 0) | (pos > rs.size - 1)] = 0.0
        # The reduction runs over the middle axis, so numpy adds the rays in order whatever the other axes'
        # sizes: a circle scores the same bits in the coarse, local and full grids.
        return val.mean(axis=1)                                                           # (centres, radii)

    span = max(1, int(round(window * r0)))
    g = np.arange(-span, span + 1, dtype=float)
    radii = np.arange(r0 * (1 - window), r0 * (1 + window) + 1e-9, 0.5)
    c, j = _grid_argmax(score, g, radii, coarse)
    f = np.arange(-1.0, 1.01, 0.25)
    fx, fy = (a.ravel() for a in np.meshgrid(c[0] + f, c[1] + f))
    fr = radii[j] + f
    s2 = score(fx, fy, fr)
    c2, j2 = np.unravel_index(int(np.argmax(s2)), s2.shape)
    return (float(x0 + fx[c2]), float(y0 + fy[c2]), float(fr[j2])), float(s2[c2, j2])


def _grid_argmax(score, g: np.ndarray, radii: np.ndarray, coarse: int) -> tuple[tuple[float, float], int]:
    """The best circle of the grid ``g × g`` (centre offsets) × ``radii``: ``((dx, dy), radius index)``.

    With ``coarse = 0`` every circle of the grid is scored.  Otherwise the grid is first scored at every
    second centre and radius (an eighth of the circles), and the full grid only within ±2 centre and ±2 radius
    steps of the ``coarse`` best coarse circles: every circle of the grid lies within one step of a coarse one,
    so the result is the exhaustive search's whenever its maximum lies next to one of the ``coarse`` best coarse
    circles — the score is smooth on that scale (a Gaussian derivative of 1 px, circles 0.5–1 px apart), which
    ``benchmarks/bench_segmentation.py --exhaustive`` measures on the real eyes.
    """
    if coarse <= 0:
        dxs, dys = (a.ravel() for a in np.meshgrid(g, g))
        s = score(dxs, dys, radii)
        c, j = np.unravel_index(int(np.argmax(s)), s.shape)
        return (float(dxs[c]), float(dys[c])), int(j)
    gc, rc = g[::2], np.arange(0, radii.size, 2)
    cdx, cdy = (a.ravel() for a in np.meshgrid(gc, gc))
    s = score(cdx, cdy, radii[rc])
    best: tuple[float, tuple[float, float], int] = (-np.inf, (0.0, 0.0), 0)
    step = np.arange(-2, 3)
    for idx in np.argsort(s, axis=None, kind="stable")[::-1][:coarse]:
        c, j = divmod(int(idx), rc.size)
        lx = g[(g >= cdx[c] - 2) & (g <= cdx[c] + 2)]
        ly = g[(g >= cdy[c] - 2) & (g <= cdy[c] + 2)]
        lr = np.unique(np.clip(rc[j] + step, 0, radii.size - 1))
        dxs, dys = (a.ravel() for a in np.meshgrid(lx, ly))
        ls = score(dxs, dys, radii[lr])
        lc, lj = np.unravel_index(int(np.argmax(ls)), ls.shape)
        if ls[lc, lj] > best[0]:
            best = (float(ls[lc, lj]), (float(dxs[lc]), float(dys[lc])), int(lr[lj]))
    return best[1], best[2]


def fit_rays(smooth: np.ndarray, circle: Circle, arcs: Arcs, step: float = 2.0, window: float = 0.08,
             rounds: int = 3) -> tuple[Circle, float, float]:
    """Edge points on rays and a robust circle fit around ``circle``: ``(circle, strength, support)``.

    On rays every ``step`` degrees over ``arcs`` from the current centre, the steepest rise of ``smooth``
    within ``±window`` × the radius of the current circle is the ray's edge point; a circle is fitted to the
    points by least squares with Tukey's biweight (points more than 4.7 × 1.5 px off get no weight: lashes
    and lids crossing a ray), and the rays are cast again from the new centre with half the window.
    ``strength`` is the median rise of the inlier points (per pixel), ``support`` the fraction of the rays
    inside the image whose point is an inlier.
    """
    cx, cy, r = circle
    ang = ray_angles(arcs, step)
    cos, sin = np.cos(ang), np.sin(ang)
    strength, support = 0.0, 0.0
    half = max(3.0, window * r)
    for _ in range(rounds):
        rs, prof, inside = profiles(smooth, cx, cy, r - half - 1.0, r + half + 1.0, ang)
        prof, inside = prof[0], inside[0]
        if inside.sum() < 6:
            return (cx, cy, r), 0.0, 0.0
        deriv = (prof[inside, 2:] - prof[inside, :-2]) / (rs[2] - rs[0])
        k = np.argmax(deriv, axis=1)
        rise = deriv[np.arange(k.size), k]
        rad = rs[1:-1][k]
        px = cx + rad * cos[inside]
        py = cy - rad * sin[inside]
        valid = rise > 0
        if valid.sum() < 6:
            return (cx, cy, r), 0.0, 0.0
        fit, weights = _robust_circle(px[valid], py[valid], (cx, cy, r))
        if fit is None:
            break
        cx, cy, r = fit
        inlier = weights > 0
        strength = float(np.median(rise[valid][inlier])) if inlier.any() else 0.0
        support = float(inlier.sum() / inside.sum())
        half = max(2.0, half / 2)
    return (float(cx), float(cy), float(r)), strength, support


def _robust_circle(x: np.ndarray, y: np.ndarray, start: Circle, scale: float = 0.6, iters: int = 20):
    """Circle through points by iteratively reweighted least squares with Tukey's biweight (c = 4.685 σ).

    Linearised (Kåsa) fit ``x² + y² + D x + E y + F = 0`` weighted per point; returns ``(circle, weights)`` or
    ``(None, None)`` when the points do not determine a circle.
    """
    cx, cy, r = start
    wts = np.ones_like(x)
    c = 4.685 * scale
    for _ in range(iters):
        res = np.hypot(x - cx, y - cy) - r
        u = res / c
        wts = np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0)
        if (wts > 0).sum() < 5:
            return None, None
        a = np.column_stack([x, y, np.ones_like(x)]) * wts[:, None]
        b = -(x * x + y * y) * wts
        try:
            d, e, f = np.linalg.lstsq(a, b, rcond=None)[0]
        except np.linalg.LinAlgError:
            return None, None
        ncx, ncy = -d / 2, -e / 2
        r2 = ncx * ncx + ncy * ncy - f
        if not (np.isfinite(r2) and r2 > 0):
            return None, None
        done = abs(ncx - cx) + abs(ncy - cy) + abs(np.sqrt(r2) - r) < 0.01
        cx, cy, r = float(ncx), float(ncy), float(np.sqrt(r2))
        if done:
            break
    return (cx, cy, r), wts
