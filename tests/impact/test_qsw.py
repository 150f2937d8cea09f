"""Ma et al.'s key local variations (USIT ``qsw``): the properties its published description implies."""
from __future__ import annotations

import numpy as np
import pytest

from forensics._shared.errors import UsageError
from forensics.impact.qsw import QswMatcher, dyadic_wavelet

N = 512


def smooth_texture(seed: int, shape=(64, N)) -> np.ndarray:
    """A random iris-like texture (smooth along both axes, circular along the angle), grey levels ~ 100 ± 20."""
    from scipy import ndimage

    t = np.random.default_rng(seed).normal(size=shape)
    t = ndimage.gaussian_filter(t, sigma=(1.5, 3.0), mode=("nearest", "wrap"))
    return (100 + 20 * t / t.std()).astype(np.float32)


def test_the_wavelet_is_a_smoothed_derivative_centred_on_the_variation():
    n = np.arange(N)
    flat = dyadic_wavelet(np.full((1, N), 7.0), (3, 4))
    assert np.abs(flat).max() < 1e-12                                 # no variation, no response
    # A bump: W rises to its maximum on the bump's rising flank and falls to its minimum on the falling one,
    # symmetrically about the bump (the filters' delay is compensated).
    x = np.exp(-0.5 * ((n - 256) / 10.0) ** 2) + 0.05 * np.cos(2 * np.pi * (n - 256) / N)
    w = dyadic_wavelet(x[None], (3, 4))[:, 0]
    for k in range(2):
        assert np.allclose(w[k][256 - 100:256 + 101], -w[k][256 + 100:256 - 101:-1], atol=1e-12)
        assert 240 <= np.argmax(w[k]) < 256 < np.argmin(w[k]) <= 272
    # Linear and shift-equivariant (circular).
    y = np.random.default_rng(1).normal(size=(2, N))
    wy = dyadic_wavelet(y, (3, 4))
    assert np.allclose(dyadic_wavelet(2 * y[:1] - y[1:], (3, 4))[:, 0], 2 * wy[:, 0] - wy[:, 1])
    assert np.allclose(dyadic_wavelet(np.roll(y, 37, axis=1), (3, 4)), np.roll(wy, 37, axis=2))
    with pytest.raises(UsageError, match="scale"):
        dyadic_wavelet(y, (9,))


def test_bits_are_one_from_a_minimum_to_the_next_maximum():
    # Ma et al.'s binary sequence: 1 where the transform rises (minimum → maximum), 0 where it falls.  Around
    # a bump the transform rises to its maximum on the rising flank, falls to its minimum on the falling
    # flank and rises again: the zeros are exactly the samples from the maximum to the minimum, centred on
    # the bump.  (Far from the bump the transform is flat to rounding and its bits are arbitrary.)
    n = np.arange(N)
    x = np.exp(-0.5 * ((n - 256) / 10.0) ** 2)
    texture = np.tile(x.astype(np.float32), (64, 1))
    code = QswMatcher().encode_texture(texture, np.ones((64, N), bool))
    bits, mask = code.unpack()
    assert mask.all() and bits.shape == (N, 20) and code.n_bits == 10240
    w = dyadic_wavelet(x[None], (3, 4))[:, 0]
    window = np.arange(206, 306)
    for k in range(2):
        top, bottom = int(np.argmax(w[k])), int(np.argmin(w[k]))
        assert (top + bottom) / 2 == 256 and 240 <= top < 256
        falling = window[~bits[window, 10 * k]]                       # every signal of a scale is the same here
        assert np.array_equal(falling, np.arange(top, bottom))
        assert (bits[window, 10 * k:10 * k + 10] == bits[window, 10 * k:10 * k + 1]).all()


def test_a_rotation_of_the_texture_is_an_exact_shift_of_the_code():
    matcher = QswMatcher()
    t = smooth_texture(3)
    m = np.ones(t.shape, bool)
    m[40:, 100:180] = False                                           # an eyelid: the mask rotates too
    code = matcher.encode_texture(t, m)
    for k in (1, 17, -5):
        rolled = matcher.encode_texture(np.roll(t, k, axis=1), np.roll(m, k, axis=1))
        shifted = code.shifted(k)
        assert np.array_equal(rolled.bits, shifted.bits) and np.array_equal(rolled.mask, shifted.mask)
        assert matcher.compare(code, rolled) == (0.0 if abs(k) <= matcher.max_shift else matcher.compare(code, rolled))
    assert matcher.compare(code, code.shifted(matcher.max_shift + 8)) > 0.3   # beyond the search range


def test_code_statistics_rising_and_falling_balance():
    # On iris-like texture the transform rises as often as it falls, and two unrelated textures disagree on
    # half of the bits at any shift (10,240 bits, neighbours correlated over ~the filter length: the
    # unshifted distance is within ±0.04 of 0.5).
    matcher = QswMatcher(max_shift=0)
    m = np.ones((64, N), bool)
    codes = [matcher.encode_texture(smooth_texture(s), m) for s in range(4)]
    for c in codes:
        bits, _ = c.unpack()
        assert 0.45 < bits.mean() < 0.55
    d = [matcher.compare(codes[i], codes[j]) for i in range(4) for j in range(i + 1, 4)]
    assert all(abs(x - 0.5) < 0.04 for x in d), d


def test_only_the_fifty_rows_nearest_the_pupil_are_used_and_masks_follow_the_majority():
    matcher = QswMatcher()
    t = smooth_texture(5)
    m = np.ones(t.shape, bool)
    base = matcher.encode_texture(t, m)
    t2 = t.copy()
    t2[50:] = 0.0                                                     # rows 50–63: outside the ten signals
    assert np.array_equal(matcher.encode_texture(t2, m).bits, base.bits)
    m2 = m.copy()
    m2[0:3, 200:210] = False                                          # 3 of signal 0's 5 rows: masked there
    m2[5:7, 300:310] = False                                          # 2 of signal 1's 5 rows: still valid
    _, mask = matcher.encode_texture(t, m2).unpack()
    assert not mask[200:210, 0].any() and not mask[200:210, 10].any()  # both scales of signal 0
    assert mask[300:310, 1].all() and mask[:, 2:10].all() and mask[:200, 0].all()


def test_layouts_that_do_not_fit_are_refused():
    with pytest.raises(UsageError, match="do not fit"):
        QswMatcher(signals=14)
    with pytest.raises(UsageError, match="scale"):
        QswMatcher(angular=32, scales=(5,))
