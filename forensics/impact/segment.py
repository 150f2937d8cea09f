"""Iris segmentation and Daugman's rubber-sheet normalisation, after Masek's implementation.

:func:`segment_iris` finds the limbus (iris/sclera boundary) first and then the pupil inside it, each with a
circular Hough transform on Canny edges (``skimage.feature.canny``, ``skimage.transform.hough_circle``), as in
L. Masek, *Recognition of Human Iris Patterns for Biometric Identification* (2003).  It works coarse to fine:
the Hough transform runs on an image reduced ``downscale`` times (2 at 320×240), then each circle is refined
at full resolution by a local vote over a few pixels of centre and radius that only counts edge pixels whose
gradient points outwards (dark inside, bright outside); several Hough peaks are refined and the best
supported wins.  The eyelid margins are then found as parabolas by a small Hough transform of their own.
About 25 ms per 320×240 image.  (``hough_circle_peaks`` is replaced by a cheaper greedy peak pick.)

:func:`normalise` unwraps the iris between the two circles into a ``radial × angular`` texture (Masek's
rubber sheet for non-concentric circles) and returns a mask of usable samples (eyelids — by their margins
and by grey-level outliers in the band —, eyelashes, specular reflections and samples outside the image
excluded).  :class:`Segmenter` bundles the parameters with a
one-image cache so that several matchers encoding the same image segment it once.

Conventions
-----------
Circles are ``(x, y, r)`` in pixels, ``x`` the column and ``y`` the row of the centre (pixel centres at
integer coordinates).  Angular sample ``j`` of a texture is at ``θ_j = 2πj / angular`` measured
counter-clockwise from the +x axis *on screen* (``x = x_p + r cos θ``, ``y = y_p − r sin θ``), so column
``angular/4`` is the top of the eye and rotating the eye counter-clockwise by ``2πk/angular`` rolls the texture
by ``+k`` columns.  Radii and image sizes given as parameters refer to a 320×240 image and are scaled with
``sqrt(H·W / (320·240))``.
"""
from __future__ import annotations

import hashlib
import math
import warnings
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage

from forensics._shared.errors import InputError

#: The image size the default radii refer to (IITD-like, rows × columns).
REFERENCE_SHAPE = (240, 320)

# A circle: centre column, centre row, radius (pixels).
Circle = tuple[float, float, float]
# An eyelid margin y = y0 + a (x − x0)²: (x0, y0, a).
Parabola = tuple[float, float, float]


@dataclass(frozen=True)
class Segmentation:
    """Pupil and limbus circles of one eye image.

    Parameters
    ----------
    pupil, iris
        ``(x, y, r)`` of the pupil boundary and of the limbus, in pixels of the full image.
    ok
        False when the result is degenerate (no edges, weak circle support, pupil not inside the iris);
        the circles are then a best guess, still usable but not to be trusted.
    quality
        Edge support of the weaker of the two circles, 0–1: the fraction of the circle's (considered) perimeter
        on which an outward-pointing edge was found.
    reason
        Why ``ok`` is False (empty when ok).
    upper_lid, lower_lid
        Eyelid margins found over the iris, as parabolas ``(x0, y0, a)``: ``y = y0 + a (x − x0)²`` (``a ≥ 0``
        for the upper lid, whose margin arches up; ``a ≤ 0`` for the lower).  The eye is below the upper and
        above the lower margin.  None when no margin crosses the iris.
    """

    pupil: Circle
    iris: Circle
    ok: bool = True
    quality: float = 1.0
    reason: str = ""
    upper_lid: Parabola | None = None
    lower_lid: Parabola | None = None

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (circles and eyelids as lists of three floats, eyelids None when absent)."""
        d = asdict(self)
        for key in ("pupil", "iris", "upper_lid", "lower_lid"):
            value = getattr(self, key)
            d[key] = None if value is None else [float(v) for v in value]
        d["quality"] = float(self.quality)
        d["ok"] = bool(self.ok)
        return d


# --------------------------------------------------------------------------- image helpers
def _grey(image: np.ndarray) -> tuple[np.ndarray, float]:
    """``(float32 grey image, full scale)``; colour images are averaged over channels.

    Full scale is 255 for 8-bit images, ``2^b − 1`` for wider integers with ``b`` the smallest bit depth
    (at least 8) that holds the image's maximum, and 1 (or the maximum, if above 1) for floats.
    """
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] in (1, 3, 4):
        a = a[..., :3].mean(axis=2) if a.shape[2] >= 3 else a[..., 0]
    if a.ndim != 2 or a.shape[0] < 16 or a.shape[1] < 16:
        raise InputError(f"an eye image must be a 2-D grey array of at least 16×16 pixels, got shape {a.shape}")
    if np.issubdtype(a.dtype, np.integer) and a.dtype.itemsize == 1:
        full = float(np.iinfo(a.dtype).max)
    elif np.issubdtype(a.dtype, np.integer):
        # 10–14-bit sensors deliver uint16 below 65535: take the smallest bit depth (≥ 8) that holds the data,
        # so that "near saturation" (specular reflections) means the same as for 8-bit images.
        top = int(a.max()) if a.size else 0
        full = float(2 ** max(8, int(top).bit_length()) - 1)
    else:
        finite = a[np.isfinite(a)]
        full = 1.0 if finite.size == 0 or finite.max() <= 1.0 else float(finite.max())
    f = np.asarray(a, dtype=np.float32)
    if not np.isfinite(f).all():
        f = np.nan_to_num(f, nan=0.0, posinf=full, neginf=0.0)
    return f, full


def _image_scale(shape: tuple[int, int]) -> float:
    return math.sqrt(shape[0] * shape[1] / (REFERENCE_SHAPE[0] * REFERENCE_SHAPE[1]))


def _block_mean(img: np.ndarray, k: int) -> np.ndarray:
    """Mean over ``k × k`` blocks (the last partial rows/columns are dropped)."""
    if k == 1:
        return img
    h, w = (img.shape[0] // k) * k, (img.shape[1] // k) * k
    return img[:h, :w].reshape(h // k, k, w // k, k).mean(axis=(1, 3))


def _fill_bright_spots(img: np.ndarray, threshold: float, radius: float) -> np.ndarray:
    """Replace near-saturated pixels (and a 1-px rim) by the mean of the other pixels in a square around them.

    Specular reflections would otherwise make small, strong circular edges inside the pupil (and stuck-bright
    pixels spurious edges everywhere).  Only pixels at or above ``threshold`` are touched, so the rest of the
    image — dark defects included — is left as it is.  (A grey opening would remove bright spots without a
    threshold, but its erosion spreads every dark stuck pixel over the whole structuring element.)
    """
    bright = img >= threshold
    if not bright.any():
        return img
    bright = ndimage.binary_dilation(bright, structure=np.ones((3, 3), bool))
    keep = (~bright).astype(np.float32)
    size = 2 * max(round(radius), 1) + 1  # a box filter costs the same whatever its size
    num = ndimage.uniform_filter(img * keep, size)
    den = ndimage.uniform_filter(keep, size)
    filled = np.where(den > 1e-3, num / np.maximum(den, 1e-3), float(np.median(img)))
    return np.where(bright, filled, img).astype(np.float32)


def _edges_and_gradient(img: np.ndarray, sigma: float, quantiles: tuple[float, float]):
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


def _hough_peaks(ey, ex, shape, radii, n_peaks, accept) -> list[tuple[float, float, float]]:
    """Up to ``n_peaks`` strongest distinct circles of the Hough transform that ``accept(x, y, r)`` allows.

    The accumulator is ``skimage.transform.hough_circle`` (normalised by the perimeter).  Peaks are picked by
    a greedy non-maximum suppression over the top 256 centres (each at its best radius) rather than ``hough_circle_peaks``, which labels
    regions per radius and costs ~100 ms per image here against <1 ms.  Returns ``[(x, y, r), …]``, best first.
    """
    from skimage.transform import hough_circle

    radii = np.asarray([r for r in radii if r >= 2], dtype=int)
    if ey.size == 0 or radii.size == 0:
        return []
    edge_img = np.zeros(shape, dtype=bool)
    edge_img[ey, ex] = True
    hspace = hough_circle(edge_img, radii, normalize=True)
    # Best radius per centre first: partitioning the 2-D map is ~20× cheaper than the whole 3-D space.
    best = hspace.max(axis=0)
    flat = best.ravel()
    top = min(256, flat.size)
    cand = np.argpartition(flat, flat.size - top)[flat.size - top:]
    cand = cand[np.argsort(flat[cand])[::-1]]
    chosen: list[tuple[int, int, int]] = []
    found: list[tuple[float, float, float]] = []
    for idx in cand:
        if flat[idx] <= 0 or len(found) >= n_peaks:
            break
        y, x = np.unravel_index(idx, best.shape)
        r = int(radii[int(np.argmax(hspace[:, y, x]))])
        # Suppress near-duplicates of a peak already examined (same circle, a pixel or two off).
        if any(abs(x - cx) <= 2 and abs(y - cy) <= 2 and abs(r - cr) <= 2 for cx, cy, cr in chosen):
            continue
        chosen.append((int(x), int(y), r))
        if accept(float(x), float(y), float(r)):
            found.append((float(x), float(y), float(r)))
    return found


def _refine(ey, ex, gy, gx, centre: tuple[float, float], radius: float, window: int, radius_window: int,
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


def _find_eyelid(ey, ex, gy, gx, pupil: Circle, iris: Circle, upper: bool, curvature: float,
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


# --------------------------------------------------------------------------- segmentation
def segment_iris(
    image: np.ndarray,
    *,
    iris_radius: tuple[float, float] = (80.0, 125.0),
    pupil_radius: tuple[float, float] = (18.0, 60.0),
    downscale: int | None = None,
    sigma: float = 1.0,
    edge_quantiles: tuple[float, float] = (0.85, 0.93),
    reflection: float = 0.9,
    specular_radius: float = 8.0,
    max_pupil_ratio: float = 0.8,
    min_support: float = 0.2,
    n_peaks: int = 5,
    eyelids: bool = True,
    lid_curvature: float = 0.5,
    lid_support: float = 0.3,
) -> Segmentation:
    """Find the limbus, then the pupil inside it, by circular Hough transforms (Masek's order).

    Parameters
    ----------
    image
        ``(H, W)`` grey eye image (any dtype; colour is averaged).  Defects (stuck, hot pixels) may disturb
        the result — that is what the ageing experiment measures — but never make it fail.
    iris_radius, pupil_radius
        Radius search ranges in pixels *of a 320×240 image*; scaled with the image size.
    downscale
        Integer reduction for the Hough stage (block mean); None: ``max(1, round(2·scale))``.
    sigma
        Canny's Gaussian σ on the reduced image (full resolution uses ``sigma·downscale``).
    edge_quantiles
        Canny's hysteresis thresholds as quantiles of the gradient magnitude (contrast-independent).
    reflection, specular_radius
        Pixels at or above ``reflection`` × full scale are specular reflections (or stuck-bright pixels): they
        are filled from their surroundings (mean over a square of half-side ``specular_radius``) before edge
        detection.
    max_pupil_ratio
        Largest pupil radius as a fraction of the iris radius.
    min_support
        ``ok`` requires both circles to have at least this edge support (see :class:`Segmentation`).
    n_peaks
        Hough peaks (geometrically acceptable, distinct) refined per circle; the best-supported one wins.
    eyelids, lid_curvature, lid_support
        Look for the eyelid margins (parabolas, see :func:`_find_eyelid`) with ``|a| ≤ lid_curvature / r_iris``,
        kept when edges cover ``lid_support`` of their length over the iris.

    Returns
    -------
    Segmentation
        Never raises on odd pixel content: a flat or nonsensical image gives ``ok=False`` with a guess
        (circles centred in the image, radii mid-range).
    """
    img, full = _grey(image)
    img = img / np.float32(full)
    h, w = img.shape
    scale = _image_scale((h, w))
    k = int(downscale) if downscale else max(1, round(2 * scale))
    ir = (iris_radius[0] * scale, iris_radius[1] * scale)
    pr = (pupil_radius[0] * scale, pupil_radius[1] * scale)
    guess_iris = (w / 2, h / 2, 0.5 * (ir[0] + ir[1]))
    guess_pupil = (w / 2, h / 2, min(0.5 * (pr[0] + pr[1]), max_pupil_ratio * guess_iris[2]))

    filled = _fill_bright_spots(img, reflection, specular_radius * scale)
    coarse = _block_mean(filled, k)
    reasons: list[str] = []

    # --- limbus, coarse: Hough on the near-vertical edges only (Masek weights vertical edges for the iris).
    ey, ex, gy, gx = _edges_and_gradient(coarse, sigma, edge_quantiles)
    vertical = np.abs(gx) >= np.abs(gy)
    radii = np.arange(math.floor(ir[0] / k), math.ceil(ir[1] / k) + 1)
    peaks = _hough_peaks(ey[vertical], ex[vertical], coarse.shape, radii, n_peaks, lambda x, y, r: True)
    if not peaks:
        return Segmentation(pupil=guess_pupil, iris=guess_iris, ok=False, quality=0.0,
                            reason="no limbus edges")

    def full_res(c: float) -> float:  # coarse pixel centre → full-resolution coordinate
        return (c + 0.5) * k - 0.5

    # --- full-resolution edges, shared by all refinements.  Each Hough peak is refined and the one with the
    # best outward-edge support wins: the raw Hough maximum can mix arcs of the pupil and the limbus.
    fey, fex, fgy, fgx = _edges_and_gradient(filled, sigma * k, edge_quantiles)
    refined = [_refine(fey, fex, fgy, fgx, (full_res(x), full_res(y)), r * k, window=k + 1,
                       radius_window=k + 1, sides_only=True) for x, y, r in peaks]
    xi, yi, ri, s_iris = max(refined, key=lambda c: c[3])
    ri = float(np.clip(ri, ir[0], ir[1]))

    # --- pupil, coarse: Hough inside the iris only (edges of the limbus and eyelids excluded).
    cxi, cyi, cri = (xi + 0.5) / k - 0.5, (yi + 0.5) / k - 0.5, ri / k
    inside = np.hypot(ex - cxi, ey - cyi) < 0.92 * cri
    p_radii = np.arange(math.floor(pr[0] / k), math.ceil(min(pr[1], max_pupil_ratio * ri) / k) + 1)

    # The accumulator only needs the iris's bounding box (the pupil centre lies inside the iris).
    y0, x0 = max(math.floor(cyi - cri), 0), max(math.floor(cxi - cri), 0)
    y1 = min(math.ceil(cyi + cri) + 1, coarse.shape[0])
    x1 = min(math.ceil(cxi + cri) + 1, coarse.shape[1])

    def in_iris(x: float, y: float, r: float) -> bool:
        return math.hypot(x + x0 - cxi, y + y0 - cyi) + r <= cri

    ppeaks = []
    if y1 > y0 and x1 > x0:
        ppeaks = _hough_peaks(ey[inside] - y0, ex[inside] - x0, (y1 - y0, x1 - x0), p_radii, n_peaks, in_iris)
    if not ppeaks:
        reasons.append("no pupil inside the iris")
        xp, yp, rp, s_pupil = xi, yi, guess_pupil[2], 0.0
    else:
        prefined = [_refine(fey, fex, fgy, fgx, (full_res(x + x0), full_res(y + y0)), r * k, window=k + 1,
                            radius_window=k + 1, sides_only=False) for x, y, r in ppeaks]
        xp, yp, rp, s_pupil = max(prefined, key=lambda c: c[3])
    if math.hypot(xp - xi, yp - yi) + rp > ri + 1 or rp >= ri:
        reasons.append("pupil not inside the iris")
    quality = float(min(s_iris, s_pupil))
    if s_iris < min_support:
        reasons.append(f"weak limbus ({s_iris:.2f})")
    if s_pupil < min_support and ppeaks:
        reasons.append(f"weak pupil boundary ({s_pupil:.2f})")
    pupil, iris = (float(xp), float(yp), float(rp)), (float(xi), float(yi), float(ri))
    upper_lid = lower_lid = None
    if eyelids:
        upper_lid = _find_eyelid(fey, fex, fgy, fgx, pupil, iris, True, lid_curvature, lid_support)
        lower_lid = _find_eyelid(fey, fex, fgy, fgx, pupil, iris, False, lid_curvature, lid_support)
    return Segmentation(pupil=pupil, iris=iris, ok=not reasons, quality=quality, reason="; ".join(reasons),
                        upper_lid=upper_lid, lower_lid=lower_lid)


# --------------------------------------------------------------------------- normalisation
def _boundary_distance(seg: Segmentation, theta: np.ndarray) -> np.ndarray:
    """Distance from the pupil centre to the limbus along each angle (Masek's non-concentric rubber sheet).

    Solves ``|P + R·u − I| = r_i`` for ``R ≥ 0`` with ``u = (cos θ, −sin θ)``; where the pupil centre lies
    outside the iris (a degenerate segmentation) the discriminant is clipped at 0.
    """
    xp, yp, _ = seg.pupil
    xi, yi, ri = seg.iris
    ox, oy = xp - xi, yp - yi
    du = ox * np.cos(theta) - oy * np.sin(theta)
    return -du + np.sqrt(np.maximum(du * du - (ox * ox + oy * oy) + ri * ri, 0.0))


def sample_grid(seg: Segmentation, radial: int = 20, angular: int = 240) -> tuple[np.ndarray, np.ndarray]:
    """Image coordinates ``(y, x)`` (each ``radial × angular``) of the rubber-sheet samples.

    Radial positions are ``radial + 2`` equally spaced points from the pupil boundary to the limbus with both
    end points dropped, as in Masek's ``normaliseiris`` (the boundaries themselves are mixed pixels).
    """
    theta = 2 * np.pi * np.arange(angular) / angular
    xp, yp, rp = seg.pupil
    outer = _boundary_distance(seg, theta)
    outer = np.maximum(outer, rp)
    t = np.linspace(0.0, 1.0, radial + 2)[1:-1]
    r = rp + t[:, None] * (outer - rp)[None, :]
    x = xp + r * np.cos(theta)[None, :]
    y = yp - r * np.sin(theta)[None, :]
    return y, x


def _occlusion_mask(texture: np.ndarray, usable: np.ndarray, k: float, smooth: tuple[int, int]) -> np.ndarray:
    """Eyelid occlusion in the unwrapped band: True where occluded.

    Each sample of a locally averaged band is compared with its own radial row's median over angle — per row,
    so that radial trends such as a dark limbal ring are not mistaken for eyelids — in units of the band's
    robust spread (MAD of those deviations over the whole band).  Samples more than ``k`` spreads away are
    suspect; occluded are the suspect runs that reach the limbus (outermost row), since eyelids enter the
    iris from outside.  The median is robust to an eyelid covering less than half of a row; two more passes
    re-estimate the statistics without the previous pass's occlusion.
    """
    fill = float(np.median(texture[usable])) if usable.any() else 0.0
    band = np.where(usable, texture, fill)
    sm = ndimage.uniform_filter(band, size=smooth, mode=("nearest", "wrap"))
    occluded = np.zeros_like(usable)
    for _ in range(3):
        ref = usable & ~occluded
        if not ref.any():
            break
        vals = np.where(ref, sm, np.nan)
        with warnings.catch_warnings():  # rows without usable samples give all-NaN slices
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(vals, axis=1, keepdims=True)
        med = np.where(np.isfinite(med), med, fill)
        # One spread for the whole band: a row's own MAD is inflated by an eyelid covering a third of it.
        dev = np.abs(sm - med)
        mad = 1.4826 * float(np.median(dev[ref]))
        # A floor on the spread stops a perfectly flat band (synthetic, saturated) from flagging its noise.
        mad = max(mad, 1e-3 * max(abs(fill), 1.0))
        suspect = dev > k * mad
        # Connected to the outer boundary along each column: cumulative AND from the last row inwards.
        occluded = np.flip(np.logical_and.accumulate(np.flip(suspect, 0), axis=0), 0)
    # The boundary of an eyelid is a mixed region: grow the occlusion by one sample in each direction.
    return ndimage.binary_dilation(occluded, structure=np.ones((3, 3), bool), border_value=0) if occluded.any() \
        else occluded


def normalise(
    image: np.ndarray,
    seg: Segmentation,
    radial: int = 20,
    angular: int = 240,
    *,
    reflection: float = 0.9,
    lash: float | None = None,
    lash_fraction: float = 0.25,
    occlusion_k: float = 3.0,
    occlusion_smooth: tuple[int, int] = (3, 9),
    lid_margin: float = 4.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Daugman's rubber sheet: the iris band unwrapped to ``radial × angular`` samples, and a usability mask.

    Parameters
    ----------
    image
        The grey eye image (the same one that was segmented).
    seg
        Its segmentation.
    radial, angular
        Output size: rows from the pupil boundary (row 0) to the limbus, columns over angle (see the module
        docstring for the angle convention).
    reflection
        Pixels at or above this fraction of full scale (255 for uint8) are specular reflections; they and
        their 2-px neighbourhood are masked.
    lash
        Eyelash threshold as a fraction of full scale; samples darker are masked.  None: adaptive, at
        ``lash_fraction`` of the way from the pupil's median grey to the band's median grey (lashes are about as
        dark as the pupil, iris crypts rarely are).
    occlusion_k, occlusion_smooth
        Occlusion detection in the band (see :func:`_occlusion_mask`): deviation threshold in robust spreads,
        and the ``(rows, columns)`` averaging window.  It catches eyelids and sclera that differ in grey level
        from the iris, whether or not the segmentation found an eyelid margin.
    lid_margin
        Pixels beyond the eyelid margins of ``seg`` (``upper_lid``, ``lower_lid``) are masked, and this many
        pixels on the eye's side of them too.

    Returns
    -------
    texture : float32 ``(radial, angular)``
        Bilinearly interpolated grey values, in the image's own units.
    mask : bool ``(radial, angular)``
        True where the sample is usable iris.
    """
    img, full = _grey(image)
    h, w = img.shape
    y, x = sample_grid(seg, radial, angular)
    inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1) & np.isfinite(x) & np.isfinite(y)
    yc, xc = np.where(inside, y, 0.0), np.where(inside, x, 0.0)
    texture = ndimage.map_coordinates(img, [yc, xc], order=1, mode="nearest").astype(np.float32)
    texture[~inside] = 0.0

    # Specular reflections: bright pixels grown by 2 px (their halo is bright too), looked up at the nearest pixel.
    bright = img >= reflection * full
    if bright.any():
        bright = ndimage.binary_dilation(bright, structure=np.ones((5, 5), bool))
        iy = np.clip(np.rint(yc).astype(np.intp), 0, h - 1)
        ix = np.clip(np.rint(xc).astype(np.intp), 0, w - 1)
        spec = bright[iy, ix] & inside
    else:
        spec = np.zeros_like(inside)
    usable = inside & ~spec

    # Eyelids found by the segmentation: everything beyond the margin, plus ``lid_margin`` px for the lash
    # line and the mixed pixels along it.
    for lid, upper in ((seg.upper_lid, True), (seg.lower_lid, False)):
        if lid is not None:
            x0, y0, a = lid
            margin_y = y0 + a * (x - x0) ** 2
            usable &= ~((y < margin_y + lid_margin) if upper else (y > margin_y - lid_margin))

    # Eyelashes: darker than a threshold.
    if lash is not None:
        dark_thr = lash * full
    else:
        xp, yp, rp = seg.pupil
        r_in = max(0.6 * rp, 1.0)
        y0, y1 = int(max(yp - r_in, 0)), int(min(yp + r_in, h - 1)) + 1
        x0, x1 = int(max(xp - r_in, 0)), int(min(xp + r_in, w - 1)) + 1
        patch = img[y0:y1, x0:x1]
        if patch.size:
            yy, xx = np.mgrid[y0:y1, x0:x1]
            disc = ((yy - yp) ** 2 + (xx - xp) ** 2 <= r_in ** 2) & (patch < reflection * full)
            pupil_level = float(np.median(patch[disc])) if disc.any() else 0.0
        else:
            pupil_level = 0.0
        band_level = float(np.median(texture[usable])) if usable.any() else pupil_level
        dark_thr = pupil_level + lash_fraction * max(band_level - pupil_level, 0.0)
    lashes = texture < dark_thr if dark_thr > 0 else np.zeros_like(usable)
    usable &= ~lashes

    occluded = _occlusion_mask(texture, usable, occlusion_k, occlusion_smooth) if usable.any() else usable
    mask = usable & ~occluded
    return texture, mask


# --------------------------------------------------------------------------- segmenter with a cache
@dataclass
class Segmenter:
    """Segmentation and normalisation parameters plus a one-image cache.

    Two matchers encoding the same image one after the other (the experiment's order) share one
    segmentation: the cache key is a BLAKE2b digest of the image bytes, shape and dtype (≈0.1 ms at 320×240).
    The cache keeps the last image's segmentation and its unwrapped bands, one per ``(radial, angular)``.

    Parameters
    ----------
    segment_params
        Keyword arguments for :func:`segment_iris`.
    normalise_params
        Keyword arguments for :func:`normalise` other than the size (e.g. ``reflection``, ``lash``).
    radial, angular
        Default band size of :meth:`unwrap`.
    """

    segment_params: dict[str, Any] = field(default_factory=dict)
    normalise_params: dict[str, Any] = field(default_factory=dict)
    radial: int = 20
    angular: int = 240
    _key: bytes | None = field(default=None, init=False, repr=False, compare=False)
    _seg: Segmentation | None = field(default=None, init=False, repr=False, compare=False)
    _bands: dict = field(default_factory=dict, init=False, repr=False, compare=False)
    #: Segmentations actually computed (cache misses); for tests and diagnostics.
    computed: int = field(default=0, init=False, compare=False)

    @staticmethod
    def image_key(image: np.ndarray) -> bytes:
        """A fast digest of the pixels, shape and dtype."""
        a = np.ascontiguousarray(image)
        hsh = hashlib.blake2b(a.tobytes(), digest_size=16)
        hsh.update(repr((a.shape, a.dtype.str)).encode())
        return hsh.digest()

    def segment(self, image: np.ndarray) -> Segmentation:
        """The segmentation of ``image`` (cached)."""
        key = self.image_key(image)
        if key != self._key or self._seg is None:
            seg = segment_iris(image, **self.segment_params)
            self._key, self._seg, self._bands = key, seg, {}
            self.computed += 1
        return self._seg

    def unwrap(self, image: np.ndarray, radial: int | None = None, angular: int | None = None
               ) -> tuple[np.ndarray, np.ndarray, Segmentation]:
        """``(texture, mask, segmentation)`` of ``image`` (see :func:`normalise`); cached, arrays read-only."""
        seg = self.segment(image)
        size = (int(radial or self.radial), int(angular or self.angular))
        if size not in self._bands:
            texture, mask = normalise(image, seg, size[0], size[1], **self.normalise_params)
            texture.flags.writeable = False
            mask.flags.writeable = False
            self._bands[size] = (texture, mask)
        texture, mask = self._bands[size]
        return texture, mask, seg

    def __getstate__(self) -> dict[str, Any]:
        # The cache is worth nothing in another process: do not ship it.
        state = self.__dict__.copy()
        state.update(_key=None, _seg=None, _bands={})
        return state
