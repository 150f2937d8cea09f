"""Reuse of comparison scores between byte-identical templates (:mod:`forensics.impact.reuse`).

A toy matcher whose score is asymmetric (``compare(a, b) != compare(b, a)``), so that a score copied or computed
with gallery and probe swapped, or at a wrong position, shows; scores are compared for equality, not to a
tolerance: a copied score must be the very number the comparison gives.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from forensics.impact.experiment import _upper_scores, upper_entries
from forensics.impact.iriscode import IrisCode
from forensics.impact.reuse import (
    ScoredPairs, best_base, fill_pairs, fill_upper, template_digest, unchanged, upper_entries_computed,
)
from forensics.impact.segment import Segmentation


class Skewed:
    """A deterministic, asymmetric score of two small vectors, with a vectorised ``compare_all``."""

    name = "skewed"
    higher_is_similar = False

    def compare(self, a, b):
        return float(np.abs(a - b).sum() + 0.25 * a[0] - 0.5 * b[1])

    def compare_all(self, xs, ys):
        return np.array([[self.compare(a, b) for b in ys] for a in xs])


class SkewedLoop:
    """:class:`Skewed` without ``compare_all`` (the pair-by-pair path)."""

    name, higher_is_similar = "skewed-loop", False
    compare = Skewed.compare


def _templates(rng, n):
    return [rng.normal(size=4) for _ in range(n)]


def _digests(templates):
    return [template_digest(t) for t in templates]


@pytest.mark.parametrize("band", [1, 3, 256])
@pytest.mark.parametrize("protocol", ["same-age", "enrol-0"])
def test_upper_scores_with_reuse_equal_the_scores_computed_in_full(band, protocol):
    rng = np.random.default_rng(4)
    n, m = 11, Skewed()
    old = _templates(rng, n)
    new = list(old)
    for k in (0, 4, 5, 10):            # changed templates, first and last positions included
        new[k] = rng.normal(size=4)
    enrol = old                          # enrol-0: the gallery stays, the probes change
    gallery_old, gallery_new = (old, new) if protocol == "same-age" else (enrol, enrol)
    base = ScoredPairs(tuple(_digests(gallery_old)), tuple(_digests(old)), _upper_scores(m, gallery_old, old))
    i, j = np.triu_indices(n, 1)
    chosen, rows, cols = best_base([base], _digests(gallery_new), _digests(new), i, j)
    assert chosen is base
    scores, computed = fill_upper(m, gallery_new, new, rows, cols, base.scores, band)
    assert np.array_equal(scores, _upper_scores(m, gallery_new, new))
    # Exactly the pairs touching a changed template were computed, every other one copied.
    changed = np.isin(np.arange(n), [0, 4, 5, 10])
    touching = (changed[i] if protocol == "same-age" else np.zeros(i.size, bool)) | changed[j]
    assert computed == int(touching.sum()) < i.size


def test_a_pair_left_to_copy_is_never_computed_and_a_changed_one_never_copied():
    # The stored scores are poisoned: NaN where a pair must be recomputed would survive a missed recomputation,
    # and a sentinel where a pair may be copied shows that it was copied, not recomputed.
    rng = np.random.default_rng(5)
    n, m = 9, Skewed()
    old = _templates(rng, n)
    new = list(old)
    new[3] = rng.normal(size=4)
    i, j = np.triu_indices(n, 1)
    same = ~((i == 3) | (j == 3))
    stored = np.where(same, 1234.5, np.nan)
    rows = cols = unchanged(_digests(new), _digests(old))
    scores, computed = fill_upper(m, new, new, rows, cols, stored, band=2)
    assert np.all(scores[same] == 1234.5)
    assert np.array_equal(scores[~same], _upper_scores(m, new, new)[~same])
    assert computed == int((~same).sum())


@pytest.mark.parametrize("matcher", [Skewed(), SkewedLoop()], ids=["compare_all", "pairwise"])
def test_sampled_pairs_with_reuse_equal_the_scores_computed_in_full(matcher):
    rng = np.random.default_rng(6)
    n = 10
    old = _templates(rng, n)
    new = list(old)
    new[2], new[7] = rng.normal(size=4), rng.normal(size=4)
    i, j = np.triu_indices(n, 1)
    pick = np.sort(rng.choice(i.size, size=20, replace=False))
    i, j = i[pick], j[pick]
    stored, _ = fill_pairs(matcher, old, old, i, j, np.zeros(n, bool), np.zeros(n, bool), None)
    rows = cols = unchanged(_digests(new), _digests(old))
    scores, computed = fill_pairs(matcher, new, new, i, j, rows, cols, stored)
    assert scores.tolist() == [matcher.compare(new[a], new[b]) for a, b in zip(i, j)]
    assert computed == int((np.isin(i, [2, 7]) | np.isin(j, [2, 7])).sum())


def test_every_pair_copied_returns_the_stored_scores_themselves():
    # (At age 0 the enrol-0 protocol's gallery is the same-age one: the scores are shared, not duplicated.)
    rng = np.random.default_rng(7)
    m, t = Skewed(), _templates(rng, 6)
    stored = _upper_scores(m, t, t)
    same = np.ones(6, bool)
    scores, computed = fill_upper(m, t, t, same, same, stored, band=256)
    assert scores is stored and computed == 0


def test_best_base_picks_the_stored_scores_leaving_the_fewest_pairs():
    rng = np.random.default_rng(8)
    n = 8
    a, b = _templates(rng, n), _templates(rng, n)
    now = list(a)
    now[1] = b[1]
    i, j = np.triu_indices(n, 1)
    empty = np.empty(0)
    far = ScoredPairs(tuple(_digests(b)), tuple(_digests(b)), empty)     # one template in common
    near = ScoredPairs(tuple(_digests(a)), tuple(_digests(a)), empty)    # all but one in common
    chosen, rows, cols = best_base([far, near], _digests(now), _digests(now), i, j)
    assert chosen is near and rows.sum() == cols.sum() == n - 1 and not rows[1]
    assert best_base([], _digests(now), _digests(now), i, j)[0] is None


def _code(bits, pupil_x=40.0, ok=True):
    seg = Segmentation((pupil_x, 50.0, 12.0), (41.0, 50.0, 40.0), ok=ok)
    return IrisCode.from_bits(bits, np.ones_like(bits), seg)


def test_the_digest_covers_the_whole_template():
    bits = np.random.default_rng(9).random((16, 8)) > 0.5
    code = _code(bits)
    assert template_digest(code) == template_digest(_code(bits.copy()))
    flipped = bits.copy()
    flipped[3, 2] ^= True
    others = [_code(flipped),                                        # one code bit
              _code(bits, pupil_x=40.0 + 1e-12),                      # the segmentation it came from
              _code(bits, ok=False),                                  # a failed segmentation
              dataclasses.replace(code, bits_per_column=7)]           # the layout
    digests = {template_digest(t) for t in [code, *others]}
    assert len(digests) == 5
    # Arrays: the same bytes in another dtype or shape are another template.
    x = np.arange(6, dtype=np.uint8)
    assert len({template_digest(v) for v in (x, x.astype(np.int8), x.reshape(2, 3), x.tobytes())}) == 4
    assert template_digest(-0.0) != template_digest(0.0)
    # What the digest cannot see into is never reused.
    assert template_digest(object()) is None
    assert template_digest((x, np.array([object()]))) is None
    assert not unchanged([None], [None]).any()


@pytest.mark.parametrize("n, band", [(11, 3), (600, 256), (2240, 280)])
def test_with_nothing_to_copy_the_plan_is_the_upper_triangles_bands(n, band):
    # The full-scale benchmark counts entries with upper_entries_computed: with no stored scores it must be what
    # the experiment's own banded upper triangle computes.
    nothing = np.zeros(n, bool)
    assert upper_entries_computed(nothing, nothing, band) == upper_entries(n, band)
    # One changed template in the middle: its row right of it and its column above it, nothing else.
    one = np.ones(n, bool)
    one[n // 2] = False
    assert upper_entries_computed(one, one, band) == (n - 1 - n // 2) + n // 2
