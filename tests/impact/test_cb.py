"""Rathgeb and Uhl's context-based code (USIT ``cb``/``cbc``): the properties its published description implies."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from forensics._shared.errors import InputError, UsageError
from forensics.impact.cb import CONTEXT, DIRECT, UNCOMPARABLE, CbMatcher, CbTemplate, cell_levels

SHAPE = (64, 512)
ALL = np.ones(SHAPE, bool)


def smooth_texture(seed: int, shape=SHAPE) -> np.ndarray:
    t = np.random.default_rng(seed).normal(size=shape)
    t = ndimage.gaussian_filter(t, sigma=(1.5, 3.0), mode=("nearest", "wrap"))
    return (100 + 20 * t / t.std()).astype(np.float32)


def described_score(a: CbTemplate, b: CbTemplate) -> float:
    """The module's description, cell by cell (no vectorisation, no padding tricks)."""
    rows, cols = a.levels.shape
    la, lb = a.levels.astype(int), b.levels.astype(int)
    valid = a.valid & b.valid

    def state(r, c):                                               # 'match', 'mismatch' or None
        if not 0 <= r < rows:
            return None
        c %= cols
        if not valid[r, c]:
            return None
        return "match" if la[r, c] == lb[r, c] else "mismatch"

    total = 0
    for r in range(rows):
        for c in range(cols):
            s = state(r, c)
            if s == "match":
                count = 0
                for dr, dc in CONTEXT:
                    if state(r + dr, c + dc) == "match":
                        count += 1 + int(la[r + dr, (c + dc) % cols] != la[r, c])
                total += 2 ** (2 + count)
            elif s == "mismatch":
                pen = 0
                for dr, dc in DIRECT:
                    if state(r + dr, c + dc) == "mismatch":
                        rr, cc = r + dr, (c + dc) % cols
                        pen += abs(la[rr, cc] - lb[rr, cc]) + int(la[rr, cc] == la[r, c])
                total -= 2 ** (1 + pen)
    return total / (valid.sum() * 2.0 ** 11)


def random_template(rng, rows=32, cols=64, p_valid=0.9) -> CbTemplate:
    return CbTemplate(rng.integers(0, 3, (rows, cols)).astype(np.uint8), rng.random((rows, cols)) < p_valid)


def test_the_vectorised_comparison_is_the_described_score():
    rng = np.random.default_rng(0)
    base = random_template(rng)
    probes = [random_template(rng)]
    # Mostly agreeing probes exercise the context (and the edges, the wrap and the masks).
    for flip in (0.05, 0.3):
        levels = base.levels.copy()
        change = rng.random(levels.shape) < flip
        levels[change] = rng.integers(0, 3, change.sum())
        probes.append(CbTemplate(levels, rng.random(levels.shape) < 0.95))
    matcher = CbMatcher(min_valid=0.0)
    scores = matcher.compare_all([base, probes[0]], probes)
    for i, a in enumerate([base, probes[0]]):
        for j, b in enumerate(probes):
            assert scores[i, j] == pytest.approx(described_score(a, b), rel=1e-12)
    # Small blocks (one pair at a time) give the same values.
    assert np.array_equal(CbMatcher(min_valid=0.0, block_bytes=1).compare_all([base, probes[0]], probes), scores)


def test_a_flat_code_scores_its_context_exactly():
    # Identical codes of one level: every cell matches, no context cell differs, so a cell's count is the
    # number of its context cells inside the texture: 8 in the middle, 7 one row from an edge, 5 on it.
    flat = CbTemplate(np.ones((32, 64), np.uint8), np.ones((32, 64), bool))
    per_row = 2 * 2 ** (2 + 5) + 2 * 2 ** (2 + 7) + 28 * 2 ** (2 + 8)
    assert CbMatcher().compare(flat, flat) == 64 * per_row / (2048 * 2 ** 11)
    # Agreement in a varied neighbourhood counts more: alternating columns of levels 0 and 2 (every diagonal
    # neighbour differs) score more against themselves than the flat code.
    cols = CbTemplate(np.tile(np.array([0, 2], np.uint8), (32, 32)), np.ones((32, 64), bool))
    assert CbMatcher().compare(cols, cols) > CbMatcher().compare(flat, flat)


def test_cells_take_the_most_frequent_of_three_levels():
    e = np.zeros((2, 16))
    e[:, :8] = [[0.1] * 8, [0.1] * 3 + [0.9] * 5]                   # 11 dark, 5 bright: dark
    e[:, 8:] = [[0.5] * 4 + [0.9] * 4, [0.5] * 4 + [0.9] * 4]       # 8 middle, 8 bright: the darker wins
    assert cell_levels(e, (2, 8)).tolist() == [[0, 1]]
    assert cell_levels(np.array([[0.0, 1 / 3, 2 / 3, 1.0]]), (1, 1)).tolist() == [[0, 1, 2, 2]]
    # After the equalisation the three levels are about equally frequent (each a third of the samples;
    # the majority per cell sharpens this a little): 25–42 % each on an iris-like texture.
    t = CbMatcher().encode_texture(smooth_texture(1), ALL)
    shares = np.bincount(t.levels.ravel(), minlength=3) / t.levels.size
    assert t.levels.shape == (32, 64) and (shares > 0.25).all() and (shares < 0.42).all()


def test_genuine_codes_score_positive_and_unrelated_ones_near_zero():
    # Unrelated codes: matches (+4 … +2^18 each, mostly small: few context cells agree by chance) and
    # mismatches (−2 …) nearly cancel; measured −0.05 … 0.00 over 8 unrelated textures.  The same texture with
    # sensor noise keeps most cells and their context: ≈ 16.
    matcher = CbMatcher()
    a, b = (matcher.encode_texture(smooth_texture(s), ALL) for s in (2, 3))
    noisy = smooth_texture(2) + np.random.default_rng(9).normal(0, 2, SHAPE).astype(np.float32)
    same_eye = matcher.encode_texture(noisy, ALL)
    assert matcher.compare(a, same_eye) > 1.0 > abs(matcher.compare(a, b)) * 10


def test_rotation_compensation_is_optional_and_off_as_published():
    rng = np.random.default_rng(4)
    a = random_template(rng, p_valid=1.0)
    turned = CbTemplate(np.roll(a.levels, 3, axis=1), np.roll(a.valid, 3, axis=1))
    self_score = CbMatcher().compare(a, a)
    assert CbMatcher(max_shift=3).compare(a, turned) == self_score
    assert CbMatcher(max_shift=2).compare(a, turned) < self_score / 4
    assert CbMatcher().compare(a, turned) < self_score / 4


def test_masks_uncomparable_pairs_and_layouts():
    m = ALL.copy()
    m[:, :256] = False
    t = CbMatcher().encode_texture(smooth_texture(5), m)
    assert not t.valid[:, :32].any() and t.valid[:, 32:].all()
    empty = CbTemplate(t.levels, np.zeros_like(t.valid))
    assert CbMatcher().compare(t, empty) == UNCOMPARABLE == -4.0
    with pytest.raises(InputError, match="layout"):
        CbMatcher().compare(t, CbTemplate(t.levels[:, :32], t.valid[:, :32]))
    with pytest.raises(UsageError, match="max_shift"):
        CbMatcher(max_shift=40)
