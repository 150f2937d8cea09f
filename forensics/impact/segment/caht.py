"""CAHT-like segmentation: contrast-adjusted circular Hough transforms, pupil first, then the limbus.

After USIT's CAHT (C. Rathgeb, A. Uhl, P. Wild, *Iris Recognition: From Segmentation to Template Security*,
Springer 2012, and USIT's ``caht``):

1. **Reflections** — small near-saturated spots much brighter than their surroundings — are filled from around
   them (:func:`~forensics.impact.segment.common.reflection_mask`).
2. **Pupil.**  The luminance is adjusted so that 2 % of the pixels are black and 4 % white; pixels below 28/255
   after the adjustment are dark (CAHT's saturating 3×3 sums), the dark map is opened (lashes) and its holes
   filled.  Where the dark region is thickest (maxima of its distance transform, at least half as thick as the
   thickest: a lash or shadow hanging off the pupil does not move them) are the candidate pupils, and the
   thickness bounds the radius, as CAHT's longest dark runs do.  Around each, a circular Hough transform
   (``skimage.transform.hough_circle``) of the dark map's rim (CAHT's Canny on the processed image); the circle
   is then fitted to the steepest rise on rays all round except the top 60° (lids and lashes), with Tukey's
   biweight (:func:`~forensics.impact.segment.boundary.fit_rays`).  The candidate whose rays agree best wins.
3. **Limbus.**  The pupil is blacked out to 1.5 pupil radii with the mean of the ring around it; the
   luminance is adjusted so that the area of that disc is black and 1 % white, and clipped at mid-grey (so
   that skin, sclera and highlights are one flat level and only the darker iris keeps an edge).  On that image,
   at half resolution, Canny edges that are near-vertical (the lids run horizontally: CAHT uses the horizontal
   gradient only) and have the iris's polarity (darker towards the pupil) vote in a weighted circular Hough
   transform, edges above the pupil weighted down quadratically to zero at about two pupil radii (CAHT's
   "dimming above the horizon"); centres within 1.3 pupil radii of the pupil's and radii of 1.5–8 pupil radii
   (CAHT's ranges); each circle's votes normalised by the length of its lateral arcs inside the image, with a
   Gaussian preference for centres near the pupil's (σ = 0.1 iris radius).  The four best distinct circles are
   each refined at full resolution by :func:`~forensics.impact.segment.boundary.polar_fit` on the lateral arcs
   (±60°) and the bottom (250–290°); the refined circle with the largest iris-to-sclera step
   (:func:`~forensics.impact.segment.boundary.band_contrast`) times ray agreement wins.
4. **Checks**: radius ratio, pupil inside the iris, iris inside the image
   (:func:`~forensics.impact.segment.common.plausibility`), pupil darker than iris darker than sclera
   (:func:`~forensics.impact.segment.common.contrast_check`), ray agreement of each boundary at least
   ``min_support``.  A failed check sets ``ok = False`` with the reason.
5. **Eyelids** as parabolas (:func:`~forensics.impact.segment.edges.find_eyelid`).

Sizes are relative: to the image's shorter side before the pupil is known, to the pupil radius after.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from forensics.impact.segment.boundary import band_contrast, fit_rays, polar_fit
from forensics.impact.segment.common import (
    Circle,
    Segmentation,
    contrast_check,
    fill_masked,
    grey,
    image_size,
    plausibility,
    reflection_mask,
    stretch,
)
from forensics.impact.segment.edges import edges_and_gradient, find_eyelid
from forensics.impact.segment.memo import StepMemo, remembered
from forensics.impact.segment.morphology import fill_holes, opening

#: CAHT's darkness threshold after the 2 %/4 % luminance adjustment (a 3×3 sum saturating at 255 stays below
#: 255 only if the mean is below 28).
DARK = 28 / 255
#: Lateral arcs (degrees, counter-clockwise from +x, y up on screen) and the lower arc used for the limbus.
LIMBUS_ARCS = ((-60.0, 60.0), (120.0, 240.0), (250.0, 290.0))
#: The pupil's arcs: all round except the top 60°, where the upper lid and its lashes often hang.
PUPIL_ARCS = ((-60.0, 60.0), (120.0, 300.0))


def segment_caht(
    image: np.ndarray,
    *,
    min_pupil: float = 0.025,
    center_range: float = 1.3,
    iris_ratio: tuple[float, float] = (1.5, 8.0),
    decentration: float = 0.1,
    min_support: float = 0.3,
    eyelids: bool = True,
    lid_curvature: float = 0.5,
    lid_support: float = 0.3,
    coarse: int = 6,
    memo: StepMemo | None = None,
) -> Segmentation:
    """Segment an eye image with the CAHT-like method (see the module docstring).

    Parameters
    ----------
    image
        ``(H, W)`` grey eye image (any dtype; colour is averaged).
    min_pupil
        Smallest pupil radius as a fraction of the image's shorter side (ISO/IEC 29794-6 asks for an iris of
        at least 120 px across; with the smallest physiological pupil/iris ratio 0.1 the pupil radius is then
        ≥ 6 px, 0.025 of 240 rows).
    center_range, iris_ratio
        The limbus's centre within ``center_range`` pupil radii of the pupil's, its radius within
        ``iris_ratio`` pupil radii (CAHT's 1.3 and 1.5–8).
    decentration
        Standard deviation of the preferred pupil–limbus centre offset, as a fraction of the iris radius.
    min_support
        Smallest edge support (0–1) for a boundary to be trusted (``ok``).
    eyelids, lid_curvature, lid_support
        Look for the eyelid margins (:func:`~forensics.impact.segment.edges.find_eyelid`).
    coarse
        The limbus refinement's circle search (:func:`~forensics.impact.segment.boundary.polar_fit`):
        coarse-to-fine from this many coarse circles, or exhaustive with 0 (about three times slower overall;
        on the 400 shared IITD eyes one limbus of 400 differs, ``benchmarks/RESULTS_impact.md``).
    memo
        Reuse the costly steps (the pupil's and the limbus's Hough transforms, the limbus fits) where their
        inputs are byte-identical to an earlier segmentation's (:class:`~forensics.impact.segment.memo.StepMemo`):
        the same result, bit for bit, in a fraction of the time for an image that differs from an earlier one
        in a few pixels.

    Returns
    -------
    Segmentation
        Never raises on odd pixel content: without a pupil or limbus the result has ``ok = False``, a reason
        and circles guessed from the image's size.
    """
    img = grey(image)
    h, w = img.shape
    side = image_size(img.shape)
    guess = Segmentation(pupil=(w / 2, h / 2, 0.1 * side), iris=(w / 2, h / 2, 0.4 * side), ok=False,
                         quality=0.0, method="caht")
    if float(img.max()) - float(img.min()) < 1e-6:
        return guess.failed("flat image: no edges")
    filled = fill_masked(img, reflection_mask(img))
    pupil, p_support = find_pupil(filled, min_pupil, memo=memo)
    if pupil is None:
        return guess.failed("no dark, round pupil found")
    iris, l_support = find_limbus(filled, pupil, center_range, iris_ratio, decentration, coarse=coarse,
                                   memo=memo)
    if iris is None:
        return Segmentation(pupil=pupil, iris=guess.iris, ok=False, quality=0.0, reason="no limbus edges",
                            method="caht")
    reasons = [plausibility(pupil, iris, img.shape), contrast_check(filled, pupil, iris)]
    if p_support < min_support:
        reasons.append(f"weak pupil boundary ({p_support:.2f})")
    if l_support < min_support:
        reasons.append(f"weak limbus ({l_support:.2f})")
    upper_lid = lower_lid = None
    if eyelids:
        ey, ex, gy, gx = edges_and_gradient(filled, max(1.0, 0.008 * side), (0.85, 0.93))
        upper_lid = find_eyelid(ey, ex, gy, gx, pupil, iris, True, lid_curvature, lid_support, memo)
        lower_lid = find_eyelid(ey, ex, gy, gx, pupil, iris, False, lid_curvature, lid_support, memo)
    reason = "; ".join(r for r in reasons if r)
    return Segmentation(pupil=pupil, iris=iris, ok=not reason, quality=float(min(p_support, l_support)),
                        reason=reason, upper_lid=upper_lid, lower_lid=lower_lid, method="caht")


# --------------------------------------------------------------------------- pupil
def dark_region(img: np.ndarray) -> np.ndarray:
    """CAHT's dark map: below :data:`DARK` after the 2 %/4 % luminance adjustment, opened, holes filled."""
    from skimage.morphology import disk

    dark = stretch(img, 0.02, 0.04) < DARK
    radius = max(1, round(0.01 * image_size(img.shape)))
    return fill_holes(opening(dark, disk(radius)))


def find_pupil(img: np.ndarray, min_pupil: float = 0.025, n_candidates: int = 4, memo: StepMemo | None = None
               ) -> tuple[Circle | None, float]:
    """The pupil circle and its edge support (0–1), or ``(None, 0)``.

    Candidates are the thickest places of the dark region (:func:`dark_region`) at least half as thick as the
    thickest (a pupil is the largest dark disc of an eye image; lash clumps and shadows are thinner); see the
    module docstring.  The candidates' Hough circles depend on the dark region alone (:func:`pupil_candidates`,
    reused through ``memo`` where it is byte-identical).
    """
    side = image_size(img.shape)
    candidates = remembered(memo, pupil_candidates, dark_region(img), float(min_pupil), int(n_candidates))
    if not candidates:
        return None, 0.0
    smooth = ndimage.gaussian_filter(img, max(1.0, 0.006 * side))
    best: tuple[float, Circle | None] = (-1.0, None)
    for coarse in candidates:
        circle, _strength, support = fit_rays(smooth, coarse, PUPIL_ARCS, step=3.0, window=0.15)
        if support > best[0]:
            best = (support, circle)
    return best[1], max(best[0], 0.0)


def pupil_candidates(dark: np.ndarray, min_pupil: float, n_candidates: int) -> tuple[Circle, ...]:
    """The pupil candidates' circles from the Hough transform of the dark region's rim (:func:`_pupil_hough`).

    The candidates are the dark region's thickest places (maxima of its distance transform, at least
    ``min_pupil`` × the shorter side and half as thick as the thickest); empty when there is none.
    """
    from skimage.feature import peak_local_max

    if not dark.any():
        return ()
    side = image_size(dark.shape)
    depth = ndimage.distance_transform_edt(dark)
    r_min = max(2.0, min_pupil * side)
    peaks = peak_local_max(depth, min_distance=max(1, int(r_min)), threshold_abs=r_min, num_peaks=n_candidates,
                           exclude_border=False)
    if len(peaks) == 0:
        return ()
    thickest = max(float(depth[py, px]) for py, px in peaks)
    # CAHT's Hough votes with the edges of the dark map (its Canny on the processed image): the dark region's
    # rim, one pixel wide.
    rim = dark & ~ndimage.binary_erosion(dark)
    found = []
    for py, px in peaks:
        if depth[py, px] < 0.5 * thickest:
            continue
        coarse = _pupil_hough(rim, float(px), float(py), float(depth[py, px]))
        if coarse is not None:
            found.append(coarse)
    return tuple(found)


def _pupil_hough(rim: np.ndarray, cx: float, cy: float, depth: float) -> Circle | None:
    """Circular Hough transform of the dark region's rim around a candidate with inscribed radius ``depth``.

    Radii from 0.9 to 1.6 × ``depth`` (a lid covering up to ~40 % of the pupil leaves an inscribed circle of
    0.7 radius); centres within ``depth`` of the candidate (its thickest point lies inside the pupil).
    """
    from skimage.transform import hough_circle

    r_lo, r_hi = max(2, int(0.9 * depth)), int(math.ceil(1.6 * depth)) + 1
    half = int(math.ceil(depth + r_hi)) + 2
    h, w = rim.shape
    x0, y0 = max(int(cx) - half, 0), max(int(cy) - half, 0)
    crop = rim[y0:min(int(cy) + half + 1, h), x0:min(int(cx) + half + 1, w)]
    if crop.sum() < 8:
        return None
    radii = np.arange(r_lo, r_hi + 1)
    hspace = hough_circle(crop, radii, normalize=True)
    yy, xx = np.mgrid[0:crop.shape[0], 0:crop.shape[1]]
    allowed = np.hypot(xx + x0 - cx, yy + y0 - cy) <= max(depth, 3.0)
    flat = np.where(allowed, hspace.max(axis=0), 0.0)
    k = int(np.argmax(flat))
    if flat.flat[k] <= 0:
        return None
    hy, hx = divmod(k, flat.shape[1])
    return float(hx + x0), float(hy + y0), float(radii[int(np.argmax(hspace[:, hy, hx]))])


# --------------------------------------------------------------------------- limbus
def limbus_image(img: np.ndarray, pupil: Circle) -> np.ndarray:
    """CAHT's contrast-adjusted image for the limbus: pupil blacked out, luminance adjusted, clipped at 0.5."""
    h, w = img.shape
    xp, yp, rp = pupil
    r2 = 1.5 * rp
    # Only the disc of radius r2 changes: computed on its box (the same pixels in the same order, so the same
    # ring mean and blend), the rest is the image.
    y0, y1, x0, x1 = 0, h, 0, w
    if np.isfinite([xp, yp, r2]).all():
        y0, y1 = max(0, math.floor(yp - abs(r2)) - 1), min(h, math.ceil(yp + abs(r2)) + 2)
        x0, x1 = max(0, math.floor(xp - abs(r2)) - 1), min(w, math.ceil(xp + abs(r2)) + 2)
        y1, x1 = max(y0, y1), max(x0, x1)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    d = np.hypot(xx - xp, yy - yp).astype(np.float32)
    box = img[y0:y1, x0:x1]
    ring = (d >= rp) & (d <= r2)
    mean = float(box[ring].mean()) if ring.any() else float(img.mean())
    alpha = np.clip((d - rp) / max(r2 - rp, 1e-6), 0.0, 1.0)
    work = img.astype(np.float32, copy=True)
    work[y0:y1, x0:x1] = np.where(d <= r2, box * alpha + np.float32(mean) * (1 - alpha), box)
    black = min(0.5, math.pi * r2 * r2 / (h * w))
    return np.minimum(stretch(work, black, 0.01), np.float32(0.5))


def find_limbus(img: np.ndarray, pupil: Circle, center_range: float = 1.3, iris_ratio: tuple[float, float] = (1.5, 8.0),
                decentration: float = 0.1, n_candidates: int = 4, coarse: int = 6, memo: StepMemo | None = None
                ) -> tuple[Circle | None, float]:
    """The limbus circle and its edge support (0–1), or ``(None, 0)``; see the module docstring.

    The Hough transform's starts depend on the voting edges alone (:func:`limbus_starts`) and each refinement
    on its ray profiles (:func:`~forensics.impact.segment.boundary.polar_fit`): both reused through ``memo``
    where those are byte-identical.
    """
    from skimage.feature import canny

    xp, yp, rp = pupil
    side = image_size(img.shape)
    k = max(1, round(side / 120))                          # coarse stage at ~120 px on the shorter side
    adj = _block_mean(limbus_image(img, pupil), k)
    sigma = max(1.0, 0.0125 * side / k)                    # CAHT's σ = 3 px at 240 rows
    smooth = ndimage.gaussian_filter(adj, sigma)
    edges = canny(smooth, sigma=0.0, low_threshold=0.7, high_threshold=0.85, use_quantiles=True)
    ey, ex = np.nonzero(edges)
    gx = ndimage.sobel(smooth, axis=1)[ey, ex]
    gy = ndimage.sobel(smooth, axis=0)[ey, ex]
    cxp, cyp, crp = (xp + 0.5) / k - 0.5, (yp + 0.5) / k - 0.5, rp / k
    keep = (np.abs(gx) >= np.abs(gy)) & ((ex - cxp) * gx > 0) & (np.hypot(ex - cxp, ey - cyp) > 1.5 * crp)
    ey, ex = ey[keep], ex[keep]
    if ey.size < 8:
        return None, 0.0
    above = np.clip(cyp - ey, 0.0, None)
    weight = np.clip(1.0 - above ** 2 / (4.25 * crp * crp), 0.0, 1.0)
    starts = remembered(memo, limbus_starts, ex, ey, weight, (cxp, cyp, crp), k, adj.shape, center_range,
                        iris_ratio, decentration, n_candidates)
    # The few best distinct circles go to the full-resolution refinement, and the refined circle with the
    # largest iris-to-sclera step wins.
    smooth_full = ndimage.gaussian_filter(img, max(1.0, 0.004 * side))
    best: tuple[float, Circle | None, float] = (-np.inf, None, 0.0)
    for x0, y0, r0 in starts:
        circle, support = polar_fit(smooth_full, (x0, y0, r0), LIMBUS_ARCS, coarse=coarse, memo=memo)
        offset = math.hypot(circle[0] - xp, circle[1] - yp)
        if offset > center_range * rp or not iris_ratio[0] * rp <= circle[2] <= iris_ratio[1] * rp:
            continue                                       # the refinement left CAHT's search ranges
        # The iris-to-sclera step times the rays' agreement: a ring inside the iris has a smaller step, a
        # circle across lashes and lids less agreement.
        value = band_contrast(smooth_full, circle, LIMBUS_ARCS) * support
        if value > best[0]:
            best = (value, circle, support)
    return best[1], best[2]


def limbus_starts(ex: np.ndarray, ey: np.ndarray, weight: np.ndarray, pupil: Circle, k: int,
                  shape: tuple[int, int], center_range: float, iris_ratio: tuple[float, float], decentration: float,
                  n_candidates: int) -> tuple[Circle, ...]:
    """The ``n_candidates`` best distinct limbus circles of the weighted Hough transform, at full resolution.

    ``ex, ey, weight`` are the voting edges of the ``k``-times reduced image of ``shape``, ``pupil`` the pupil
    in its coordinates; see the module docstring.  The lateral edges leave the vertical position loose, so
    several distinct circles go to the refinement.
    """
    cxp, cyp, crp = pupil
    r_lo = max(2, int(iris_ratio[0] * crp))
    # Beyond 0.8 × the longer side, less than half the iris disc can be in the image (see plausibility).
    r_hi = max(r_lo + 1, int(min(iris_ratio[1] * crp, 0.8 * max(shape))))
    radii = np.arange(r_lo, r_hi + 1, dtype=float)
    span = int(math.ceil(center_range * crp))
    offs = np.arange(-span, span + 1, 2, dtype=float)  # every 2 coarse px; the refinement searches ±(k + 2) px
    gxs, gys = np.meshgrid(round(cxp) + offs, round(cyp) + offs)
    near = np.hypot(gxs - cxp, gys - cyp) <= center_range * crp
    cx, cy = gxs[near], gys[near]
    cover = _lateral_votes(ex, ey, weight, cx, cy, radii, shape)
    prior = np.exp(-0.5 * (np.hypot(cx - cxp, cy - cyp)[:, None] / (decentration * radii[None, :])) ** 2)
    score = cover * prior
    starts = []
    for _ in range(n_candidates):
        idx = int(np.argmax(score))
        if score.flat[idx] <= 0:
            break
        c, r = divmod(idx, radii.size)
        starts.append((float((cx[c] + 0.5) * k - 0.5), float((cy[c] + 0.5) * k - 0.5), float(radii[r] * k)))
        # Suppress this circle's neighbourhood (3 coarse pixels of centre and radius) before the next pick.
        close = np.hypot(cx - cx[c], cy - cy[c]) <= 3
        score[np.ix_(close, np.abs(radii - radii[r]) <= 3)] = 0
    return tuple(starts)


def _lateral_votes(ex, ey, weight, cx, cy, radii, shape) -> np.ndarray:
    """Weighted circular Hough votes, ``(centres, radii)``, normalised by the lateral arc length in the image.

    Each edge pixel votes for the radius at which it lies from each candidate centre (a direct vote:
    ``|edge − centre|`` rounded, which is what drawing circles around the edges accumulates, at a fraction of
    the cost for the few thousand centres CAHT allows).  The normaliser is the length of the arcs within 45°
    of the horizontal that lie inside the image, so that an iris cut by the image border is not penalised for
    its missing edges.
    """
    r0, nr = int(radii[0]), radii.size
    votes = np.zeros(cx.size * nr)
    rows = np.arange(cx.size)[:, None] * nr
    for s in range(0, ex.size, 1024):
        dist = np.hypot(ex[None, s:s + 1024] - cx[:, None], ey[None, s:s + 1024] - cy[:, None])
        ri = np.rint(dist).astype(np.int64) - r0
        good = (ri >= 0) & (ri < nr)
        votes += np.bincount((rows + ri)[good], weights=np.broadcast_to(weight[None, s:s + 1024], good.shape)[good],
                             minlength=votes.size)
    votes = votes.reshape(cx.size, nr)
    ang = np.deg2rad(np.concatenate([np.arange(-40, 41, 20), np.arange(140, 221, 20)]))
    px = cx[:, None, None] + radii[None, :, None] * np.cos(ang)[None, None, :]
    py = cy[:, None, None] - radii[None, :, None] * np.sin(ang)[None, None, :]
    inside = ((px >= 0) & (px <= shape[1] - 1) & (py >= 0) & (py <= shape[0] - 1)).mean(axis=2)
    cover = votes / np.maximum(np.pi * radii[None, :] * inside, 1.0)
    cover[inside < 0.25] = 0.0  # less than a quarter of the lateral arcs visible: not a limbus to trust
    return cover


def _block_mean(img: np.ndarray, k: int) -> np.ndarray:
    """Mean over ``k × k`` blocks (the last partial rows/columns are dropped)."""
    if k == 1:
        return img
    h, w = (img.shape[0] // k) * k, (img.shape[1] // k) * k
    return img[:h, :w].reshape(h // k, k, w // k, k).mean(axis=(1, 3))
