"""Iris segmentation (circular Hough, eyelid parabolas), rubber-sheet normalisation and the Segmenter cache.

The eyes are rendered here (:func:`render_eye`), independently of :mod:`forensics.impact.irises`, with known
circles, a known eyelid and a known specular spot, so that every result can be checked against the truth.
"""
from __future__ import annotations

import json
import warnings
from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage

from forensics.impact.segment import (
    Segmentation,
    Segmenter,
    normalise,
    sample_grid,
    segment_iris,
)

PUPIL = (158.0, 122.0, 38.0)
IRIS = (160.0, 120.0, 100.0)


def polar_texture(seed: int, shape: tuple[int, int] = (48, 512)) -> np.ndarray:
    """A random, smooth iris pattern in rubber-sheet coordinates (rows: pupil → limbus; columns: angle)."""
    t = np.random.default_rng(seed).normal(size=shape)
    t = ndimage.gaussian_filter(t, sigma=(2.0, 3.0), mode=("nearest", "wrap"))
    return t / t.std()


def render_eye(pupil=PUPIL, iris=IRIS, texture_seed: int = 1, rotation: float = 0.0, noise_seed: int = 0,
               noise: float = 3.0, eyelid: float | None = 50.0, spot: tuple[float, float, float] | None = (10.0, -8.0, 5.0),
               shape: tuple[int, int] = (240, 320), limbus_width: float = 1.0) -> np.ndarray:
    """A 320×240 uint8 near-infrared eye with known geometry.

    Dark pupil disc (30), textured iris annulus (105 ± 22), brighter sclera (~175), an upper eyelid (185)
    whose margin is ``y = eyelid + 0.004 (x − x_iris)²``, one saturated specular spot ``(dx, dy, r)``
    relative to the pupil centre, Gaussian noise.  The texture is laid out in exactly the rubber-sheet
    coordinates of the normalisation (angle about the pupil centre counter-clockwise on screen, radius
    normalised between the pupil circle and the limbus along that ray), turned by ``rotation`` radians,
    so that a rotation of ``2πk/240`` shifts a 240-column normalised texture by ``k`` columns.
    ``limbus_width``: the width in pixels of the linear ramp from iris to sclera (1: a sharp, anti-aliased edge;
    real near-infrared limbi are ramps of 10–20 px at this size).
    """
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    xp, yp, rp = pupil
    xi, yi, ri = iris
    dx, dy = xx - xp, yy - yp
    dist = np.hypot(dx, dy)
    theta = np.arctan2(-dy, dx)
    ux, uy = np.cos(theta), -np.sin(theta)
    du = (xp - xi) * ux + (yp - yi) * uy
    outer = -du + np.sqrt(np.maximum(du ** 2 - ((xp - xi) ** 2 + (yp - yi) ** 2) + ri ** 2, 0))
    rho = np.clip((dist - rp) / np.maximum(outer - rp, 1e-6), 0, 1)
    tex = polar_texture(texture_seed)
    col = ((theta - rotation) % (2 * np.pi)) / (2 * np.pi) * tex.shape[1]
    iris_tex = ndimage.map_coordinates(tex, [rho * (tex.shape[0] - 1), col], order=1, mode="grid-wrap")
    img = 175.0 + 0.05 * (xx - w / 2)
    # Anti-aliased layers (alpha = coverage of each pixel), painted back to front.
    a = np.clip((ri - np.hypot(xx - xi, yy - yi)) / limbus_width + 0.5, 0, 1)
    img = img * (1 - a) + (105.0 + 22.0 * iris_tex) * a
    a = np.clip(rp - dist + 0.5, 0, 1)
    img = img * (1 - a) + 30.0 * a
    if eyelid is not None:
        a = np.clip(eyelid + 0.004 * (xx - xi) ** 2 - yy + 0.5, 0, 1)
        img = img * (1 - a) + (185.0 + 0.03 * (xx - w / 2)) * a
    if spot is not None:
        sx, sy, sr = spot
        a = np.clip(sr - np.hypot(xx - xp - sx, yy - yp - sy) + 0.5, 0, 1)
        img = img * (1 - a) + 255.0 * a
    img = img + np.random.default_rng(noise_seed).normal(0, noise, size=img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def circle_error(found, truth) -> float:
    return float(np.abs(np.subtract(found, truth)).max())


# --------------------------------------------------------------------------- segmentation
# Tolerances: the refinement searches whole pixels of centre and radius, and Canny puts an anti-aliased
# boundary's edge within half a pixel of it, so a clean circle is found within ~1 px.  The pupil boundary is
# fully visible: 2 px.  The limbus votes only with its left and right thirds (eyelids must not vote) and its
# top is under the eyelid, so its vertical position is the least constrained: 3 px.
@pytest.mark.parametrize("pupil, iris, eyelid", [
    (PUPIL, IRIS, 50.0),                                   # pupil slightly off-centre, lid over the top
    ((150.0, 125.0, 25.0), (155.0, 118.0, 110.0), 40.0),   # small pupil, large iris
    ((170.0, 110.0, 55.0), (165.0, 115.0, 90.0), 35.0),    # dilated pupil, small iris
    ((140.0, 130.0, 30.0), (150.0, 120.0, 120.0), None),   # no eyelid, iris almost as tall as the image
])
def test_segmentation_recovers_known_circles(pupil, iris, eyelid):
    for seed in range(2):
        img = render_eye(pupil=pupil, iris=iris, eyelid=eyelid, texture_seed=seed + 3, noise_seed=seed)
        seg = segment_iris(img)
        assert seg.ok, seg.reason
        assert circle_error(seg.pupil, pupil) <= 2.0, (seg.pupil, pupil)
        assert circle_error(seg.iris, iris) <= 3.0, (seg.iris, iris)


def test_a_large_specular_spot_does_not_derail_the_pupil():
    # A reflection of radius 9 px straddling the pupil's centre makes a strong small circle of edges;
    # it is filled before edge detection.
    img = render_eye(spot=(0.0, 0.0, 9.0))
    seg = segment_iris(img)
    assert circle_error(seg.pupil, PUPIL) <= 2.0 and circle_error(seg.iris, IRIS) <= 3.0


def test_eyelid_margin_is_found_and_absent_when_there_is_none():
    seg = segment_iris(render_eye(eyelid=50.0))
    assert seg.upper_lid is not None and seg.lower_lid is None
    x0, y0, a = seg.upper_lid
    # The margin is y = 50 + 0.004 (x − 160)²: the apex within 2 px, the curve within 3 px over the iris.
    xs = np.linspace(100, 220, 7)
    assert np.abs(y0 + a * (xs - x0) ** 2 - (50 + 0.004 * (xs - 160) ** 2)).max() <= 3.0
    for seed in range(3):
        open_eye = segment_iris(render_eye(eyelid=None, texture_seed=seed, noise_seed=seed))
        assert open_eye.upper_lid is None and open_eye.lower_lid is None


def test_scales_with_the_image_size():
    img = np.kron(render_eye(), np.ones((2, 2), np.uint8))    # 640×480: radii in pixels double
    seg = segment_iris(img)
    # Centres of 2×2 blocks: x' = 2x + 0.5.
    assert circle_error(seg.pupil, (2 * PUPIL[0] + 0.5, 2 * PUPIL[1] + 0.5, 2 * PUPIL[2])) <= 3.0
    assert circle_error(seg.iris, (2 * IRIS[0] + 0.5, 2 * IRIS[1] + 0.5, 2 * IRIS[2])) <= 5.0


def test_light_defects_do_not_move_the_circles():
    # 0.1 % stuck pixels (half dark, half saturated) — far more than a sensor gathers in years.
    img = render_eye()
    rng = np.random.default_rng(5)
    hit = rng.random(img.shape) < 0.001
    img[hit] = rng.choice(np.array([0, 255], np.uint8), size=int(hit.sum()))
    seg = segment_iris(img)
    assert circle_error(seg.pupil, PUPIL) <= 2.0 and circle_error(seg.iris, IRIS) <= 3.0


def _finite_segmentation(seg: Segmentation) -> None:
    assert isinstance(seg, Segmentation)
    assert np.isfinite(seg.pupil).all() and np.isfinite(seg.iris).all()
    assert seg.pupil[2] > 0 and seg.iris[2] > 0


@pytest.mark.parametrize("case", ["zeros", "saturated", "noise", "stuck5", "tiny", "float_nan"])
def test_never_crashes(case):
    rng = np.random.default_rng(0)
    if case == "zeros":
        img = np.zeros((240, 320), np.uint8)
    elif case == "saturated":
        img = np.full((240, 320), 255, np.uint8)
    elif case == "noise":
        img = rng.integers(0, 256, (240, 320)).astype(np.uint8)
    elif case == "stuck5":   # 5 % of the pixels stuck at 0 or 255
        img = render_eye()
        hit = rng.random(img.shape) < 0.05
        img[hit] = rng.choice(np.array([0, 255], np.uint8), size=int(hit.sum()))
    elif case == "tiny":
        img = np.full((16, 16), 7, np.uint8)
    else:
        img = render_eye().astype(np.float64) / 255
        img[:10] = np.nan
    seg = segment_iris(img)
    _finite_segmentation(seg)
    if case in ("zeros", "saturated", "tiny"):
        assert not seg.ok and seg.reason
    texture, mask = normalise(img, seg)
    assert texture.shape == (20, 240) and mask.shape == (20, 240)
    assert np.isfinite(texture).all()


def test_ten_bit_images_behave_like_eight_bit_ones():
    # A 10-bit sensor's uint16 frame (×4): same circles, same mask (the reflection threshold follows the data's
    # bit depth, not uint16's 65535).
    img = render_eye(spot=(PUPIL[2] + 4.0, 0.0, 6.0))
    wide = img.astype(np.uint16) * 4
    seg8, seg10 = segment_iris(img), segment_iris(wide)
    # Same circles, lids and verdict; the quality (a mean of ratios computed in float32 from x/255 and
    # 4x/1023) may differ in its last digits.
    assert replace(seg8, quality=0.0) == replace(seg10, quality=0.0)
    assert seg8.quality == pytest.approx(seg10.quality, abs=1e-6)
    assert np.array_equal(normalise(img, seg8)[1], normalise(wide, seg10)[1])


def test_to_dict_is_json_ready():
    seg = segment_iris(render_eye())
    d = json.loads(json.dumps(seg.to_dict()))
    assert d["pupil"] == list(seg.pupil) and d["iris"] == list(seg.iris) and d["ok"] is True
    assert len(d["upper_lid"]) == 3 and d["lower_lid"] is None


# --------------------------------------------------------------------------- normalisation
def test_normalise_shapes_and_types():
    img = render_eye()
    seg = segment_iris(img)
    texture, mask = normalise(img, seg)
    assert texture.shape == mask.shape == (20, 240)
    assert texture.dtype == np.float32 and mask.dtype == bool
    texture, mask = normalise(img, seg, radial=32, angular=128)
    assert texture.shape == mask.shape == (32, 128)
    # Grey values stay in the image's units: the iris is ~105 ± 22.
    assert 80 < float(np.median(texture[mask])) < 130


def test_mask_excludes_eyelid_and_specular_spot():
    # A reflection straddling the pupil margin (centre 4 px outside the pupil, radius 6) reaches the iris.
    img = render_eye(spot=(PUPIL[2] + 4.0, 0.0, 6.0))
    seg = segment_iris(img)
    _texture, mask = normalise(img, seg)
    y, x = sample_grid(seg)
    lid = y < 50 + 0.004 * (x - IRIS[0]) ** 2
    spot = np.hypot(x - (PUPIL[0] + PUPIL[2] + 4.0), y - PUPIL[1]) <= 6.5
    assert lid.sum() > 200 and spot.sum() > 10
    assert not mask[lid].any(), "eyelid samples left usable"
    assert not mask[spot].any(), "specular samples left usable"
    # Away from both (beyond the dilation margins), almost everything is kept.
    lid_far = y > 50 + 0.004 * (x - IRIS[0]) ** 2 + 8
    spot_far = np.hypot(x - (PUPIL[0] + PUPIL[2] + 4.0), y - PUPIL[1]) > 12
    assert mask[lid_far & spot_far].mean() > 0.97


def test_grey_level_occlusion_is_masked_without_an_eyelid_margin():
    # With a hand-made segmentation (no eyelid parabola), the bright lid is still found in the band.
    img = render_eye()
    seg = Segmentation(pupil=PUPIL, iris=IRIS)
    _texture, mask = normalise(img, seg)
    y, x = sample_grid(seg)
    lid = y < 50 + 0.004 * (x - IRIS[0]) ** 2
    assert (~mask[lid]).mean() > 0.95
    assert mask[~lid].mean() > 0.9


@pytest.mark.parametrize("k", [5, -7, 17])
def test_rotating_the_eye_shifts_the_texture_by_whole_columns(k):
    seg = Segmentation(pupil=PUPIL, iris=IRIS)
    base, mask0 = normalise(render_eye(eyelid=None, spot=None, noise_seed=1), seg)
    turned, mask1 = normalise(render_eye(eyelid=None, spot=None, noise_seed=2, rotation=2 * np.pi * k / 240), seg)
    corr = {}
    for s in range(-24, 25):
        rolled = np.roll(base, s, axis=1)
        both = mask1 & np.roll(mask0, s, axis=1)
        corr[s] = np.corrcoef(rolled[both], turned[both])[0, 1]
    best = max(corr, key=corr.get)
    assert best == k
    assert corr[k] > 0.95           # the same pattern up to noise and bilinear interpolation
    assert corr[0] < 0.8


def test_samples_outside_the_image_are_masked():
    # An iris cut by the left border of the image.
    seg = Segmentation(pupil=(40.0, 120.0, 30.0), iris=(40.0, 120.0, 90.0))
    img = render_eye(pupil=seg.pupil, iris=seg.iris, eyelid=None, spot=None)
    texture, mask = normalise(img, seg)
    y, x = sample_grid(seg)
    outside = (x < 0) | (x > 319) | (y < 0) | (y > 239)
    assert outside.sum() > 100
    assert not mask[outside].any()
    assert mask[~outside].mean() > 0.9
    assert np.isfinite(texture).all()


# --------------------------------------------------------------------------- Segmenter
def test_segmenter_caches_one_image():
    seg = Segmenter()
    img = render_eye()
    t1, m1, s1 = seg.unwrap(img)
    t2, _m2, s2 = seg.unwrap(img.copy())          # same pixels, another array: a cache hit
    assert seg.computed == 1 and s1 == s2 and np.array_equal(t1, t2)
    assert not t1.flags.writeable and not m1.flags.writeable
    t3, _, s3 = seg.unwrap(img, radial=30, angular=360)   # another band size: same segmentation
    assert seg.computed == 1 and s3 == s1 and t3.shape == (30, 360)
    other = render_eye(texture_seed=9, noise_seed=9)
    seg.unwrap(other)
    assert seg.computed == 2
    seg.unwrap(img)                               # one entry only: the first image is segmented again
    assert seg.computed == 3
    # The same bytes with another shape or dtype are another image.
    assert Segmenter.image_key(img) != Segmenter.image_key(img.reshape(320, 240))
    assert Segmenter.image_key(img) != Segmenter.image_key(img.view(np.int8))


def test_segmenter_passes_its_parameters():
    img = render_eye()
    narrow = Segmenter(segment_params={"iris_ratio": (1.5, 2.0)}, normalise_params={"reflection": 0.5})
    _texture, mask, seg = narrow.unwrap(img)
    # The limbus (radius 100, 2.6 pupil radii) was looked for within 2 pupil radii only: not found there.
    assert seg.iris[2] <= 2.0 * seg.pupil[2] + 1e-6 or not seg.ok
    assert circle_error(segment_iris(img).iris, IRIS) <= 3.0
    # reflection 0.5 × 255 masks everything brighter than 127: most of the iris's light half.
    assert mask.mean() < normalise(img, seg)[1].mean()


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), (4.0, -3.0, 5.0), (-6.0, 5.0, -6.0)])
def test_coarse_to_fine_circle_search_finds_the_exhaustive_optimum(offset):
    # polar_fit's coarse-to-fine search scores every second centre and radius and then the full grid around
    # the best coarse circles; on an eye whose limbus score has one clear peak it must land on exactly the
    # circle the exhaustive search finds (the same bits: a circle's score does not depend on the grid it is
    # scored in), from any start within the window.
    from forensics.impact.segment.boundary import polar_fit
    from forensics.impact.segment.caht import LIMBUS_ARCS

    smooth = ndimage.gaussian_filter(render_eye(eyelid=None, spot=None).astype(np.float32) / 255, 1.0)
    start = (IRIS[0] + offset[0], IRIS[1] + offset[1], IRIS[2] + offset[2])
    fast = polar_fit(smooth, start, LIMBUS_ARCS)
    full = polar_fit(smooth, start, LIMBUS_ARCS, coarse=0)
    assert fast == full
    assert circle_error(fast[0], IRIS) < 1.5


@pytest.mark.parametrize("size", [3, 5])
def test_the_square_growth_of_masks_is_the_binary_dilation(size):
    # The rubber sheet grows reflections (5 × 5) and occlusions (3 × 3) by running maxima instead of a binary
    # dilation: the same pixels, edges included (nothing beyond them), on sparse and dense random masks.
    from forensics.impact.segment.morphology import grow_square

    rng = np.random.default_rng(size)
    for density in (0.002, 0.05, 0.5):
        mask = rng.random((61, 83)) < density
        mask[0, 5] = mask[-1, -1] = True                       # at the edges
        for m in (mask, np.flip(mask, 0)):                      # a flipped (negative-stride) view too
            want = ndimage.binary_dilation(m, structure=np.ones((size, size), bool), border_value=0)
            assert np.array_equal(grow_square(m, size), want)


def test_disc_morphology_is_scipys_binary_morphology():
    # CAHT's dark map is opened by a disc and its holes filled, reflections grow by a disc: the row-run forms
    # (forensics.impact.segment.morphology) give scipy's pixels, edges included, for discs of radius 1-5, a cross,
    # a rectangle and (by falling back) a structure that is not symmetric, on sparse and dense random masks and
    # negative-stride views.
    from skimage.morphology import disk

    from forensics.impact.segment.morphology import fill_holes, grow, opening, shrink

    rng = np.random.default_rng(7)
    structures = [disk(r).astype(bool) for r in range(1, 6)] + [
        ndimage.generate_binary_structure(2, 1), np.ones((3, 5), bool),
        np.array([[1, 1, 0], [0, 1, 0], [0, 1, 1]], bool)]
    for density in (0.01, 0.2, 0.6, 0.9):
        mask = rng.random((47, 71)) < density
        mask[0, 3] = mask[-1, -1] = True
        for m in (mask, np.flip(mask, 0)):
            for st in structures:
                assert np.array_equal(grow(m, st), ndimage.binary_dilation(m, structure=st))
                assert np.array_equal(shrink(m, st), ndimage.binary_erosion(m, structure=st))
                assert np.array_equal(opening(m, st), ndimage.binary_opening(m, structure=st))
            assert np.array_equal(fill_holes(m), ndimage.binary_fill_holes(m))
    # A dark map with a hole (a pupil with a reflection) and a region touching the edge.
    ring = np.zeros((40, 40), bool)
    ring[5:20, 5:20], ring[9:12, 9:12], ring[30:, 30:] = True, False, True
    assert np.array_equal(fill_holes(ring), ndimage.binary_fill_holes(ring)) and fill_holes(ring)[10, 10]


def test_the_row_medians_are_numpys_nanmedian_bit_for_bit():
    # The occlusion mask's per-row medians over angle: numpy's sort-and-halve method without the masked arrays,
    # on float32 rows of the rubber sheets' widths with NaN holes, empty rows, odd and even counts and ties.
    from forensics.impact.segment.normalise import _row_medians

    rng = np.random.default_rng(11)
    for width in (240, 360, 512, 516, 7):
        values = rng.normal(100, 20, (40, width)).astype(np.float32)
        values[::3] = np.round(values[::3] / 8) * 8                     # ties
        values[rng.random(values.shape) < rng.uniform(0, 1, (40, 1))] = np.nan
        values[5], values[6, 1:] = np.nan, np.nan                        # empty, and one number
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            want = np.nanmedian(values, axis=1, keepdims=True)
        got = _row_medians(values)
        assert got.dtype == want.dtype and np.array_equal(got, want, equal_nan=True)



def test_a_reflection_is_found_whatever_the_exposure_and_black_level():
    # an eye-like image spanning 0 … 1 with one small saturated reflection: the mask is the same after a change of
    # exposure and black level (0.8 × grey + 0.08, as 20 grey levels at 8 bits) — at a fixed 0.9 of full scale the
    # reflection (0.88 after the change) was no longer found at all
    from forensics.impact.segment.common import reflection_mask

    yy, xx = np.mgrid[0:240, 0:320]
    img = np.full((240, 320), 0.55, np.float32)
    img[np.hypot(xx - 160, yy - 120) < 90] = 0.35          # iris
    img[np.hypot(xx - 160, yy - 120) < 35] = 0.0           # pupil
    img[np.hypot(xx - 150, yy - 110) < 4] = 1.0            # the illuminator's reflection, on the pupil's edge
    mask = reflection_mask(img)
    assert mask[110, 150] and mask.sum() < 0.013 * img.size * 4
    dimmer = (0.8 * img + 0.08).astype(np.float32)
    assert np.array_equal(reflection_mask(dimmer), mask)
