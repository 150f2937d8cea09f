"""Exact reuse of comparison scores between byte-identical templates (the impact experiment's inner reuse).

When a virtual sensor gains a defect every aged image changes (the defect sits at the same pixel of every
image), but the defect lands in the sampled iris annulus of only some images: most *templates* of a
(sensor, age) are byte for byte those of the sensor's previous distinct age.  A comparison is a function of
its two templates (and of the matcher's settings, fixed for a run), so the score of a pair whose two
templates are byte-identical to those of a pair already scored is that pair's score: it is copied, not
recomputed.

Exact by construction: a template's digest (:func:`template_digest`) is the SHA-256 of its complete content —
every array's dtype, shape, strides and bytes, every scalar's type and exact value, every field of a
dataclass, recursively.  The scores are keyed by :func:`score_digest`: the digest of what the comparison
reads — for a user's matcher the whole template, for a built-in its code without the segmentation it carries
(no built-in comparator reads it; a failed segmentation is handled apart from the scores, from the templates
of the age being scored).  A score is copied only where *both* digests equal those of the already-scored pair
at the same position; a template of a type the digest does not know (a user's class that is not a dataclass,
say) has no digest, and every pair involving it is computed.

:class:`ScoredPairs` keeps one protocol's scores with the digests of its gallery and probe templates;
:func:`best_base` picks the stored scores that leave the fewest pairs to compute; :func:`fill_upper` and
:func:`fill_pairs` compute only those pairs (the others copied) and return every score; :func:`upper_blocks`
is :func:`fill_upper`'s plan of ``compare_all`` calls (counted by the full-scale benchmark).

**Templates too** (:func:`encode_reusing`): a built-in matcher's template is ``encode_texture`` of its rubber-sheet
band — the texture, usability mask and segmentation :meth:`~forensics.impact.segment.Segmenter.unwrap` returns —
and ``encode_texture`` is a deterministic function of those three alone (no random draw, no state).  So when an
aged image's band is byte-identical to the band of the same source image at the sensor's previous computed age
(the digests agree), the template *is* that age's template and its encoding is skipped.  The unwrapping is still
computed (the band's digest needs the band), and so is the segmentation, whose whole-image thresholds a defect
anywhere can move; what is saved is the feature extraction.

**And the segmentation's costly steps** (:func:`segment_reusing`): each image is segmented with a
:class:`~forensics.impact.segment.memo.StepMemo` holding the steps of the same source image's segmentation at the
previous computed age.  The cheap steps run; a costly one (a Hough transform, a limbus fit) whose inputs are
byte-identical to the stored ones — the dark map, the voting edges, the ray profiles — returns the stored result,
which is what it would compute.  The segmentation is the fresh one bit for bit.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from forensics._shared.digest import content_digest
from forensics._shared.plugins import load_class
from forensics.impact.matchers import BUILTIN_MATCHERS, compare_all
from forensics.impact.segment.memo import StepMemo
from forensics.impact.segment.normalise import footprint
from forensics.impact.segment.segmenter import Segmenter

__all__ = ["ScoredPairs", "band_encoder", "band_untouched", "best_base", "encode_reusing", "fill_pairs", "fill_upper",
           "score_digest", "segment_reusing", "step_segmenters", "template_digest", "unchanged", "upper_blocks",
           "upper_entries_computed"]


@dataclass(frozen=True, eq=False)
class ScoredPairs:
    """The scores of the run's pairs ``(gallery[i], probe[j])`` with the digests of the templates compared.

    ``gallery`` and ``probe`` hold :func:`score_digest` of every template (None: no digest, never reused);
    ``scores`` the float64 scores of the run's pairs, in the run's pair order.
    """

    gallery: tuple[bytes | None, ...]
    probe: tuple[bytes | None, ...]
    scores: np.ndarray


def template_digest(template: Any) -> bytes | None:
    """SHA-256 of a template's complete content, or None for a template holding a type it does not know.

    Known: None, bool, int, float (its exact bits), complex, str, bytes, numpy arrays and scalars (dtype,
    shape, strides and bytes; object arrays are unknown), tuples, lists, dicts (in their order) and dataclass
    instances (their class and every attribute) (:func:`~forensics._shared.digest.content_digest`).  Two
    templates with the same digest are equal value by value, in the same types and memory layout, so a
    deterministic comparator gives them the same score.
    """
    return content_digest(template)


def score_digest(matcher: Any, template: Any) -> bytes | None:
    """:func:`template_digest` of what ``matcher``'s comparison reads of ``template``: for a built-in
    (:func:`band_encoder`) the code alone (``template.code_only()``), for any other matcher the whole template.

    A built-in template also carries the segmentation it was encoded with, which its comparators never read
    (a failed segmentation is handled by the experiment apart from the scores).  A new defect often moves only
    that segmentation's edge support (``quality``) and leaves the code byte for byte as it was; keyed by the
    code, such a template keeps its pairs' scores.
    """
    if band_encoder(matcher):
        code_only = getattr(template, "code_only", None)
        if callable(code_only):
            return template_digest(code_only())
    return template_digest(template)


def band_encoder(matcher: Any) -> bool:
    """Whether ``matcher`` is a built-in whose ``encode(image)`` is ``encode_texture(*segmenter.unwrap(image,
    radial, angular))`` with a deterministic ``encode_texture`` (exactly a built-in class: a subclass may
    change either)."""
    name = getattr(matcher, "name", None)
    builtin = BUILTIN_MATCHERS.get(name) if isinstance(name, str) else None
    if builtin is None:
        return False
    return type(matcher) is (load_class(builtin, "matcher") if isinstance(builtin, str) else builtin)


def encode_reusing(matcher: Any, image: np.ndarray, before: tuple[bytes | None, Any] | None,
                   previous: np.ndarray | None = None) -> tuple[bytes | None, Any, bool]:
    """``(band digest, template, reused)`` of ``image``: ``before``'s template when its band digest is this
    image's (see the module's note), else a new encoding.

    ``before`` is ``(band digest, template)`` of the same source image at the previous computed age (None: none),
    ``previous`` that age's image (None: not known).  With it the band is not even unwrapped when it provably
    equals that age's (:func:`band_untouched`).  A matcher that is not a :func:`band_encoder` encodes the image
    as usual and has no band digest.
    """
    if not band_encoder(matcher):
        return None, matcher.encode(image), False
    if before is not None and before[0] is not None and previous is not None and \
            band_untouched(matcher, image, previous, getattr(before[1], "segmentation", None)):
        return before[0], before[1], True
    band = matcher.segmenter.unwrap(image, matcher.radial, matcher.angular)
    key = template_digest(band)
    if key is not None and before is not None and before[0] == key:
        return key, before[1], True
    return key, matcher.encode_texture(*band), False


def band_untouched(matcher: Any, image: np.ndarray, previous: np.ndarray, prior: Any) -> bool:
    """Whether ``matcher``'s band of ``image`` is provably the band it had in ``previous`` (the same eye at the
    previous computed age), whose template carried the segmentation ``prior``: without unwrapping it.

    True when ``image`` is segmented (the shared :class:`~forensics.impact.segment.Segmenter`, cached) exactly as
    ``prior`` (content digests equal), both are 8-bit grey images of one shape (their full scale is the dtype's),
    and they agree on every pixel of the box :func:`~forensics.impact.segment.normalise.footprint` says the
    unwrapping reads: the unwrapping is then a deterministic function of byte-identical inputs.  ``prior`` is
    the segmentation the band was encoded with — the image's own, or that one marked failed for too little usable
    iris, in which case they differ and the band is unwrapped (never wrongly reused).
    """
    if prior is None or image.ndim != 2 or image.shape != previous.shape or image.dtype != previous.dtype or \
            image.dtype.itemsize != 1 or not np.issubdtype(image.dtype, np.integer):
        return False
    seg = matcher.segmenter.segment(image)
    if content_digest(seg) != content_digest(prior):
        return False
    y0, y1, x0, x1 = footprint(seg, matcher.radial, matcher.angular, image.shape)
    return bool(np.array_equal(image[y0:y1, x0:x1], previous[y0:y1, x0:x1]))


def step_segmenters(matchers: Sequence[Any]) -> list[Segmenter]:
    """The distinct built-in :class:`~forensics.impact.segment.Segmenter` objects of the :func:`band_encoder`
    matchers, in the matchers' order: the segmentations :func:`segment_reusing` runs."""
    out: list[Segmenter] = []
    for matcher in matchers:
        segmenter = getattr(matcher, "segmenter", None)
        if band_encoder(matcher) and type(segmenter) is Segmenter and all(segmenter is not s for s in out):
            out.append(segmenter)
    return out


def segment_reusing(segmenter: Segmenter, image: np.ndarray, before: dict[bytes, Any] | None) -> StepMemo:
    """Segment ``image`` (into ``segmenter``'s one-image cache, where the matchers' encodings find it), reusing
    the costly steps whose inputs are byte-identical to those recorded in ``before``
    (:class:`~forensics.impact.segment.memo.StepMemo`: the same segmentation, bit for bit); the memo, whose
    ``entries`` are this image's steps for the next age and ``hits`` the steps reused.

    ``before`` is the step record of the same source image at the previous computed age (None: none).
    """
    memo = StepMemo(before)
    segmenter.segment(image, memo=memo)
    return memo


def unchanged(now: Sequence[bytes | None], before: Sequence[bytes | None]) -> np.ndarray:
    """Which positions hold a template byte-identical to the one before (both digests known and equal)."""
    return np.array([a is not None and a == b for a, b in zip(now, before, strict=True)], dtype=bool)


def _needed(rows_same: np.ndarray, cols_same: np.ndarray, i: np.ndarray, j: np.ndarray) -> int:
    """How many of the pairs ``(i, j)`` must be computed when rows ``rows_same`` and columns ``cols_same`` are
    unchanged."""
    return int((~(rows_same[i] & cols_same[j])).sum())


def best_base(bases: Sequence[ScoredPairs], gallery: Sequence[bytes | None], probe: Sequence[bytes | None],
              i: np.ndarray, j: np.ndarray) -> tuple[ScoredPairs | None, np.ndarray, np.ndarray]:
    """The stored scores leaving the fewest pairs to compute, with its unchanged rows and columns.

    Returns ``(None, all False, all False)`` when there is no base (every pair is computed).
    """
    best: tuple[int, ScoredPairs | None, np.ndarray, np.ndarray] = (
        i.size + 1, None, np.zeros(len(gallery), bool), np.zeros(len(probe), bool))
    for base in bases:
        rows, cols = unchanged(gallery, base.gallery), unchanged(probe, base.probe)
        needed = _needed(rows, cols, i, j)
        if needed < best[0]:
            best = (needed, base, rows, cols)
    return best[1], best[2], best[3]


def _upper_offsets(n: int) -> np.ndarray:
    """Position of pair ``(r, r + 1)`` in :func:`numpy.triu_indices` ``(n, 1)`` order, for every row ``r``."""
    r = np.arange(n, dtype=np.int64)
    return r * n - r * (r + 1) // 2


def upper_blocks(rows_same: np.ndarray, cols_same: np.ndarray, band: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The ``compare_all`` calls that score every pair ``i < j`` not left to copy: ``(rows, columns)`` blocks.

    Two kinds, each in bands of at most ``band`` rows (a matcher prepares its column templates once per call):
    every changed row against the columns right of its band's first row, and the unchanged rows against the
    changed columns right of the band's first row.  Their entries right of the diagonal are the pairs to
    compute; the others are computed and not used (what :func:`upper_entries_computed` counts).
    """
    n = rows_same.size
    blocks = []
    changed_rows = np.flatnonzero(~rows_same[:n - 1])
    for k in range(0, changed_rows.size, band):
        rows = changed_rows[k:k + band]
        blocks.append((rows, np.arange(rows[0] + 1, n)))
    changed_cols = np.flatnonzero(~cols_same)
    if changed_cols.size:
        kept_rows = np.flatnonzero(rows_same[:int(changed_cols[-1])])
        for k in range(0, kept_rows.size, band):
            rows = kept_rows[k:k + band]
            blocks.append((rows, changed_cols[changed_cols > rows[0]]))
    return blocks


def upper_entries_computed(rows_same: np.ndarray, cols_same: np.ndarray, band: int) -> int:
    """Matrix entries :func:`fill_upper` computes (its blocks' sizes, slivers left of the diagonal included)."""
    return sum(r.size * c.size for r, c in upper_blocks(rows_same, cols_same, band))


def fill_upper(matcher: Any, gallery: Sequence[Any], probe: Sequence[Any], rows_same: np.ndarray,
               cols_same: np.ndarray, base: np.ndarray | None, band: int) -> tuple[np.ndarray, int]:
    """Scores of every pair ``i < j`` (triu order): copied from ``base`` where row ``i`` and column ``j`` are
    unchanged, computed otherwise (:func:`upper_blocks`).  Returns the scores and how many pairs were computed.

    A score is a function of its two templates, so each computed one equals the one the whole matrix would
    give (what ``experiment._upper_scores`` computes).
    """
    n = len(gallery)
    if base is None:
        rows_same, cols_same = np.zeros(n, bool), np.zeros(n, bool)
    elif rows_same[:n - 1].all() and cols_same[1:].all():
        return base, 0      # every pair copied: the stored array itself (never written to)
    out = np.array(base, dtype=np.float64, copy=True) if base is not None else np.empty(n * (n - 1) // 2)
    start = _upper_offsets(n)
    computed = 0
    for rows, cols in upper_blocks(rows_same, cols_same, band):
        block = np.asarray(compare_all(matcher, [gallery[r] for r in rows], [probe[c] for c in cols]), np.float64)
        rr, cc = np.meshgrid(rows, cols, indexing="ij")
        right = cc > rr
        out[start[rr[right]] + cc[right] - rr[right] - 1] = block[right]
        computed += int(right.sum())
    return out, computed


def fill_pairs(matcher: Any, gallery: Sequence[Any], probe: Sequence[Any], i: np.ndarray, j: np.ndarray,
               rows_same: np.ndarray, cols_same: np.ndarray, base: np.ndarray | None) -> tuple[np.ndarray, int]:
    """Scores of the listed pairs ``(gallery[i], probe[j])`` (a sample of the pairs): copied from ``base`` where
    both templates are unchanged, the others computed (one ``compare_all`` over their rows and columns, or
    pair by pair for matchers without one).  Returns the scores and how many were computed."""
    todo = np.ones(i.size, bool) if base is None else ~(rows_same[i] & cols_same[j])
    out = np.array(base, dtype=np.float64, copy=True) if base is not None else np.empty(i.size, np.float64)
    if not todo.any():
        return out, 0
    ti, tj = i[todo], j[todo]
    if hasattr(matcher, "compare_all"):
        rows, row_at = np.unique(ti, return_inverse=True)
        cols, col_at = np.unique(tj, return_inverse=True)
        block = np.asarray(compare_all(matcher, [gallery[r] for r in rows], [probe[c] for c in cols]), np.float64)
        out[todo] = block[row_at, col_at]
    else:
        out[todo] = [float(matcher.compare(gallery[a], probe[b])) for a, b in zip(ti, tj)]
    return out, int(todo.sum())
