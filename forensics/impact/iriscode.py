"""Bit-packed iris codes and the masked fractional Hamming distance, shared by the built-in matchers.

:class:`IrisCode` stores code and mask column by column (angle-major) so that a rotation of the eye is a roll of
whole rows; :func:`hamming_distance` is the masked fractional Hamming distance minimised over circular shifts;
:func:`hamming_all` does the same for all pairs of two lists at once on 64-bit words with ``np.bitwise_count``
and equals the pairwise loop exactly, as does :func:`hamming_all_spectral` (exact counts by cross-correlation,
:mod:`~forensics.impact.spectral`, faster for long codes at many shifts); :class:`IrisCodeMatcher` is the
comparison half of a built-in matcher.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np

from forensics._shared.errors import InputError
from forensics.impact.segment import Segmentation
from forensics.impact.spectral import shift_counts


@dataclass(frozen=True, eq=False)
class IrisCode:
    """A binary iris template packed column by column (angle-major).

    ``bits`` and ``mask`` are uint8 arrays of shape ``(columns, bytes_per_column)``: row ``c`` holds, packed
    with :func:`numpy.packbits` (big-endian bit order), the ``bits_per_column`` bits of angular column ``c``,
    padded with zeros to whole bytes (padding bits are invalid in ``mask``).  Because a column is whole bytes,
    a circular shift of the angle by ``s`` columns is ``np.roll(…, s, axis=0)`` — no bit shuffling, and all
    bits of a column (both phase bits of a Masek sample, all codes of a Ko cell) move together.

    ``segmentation`` is the segmentation the code came from (None if unknown).
    """

    bits: np.ndarray
    mask: np.ndarray
    bits_per_column: int
    segmentation: Segmentation | None = None

    @classmethod
    def from_bits(cls, bits: np.ndarray, mask: np.ndarray, segmentation: Segmentation | None = None) -> IrisCode:
        """Pack boolean ``(columns, bits_per_column)`` code and validity arrays."""
        bits = np.asarray(bits, dtype=bool)
        mask = np.asarray(mask, dtype=bool)
        if bits.shape != mask.shape or bits.ndim != 2:
            raise ValueError(f"bits {bits.shape} and mask {mask.shape} must be equal 2-D shapes")
        # Bits outside the mask are cleared so that equal codes compare equal byte for byte.
        return cls(np.packbits(bits & mask, axis=1), np.packbits(mask, axis=1), bits.shape[1], segmentation)

    @property
    def columns(self) -> int:
        return int(self.bits.shape[0])

    @property
    def n_bits(self) -> int:
        """Number of code bits (padding excluded)."""
        return self.columns * self.bits_per_column

    @property
    def n_valid(self) -> int:
        """Number of valid bits."""
        return int(np.bitwise_count(self.mask).sum())

    def unpack(self) -> tuple[np.ndarray, np.ndarray]:
        """Boolean ``(columns, bits_per_column)`` code and mask."""
        n = self.bits_per_column
        return (np.unpackbits(self.bits, axis=1, count=n).astype(bool),
                np.unpackbits(self.mask, axis=1, count=n).astype(bool))

    def code_only(self) -> IrisCode:
        """The code without the segmentation it carries: all that a comparison reads (the experiment handles a
        failed segmentation apart from the scores), so two codes equal here get equal scores from every
        comparator in this module."""
        return replace(self, segmentation=None)

    def shifted(self, s: int) -> IrisCode:
        """The code with its angle rolled by ``s`` columns (what rotating the eye by ``s`` columns gives)."""
        return IrisCode(np.roll(self.bits, s, axis=0), np.roll(self.mask, s, axis=0), self.bits_per_column,
                        self.segmentation)


def _check_codes(a: Any, b: Any) -> None:
    if not (isinstance(a, IrisCode) and isinstance(b, IrisCode)):
        raise InputError(f"iris codes expected, got {type(a).__name__} and {type(b).__name__}")
    if a.bits.shape != b.bits.shape or a.bits_per_column != b.bits_per_column:
        raise InputError(f"iris codes of different layouts: {a.bits.shape}/{a.bits_per_column} bits per column "
                         f"and {b.bits.shape}/{b.bits_per_column}; encode both with the same matcher settings")


def hamming_distance(a: IrisCode, b: IrisCode, max_shift: int, min_valid: int) -> float:
    """Fractional Hamming distance minimised over circular shifts of ``b`` by ``-max_shift … max_shift`` columns.

    For each shift, the distance is ``popcount((a ⊕ b) ∧ mₐ ∧ m_b) / popcount(mₐ ∧ m_b)``; shifts with fewer
    than ``min_valid`` bits valid in both are skipped, and if none is left the distance is 1.0 (an
    uncomparable pair counts as a non-match, never as a lucky match).  Symmetric: shifting ``b`` by ``s`` is
    shifting ``a`` by ``−s`` and the shift range is symmetric.
    """
    _check_codes(a, b)
    best = 1.0
    for s in range(-max_shift, max_shift + 1):
        bb = np.roll(b.bits, s, axis=0)
        m = a.mask & np.roll(b.mask, s, axis=0)
        valid = int(np.bitwise_count(m).sum())
        if valid < max(min_valid, 1):
            continue
        diff = int(np.bitwise_count((a.bits ^ bb) & m).sum())
        best = min(best, diff / valid)
    return best


def _words(packed: np.ndarray) -> np.ndarray:
    """``(n, bytes)`` uint8 → ``(words, n)`` uint64, zero-padded to whole words, word-major (see below)."""
    n, nbytes = packed.shape
    pad = (-nbytes) % 8
    if pad:
        packed = np.concatenate([packed, np.zeros((n, pad), np.uint8)], axis=1)
    return np.ascontiguousarray(packed.view(np.uint64).T)


#: Bytes of the working buffers of one block of :func:`hamming_all` (tuned on a 2-core x86 machine).
BLOCK_BYTES = 4 * 2**20


def hamming_all(codes_a: Sequence[IrisCode], codes_b: Sequence[IrisCode], max_shift: int, min_valid: int,
                memory: int = 32 * 2**20, block_bytes: int = BLOCK_BYTES) -> np.ndarray:
    """All-against-all :func:`hamming_distance`, ``(len(a), len(b))``, equal to the pairwise loop exactly.

    The codes are stacked as 64-bit words, word-major (``(words, n)``), and processed in blocks of
    ``(words, chunk_a, chunk_b)`` whose innermost axis runs over templates of ``b``: every numpy operation
    then has long contiguous inner loops, and the per-pair popcounts are sums over the outer axis.  For a
    chunk of ``b`` the rolled words of all shifts are prepared once; for a chunk of ``a`` its words are
    spread over the block once and reused for every shift (a broadcast operand costs ~1.7× more per
    operation).  Integer counts and one float64 division per shift give the same values as
    :func:`hamming_distance`.  Working memory is about ``memory`` bytes (of which ``block_bytes`` for the
    block buffers) besides the stacked codes (``2 × bits / 8`` bytes per template) and the result; chunks
    hold at least 16 templates of ``b`` and one of ``a``.
    """
    na, nb = len(codes_a), len(codes_b)
    out = np.ones((na, nb), dtype=np.float64)
    if na == 0 or nb == 0:
        return out
    first = codes_a[0]
    for c in (*codes_a, *codes_b):
        _check_codes(first, c)
    cols, bpc = first.bits.shape
    shifts = range(-max_shift, max_shift + 1)
    a_bits = _words(np.stack([c.bits.reshape(-1) for c in codes_a]))
    a_mask = _words(np.stack([c.mask.reshape(-1) for c in codes_a]))
    b_bits3 = np.stack([c.bits for c in codes_b])   # (nb, columns, bytes_per_column)
    b_mask3 = np.stack([c.mask for c in codes_b])
    n_words = a_bits.shape[0]
    count_dtype = np.uint16 if n_words * 64 < 2**16 else np.uint32
    # Most of the budget for the rolled words of a chunk of b (bits and mask, every shift); the block buffers
    # (per element four uint64 and one uint8) stay small, as numpy passes over them are cache-bound.
    per_elem = n_words * 33
    chunk_b = int(min(nb, max(16, memory // (2 * len(shifts) * 2 * n_words * 8))))
    chunk_a = int(max(1, min(na, block_bytes // (per_elem * chunk_b))))
    block = (n_words, chunk_a, chunk_b)
    rep_bits, rep_mask = np.empty(block, np.uint64), np.empty(block, np.uint64)
    m, x = np.empty(block, np.uint64), np.empty(block, np.uint64)
    cnt = np.empty(block, np.uint8)
    valid = np.empty(block[1:], count_dtype)
    diff = np.empty_like(valid)
    threshold = max(min_valid, 1)
    for j0 in range(0, nb, chunk_b):
        j1 = min(j0 + chunk_b, nb)
        nj = j1 - j0

        def rolled(stack3: np.ndarray, s: int, j0: int = j0, j1: int = j1, nj: int = nj) -> np.ndarray:
            return _words(np.roll(stack3[j0:j1], s, axis=1).reshape(nj, cols * bpc))[:, None, :]

        b_shifted = [(rolled(b_bits3, s), rolled(b_mask3, s)) for s in shifts]
        for i0 in range(0, na, chunk_a):
            i1 = min(i0 + chunk_a, na)
            ni = i1 - i0
            ab, am = rep_bits[:, :ni, :nj], rep_mask[:, :ni, :nj]
            np.copyto(ab, a_bits[:, i0:i1, None])
            np.copyto(am, a_mask[:, i0:i1, None])
            mm, xx, cc = m[:, :ni, :nj], x[:, :ni, :nj], cnt[:, :ni, :nj]
            vv, dd = valid[:ni, :nj], diff[:ni, :nj]
            best = out[i0:i1, j0:j1]
            for bb, bm in b_shifted:
                np.bitwise_and(am, bm, out=mm)
                np.bitwise_count(mm, out=cc)
                np.add.reduce(cc, axis=0, dtype=count_dtype, out=vv)
                np.bitwise_xor(ab, bb, out=xx)
                np.bitwise_and(xx, mm, out=xx)
                np.bitwise_count(xx, out=cc)
                np.add.reduce(cc, axis=0, dtype=count_dtype, out=dd)
                with np.errstate(invalid="ignore", divide="ignore"):
                    hd = np.where(vv >= threshold, dd.astype(np.float64) / vv.astype(np.float64), 1.0)
                np.minimum(best, hd, out=best)
    return out


def hamming_planes(codes_a: Sequence[Sequence[IrisCode]], codes_b: Sequence[Sequence[IrisCode]],
                   shifts: Sequence[int], min_valid: int, chunk: tuple[int, int] = (32, 256)) -> np.ndarray:
    """Distances of templates made of several bit planes under one mask, plane by plane at each shift:
    ``(shifts, planes, len(a), len(b))``.

    Entry ``[k, p, i, j]`` is ``hamming_all([a[p] for a in codes_a], [b[p].shifted(shifts[k]) for b in codes_b],
    0, min_valid)[i, j]`` exactly (the same integer counts, the same division).  When every template's planes share
    one mask (Monro's DCT planes: one usability per patch pair), the valid counts are computed once per shift for
    all planes and every code is packed once, not once per plane and shift; otherwise each plane and shift is a
    :func:`hamming_all` call.  ``chunk``: templates of ``a`` and ``b`` per block.
    """
    na, nb = len(codes_a), len(codes_b)
    n_planes = len(codes_a[0]) if na else 0
    out = np.ones((len(shifts), n_planes, na, nb), dtype=np.float64)
    if na == 0 or nb == 0:
        return out
    first = codes_a[0][0]
    for t in (*codes_a, *codes_b):
        if len(t) != n_planes:
            raise InputError(f"templates of {n_planes} and {len(t)} bit planes; encode both with the same settings")
        for c in t:
            _check_codes(first, c)
    if not all(np.array_equal(c.mask, t[0].mask) for t in (*codes_a, *codes_b) for c in t[1:]):
        for k, s in enumerate(shifts):
            for p in range(n_planes):
                out[k, p] = hamming_all([t[p] for t in codes_a], [t[p].shifted(s) for t in codes_b], 0, min_valid)
        return out
    cols, bpc = first.bits.shape
    a_bits = [_words(np.stack([t[p].bits.reshape(-1) for t in codes_a])) for p in range(n_planes)]
    a_mask = _words(np.stack([t[0].mask.reshape(-1) for t in codes_a]))
    b_bits3 = [np.stack([t[p].bits for t in codes_b]) for p in range(n_planes)]
    b_mask3 = np.stack([t[0].mask for t in codes_b])
    n_words = a_mask.shape[0]
    count_dtype = np.uint16 if n_words * 64 < 2**16 else np.uint32
    threshold = max(min_valid, 1)
    chunk_a, chunk_b = min(na, chunk[0]), min(nb, chunk[1])
    block = (n_words, chunk_a, chunk_b)
    m, x = np.empty(block, np.uint64), np.empty(block, np.uint64)
    cnt = np.empty(block, np.uint8)
    valid, diff = np.empty(block[1:], count_dtype), np.empty(block[1:], count_dtype)
    for j0 in range(0, nb, chunk_b):
        j1 = min(j0 + chunk_b, nb)
        nj = j1 - j0

        def rolled(stack3: np.ndarray, s: int, j0: int = j0, j1: int = j1, nj: int = nj) -> np.ndarray:
            return _words(np.roll(stack3[j0:j1], s, axis=1).reshape(nj, cols * bpc))[:, None, :]

        for k, s in enumerate(shifts):
            b_mask = rolled(b_mask3, s)
            b_bits = [rolled(b3, s) for b3 in b_bits3]
            for i0 in range(0, na, chunk_a):
                i1 = min(i0 + chunk_a, na)
                ni = i1 - i0
                mm, xx, cc = m[:, :ni, :nj], x[:, :ni, :nj], cnt[:, :ni, :nj]
                vv, dd = valid[:ni, :nj], diff[:ni, :nj]
                np.bitwise_and(a_mask[:, i0:i1, None], b_mask, out=mm)
                np.bitwise_count(mm, out=cc)
                np.add.reduce(cc, axis=0, dtype=count_dtype, out=vv)
                comparable = vv >= threshold
                denominator = vv.astype(np.float64)
                for p in range(n_planes):
                    np.bitwise_xor(a_bits[p][:, i0:i1, None], b_bits[p], out=xx)
                    np.bitwise_and(xx, mm, out=xx)
                    np.bitwise_count(xx, out=cc)
                    np.add.reduce(cc, axis=0, dtype=count_dtype, out=dd)
                    with np.errstate(invalid="ignore", divide="ignore"):
                        out[k, p, i0:i1, j0:j1] = np.where(comparable, dd.astype(np.float64) / denominator, 1.0)
    return out


def hamming_all_spectral(codes_a: Sequence[IrisCode], codes_b: Sequence[IrisCode], max_shift: int, min_valid: int,
                         groups: np.ndarray | None = None) -> np.ndarray:
    """:func:`hamming_all` from exact counts by cross-correlation (:func:`~forensics.impact.spectral.shift_counts`).

    Equal to :func:`hamming_all` and the pairwise loop exactly (the counts are exact integers; the division
    and the minimum are the same operations).  Faster for long codes tried at many shifts (``cr``, ``qsw``,
    Masek).  ``groups``: bits of a column that share their mask bit in every code (the matcher's layout).
    """
    out = np.ones((len(codes_a), len(codes_b)), dtype=np.float64)
    if len(codes_a) == 0 or len(codes_b) == 0:
        return out
    for c in (*codes_a, *codes_b):
        _check_codes(codes_a[0], c)
    threshold = max(min_valid, 1)
    for rows, cols, diff, valid in shift_counts(codes_a, codes_b, max_shift, groups):
        if diff is None or valid is None:           # counts not provably exact: bit by bit instead
            out[rows, cols] = hamming_all(codes_a[rows], codes_b[cols], max_shift, min_valid)
            continue
        with np.errstate(invalid="ignore", divide="ignore"):
            hd = np.where(valid >= threshold, diff / valid, 1.0)
        np.minimum(out[rows, cols], hd.min(axis=0), out=out[rows, cols])
    return out


class IrisCodeMatcher:
    """Shared comparison of the built-ins: masked fractional Hamming distance, minimised over shifts.

    A matcher whose code has a fixed *mask grouping* (bits of a column that always share their mask bit)
    returns it from :meth:`mask_groups`; its :meth:`compare_all` then uses the exact cross-correlation
    (:func:`hamming_all_spectral`), else the bit-packed :func:`hamming_all`.  Both equal the pairwise loop.
    """

    name: ClassVar[str] = ""
    higher_is_similar: ClassVar[bool] = False
    max_shift: int
    min_valid: float

    def _min_valid_bits(self, code: IrisCode) -> int:
        return math.ceil(self.min_valid * code.n_bits)

    def mask_groups(self) -> np.ndarray | None:
        """Group of each bit of a code column (bits of one group share their mask bit), or None: compare
        bit-packed (few bits or few shifts, where the cross-correlation does not pay)."""
        return None

    def compare(self, a: IrisCode, b: IrisCode) -> float:
        """Fractional Hamming distance, 0 (same) … 1; about 0.5 or less for different eyes (see the class)."""
        _check_codes(a, b)
        return hamming_distance(a, b, self.max_shift, self._min_valid_bits(a))

    def compare_all(self, templates_a: Sequence[IrisCode], templates_b: Sequence[IrisCode]) -> np.ndarray:
        """Vectorised :meth:`compare` of every pair; equal to the loop exactly."""
        if len(templates_a) == 0 or len(templates_b) == 0:
            return np.ones((len(templates_a), len(templates_b)))
        groups = self.mask_groups()
        need = self._min_valid_bits(templates_a[0])
        if groups is None:
            return hamming_all(templates_a, templates_b, self.max_shift, need)
        return hamming_all_spectral(list(templates_a), list(templates_b), self.max_shift, need, groups)
