"""Daugman's rubber sheet between the pupil and limbus boundaries, and the mask of usable iris samples.

:func:`sample_grid` places ``radial × angular`` samples on rays from the pupil centre between the two
boundaries (Masek's rubber sheet for non-concentric boundaries; circles or, when the segmentation fitted them,
ellipses); :func:`normalise` samples the image there and masks what is not iris: samples outside the image,
specular reflections, beyond the eyelid margins, eyelashes darker than a threshold, and grey-level occlusions
(eyelids, sclera) that reach the limbus.

Angular sample ``j`` is at ``θ_j = 2πj / angular`` counter-clockwise from the +x axis *on screen*
(``x = x_p + r cos θ``, ``y = y_p − r sin θ``), so column ``angular/4`` is the top of the eye and rotating the
eye counter-clockwise by ``2πk/angular`` rolls the texture by ``+k`` columns.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from forensics.impact.segment.common import Segmentation, as_float, ray_to_ellipse
from forensics.impact.segment.morphology import grow_square


def _ray_to_circle(origin: tuple[float, float], circle, theta: np.ndarray) -> np.ndarray:
    """Distance along each ray from ``origin`` (direction ``(cos θ, −sin θ)``) to a circle ``(x, y, r)``.

    Solves ``|O + R·u − C| = r`` for ``R ≥ 0``; where the origin lies outside the circle (a degenerate
    segmentation) the discriminant is clipped at 0.
    """
    ox, oy = origin[0] - circle[0], origin[1] - circle[1]
    du = ox * np.cos(theta) - oy * np.sin(theta)
    return -du + np.sqrt(np.maximum(du * du - (ox * ox + oy * oy) + circle[2] ** 2, 0.0))


def boundary_radii(seg: Segmentation, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distances from the pupil centre to the pupil boundary and to the limbus along each angle."""
    origin = (seg.pupil[0], seg.pupil[1])
    if seg.pupil_ellipse is not None:
        origin = (seg.pupil_ellipse[0], seg.pupil_ellipse[1])
        inner = ray_to_ellipse(origin, seg.pupil_ellipse, theta)
    else:
        inner = np.full(theta.shape, float(seg.pupil[2]))
    if seg.iris_ellipse is not None:
        outer = ray_to_ellipse(origin, seg.iris_ellipse, theta)
    else:
        outer = _ray_to_circle(origin, seg.iris, theta)
    return inner, np.maximum(outer, inner)


def sample_grid(seg: Segmentation, radial: int = 20, angular: int = 240) -> tuple[np.ndarray, np.ndarray]:
    """Image coordinates ``(y, x)`` (each ``radial × angular``) of the rubber-sheet samples.

    Radial positions are ``radial + 2`` equally spaced points from the pupil boundary to the limbus with both
    end points dropped, as in Masek's ``normaliseiris`` (the boundaries themselves are mixed pixels).
    """
    theta = 2 * np.pi * np.arange(angular) / angular
    xp, yp = (seg.pupil_ellipse[0], seg.pupil_ellipse[1]) if seg.pupil_ellipse is not None else seg.pupil[:2]
    inner, outer = boundary_radii(seg, theta)
    t = np.linspace(0.0, 1.0, radial + 2)[1:-1]
    r = inner[None, :] + t[:, None] * (outer - inner)[None, :]
    x = xp + r * np.cos(theta)[None, :]
    y = yp - r * np.sin(theta)[None, :]
    return y, x


def _row_medians(values: np.ndarray) -> np.ndarray:
    """``np.nanmedian(values, axis=1, keepdims=True)`` (NaN for a row without a number), by numpy's own method for
    rows shorter than 600 — sort, then halve the sum of the two middle values (the one middle value twice for an
    odd count) — without its masked-array overhead (a third of the rubber sheet's time); the same bits
    (``tests/impact/test_segment.py``)."""
    ordered = np.sort(values, axis=1)                                  # NaN last, as the masked sort puts them
    n = np.count_nonzero(~np.isnan(values), axis=1)
    half = n // 2
    low = np.take_along_axis(ordered, np.where(n % 2 == 1, half, half - 1)[:, None], axis=1)
    high = np.take_along_axis(ordered, half[:, None], axis=1)
    med = (low + high) / 2
    med[n == 0] = np.nan
    return med


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
        med = _row_medians(np.where(ref, sm, np.nan))
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
    return grow_square(occluded, 3) if occluded.any() else occluded


def footprint(seg: Segmentation, radial: int, angular: int, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """The box ``(y0, y1, x0, x1)`` holding every pixel :func:`normalise` reads for a band of this size.

    :func:`normalise` reads the image at its samples (bilinear: the pixels around each), around their nearest
    pixels (reflections grown by 2 px), and in the pupil patch of the adaptive lash threshold; beyond that only
    the full scale, fixed by the dtype for 8-bit images.  A sample outside the image reads nothing that is used.
    The box is all of these with a pixel to spare, clipped to the image.
    """
    h, w = shape
    y, x = sample_grid(seg, radial, angular)
    inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1) & np.isfinite(x) & np.isfinite(y)
    xp, yp, rp = seg.pupil
    if not np.isfinite([xp, yp, rp]).all():
        return 0, h, 0, w
    r_in = max(0.6 * rp, 1.0)                           # the lash threshold's pupil patch, as normalise takes it
    y0, y1 = int(max(yp - r_in, 0)), int(min(yp + r_in, h - 1)) + 1
    x0, x1 = int(max(xp - r_in, 0)), int(min(xp + r_in, w - 1)) + 1
    if inside.any():
        ys, xs = y[inside], x[inside]
        y0, y1 = min(y0, math.floor(ys.min()) - 4), max(y1, math.ceil(ys.max()) + 5)
        x0, x1 = min(x0, math.floor(xs.min()) - 4), max(x1, math.ceil(xs.max()) + 5)
    return max(y0, 0), min(y1, h), max(x0, 0), min(x1, w)


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
    img, full = as_float(image)
    h, w = img.shape
    y, x = sample_grid(seg, radial, angular)
    inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1) & np.isfinite(x) & np.isfinite(y)
    yc, xc = np.where(inside, y, 0.0), np.where(inside, x, 0.0)
    texture = ndimage.map_coordinates(img, [yc, xc], order=1, mode="nearest").astype(np.float32)
    texture[~inside] = 0.0

    # Specular reflections: bright pixels grown by 2 px (their halo is bright too), looked up at the nearest pixel.
    bright = img >= reflection * full
    if bright.any():
        bright = grow_square(bright, 5)
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

