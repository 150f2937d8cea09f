"""Rathgeb and Uhl's context-based iris code: USIT's ``cb`` (with its comparator ``cbc``).

C. Rathgeb and A. Uhl, "Context-based biometric key generation for iris", *IET Computer Vision* 5(6), 2011,
389–397 — the paper USIT's ``cb`` cites ("Context-based texture analysis for secure revocable
iris-biometric key generation", ICDP 2009, is the conference version).  (USIT's ``cr`` is the other
Rathgeb–Uhl algorithm: :mod:`forensics.impact.cr`.)

Feature extraction, as published and as USIT implements it:

1. The normalised texture (USIT: 64 × 512, contrast-enhanced by the segmenter's ``-e`` option: adaptive
   histogram equalisation, :func:`~forensics.impact.texture.equalise`) is divided into cells of ``cell`` =
   2 radial × 8 angular samples: 32 × 64 cells.
2. Every sample is quantised to one of three grey levels (below 1/3, below 2/3, above — of the equalised
   range); a cell takes the level most of its samples have (ties to the darker level).  A level is coded
   with two bits ``00``, ``01``, ``11``, so a cell's code is 2 bits: 4,096 bits in all.

Comparison is the *context-based* matching of the paper, as USIT's ``cbc`` implements it: a cell counts more
when its context agrees.

* A cell valid in both codes and equal in both (a *match*) scores ``2^(2 + c)``, with ``c`` its context
  count: for each of its 8 context cells — the 4 diagonal neighbours and the 4 cells two steps away along
  the radius and along the angle — 1 if that cell matches too, and 1 more if, in the first (reference)
  code, it holds another level than the cell itself (agreement in a varied neighbourhood is worth more
  than in a flat one).
* A cell valid in both and different (a *mismatch*) scores ``−2^(1 + p)``, with ``p`` summed over its 4
  direct neighbours that are mismatches too: their level difference (1 or 2) plus 1 if, in the reference
  code, they hold the same level as the cell (a coherent region of disagreement).
* Cells invalid in either code score 0.  The similarity is the sum over cells divided by
  ``n_valid · 2^11`` (USIT's normalisation: ``2^(neighbours + 2)`` per valid cell, ``neighbours`` = 9 — the
  8 context cells and the cell itself); ``higher_is_similar``.

Differences from USIT's ``cbc`` (each a clarification, none tuned on data): USIT returns ``1 / score`` as a
distance, which turns a negative score into the best possible distance; we return the score itself
(the same order wherever USIT's score is positive).  USIT counts a context cell as agreeing when it is
merely not a mismatch (so invalid cells count as agreeing) and skips the context of cells within two rows
of the texture's edges; we count matches only, treat cells beyond the radial edges as absent and wrap
around the angle.  USIT's codes carry no mask (its intended mask of bright cells is overwritten by a slip
in ``cb``); ours mark a cell invalid unless more than half of its samples are usable.  USIT's segmenters
size their equalisation tiles from the eye image (a slip: 40 × 120 samples at 320 × 240); we use ``cr``'s
64 × 32.

USIT's ``cbc`` does not compensate rotation (the algorithm comes from key generation, where no shifting is
possible); ``max_shift`` > 0 takes the best score over circular shifts of whole cells (default 0, as
published).

Speed: the comparison is vectorised over blocks of pairs with one byte per cell; the context of every cell
is read from padded codes laid out on one line each (every neighbour a contiguous view, no copies), and the cell
scores are bit shifts summed as integers, so one pair and a block of pairs give exactly the same value.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from forensics._shared.errors import InputError, UsageError
from forensics.impact.segment import Segmentation, Segmenter
from forensics.impact.texture import TEXTURE_SHAPE, cell_validity, equalise

__all__ = ["CONTEXT", "DIRECT", "UNCOMPARABLE", "CbMatcher", "CbTemplate", "cell_levels"]

#: Context cells of a match, ``(rows, columns)`` offsets: diagonal neighbours, then two steps along each axis.
CONTEXT: tuple[tuple[int, int], ...] = ((-1, -1), (-1, 1), (1, -1), (1, 1), (-2, 0), (2, 0), (0, -2), (0, 2))
#: Direct neighbours of a mismatch.
DIRECT: tuple[tuple[int, int], ...] = ((-1, 0), (0, -1), (0, 1), (1, 0))
_PAD = 2
#: USIT's normalisation exponent per valid cell: 2 + (context cells + the cell itself).
_NORM = 2 + len(CONTEXT) + 1
#: Similarity of a pair with too few cells valid in both codes: the lowest score any pair can have (every
#: cell a mismatch with the largest penalty, −4), so an uncomparable pair never passes for a match.
UNCOMPARABLE = -(2.0 ** (1 + 3 * len(DIRECT))) / 2.0 ** _NORM


@dataclass(frozen=True, eq=False)
class CbTemplate:
    """Cell levels ``(rows, columns)`` in {0, 1, 2} (uint8) and their validity; columns run along the angle."""

    levels: np.ndarray
    valid: np.ndarray
    segmentation: Segmentation | None = None

    @property
    def n_cells(self) -> int:
        return int(self.levels.size)

    def code_only(self) -> CbTemplate:
        """The levels and validity without the segmentation: all that the comparison reads."""
        return replace(self, segmentation=None)


def cell_levels(enhanced: np.ndarray, cell: tuple[int, int], n_levels: int = 3) -> np.ndarray:
    """The most frequent of ``n_levels`` equal grey bands in each cell of an equalised texture (values in [0, 1]).

    Ties go to the darker level.  Returns uint8 ``(rows // cell[0], columns // cell[1])``.
    """
    e = np.asarray(enhanced, dtype=np.float64)
    ch, cw = int(cell[0]), int(cell[1])
    r, c = e.shape[0] // ch, e.shape[1] // cw
    level = np.minimum((e[: r * ch, : c * cw] * n_levels).astype(np.intp), n_levels - 1)
    blocks = level.reshape(r, ch, c, cw)
    counts = np.stack([(blocks == k).sum(axis=(1, 3)) for k in range(n_levels)])
    return np.argmax(counts, axis=0).astype(np.uint8)          # argmax takes the first (darker) of ties


def _padded(x: np.ndarray) -> np.ndarray:
    """``x`` (…, rows, columns) padded by 2: zeros beyond the radial edges, wrapped around the angle."""
    wrapped = np.concatenate([x[..., -_PAD:], x, x[..., :_PAD]], axis=-1)
    zeros = np.zeros((*wrapped.shape[:-2], _PAD, wrapped.shape[-1]), wrapped.dtype)
    return np.concatenate([zeros, wrapped, zeros], axis=-2)


def _at(padded: np.ndarray, dr: int, dc: int) -> np.ndarray:
    """The neighbour ``(dr, dc)`` of every cell, read from a :func:`_padded` array (a view)."""
    r, c = padded.shape[-2] - 2 * _PAD, padded.shape[-1] - 2 * _PAD
    return padded[..., _PAD + dr:_PAD + dr + r, _PAD + dc:_PAD + dc + c]


def _flat(padded: np.ndarray) -> np.ndarray:
    """A :func:`_padded` ``(n, rows + 4, columns + 4)`` array as ``(n, (rows + 4)(columns + 4) + 4)``: each padded
    code on one line, with ``_PAD`` zeros before and after (see :func:`_span`)."""
    n = padded.shape[0]
    out = np.zeros((n, padded[0].size + 2 * _PAD), padded.dtype)
    out[:, _PAD:_PAD + padded[0].size] = padded.reshape(n, -1)
    return out


def _span(flat: np.ndarray, shape: tuple[int, int], dr: int = 0, dc: int = 0) -> np.ndarray:
    """The neighbour ``(dr, dc)`` of every cell of the code rows, padding columns included, from a :func:`_flat`
    array: one contiguous run of ``rows × (columns + 4)`` per code (a view).

    A cell's neighbour lies ``dr (columns + 4) + dc`` places further along the line; for the code's own cells it
    is inside their padded code (the padding is 2 wide), and the padding columns' garbage is never summed.  Long
    contiguous runs instead of short rows make every numpy pass several times faster.
    """
    rows, cols = shape
    width = cols + 2 * _PAD
    start = _PAD + _PAD * width + dr * width + dc
    return flat[..., start:start + rows * width]


def _interior(span: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The code's own cells of a :func:`_span`-shaped array, ``(…, rows, columns)`` (a view)."""
    rows, cols = shape
    return span.reshape(*span.shape[:-1], rows, cols + 2 * _PAD)[..., _PAD:_PAD + cols]


@dataclass(frozen=True)
class _Stack:
    """Templates prepared for comparison, all ``(n, (rows + 4)(columns + 4) + 4)`` uint8 (:func:`_flat` of
    :func:`_padded`): the two thermometer bits of the level (``level ≥ 1``, ``level ≥ 2``) and the validity (0
    beyond the radial edges); ``shape`` the cells ``(rows, columns)``."""

    t1: np.ndarray
    t2: np.ndarray
    valid: np.ndarray
    shape: tuple[int, int]

    @classmethod
    def of(cls, levels: np.ndarray, valid: np.ndarray) -> _Stack:
        return cls(_flat(_padded((levels >= 1).view(np.uint8))), _flat(_padded((levels >= 2).view(np.uint8))),
                   _flat(_padded(np.asarray(valid, bool).view(np.uint8))), levels.shape[1:])

    def rolled(self, s: int) -> _Stack:
        """The templates rotated by ``s`` cells along the angle (padding rebuilt)."""
        if s == 0:
            return self
        rows, cols = self.shape
        n = self.t1.shape[0]

        def roll(x: np.ndarray) -> np.ndarray:
            padded = x[:, _PAD:_PAD + (rows + 2 * _PAD) * (cols + 2 * _PAD)].reshape(n, rows + 2 * _PAD, -1)
            return _flat(_padded(np.roll(_at(padded, 0, 0), s, axis=-1)))

        return _Stack(roll(self.t1), roll(self.t2), roll(self.valid), self.shape)

    def take(self, i0: int, i1: int) -> _Stack:
        return _Stack(self.t1[i0:i1], self.t2[i0:i1], self.valid[i0:i1], self.shape)


def _reference_context(levels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For reference codes ``(n, rows, columns)``: per context cell 1 + [its level differs] (uint8, (8, n, span)),
    and per direct neighbour [its level is the same] (uint8, (4, n, span)), in :func:`_span` layout."""
    flat, shape = _flat(_padded(levels)), levels.shape[1:]
    centre = _span(flat, shape)
    grow = np.stack([1 + (_span(flat, shape, dr, dc) != centre) for dr, dc in CONTEXT]).astype(np.uint8)
    same = np.stack([_span(flat, shape, dr, dc) == centre for dr, dc in DIRECT]).astype(np.uint8)
    return grow, same


def _scores(a: _Stack, grow: np.ndarray, same: np.ndarray, b: _Stack, min_cells: int) -> np.ndarray:
    """Context-based similarities of references ``a`` (with their :func:`_reference_context`) against probes ``b``.

    Works on the :func:`_flat` arrays, so every neighbour is a contiguous view (:func:`_span`); the per-cell
    scores ``2^(2 + c)`` and ``2^(1 + p)`` are bit shifts of the match and mismatch indicators, summed exactly as
    integers over the code's own cells.
    """
    shape = a.shape
    # Level difference |a − b| = number of differing thermometer bits.
    diff = (a.t1[:, None] ^ b.t1[None, :]) + (a.t2[:, None] ^ b.t2[None, :])
    valid = a.valid[:, None] & b.valid[None, :]
    match = ((diff == 0) & valid.view(bool)).view(np.uint8)
    mismatch = valid - match                            # valid and not equal (match ≤ valid: no wrap-around)
    diff *= valid                                       # level difference where both are valid (0 where equal)
    # The code's own cells (the padding columns of the span are neighbours only, never summed).
    own = np.zeros((shape[0], shape[1] + 2 * _PAD), np.uint8)
    own[:, _PAD:_PAD + shape[1]] = 1
    own = own.ravel()
    centre_match, centre_mismatch = _span(match, shape) * own, _span(mismatch, shape) * own
    term = np.empty(centre_match.shape, np.uint8)
    context = np.full(centre_match.shape, 2, np.uint8)  # the exponent 2 + c
    for k, (dr, dc) in enumerate(CONTEXT):
        np.multiply(_span(match, shape, dr, dc), grow[k][:, None], out=term)
        context += term
    penalty = np.ones(centre_match.shape, np.uint8)     # the exponent 1 + p
    for k, (dr, dc) in enumerate(DIRECT):
        np.multiply(_span(mismatch, shape, dr, dc), same[k][:, None], out=term)
        penalty += term
        penalty += _span(diff, shape, dr, dc)
    # Exact integer sums: a cell adds at most 2^(2 + 16) (or subtracts 2^(1 + 12)), so below 2^14 cells uint32
    # cannot overflow.
    total = np.uint32 if shape[0] * shape[1] < 2**14 else np.uint64
    positive = np.left_shift(centre_match, context, dtype=np.uint32).sum(axis=-1, dtype=total)
    negative = np.left_shift(centre_mismatch, penalty, dtype=np.uint32).sum(axis=-1, dtype=total)
    n_valid = _interior(_span(valid, shape), shape).sum(axis=(-2, -1), dtype=np.int64)
    with np.errstate(invalid="ignore", divide="ignore"):
        score = (positive.astype(np.float64) - negative.astype(np.float64)) / (n_valid * 2.0 ** _NORM)
    return np.where(n_valid >= max(min_cells, 1), score, UNCOMPARABLE)


class CbMatcher:
    """Rathgeb & Uhl (IET Computer Vision 2011) through USIT's ``cb``/``cbc``: context-based cell matching.

    Parameters
    ----------
    segmenter
        Shared segmenter (cache); a new one if None.
    radial, angular
        Rubber-sheet size (USIT: 64 × 512).
    cell
        Cell size ``(rows, columns)`` in samples (USIT: 2 × 8).
    tiles
        Equalisation tiles ``(rows, columns)`` (USIT: 2 × 8).
    max_shift
        Circular shifts of whole cells tried, ``±max_shift`` (USIT: none).
    min_valid
        Fraction of the cells that must be valid in both codes; otherwise the similarity is
        :data:`UNCOMPARABLE`.
    block_bytes
        Working memory per block of pairs (about 20 bytes per cell and pair).  The default keeps a block's
        arrays within a core's cache (measured on 280 × 1,120 real templates, ``benchmarks/bench_compare_block.py``:
        7.2 µs per pair at 4 MiB against 8.7 µs at 32 MiB, whose arrays spill to memory — 17–20 µs in a fresh
        process, where they are new pages).
    """

    name: ClassVar[str] = "cb"
    higher_is_similar: ClassVar[bool] = True

    def __init__(self, segmenter: Segmenter | None = None, *, radial: int = TEXTURE_SHAPE[0],
                 angular: int = TEXTURE_SHAPE[1], cell: tuple[int, int] = (2, 8), tiles: tuple[int, int] = (2, 8),
                 max_shift: int = 0, min_valid: float = 0.1, block_bytes: int = 4 * 2**20) -> None:
        self.segmenter = segmenter if segmenter is not None else Segmenter()
        self.radial, self.angular = int(radial), int(angular)
        self.cell = (int(cell[0]), int(cell[1]))
        self.tiles = (int(tiles[0]), int(tiles[1]))
        self.max_shift, self.min_valid, self.block_bytes = int(max_shift), float(min_valid), int(block_bytes)
        rows, cols = self.radial // self.cell[0], self.angular // self.cell[1]
        if rows < 1 or cols <= 2 * _PAD:
            raise UsageError(f"cb: {self.radial} × {self.angular} samples hold {rows} × {cols} cells of "
                             f"{self.cell[0]} × {self.cell[1]}; the context needs at least 1 × {2 * _PAD + 1}")
        if self.max_shift < 0 or 2 * self.max_shift >= cols:
            raise UsageError(f"cb: max_shift {self.max_shift} must lie in 0 … {(cols - 1) // 2}")

    # ------------------------------------------------------------------ encoding
    def encode_texture(self, texture: np.ndarray, mask: np.ndarray,
                       segmentation: Segmentation | None = None) -> CbTemplate:
        """The template of an already normalised ``(radial, angular)`` texture and its usability mask."""
        e = equalise(texture, mask, self.tiles)
        return CbTemplate(cell_levels(e, self.cell), cell_validity(mask, self.cell), segmentation)

    def encode(self, image: np.ndarray) -> CbTemplate:
        """Segment (cached), normalise and encode an eye image."""
        texture, mask, seg = self.segmenter.unwrap(image, self.radial, self.angular)
        return self.encode_texture(texture, mask, seg)

    # ------------------------------------------------------------------ comparison
    def _stack(self, templates: Sequence[CbTemplate]) -> tuple[np.ndarray, np.ndarray]:
        shape = None
        for t in templates:
            if not isinstance(t, CbTemplate):
                raise InputError(f"cb templates expected, got {type(t).__name__}")
            if shape is not None and t.levels.shape != shape:
                raise InputError(f"cb templates of different layouts: {shape} and {t.levels.shape} cells; encode "
                                 "both with the same matcher settings")
            shape = t.levels.shape
        return np.stack([t.levels for t in templates]), np.stack([t.valid for t in templates])

    def compare(self, a: CbTemplate, b: CbTemplate) -> float:
        """Context-based similarity of ``b`` to the reference ``a`` (:data:`UNCOMPARABLE` if not comparable)."""
        return float(self.compare_all([a], [b])[0, 0])

    def compare_all(self, templates_a: Sequence[CbTemplate], templates_b: Sequence[CbTemplate]) -> np.ndarray:
        """Similarities of every probe in ``templates_b`` to every reference in ``templates_a``."""
        out = np.full((len(templates_a), len(templates_b)), UNCOMPARABLE)
        if len(templates_a) == 0 or len(templates_b) == 0:
            return out
        la, va = self._stack(templates_a)
        lb, vb = self._stack(templates_b)
        if la.shape[1:] != lb.shape[1:]:
            raise InputError(f"cb templates of different layouts: {la.shape[1:]} and {lb.shape[1:]} cells")
        min_cells = math.ceil(self.min_valid * la[0].size)
        grow, same = _reference_context(la)
        ref, probes = _Stack.of(la, va), _Stack.of(lb, vb)
        per_pair = 16 * ref.t1[0].size                 # bytes of the block's working arrays per pair
        chunk_b = max(1, min(len(lb), self.block_bytes // per_pair))
        chunk_a = max(1, min(len(la), self.block_bytes // (per_pair * chunk_b)))
        for s in range(-self.max_shift, self.max_shift + 1):
            shifted = probes.rolled(s)
            for j0 in range(0, len(lb), chunk_b):
                j1 = min(j0 + chunk_b, len(lb))
                for i0 in range(0, len(la), chunk_a):
                    i1 = min(i0 + chunk_a, len(la))
                    block = _scores(ref.take(i0, i1), grow[:, i0:i1], same[:, i0:i1], shifted.take(j0, j1), min_cells)
                    np.maximum(out[i0:i1, j0:j1], block, out=out[i0:i1, j0:j1])
        return out
