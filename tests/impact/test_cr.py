"""Rathgeb and Uhl's local intensity variations (USIT ``cr``): the properties its published description implies."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from forensics._shared.errors import UsageError
from forensics.impact.cr import CrMatcher, pixel_paths, smooth_paths

SHAPE = (64, 512)
ALL = np.ones(SHAPE, bool)


def smooth_texture(seed: int, shape=SHAPE) -> np.ndarray:
    t = np.random.default_rng(seed).normal(size=shape)
    t = ndimage.gaussian_filter(t, sigma=(1.5, 3.0), mode=("nearest", "wrap"))
    return (100 + 20 * t / t.std()).astype(np.float32)


def stepwise_paths(values: np.ndarray, start: int = 1) -> np.ndarray:
    """The published rule, one column at a time: move up or down only to a value strictly greater than
    both other candidates, else stay."""
    n_paths, _, n_cols = values.shape
    rows = np.empty((n_paths, n_cols), int)
    for p in range(n_paths):
        r = start
        rows[p, 0] = r
        for j in range(1, n_cols):
            col = values[p, :, j]
            same = col[r]
            up = col[r - 1] if r > 0 else -np.inf
            down = col[r + 1] if r < 2 else -np.inf
            if up > same and up > down:
                r -= 1
            elif down > same and down > up:
                r += 1
            rows[p, j] = r
    return rows


def test_the_vectorised_paths_follow_the_stepwise_rule():
    rng = np.random.default_rng(0)
    values = rng.normal(size=(6, 3, 200))
    assert np.array_equal(pixel_paths(values), stepwise_paths(values))
    ties = rng.integers(0, 3, size=(6, 3, 200)).astype(float)        # ties: the path stays
    assert np.array_equal(pixel_paths(ties), stepwise_paths(ties))


def test_light_and_dark_paths_follow_bright_and_dark_structures():
    matcher = CrMatcher()
    t = smooth_texture(1) * 0.2 + 80
    t[1::3, 100:300] += 60.0                                          # a bright ridge in every stripe's middle row
    t[2::3, 100:300] -= 60.0                                          # a dark groove in every bottom row
    rows, valid = matcher.paths(t, ALL)
    assert rows.shape == (2, 21, 512) and valid.all()
    light, dark = rows
    # (Stripe 0 borders the pupil, where the 3 × 3 smoothing reflects the ridge into row 0: left out.)
    assert (light[1:, 110:290] == 1).all()                            # the light path rides the ridge
    # The dark path never climbs onto the ridge: it stays in the groove, or in the top row if it was there
    # when the ridge began (one row per step: it cannot cross the ridge).
    assert (dark[1:, 110:290] != 1).all() and (dark[1:, 150:290] == 2).mean() > 0.4
    assert (light[0, 110:290] == 1).mean() > 0.9


def test_smoothing_flattens_short_excursions_only():
    # USIT's two passes: a one-sample excursion (first pass), then up to three samples between two equal
    # samples four apart (second pass); anything longer is a real variation and stays.
    paths = np.array([
        [1, 1, 2, 1, 1, 1, 1, 1, 1, 1],                               # one sample
        [1, 1, 2, 2, 1, 1, 1, 1, 1, 1],                               # two samples
        [1, 1, 2, 2, 2, 1, 1, 1, 1, 1],                               # three samples
        [1, 1, 2, 2, 2, 2, 1, 1, 1, 1],                               # four samples: kept
        [0, 0, 0, 1, 2, 2, 2, 2, 2, 2],                               # a step: kept
    ])
    out = smooth_paths(paths)
    assert (out[:3] == 1).all()
    assert np.array_equal(out[3:], paths[3:])
    assert np.array_equal(paths[1], [1, 1, 2, 2, 1, 1, 1, 1, 1, 1])  # the input is not modified


def test_code_counts_rows_of_difference_and_is_balanced():
    # Rows 0, 1, 2 are coded 00, 01, 11: codes of paths one row apart differ in one bit, two rows in two.
    matcher = CrMatcher(max_shift=0)
    code = matcher.encode_texture(smooth_texture(2), ALL)
    bits, mask = code.unpack()
    assert bits.shape == (512, 21 * 2 * 2) and mask.all() and code.n_bits == 43008
    rows, _ = matcher.paths(smooth_texture(2), ALL)
    thermo = np.stack([rows >= 1, rows >= 2]).transpose(3, 0, 1, 2).reshape(512, -1)
    assert np.array_equal(bits, thermo)
    # Light and dark paths spend comparable time in every row: about half the bits are set, and unrelated
    # textures disagree on about half (43,008 bits, correlated along the paths: ±0.05).
    assert 0.4 < bits.mean() < 0.6
    other = matcher.encode_texture(smooth_texture(3), ALL)
    assert abs(matcher.compare(code, other) - 0.5) < 0.05


def test_a_rotation_of_the_texture_is_almost_a_shift_of_the_code():
    # Not exact: a path starts in the middle row at column 0 wherever the eye is turned (it re-joins the
    # rotated path within a few columns), and the equalisation's tiles do not turn with the texture.
    # Measured: under 1 % of the bits for rotations up to the search range; unrelated textures ≈ 0.47.
    matcher = CrMatcher()
    t = smooth_texture(4)
    a = matcher.encode_texture(t, ALL)
    for k in (1, 9, 17):
        assert matcher.compare(a, matcher.encode_texture(np.roll(t, k, axis=1), ALL)) < 0.02
    assert matcher.compare(a, matcher.encode_texture(np.roll(t, 60, axis=1), ALL)) > 0.4


def test_masks_follow_the_majority_of_a_stripe_column():
    m = ALL.copy()
    m[0:2, 50:60] = False                                             # 2 of stripe 0's 3 rows: masked
    m[3:4, 70:80] = False                                             # 1 of stripe 1's 3 rows: valid
    _, valid = CrMatcher().paths(smooth_texture(5), m)
    assert not valid[0, 50:60].any() and valid[1, 70:80].all() and valid[:, :50].all()
    with pytest.raises(UsageError, match="3"):
        CrMatcher(stripe=4)
