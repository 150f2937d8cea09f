"""WAHET-like segmentation: a reflection-free centre by weighted adaptive Hough voting, then both boundaries in
the polar and ellipsopolar transforms around it, fitted as ellipses.

After A. Uhl and P. Wild, "Weighted adaptive Hough and ellipsopolar transforms for real-time iris
segmentation", ICB 2012, and USIT's ``wahet``:

1. **Reflections** (small near-saturated spots brighter than their surroundings by 60/255) are masked and
   filled (:func:`~forensics.impact.segment.common.reflection_mask`); their gradients do not vote.
2. **Boundary edges**: the strongest 20 % of the gradient magnitude, kept only in cells (a 30 × 30 grid) whose
   gradients agree in direction (length of the mean gradient ≥ 1/√2 of the mean magnitude) — the pupil and
   limbus are smooth curves; lashes and iris texture point every way.
3. **Centre** (the *weighted adaptive Hough transform*): every boundary edge pixel votes along the line of its
   gradient, with its magnitude; the accumulator covers the image at first and is then narrowed to a quarter of
   its area around the best cell (and smoothed with a Gaussian of a third of its width, which also prefers the
   middle of the current window), until its cells are half a pixel.  Lines through a circle's edge meet at its
   centre, so the pupil and limbus, which are nearly concentric, make the peak.
4. **First boundary** in the polar transform around the centre: the radius whose positive radial derivative
   (dark inside, bright outside) summed over angle is largest, then per angle the strongest rise within a window
   around it, smoothed to its first Fourier terms (USIT: a window of 15 px and 1 term, then 5 px and 3 terms;
   here 6 % of the image's shorter side with 1 and then 2 terms — a pass that lets the circle move off the
   voted centre — then 2 % with 3 terms, an ellipse); an ellipse is fitted to the contour.
5. **Ellipsopolar transform** around that ellipse (``ρ = 1`` on it).  An inner candidate is sought inside
   (``ρ < 1``, preferring ``ρ ≈ 0.66`` with σ 0.4: a pupil inside a limbus) and an outer one outside (``ρ > 1``,
   on the lateral sectors only, preferring ``ρ ≈ 2.5`` with σ 1: a limbus around a pupil), each refined as in
   step 4 and fitted with an ellipse; the one with the larger prior-weighted edge energy decides whether the
   first boundary was the limbus (the inner candidate is then the pupil) or the pupil.
6. **Checks** and **eyelids** as for CAHT.  A boundary's *support* is CAHT's measure (:func:`_agreement`): the mean
   over its rays (the limbus: the lateral sectors) of the rise where the returned ellipse crosses the ray relative
   to the ray's strongest rise nearby.  The checks are this project's (issue 29 asks for failures to be detected),
   not the paper's.  The first support measure here (the share of rays whose strongest rise lay within 1.5 px of
   the intermediate contour) rejected correct limbi, which on near-infrared eyes are ramps 10–20 px wide, partly
   under lashes: 64 of the 400 IITD eyes.

Parameters in the paper and USIT are pixel counts at 320 × 240; here they are fractions of the image's shorter
side.  Returns circles (the ellipse's centre and mean semi-axis) and the ellipses themselves.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from forensics.impact.segment.common import (
    RATIO_BOUNDS,
    Circle,
    Ellipse,
    Segmentation,
    contrast_check,
    fill_masked,
    grey,
    image_size,
    plausibility,
    ray_to_ellipse,
    reflection_mask,
)
from forensics.impact.segment.edges import edges_and_gradient, find_eyelid

#: Angles of the polar and ellipsopolar transforms.
N_ANGLES = 256
#: Lateral sectors (degrees, y up) where the limbus is sought: the lids cover its top and bottom.
LATERAL = ((-45.0, 45.0), (135.0, 225.0))


def segment_wahet(
    image: np.ndarray,
    *,
    top_fraction: float = 0.2,
    coherence: float = math.sqrt(0.5),
    inner_prior: tuple[float, float] = (0.66, 0.4),
    outer_prior: tuple[float, float] = (2.5, 1.0),
    min_support: float = 0.3,
    eyelids: bool = True,
    lid_curvature: float = 0.5,
    lid_support: float = 0.3,
) -> Segmentation:
    """Segment an eye image with the WAHET-like method (see the module docstring).

    Parameters
    ----------
    image
        ``(H, W)`` grey eye image (any dtype; colour is averaged).
    top_fraction, coherence
        Boundary edges: the strongest ``top_fraction`` of the gradient magnitude in cells whose mean gradient
        is at least ``coherence`` of their mean magnitude (Uhl and Wild: 20 %, 1/√2).
    inner_prior, outer_prior
        ``(mean, sd)`` of the preferred radius of the inner and outer candidate relative to the first boundary
        (USIT: 0.66 ± 0.4 and 2.5 ± 1).
    min_support
        Smallest edge support of a trusted boundary: the mean over its rays (the limbus: lateral sectors) of the
        rise where the boundary crosses the ray, relative to the ray's strongest rise nearby — CAHT's measure and
        threshold (:func:`~forensics.impact.segment.boundary.polar_fit`), so that 0.3 means the same for both.
    eyelids, lid_curvature, lid_support
        Look for the eyelid margins (:func:`~forensics.impact.segment.edges.find_eyelid`).
    """
    img = grey(image)
    h, w = img.shape
    side = image_size(img.shape)
    guess = Segmentation(pupil=(w / 2, h / 2, 0.1 * side), iris=(w / 2, h / 2, 0.4 * side), ok=False,
                         quality=0.0, method="wahet")
    if float(img.max()) - float(img.min()) < 1e-6:
        return guess.failed("flat image: no edges")
    spec = reflection_mask(img)
    filled = fill_masked(img, spec)
    smooth = ndimage.gaussian_filter(filled, max(1.0, 0.006 * side))
    gx = ndimage.sobel(smooth, axis=1)
    gy = ndimage.sobel(smooth, axis=0)
    gx[spec], gy[spec] = 0.0, 0.0
    edges = boundary_edges(gx, gy, top_fraction, coherence)
    if edges.sum() < 16:
        return guess.failed("no coherent boundary edges")
    centre = hough_centre(edges, gx, gy)
    first = first_boundary(smooth, centre, spec)
    if first is None:
        return guess.failed("no boundary around the centre")
    inner = ellipse_candidate(smooth, spec, first, inside=True, prior=inner_prior)
    outer = ellipse_candidate(smooth, spec, first, inside=False, prior=outer_prior)
    if inner is None and outer is None:
        return guess.failed("no second boundary")
    # Each boundary's support as its role's: the pupil's over all angles, the limbus's over the lateral sectors.
    if outer is None or (inner is not None and inner[1] > outer[1]):
        pupil_e, iris_e = inner[0], first[0]
        supports = (inner[2], first[2])
    else:
        pupil_e, iris_e = first[0], outer[0]
        supports = (first[1], outer[2])
    pupil, iris = _circle_of(pupil_e), _circle_of(iris_e)
    reasons = [plausibility(pupil, iris, img.shape), contrast_check(filled, pupil, iris)]
    if supports[0] < min_support:
        reasons.append(f"weak pupil boundary ({supports[0]:.2f})")
    if supports[1] < min_support:
        reasons.append(f"weak limbus ({supports[1]:.2f})")
    upper_lid = lower_lid = None
    if eyelids:
        ey, ex, egy, egx = edges_and_gradient(filled, max(1.0, 0.008 * side), (0.85, 0.93))
        upper_lid = find_eyelid(ey, ex, egy, egx, pupil, iris, True, lid_curvature, lid_support)
        lower_lid = find_eyelid(ey, ex, egy, egx, pupil, iris, False, lid_curvature, lid_support)
    reason = "; ".join(r for r in reasons if r)
    return Segmentation(pupil=pupil, iris=iris, ok=not reason, quality=float(min(supports)), reason=reason,
                        upper_lid=upper_lid, lower_lid=lower_lid, pupil_ellipse=pupil_e, iris_ellipse=iris_e,
                        method="wahet")


# --------------------------------------------------------------------------- centre
def boundary_edges(gx: np.ndarray, gy: np.ndarray, top_fraction: float = 0.2,
                   coherence: float = math.sqrt(0.5), grid: int = 30) -> np.ndarray:
    """Pixels among the strongest ``top_fraction`` of the gradient in cells of coherent gradient direction."""
    mag = np.hypot(gx, gy)
    if not np.any(mag > 0):
        return np.zeros_like(mag, dtype=bool)
    strong = mag >= np.quantile(mag, 1.0 - top_fraction)
    h, w = mag.shape
    ch, cw = max(1, h // grid), max(1, w // grid)
    rows, cols = -(-h // ch), -(-w // cw)
    pad = ((0, rows * ch - h), (0, cols * cw - w))

    def cell_sum(a: np.ndarray) -> np.ndarray:
        return np.pad(np.where(strong, a, 0.0), pad).reshape(rows, ch, cols, cw).sum(axis=(1, 3))

    sx, sy, sm = cell_sum(gx), cell_sum(gy), cell_sum(mag)
    with np.errstate(invalid="ignore", divide="ignore"):
        agree = np.hypot(sx, sy) >= coherence * sm
    agree &= sm > 0
    keep = np.repeat(np.repeat(agree, ch, axis=0), cw, axis=1)[:h, :w]
    return strong & keep


def hough_centre(edges: np.ndarray, gx: np.ndarray, gy: np.ndarray, cells: int = 51,
                 precision: float = 0.5) -> tuple[float, float]:
    """The point where the gradient lines of the edge pixels meet: WAHET's weighted adaptive Hough transform.

    An accumulator of ``cells × cells`` over a window (first the image) receives, for every edge pixel, its
    gradient magnitude along the line through it in its gradient's direction (both ways); the accumulator is
    smoothed and multiplied by a Gaussian of a third of its width, the best cell becomes the centre of a window
    of half the size, until a cell is at most ``precision`` px.  Lines are sampled at a third of a cell.
    """
    ey, ex = np.nonzero(edges)
    ux, uy = gx[ey, ex], gy[ey, ex]
    mag = np.hypot(ux, uy)
    ux, uy = ux / mag, uy / mag
    h, w = edges.shape
    x0, y0, size_x, size_y = -0.5, -0.5, float(w), float(h)
    idx = np.arange(cells)
    prior = np.exp(-0.5 * ((idx - (cells - 1) / 2) / (cells / 3)) ** 2)
    prior = prior[:, None] * prior[None, :]
    while size_x / cells > precision or size_y / cells > precision:
        step = min(size_x, size_y) / cells / 3
        reach = math.hypot(size_x, size_y)
        # Parameter range along each line that can fall in the window: project the window's centre.
        cxw, cyw = x0 + size_x / 2, y0 + size_y / 2
        t_mid = (cxw - ex) * ux + (cyw - ey) * uy
        ts = np.arange(-reach / 2, reach / 2 + step, step)
        px = ex[:, None] + (t_mid[:, None] + ts[None, :]) * ux[:, None]
        py = ey[:, None] + (t_mid[:, None] + ts[None, :]) * uy[:, None]
        col = np.floor((px - x0) / size_x * cells).astype(np.int64)
        row = np.floor((py - y0) / size_y * cells).astype(np.int64)
        ok = (col >= 0) & (col < cells) & (row >= 0) & (row < cells)
        weights = np.broadcast_to(mag[:, None], ok.shape)[ok] * step
        acc = np.bincount((row[ok] * cells + col[ok]), weights=weights, minlength=cells * cells)
        acc = ndimage.gaussian_filter(acc.reshape(cells, cells), 1.0) * prior
        r, c = np.unravel_index(int(np.argmax(acc)), acc.shape)
        bx, by = x0 + (c + 0.5) * size_x / cells, y0 + (r + 0.5) * size_y / cells
        size_x, size_y = size_x / 2, size_y / 2
        x0, y0 = bx - size_x / 2, by - size_y / 2
    return x0 + size_x / 2, y0 + size_y / 2


# --------------------------------------------------------------------------- boundaries
def _angles() -> np.ndarray:
    return 2 * np.pi * np.arange(N_ANGLES) / N_ANGLES


def _ellipse_radius(ellipse: Ellipse, theta: np.ndarray) -> np.ndarray:
    """Distance from the ellipse's centre to the ellipse along angles ``theta`` (y up)."""
    _, _, a, b, phi = ellipse
    c, s = np.cos(theta - phi), np.sin(theta - phi)
    return 1.0 / np.sqrt((c / a) ** 2 + (s / b) ** 2)


def _rise(polar: np.ndarray, sigma_rho: float) -> np.ndarray:
    """Positive radial derivative of a polar image (rows: angles, columns: radius), smoothed along both axes."""
    d = ndimage.gaussian_filter1d(polar, sigma_rho, axis=1, order=1)
    d = ndimage.gaussian_filter1d(d, 1.0, axis=0, mode="wrap")
    return np.maximum(d, 0.0)


def _fourier(contour: np.ndarray, terms: int) -> np.ndarray:
    """The contour (one value per angle) keeping its first ``terms`` Fourier coefficients (the mean is the first)."""
    spec = np.fft.rfft(contour)
    spec[terms:] = 0
    return np.fft.irfft(spec, n=contour.size)


def _fit_contour(rise: np.ndarray, start: np.ndarray, windows: tuple[int, int], lo: int, hi: int,
                 weight_rows: np.ndarray | None = None) -> np.ndarray:
    """WAHET's gradient fit: per angle the strongest rise within a window, Fourier-smoothed, twice."""
    cont = start.astype(float)
    cols = np.arange(rise.shape[1])
    for window, terms in ((windows[0], 1), (windows[0], 2), (windows[1], 3)):
        near = (np.abs(cols[None, :] - cont[:, None]) <= window) & (cols[None, :] >= lo) & (cols[None, :] < hi)
        score = np.where(near, rise, -1.0)
        best = np.argmax(score, axis=1).astype(float)
        found = score[np.arange(rise.shape[0]), best.astype(int)] > 0
        if weight_rows is not None:
            found &= weight_rows
        target = np.where(found, best, cont)
        cont = _fourier(target, terms)
    return cont


def _agreement(rise: np.ndarray, valid: np.ndarray, index: np.ndarray, rows: np.ndarray, window: float) -> float:
    """How well a boundary meets its rays' own strongest rises: CAHT's support (``boundary.polar_fit``'s score).

    ``index`` is the boundary's (fractional) column in each row of ``rise``; each row's rise there is divided by
    the row's largest rise within ``window`` columns of it and clipped to 0–1, and the mean is taken over the
    ``rows`` whose boundary point is ``valid`` (in the image: rays leaving it neither support nor contradict).
    A ray crossed by a lash or a lid scores low but cannot outvote the others, and a soft boundary (the limbus
    is a ramp several pixels wide, so its rise peaks broadly) scores by how close to its peak the boundary runs,
    not by whether the peak's argmax falls within a pixel or two.
    """
    n_rows, n_cols = rise.shape
    r = np.arange(n_rows)
    k0 = np.clip(np.floor(index).astype(np.int64), 0, n_cols - 2)
    frac = np.clip(index - k0, 0.0, 1.0)
    inside = rows & (index >= 0) & (index <= n_cols - 1) & valid[r, np.clip(np.rint(index).astype(np.int64), 0,
                                                                             n_cols - 1)]
    if not inside.any():
        return 0.0
    at = rise[r, k0] * (1 - frac) + rise[r, k0 + 1] * frac
    cols = np.arange(n_cols)
    top = np.where(np.abs(cols[None, :] - index[:, None]) <= window, rise, 0.0).max(axis=1)
    norm = np.clip(at / np.where(top > 0, top, np.inf), 0.0, 1.0)
    return float(norm[inside].mean())


def _lateral_rows(theta: np.ndarray) -> np.ndarray:
    """Angles within the :data:`LATERAL` sectors."""
    deg = np.rad2deg(theta)
    deg = np.where(deg > 315, deg - 360, deg)
    rows = np.zeros(theta.size, bool)
    for a0, a1 in LATERAL:
        rows |= (deg >= a0) & (deg <= a1)
    return rows


def _fit_ellipse(x: np.ndarray, y: np.ndarray) -> Ellipse | None:
    """Least-squares ellipse ``(x, y, a, b, phi)`` through points (screen coordinates), or None."""
    from skimage.measure import EllipseModel

    model = EllipseModel.from_estimate(np.column_stack([x, y]))
    if not model:
        return None
    (xc, yc), (a, b), theta = (float(v) for v in model.center), (float(v) for v in model.axis_lengths), \
        float(model.theta)
    if not all(np.isfinite([xc, yc, a, b, theta])) or a <= 0 or b <= 0:
        return None
    # skimage measures theta clockwise on screen (y down); ours is counter-clockwise.
    return xc, yc, a, b, -theta


def _circle_of(ellipse: Ellipse) -> Circle:
    return ellipse[0], ellipse[1], 0.5 * (ellipse[2] + ellipse[3])


def first_boundary(smooth: np.ndarray, centre: tuple[float, float], spec: np.ndarray):
    """The strongest boundary around ``centre`` in the polar transform, or None.

    Returns ``(ellipse, support over all angles, support over the lateral sectors)`` (:func:`_agreement`): the
    first as a pupil's, the second as a limbus's, whose top and bottom the lids may hide.
    """
    h, w = smooth.shape
    side = image_size(smooth.shape)
    cx, cy = centre
    r_max = min(0.8 * max(h, w), math.hypot(max(cx, w - cx), max(cy, h - cy)))
    rs = np.arange(0.0, r_max, 1.0)
    theta = _angles()
    px = cx + rs[None, :] * np.cos(theta)[:, None]
    py = cy - rs[None, :] * np.sin(theta)[:, None]
    inside = (px >= 0) & (px <= w - 1) & (py >= 0) & (py <= h - 1)
    polar = ndimage.map_coordinates(smooth, [py, px], order=1, mode="nearest")
    masked = ndimage.map_coordinates(spec.astype(np.float32), [py, px], order=0, mode="constant") > 0
    rise = np.where(inside & ~masked, _rise(polar, 1.5), 0.0)
    lo = max(2, int(0.05 * side))
    energy = rise[:, lo:].sum(axis=0)
    if energy.size == 0 or energy.max() <= 0:
        return None
    r0 = lo + int(np.argmax(energy))
    window = int(0.06 * side)
    cont = _fit_contour(rise, np.full(theta.size, float(r0)), (window, max(2, int(0.02 * side))), lo, rs.size)
    ex = cx + cont * np.cos(theta)
    ey = cy - cont * np.sin(theta)
    ellipse = _fit_ellipse(ex, ey)
    if ellipse is None:
        return None
    # The support of the ellipse returned, not of the contour it was fitted to (rs are 1 px apart from 0).
    index = ray_to_ellipse((cx, cy), ellipse, theta)
    valid = inside & ~masked
    return (ellipse, _agreement(rise, valid, index, np.ones(theta.size, bool), window),
            _agreement(rise, valid, index, _lateral_rows(theta), window))


def ellipse_candidate(smooth: np.ndarray, spec: np.ndarray, first, inside: bool, prior: tuple[float, float]):
    """A second boundary in the ellipsopolar transform of ``first``: ``(ellipse, energy, support)`` or None.

    ``inside``: sought at ``ρ < 1`` over all angles, else at ``ρ > 1`` on the lateral sectors.  The energy is
    the mean rise along the fitted ellipse times the Gaussian prior on its ``ρ``.
    """
    ellipse = first[0]
    h, w = smooth.shape
    side = image_size(smooth.shape)
    theta = _angles()
    base = _ellipse_radius(ellipse, theta)
    mean_r = float(base.mean())
    drho = 0.5 / mean_r                                   # half a pixel at the first boundary
    # Radius ratios within the physiological bounds (pupil 0.1–0.8 of the iris): the inner boundary at most
    # 0.8 of the first, the outer at least 1.25 times it.
    lo_ratio, hi_ratio = RATIO_BOUNDS
    rho_hi = hi_ratio if inside else min(1.0 / lo_ratio, 0.8 * max(h, w) / mean_r)
    rho_lo = lo_ratio if inside else 1.0 / hi_ratio
    rhos = np.arange(rho_lo, rho_hi, drho)
    if rhos.size < 8:
        return None
    dist = rhos[None, :] * base[:, None]
    px = ellipse[0] + dist * np.cos(theta)[:, None]
    py = ellipse[1] - dist * np.sin(theta)[:, None]
    valid = (px >= 0) & (px <= w - 1) & (py >= 0) & (py <= h - 1)
    polar = ndimage.map_coordinates(smooth, [py, px], order=1, mode="nearest")
    masked = ndimage.map_coordinates(spec.astype(np.float32), [py, px], order=0, mode="constant") > 0
    rise = np.where(valid & ~masked, _rise(polar, 3.0), 0.0)
    rows = np.ones(theta.size, bool) if inside else _lateral_rows(theta)
    mu, sd = prior
    weight = np.exp(-0.5 * ((rhos - mu) / sd) ** 2)
    energy = rise[rows].sum(axis=0) * weight
    if energy.max() <= 0:
        return None
    k0 = int(np.argmax(energy))
    win = (max(2, int(0.06 * side / (mean_r * drho))), max(2, int(0.02 * side / (mean_r * drho))))
    cont = _fit_contour(rise, np.full(theta.size, float(k0)), win, 0, rhos.size, weight_rows=rows)
    rho = rhos[0] + cont * drho
    ex = ellipse[0] + rho * base * np.cos(theta)
    ey = ellipse[1] - rho * base * np.sin(theta)
    # The whole contour: away from the lateral sectors it is the low-order Fourier continuation of them.
    fitted = _fit_ellipse(ex, ey)
    if fitted is None:
        return None
    rr = _ellipse_radius_from(fitted, ellipse, theta) / base          # the fitted ellipse's ρ along each angle
    idx = np.clip(np.rint((rr - rhos[0]) / drho).astype(int), 0, rhos.size - 1)
    along = float(rise[np.arange(theta.size), idx][rows].mean())
    prior_w = float(np.exp(-0.5 * ((np.median(rr[rows]) - mu) / sd) ** 2))
    support = _agreement(rise, valid & ~masked, (rr - rhos[0]) / drho, rows, win[0])
    return fitted, along * prior_w, support


def _ellipse_radius_from(target: Ellipse, origin: Ellipse, theta: np.ndarray) -> np.ndarray:
    """Distance from ``origin``'s centre to ``target`` along angles ``theta`` (y up)."""
    return ray_to_ellipse((origin[0], origin[1]), target, theta)
