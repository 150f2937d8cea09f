"""Exact Hamming counts by cross-correlation (:mod:`forensics.impact.spectral`): equal to counting bits.

The fast comparison of ``cr``, ``qsw`` and Masek must give the pairwise loop's distances bit for bit: every count
at every shift is checked against popcounts of the rolled codes, and every distance against
:func:`~forensics.impact.iriscode.hamming_distance`, on random codes (odd and even column counts, holes, almost
empty codes, chunked), on each matcher's own codes (its mask grouping in force) and on real eyes where
``../shared`` has them.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from forensics.impact import spectral
from forensics.impact.cr import CrMatcher
from forensics.impact.iriscode import IrisCode, hamming_all, hamming_all_spectral, hamming_distance
from forensics.impact.masek import MasekMatcher
from forensics.impact.qsw import QswMatcher

IITD = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "iitd-iris-001-040"
MATCHERS = {"cr": CrMatcher, "qsw": QswMatcher, "masek": MasekMatcher}


def random_codes(rng, n, columns, bits_per_column, groups=None):
    """Random codes with holes (an eyelid-like run of columns, drop-outs, every fifth almost empty); with
    ``groups``, bits of a group share their mask bit."""
    g = np.arange(bits_per_column) if groups is None else np.asarray(groups)
    codes = []
    for i in range(n):
        bits = rng.random((columns, bits_per_column)) < 0.5
        mask = (rng.random((columns, g.max() + 1)) < 0.9)[:, g]
        mask[(rng.integers(0, columns) + np.arange(rng.integers(0, columns // 3))) % columns] = False
        if i % 5 == 3:
            mask &= (rng.random((columns, g.max() + 1)) < 0.05)[:, g]
        codes.append(IrisCode.from_bits(bits, mask))
    return codes


def popcounts(a: IrisCode, b: IrisCode, s: int) -> tuple[int, int]:
    m = a.mask & np.roll(b.mask, s, axis=0)
    return (int(np.bitwise_count((a.bits ^ np.roll(b.bits, s, axis=0)) & m).sum()), int(np.bitwise_count(m).sum()))


@pytest.mark.parametrize("columns, bits, groups", [(45, 13, None), (64, 12, np.repeat(np.arange(4), 3)),
                                                   (32, 6, np.tile(np.arange(3), 2))])
def test_counts_at_every_shift_equal_popcounts(columns, bits, groups):
    rng = np.random.default_rng(columns)
    a = random_codes(rng, 7, columns, bits, groups)
    b = random_codes(rng, 6, columns, bits, groups)
    max_shift = 5
    seen = np.zeros((7, 6), int)
    # A small memory budget splits both sides into several blocks.
    for rows, cols, diff, valid in spectral.shift_counts(a, b, max_shift, groups, memory=2**16):
        assert diff is not None and valid is not None
        for i in range(rows.start, rows.stop):
            for j in range(cols.start, cols.stop):
                seen[i, j] += 1
                for k, s in enumerate(range(-max_shift, max_shift + 1)):
                    assert (diff[k, i - rows.start, j - cols.start], valid[k, i - rows.start, j - cols.start]) == \
                        popcounts(a[i], b[j], s), (i, j, s)
    assert (seen == 1).all()


def test_distances_equal_the_loop_even_where_the_groups_do_not_hold():
    # Codes whose masks ignore the groups (made by hand, not by the matcher) are correlated bit by bit.
    rng = np.random.default_rng(3)
    groups = np.repeat(np.arange(5), 2)
    a, b = random_codes(rng, 6, 40, 10), random_codes(rng, 5, 40, 10)
    layout = spectral._group_layout(groups, 10)
    assert not spectral._groups_hold(a, layout)
    loop = np.array([[hamming_distance(x, y, 6, 30) for y in b] for x in a])
    assert np.array_equal(hamming_all_spectral(a, b, 6, 30, groups), loop)
    assert (loop == 1.0).any()                     # some pairs had too few valid bits at every shift


def test_a_block_not_within_the_rounding_tolerance_is_counted_bit_by_bit(monkeypatch):
    rng = np.random.default_rng(4)
    a, b = random_codes(rng, 5, 30, 7), random_codes(rng, 4, 30, 7)
    loop = np.array([[hamming_distance(x, y, 3, 20) for y in b] for x in a])
    monkeypatch.setattr(spectral, "_TOLERANCE", -1.0)     # no block passes the guard
    assert all(d is None for _, _, d, _ in spectral.shift_counts(a, b, 3))
    assert np.array_equal(hamming_all_spectral(a, b, 3, 20), loop)


def _texture(seed: int, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = ndimage.gaussian_filter(rng.normal(size=shape), sigma=(1.5, 3.0), mode=("nearest", "wrap"))
    mask = np.ones(shape, bool)
    mask[:, int(rng.integers(0, shape[1])):][:, :int(rng.integers(0, shape[1] // 4))] = False    # an eyelid
    mask[int(shape[0] * rng.uniform(0.6, 1.0)):] = False                                        # lashes, outer ring
    return (100 + 20 * t / t.std()).astype(np.float32), mask


@pytest.mark.parametrize("name", list(MATCHERS))
def test_each_matchers_comparison_equals_the_pairwise_loop_with_its_mask_groups(name):
    matcher = MATCHERS[name]()
    shape = (matcher.radial, matcher.angular)
    codes = [matcher.encode_texture(*_texture(seed, shape)) for seed in range(8)]
    codes.append(matcher.encode_texture(np.full(shape, 100.0, np.float32), np.zeros(shape, bool)))  # nothing usable
    codes.append(codes[0].shifted(3))
    assert spectral._groups_hold(codes, spectral._group_layout(matcher.mask_groups(), codes[0].bits_per_column))
    loop = np.array([[matcher.compare(x, y) for y in codes] for x in codes])
    fast = matcher.compare_all(codes, codes)
    assert np.array_equal(fast, loop)
    assert np.array_equal(fast, hamming_all(codes, codes, matcher.max_shift, matcher._min_valid_bits(codes[0])))
    assert fast[0, -1] == 0.0 and (fast[-2] == 1.0).all()


@pytest.mark.realdata
def test_real_eyes_cr_qsw_and_masek_distances_equal_the_pairwise_loop():
    if not (IITD / "manifest.csv").is_file():
        pytest.skip(f"the IITD iris images are not at {IITD} (research-use data kept outside the repository)")
    from forensics.impact.segment import Segmenter
    from forensics.io.dataset import open_dataset

    frames = [f for f in open_dataset(IITD).frames if f.subject[:3] in {"021", "022"}][:12]
    images = [f.load() for f in frames]
    seg = Segmenter()
    for cls in MATCHERS.values():
        matcher = cls(seg)
        codes = [matcher.encode(im) for im in images]
        loop = np.array([[matcher.compare(x, y) for y in codes] for x in codes])
        assert np.array_equal(matcher.compare_all(codes, codes), loop), matcher.name
