"""Boundary tools on radial profiles: edge points along rays, the consensus circle, band contrast.

A boundary of the eye (pupil margin, limbus) is dark inside and bright outside; along a ray from a point inside,
its position is the steepest rise of the smoothed grey level.  These tools turn rays into circles:

* :func:`ray_edges` — up to a few rises (local maxima of the radial derivative) per ray;
* :func:`consensus_circle` — among all circles within a window of a start, the one on which most rays have a
  rise within a narrow band (an exhaustive, start-independent RANSAC), then refitted by least squares to those
  rises.  Unlike a fit that follows each ray's single steepest rise from wherever it starts, it returns the same
  circle from any start within the window, which a boundary seen only on its lateral arcs needs (its vertical
  position is loosely held).  The IITD ground truth (``tests/impact/data``) is defined with it;
* :func:`band_contrast` — how much brighter a band outside a circle is than a band inside (the limbus has the
  sclera outside; rings within the iris do not).

Angles are degrees counter-clockwise from +x with y up on screen (``x = xc + r cos θ``, ``y = yc − r sin θ``).
"""
from __future__ import annotations

import warnings

import numpy as np
from scipy import ndimage

from forensics.impact.segment.common import Circle

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


def ray_edges(smooth: np.ndarray, centre: tuple[float, float], r_lo: float, r_hi: float, ang: np.ndarray,
              per_ray: int = 3, dr: float = 0.5) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rises along rays from ``centre``: ``(x, y, strength, ray)`` of up to ``per_ray`` per ray.

    A rise is a local maximum of the radial derivative (central differences of ``smooth``) with positive value,
    between ``r_lo`` and ``r_hi``; the strongest ``per_ray`` of each ray inside the image are kept.
    """
    rs, prof, inside = profiles(smooth, centre[0], centre[1], r_lo - dr, r_hi + dr, ang, dr)
    prof, inside = prof[0], inside[0]
    deriv = (prof[:, 2:] - prof[:, :-2]) / (2 * dr)
    radii = rs[1:-1]
    peak = np.zeros_like(deriv, dtype=bool)
    peak[:, 1:-1] = (deriv[:, 1:-1] > deriv[:, :-2]) & (deriv[:, 1:-1] >= deriv[:, 2:]) & (deriv[:, 1:-1] > 0)
    peak &= inside[:, None]
    strength = np.where(peak, deriv, 0.0)
    if per_ray < strength.shape[1]:
        order = np.argsort(-strength, axis=1)[:, :per_ray]
    else:
        order = np.argsort(-strength, axis=1)
    rows = np.repeat(np.arange(ang.size), order.shape[1])
    cols = order.ravel()
    keep = strength[rows, cols] > 0
    rows, cols = rows[keep], cols[keep]
    r = radii[cols]
    x = centre[0] + r * np.cos(ang[rows])
    y = centre[1] - r * np.sin(ang[rows])
    return x, y, strength[rows, cols], rows


def consensus_circle(smooth: np.ndarray, start: Circle, arcs: Arcs, window: float = 0.08, band: float = 1.5,
                     step: float = 1.0, per_ray: int = 3) -> tuple[Circle, float, float]:
    """The circle near ``start`` that most rays agree on: ``(circle, support, strength)``.

    Rises (:func:`ray_edges`) are taken on rays from ``start``'s centre every ``step`` degrees over ``arcs``,
    within ±2 ``window`` of its radius.  Every circle with its centre within ``window`` × the radius of the
    start's (1-px grid) and its radius within ±``window`` (0.5-px grid) is scored by the number of rays with a
    rise within ``band`` px of it (ties: the larger sum of rises); the best is refitted by least squares to those
    rises (one per ray, the nearest).  ``support`` is the fraction of the rays inside the image that agree,
    ``strength`` the median rise of the agreeing ones (grey level per pixel).
    """
    x0, y0, r0 = start
    ang = ray_angles(arcs, step)
    ex, ey, es, ray = ray_edges(smooth, (x0, y0), r0 * (1 - 2 * window), r0 * (1 + 2 * window), ang, per_ray)
    n_inside = int(profiles(smooth, x0, y0, r0 * (1 - 2 * window), r0 * (1 + 2 * window), ang)[2].sum())
    if ex.size < 5 or n_inside < 5:
        return (float(x0), float(y0), float(r0)), 0.0, 0.0
    span = max(1, int(round(window * r0)))
    offs = np.arange(-span, span + 1, dtype=float)
    cx, cy = np.meshgrid(x0 + offs, y0 + offs)
    cx, cy = cx.ravel(), cy.ravel()
    dr = 0.5
    r_lo = r0 * (1 - window)
    n_r = int(np.floor(2 * window * r0 / dr)) + 1
    dist = np.hypot(ex[None, :] - cx[:, None], ey[None, :] - cy[:, None])           # (centres, points)
    # Every (centre, point) pair agrees with the radius bins within ``band`` of its distance: mark the point's
    # ray in each, then count rays per (centre, radius) — one vote per ray however many rises it has.
    agree = np.zeros((cx.size, n_r, ang.size), dtype=bool)
    strength = np.zeros((cx.size, n_r))
    centre_idx = np.broadcast_to(np.arange(cx.size)[:, None], dist.shape)
    ray_idx = np.broadcast_to(ray[None, :], dist.shape)
    reach = int(np.floor(band / dr))
    base = np.rint((dist - r_lo) / dr).astype(np.int64)
    for off in range(-reach, reach + 1):
        b = base + off
        ok = (b >= 0) & (b < n_r) & (np.abs(r_lo + b * dr - dist) <= band)
        agree[centre_idx[ok], b[ok], ray_idx[ok]] = True
        np.add.at(strength, (centre_idx[ok], b[ok]), np.broadcast_to(es[None, :], dist.shape)[ok])
    count = agree.sum(axis=2)
    c, j = np.unravel_index(int(np.lexsort((strength.ravel(), count.ravel()))[-1]), count.shape)
    radius = r_lo + j * dr
    near = np.abs(dist[c] - radius) <= band
    # One point per agreeing ray: the one nearest the circle.
    order = np.argsort(np.abs(dist[c] - radius))
    seen: set[int] = set()
    pick = []
    for p in order:
        if near[p] and ray[p] not in seen:
            seen.add(int(ray[p]))
            pick.append(p)
    pick = np.array(pick, dtype=int)
    circle = fit_circle(ex[pick], ey[pick]) if pick.size >= 5 else None
    if circle is None:
        circle = (float(cx[c]), float(cy[c]), float(radius))
    return circle, float(pick.size / n_inside), float(np.median(es[pick])) if pick.size else 0.0


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


def median_rise(smooth: np.ndarray, xs, ys, r_lo: float, r_hi: float, ang: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Daugman's integro-differential operator with a median over rays, for several centres.

    For each centre: the radius in ``[r_lo, r_hi]`` with the largest median radial derivative over the rays that
    stay inside the image, and that median (``-inf`` with fewer than 5 rays inside).
    """
    rs, prof, inside = profiles(smooth, xs, ys, r_lo - 0.5, r_hi + 0.5, ang)
    deriv = (prof[:, :, 2:] - prof[:, :, :-2]) / (rs[2] - rs[0])
    deriv = np.where(inside[:, :, None], deriv, np.nan)
    with warnings.catch_warnings():  # centres without rays inside give all-NaN slices
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(deriv, axis=1)
    med = np.where(inside.sum(axis=1)[:, None] >= 5, med, -np.inf)
    med = np.nan_to_num(med, nan=-np.inf)
    k = np.argmax(med, axis=1)
    return rs[1:-1][k], med[np.arange(med.shape[0]), k]


def polar_fit(smooth: np.ndarray, start: Circle, arcs: Arcs, window: float = 0.08, step: float = 2.0,
              sigma: float = 1.0) -> tuple[Circle, float]:
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
    """
    x0, y0, r0 = start
    ang = ray_angles(arcs, step)
    dr = 0.5
    rs, prof, inside = profiles(smooth, x0, y0, r0 * (1 - 2 * window), r0 * (1 + 2 * window), ang, dr)
    prof = prof[0][inside[0]]
    ang = ang[inside[0]]
    if ang.size < 5:
        return (float(x0), float(y0), float(r0)), 0.0
    deriv = ndimage.gaussian_filter1d(prof, sigma / dr, axis=1, order=1)
    top = deriv.max(axis=1, keepdims=True)
    norm = np.clip(deriv / np.where(top > 0, top, np.inf), 0.0, 1.0)
    cos, sin = np.cos(ang), np.sin(ang)

    def score(dxs: np.ndarray, dys: np.ndarray, radii: np.ndarray) -> np.ndarray:
        proj = dxs[:, None] * cos[None, :] - dys[:, None] * sin[None, :]                 # (centres, rays)
        off2 = (dxs * dxs + dys * dys)[:, None]
        disc = proj[:, :, None] ** 2 - off2[:, :, None] + radii[None, None, :] ** 2       # (centres, rays, radii)
        rho = proj[:, :, None] + np.sqrt(np.maximum(disc, 0.0))
        pos = (rho - rs[0]) / dr
        i0 = np.clip(np.floor(pos).astype(np.int64), 0, rs.size - 2)
        frac = np.clip(pos - i0, 0.0, 1.0)
        rows = np.arange(ang.size)[None, :, None]
        val = norm[rows, i0] * (1 - frac) + norm[rows, i0 + 1] * frac
        val = np.where((pos >= 0) & (pos <= rs.size - 1), val, 0.0)
        return val.mean(axis=1)                                                           # (centres, radii)

    span = max(1, int(round(window * r0)))
    g = np.arange(-span, span + 1, dtype=float)
    dxs, dys = (a.ravel() for a in np.meshgrid(g, g))
    radii = np.arange(r0 * (1 - window), r0 * (1 + window) + 1e-9, 0.5)
    s = score(dxs, dys, radii)
    c, j = np.unravel_index(int(np.argmax(s)), s.shape)
    f = np.arange(-1.0, 1.01, 0.25)
    fx, fy = (a.ravel() for a in np.meshgrid(dxs[c] + f, dys[c] + f))
    fr = radii[j] + f
    s2 = score(fx, fy, fr)
    c2, j2 = np.unravel_index(int(np.argmax(s2)), s2.shape)
    return (float(x0 + fx[c2]), float(y0 + fy[c2]), float(fr[j2])), float(s2[c2, j2])
