"""What every segmentation shares: the result type, image preparation, and the plausibility checks.

Conventions
-----------
Circles are ``(x, y, r)`` in pixels, ``x`` the column and ``y`` the row of the centre (pixel centres at
integer coordinates, ``y`` down).  Ellipses are ``(x, y, a, b, phi)``: centre, semi-axes and the angle of the
``a`` axis in radians, counter-clockwise on screen from the +x axis.  Lengths that are parameters are given
relative to the image (its shorter side) or to a boundary found earlier, so that a segmentation behaves the
same on a 320×240 and a 640×480 image of the same eye.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
from scipy import ndimage

from forensics._shared.errors import InputError
from forensics.impact.segment.morphology import grow as grow_mask

# A circle: centre column, centre row, radius (pixels).
Circle = tuple[float, float, float]
# An ellipse: centre column, centre row, semi-axes a and b, angle of a (radians, counter-clockwise on screen).
Ellipse = tuple[float, float, float, float, float]
# An eyelid margin y = y0 + a (x − x0)²: (x0, y0, a).
Parabola = tuple[float, float, float]

#: Physiological bounds of the pupil/iris radius ratio (Daugman, "How iris recognition works", 2004: the
#: pupil's radius ranges from 0.1 to 0.8 of the iris's).
RATIO_BOUNDS = (0.1, 0.8)


@dataclass(frozen=True)
class Segmentation:
    """Pupil and limbus boundaries of one eye image.

    Parameters
    ----------
    pupil, iris
        ``(x, y, r)`` of the pupil boundary and of the limbus (for an ellipse, its centre and the mean of its
        semi-axes), in pixels of the full image.
    ok
        False when the segmentation failed a plausibility check (see :func:`plausibility`) or found no
        boundary; the circles are then a best guess, and the experiment does not score the image.
    quality
        Edge support of the weaker of the two boundaries, 0–1 (the fraction of the considered arcs on which
        the boundary's edge was found).
    reason
        Why ``ok`` is False (empty when ok).
    upper_lid, lower_lid
        Eyelid margins found over the iris, as parabolas ``(x0, y0, a)``: ``y = y0 + a (x − x0)²``.  The eye
        is below the upper and above the lower margin.  None when no margin crosses the iris.
    pupil_ellipse, iris_ellipse
        The boundaries as ellipses ``(x, y, a, b, phi)`` when the segmentation fits ellipses (WAHET-like);
        None for circles.  Normalisation follows the ellipses when present.
    method
        Name of the segmentation that made this result (``"caht"``, ``"wahet"``; empty if made by hand).
    """

    pupil: Circle
    iris: Circle
    ok: bool = True
    quality: float = 1.0
    reason: str = ""
    upper_lid: Parabola | None = None
    lower_lid: Parabola | None = None
    pupil_ellipse: Ellipse | None = None
    iris_ellipse: Ellipse | None = None
    method: str = ""

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (boundaries and eyelids as lists of floats, None when absent)."""
        d = asdict(self)
        for key in ("pupil", "iris", "upper_lid", "lower_lid", "pupil_ellipse", "iris_ellipse"):
            value = getattr(self, key)
            d[key] = None if value is None else [float(v) for v in value]
        d["quality"] = float(self.quality)
        d["ok"] = bool(self.ok)
        return d

    def failed(self, reason: str) -> Segmentation:
        """This segmentation marked as failed, ``reason`` added to any earlier one."""
        reasons = "; ".join(r for r in (self.reason, reason) if r)
        return replace(self, ok=False, reason=reasons)


# --------------------------------------------------------------------------- image preparation
def as_float(image: np.ndarray) -> tuple[np.ndarray, float]:
    """``(float32 grey image in the image's own units, full scale)``; colour images are averaged over channels.

    Full scale is 255 for 8-bit images, ``2^b − 1`` for wider integers with ``b`` the smallest bit depth (at
    least 8) that holds the image's maximum (10–14-bit sensors deliver uint16 far below 65535), and 1 (or the
    maximum, if above 1) for floats.  Non-finite values become 0 (NaN, −inf) or full scale (+inf).

    Raises
    ------
    InputError
        For an array that is not a 2-D grey (or 3-D colour) image of at least 16×16 pixels.
    """
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] in (1, 3, 4):
        a = a[..., :3].mean(axis=2) if a.shape[2] >= 3 else a[..., 0]
    if a.ndim != 2 or a.shape[0] < 16 or a.shape[1] < 16:
        raise InputError(f"an eye image must be a 2-D grey array of at least 16×16 pixels, got shape {a.shape}")
    if np.issubdtype(a.dtype, np.integer) and a.dtype.itemsize == 1:
        full = float(np.iinfo(a.dtype).max)
    elif np.issubdtype(a.dtype, np.integer):
        top = int(a.max()) if a.size else 0
        full = float(2 ** max(8, int(top).bit_length()) - 1)
    else:
        finite = a[np.isfinite(a)]
        full = 1.0 if finite.size == 0 or finite.max() <= 1.0 else float(finite.max())
    f = np.asarray(a, dtype=np.float32)
    if not np.isfinite(f).all():
        f = np.nan_to_num(f, nan=0.0, posinf=full, neginf=0.0)
    return f, full


def grey(image: np.ndarray) -> np.ndarray:
    """The image as float32 grey values in units of its full scale (0 black, 1 full scale); see :func:`as_float`."""
    f, full = as_float(image)
    return f / np.float32(full)


def image_size(shape: tuple[int, int]) -> float:
    """The length that relative sizes refer to: the image's shorter side, in pixels."""
    return float(min(shape[0], shape[1]))


def stretch(img: np.ndarray, black: float, white: float, region: np.ndarray | None = None) -> np.ndarray:
    """CAHT's luminance adjustment: a linear map making a fraction ``black`` of the pixels 0 and ``white`` 1.

    The quantiles are taken over ``region`` (a boolean mask) when given.  Being relative, the result is the same
    for any positive rescaling of the input: the segmentation does not depend on exposure or bit depth.
    """
    vals = img[region] if region is not None else img
    if vals.size == 0:
        return np.zeros_like(img, dtype=np.float32)
    lo, hi = np.quantile(vals, [black, 1.0 - white])
    if not hi > lo:
        hi = lo + 1e-6
    return np.clip((img - np.float32(lo)) / np.float32(hi - lo), 0.0, 1.0).astype(np.float32)


def reflection_mask(img: np.ndarray, contrast: float = 60 / 255, level: float = 0.9, window: float = 0.1,
                    max_area: float = 0.013, grow: float = 0.021) -> np.ndarray:
    """Specular reflections: small spots at the top of the image's range, much brighter than their surroundings.

    A pixel is a candidate when it exceeds the mean of a square window (side ``window`` × the shorter image
    side, 23 px at 240 rows) by ``contrast`` (in units of the image's range, darkest to brightest pixel) — WAHET's
    adaptive threshold — and lies at least ``level`` of the way up that range (a specular reflection of the
    illuminator is the brightest thing in a near-infrared eye image, saturated or not; without this, the bright rim
    of a light iris next to the black pupil passes the adaptive test too).
    Connected candidates of at most ``max_area`` × the image's area are kept (large bright regions are skin or
    sclera) and grown by a disc of radius ``grow`` × the shorter side (their halo is bright too).  Uhl and Wild
    use an adaptive threshold of 60 grey levels over a 23×23 mean, regions of 10–1000 px at 320×240, dilated by
    an 11-px disc.  Hot or stuck-bright pixels of an ageing sensor are caught as well.
    """
    side = image_size(img.shape)
    size = max(3, int(round(window * side)) | 1)
    local = ndimage.uniform_filter(img, size)
    # both thresholds in units of the image's own range, as CAHT's stretch is: a reflection that does not saturate
    # (a dimmer illuminator, another exposure or black level) is still the brightest small spot.  At a fixed 0.9 of
    # full scale none of the 400 shared IITD eyes kept a reflection under 0.8 × grey + 20, and the pupils of 57 of
    # them moved under WAHET (benchmarks/bench_segmentation_stability.py); an image spanning the full scale (every
    # shared eye: 0 … 255) gets the same thresholds bit for bit
    lo = np.float32(img.min())
    span = np.float32(img.max()) - lo
    cand = (img > local + np.float32(contrast) * span) & (img >= lo + np.float32(level) * span)
    if not cand.any():
        return cand
    lab, n = ndimage.label(cand)
    areas = np.bincount(lab.ravel(), minlength=n + 1)
    keep = areas <= max_area * img.size
    keep[0] = False
    mask = keep[lab]
    radius = max(1, round(grow * side))
    if mask.any():
        yy, xx = np.mgrid[-radius:radius + 1, -radius:radius + 1]
        mask = grow_mask(mask, xx * xx + yy * yy <= radius * radius)
    return mask


def fill_masked(img: np.ndarray, mask: np.ndarray, window: float = 0.03) -> np.ndarray:
    """``img`` with the pixels of ``mask`` replaced by the mean of the unmasked pixels around them.

    A normalised box filter (side ``window`` × the shorter image side) fills the rim of each masked region
    first; the window doubles until every pixel is filled (a large reflection is filled from its whole
    surroundings rather than from a few pixels).  Used instead of OpenCV's inpainting, which scikit-image
    offers only in a biharmonic form that costs ~1 s per image.
    """
    if not mask.any():
        return img
    out = img.astype(np.float32, copy=True)
    keep = (~mask).astype(np.float32)
    size = max(3, int(round(window * image_size(img.shape))) | 1)
    todo = mask.copy()
    for _ in range(12):
        num = ndimage.uniform_filter(out * keep, size)
        den = ndimage.uniform_filter(keep, size)
        ready = todo & (den > 1e-3)
        out[ready] = num[ready] / den[ready]
        keep[ready] = 1.0
        todo &= ~ready
        if not todo.any():
            break
        size = 2 * size + 1
    if todo.any():  # nothing unmasked anywhere near (a masked image): the global median
        out[todo] = float(np.median(img))
    return out


# --------------------------------------------------------------------------- plausibility
def plausibility(pupil: Circle, iris: Circle, shape: tuple[int, int],
                 ratio_bounds: tuple[float, float] = RATIO_BOUNDS, min_inside: float = 0.5) -> str:
    """Why a pair of boundaries cannot be an eye (empty string when it can).

    Checks: the pupil/iris radius ratio within ``ratio_bounds`` (physiological limits); the pupil inside the
    iris; at least ``min_inside`` of the iris disc inside the image (otherwise too little iris can be seen to
    compare).
    """
    xp, yp, rp = pupil
    xi, yi, ri = iris
    reasons = []
    if not (rp > 0 and ri > 0) or not np.isfinite([xp, yp, rp, xi, yi, ri]).all():
        return "degenerate boundaries"
    ratio = rp / ri
    if not ratio_bounds[0] <= ratio <= ratio_bounds[1]:
        reasons.append(f"implausible pupil/iris radius ratio {ratio:.2f} (outside {ratio_bounds[0]:g}–"
                       f"{ratio_bounds[1]:g})")
    if math.hypot(xp - xi, yp - yi) + rp > ri:
        reasons.append("pupil not inside the iris")
    inside = disc_fraction_inside(iris, shape)
    if inside < min_inside:
        reasons.append(f"only {100 * inside:.0f} % of the iris inside the image")
    return "; ".join(reasons)


def contrast_check(img: np.ndarray, pupil: Circle, iris: Circle, margin: float = 0.05) -> str:
    """Why the grey levels cannot be a pupil inside an iris inside a sclera (empty string when they can).

    In a near-infrared eye image the pupil is darker than the iris, and the iris darker than the sclera beside
    it.  The medians of the pupil disc (0.8 × its radius), of the iris ring (from 1.1 pupil radii to 0.9 iris
    radii, on the lateral thirds, away from the lids) and of the ring just outside the limbus (1.05–1.2 iris
    radii, lateral thirds) must increase in that order by at least ``margin`` × the image's robust grey range
    (2nd to 98th percentile).  A closed eye, skin or a blank frame fails.
    """
    h, w = img.shape
    lo, hi = np.quantile(img, [0.02, 0.98])
    step = margin * max(float(hi - lo), 1e-6)
    xp, yp, rp = pupil
    xi, yi, ri = iris
    # Every region lies within 1.2 iris radii of the iris centre or 0.8 pupil radii of the pupil's: only that box
    # is measured (the same pixels in the same order, so the same medians; the whole image for odd circles).
    y0, y1, x0, x1 = 0, h, 0, w
    if np.isfinite([xp, yp, rp, xi, yi, ri]).all():
        reach_i, reach_p = 1.2 * abs(ri) + 2, 0.8 * abs(rp) + 2
        x0 = max(0, min(math.floor(xi - reach_i), math.floor(xp - reach_p)))
        x1 = min(w, max(math.ceil(xi + reach_i), math.ceil(xp + reach_p)) + 1)
        y0 = max(0, min(math.floor(yi - reach_i), math.floor(yp - reach_p)))
        y1 = min(h, max(math.ceil(yi + reach_i), math.ceil(yp + reach_p)) + 1)
        x1, y1 = max(x1, x0), max(y1, y0)
    img = img[y0:y1, x0:x1]
    yy, xx = np.mgrid[y0:y1, x0:x1]
    dp = np.hypot(xx - xp, yy - yp)
    di = np.hypot(xx - xi, yy - yi)
    lateral = np.abs(xx - xi) >= 0.5 * np.maximum(di, 1e-9)

    def median(region: np.ndarray) -> float | None:
        return float(np.median(img[region])) if region.sum() >= 10 else None

    levels = [median(dp <= 0.8 * rp), median((dp >= 1.1 * rp) & (di <= 0.9 * ri) & lateral),
              median((di >= 1.05 * ri) & (di <= 1.2 * ri) & lateral)]
    names = ("pupil", "iris", "sclera")
    for k in range(2):
        if levels[k] is None or levels[k + 1] is None:
            continue
        if levels[k] > levels[k + 1] - step:
            return f"the {names[k]} is not darker than the {names[k + 1]}"
    return ""


def ray_to_ellipse(origin: tuple[float, float], ellipse: Ellipse, theta: np.ndarray) -> np.ndarray:
    """Distance along each ray from ``origin`` to an ellipse ``(x, y, a, b, phi)`` (the positive root).

    In the ellipse's frame (axes along ``phi``) the ray ``O + R·u`` meets ``(X/a)² + (Y/b)² = 1`` where a
    quadratic in ``R`` vanishes; its larger root is taken, clipped at 0 when the origin lies outside.
    """
    xc, yc, a, b, phi = ellipse
    # Screen y points down; the ellipse's angle is counter-clockwise on screen, so work in y-up coordinates.
    px, py = origin[0] - xc, -(origin[1] - yc)
    ux, uy = np.cos(theta), np.sin(theta)
    c, s = np.cos(phi), np.sin(phi)
    pX, pY = px * c + py * s, -px * s + py * c
    uX, uY = ux * c + uy * s, -ux * s + uy * c
    qa = (uX / a) ** 2 + (uY / b) ** 2
    qb = 2 * (pX * uX / a ** 2 + pY * uY / b ** 2)
    qc = (pX / a) ** 2 + (pY / b) ** 2 - 1
    disc = np.maximum(qb * qb - 4 * qa * qc, 0.0)
    return np.maximum((-qb + np.sqrt(disc)) / (2 * qa), 0.0)


def disc_fraction_inside(circle: Circle, shape: tuple[int, int], n: int = 32) -> float:
    """Fraction of the disc's area inside the image (sampled on an ``n × n`` grid over its bounding box)."""
    x, y, r = circle
    t = (np.arange(n) + 0.5) / n * 2 - 1
    gx, gy = np.meshgrid(x + r * t, y + r * t)
    disc = (gx - x) ** 2 + (gy - y) ** 2 <= r * r
    inside = (gx >= -0.5) & (gx <= shape[1] - 0.5) & (gy >= -0.5) & (gy <= shape[0] - 0.5)
    return float((disc & inside).sum() / max(disc.sum(), 1))
