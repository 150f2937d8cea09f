"""Monro et al.'s DCT code (USIT ``dct``/``dctc``): the properties its published description implies."""
from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy import ndimage

from forensics._shared.errors import InputError, UsageError
from forensics.impact.dct import DctMatcher, patch_coefficients

SHAPE = (64, 516)


def smooth_texture(seed: int, shape=SHAPE) -> np.ndarray:
    t = np.random.default_rng(seed).normal(size=shape)
    t = ndimage.gaussian_filter(t, sigma=(1.5, 3.0), mode=("nearest", "wrap"))
    return (100 + 20 * t / t.std()).astype(np.float32)


ALL = np.ones(SHAPE, bool)


def test_patches_tile_the_circle_and_code_coefficient_increases():
    coeffs, usable = patch_coefficients(smooth_texture(0), ALL)
    assert coeffs.shape == (3, 12, 86) and usable.all()              # 516 / 6 = 86 patches, 12 patch rows
    # A texture that only varies along the radius: every patch row holds identical patches, so no
    # coefficient ever increases from one patch to the next and every bit is 0.
    radial = np.repeat(np.linspace(50, 150, 64, dtype=np.float32)[:, None], SHAPE[1], axis=1)
    code = DctMatcher().encode_texture(radial, ALL)
    for plane in code.codes[0]:
        bits, mask = plane.unpack()
        assert mask.all() and not bits.any()
    # Brightness growing along the angle (a ramp with one drop where it wraps): the DC coefficient
    # increases from patch to patch everywhere but next to the drop.  In the slanted patches the drop of
    # band row y (0 … 51) sits y columns further along, so only patches over columns 0 … 51 (the first 9)
    # and the last one, which reaches them, see it.
    ramp = np.tile(np.arange(SHAPE[1], dtype=np.float32) / 4, (64, 1))
    dc_bits, _ = DctMatcher().encode_texture(ramp, ALL).codes[0][0].unpack()
    assert dc_bits[9:84].all() and not dc_bits.all()


def test_patches_are_slanted_by_45_degrees():
    # A line at 45° (one column back along the angle per row outwards) lies along the slanted patches: in
    # every patch row it touches only the 2 half-overlapping patches over it.  The other diagonal crosses
    # the patches and touches 4–5 per patch row.
    rows = np.arange(3, 55)

    def touched(direction: int) -> np.ndarray:
        t = np.full(SHAPE, 100.0, np.float32)
        t[rows, (200 + direction * (rows - 3)) % SHAPE[1]] = 200.0
        dc = patch_coefficients(t, ALL)[0][0]
        return (np.abs(dc - dc.min()) > 1e-6).sum(axis=1)

    assert (touched(-1) == 2).all()
    assert touched(+1).min() >= 4


def test_a_rotation_by_whole_patches_is_an_exact_shift_and_sub_patch_rotations_are_matched():
    matcher = DctMatcher()
    t = smooth_texture(1)
    m = ALL.copy()
    m[45:, 300:360] = False
    a = matcher.encode_texture(t, m)
    rolled = matcher.encode_texture(np.roll(t, 6, axis=1), np.roll(m, 6, axis=1))
    for planes, rplanes in zip(a.codes, rolled.codes):
        for p, r in zip(planes, rplanes):
            assert np.array_equal(r.bits, p.shifted(1).bits) and np.array_equal(r.mask, p.shifted(1).mask)
    # Every even rotation up to ±(6·max_shift + 4) = ±16 columns is among the rotations compared: distance 0.
    for cols in range(-16, 17, 2):
        b = matcher.encode_texture(np.roll(t, cols, axis=1), np.roll(m, cols, axis=1))
        assert matcher.compare(a, b) == 0.0 == matcher.compare(b, a), cols
    beyond = matcher.encode_texture(np.roll(t, 30, axis=1), np.roll(m, 30, axis=1))
    assert matcher.compare(a, beyond) > 0.2


def _plane_hd(p, q) -> float:
    """Masked fractional Hamming distance from unpacked bits (independent of the bit-packed helpers)."""
    pb, pm = p.unpack()
    qb, qm = q.unpack()
    both = pm & qm
    return float((pb ^ qb)[both].sum() / both.sum())


def test_distance_is_the_product_of_sum_minimised_over_rotations():
    matcher = DctMatcher()
    a, b = (matcher.encode_texture(smooth_texture(s), ALL) for s in (2, 3))
    expected = 1.0
    for (ka, kb), q in itertools.product([(0, 0), (1, 0), (2, 0), (0, 1), (0, 2)], range(-2, 3)):
        hds = [_plane_hd(pa, pb.shifted(q)) for pa, pb in zip(a.codes[ka], b.codes[kb])]
        expected = min(expected, float(np.prod(hds) ** (1 / 3)))
    assert matcher.compare(a, b) == pytest.approx(expected, abs=1e-12)
    assert matcher.compare(a, b) == matcher.compare(b, a)            # the rotation set is symmetric
    # Unrelated textures: each plane's bits disagree about half the time (3 × 1,032 bits); the best of 25
    # rotations takes the geometric mean to ≈ 0.45.
    assert 0.4 < matcher.compare(a, b) < 0.5


def test_templates_of_another_layout_are_refused():
    a = DctMatcher().encode_texture(smooth_texture(4), ALL)
    other = DctMatcher(coefficients=(1, 2)).encode_texture(smooth_texture(4), ALL)
    with pytest.raises(InputError, match="layout"):
        DctMatcher().compare(a, other)
    with pytest.raises(InputError, match="dct templates"):
        DctMatcher().compare_all([a], [np.zeros(3)])
    with pytest.raises(UsageError, match="whole number of patch steps"):
        DctMatcher(angular=512)
    with pytest.raises(UsageError, match="coefficients"):
        DctMatcher(coefficients=(0, 9))
