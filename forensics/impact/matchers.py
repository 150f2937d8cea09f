"""The matcher interface, its loader, and two built-in iris codes.

A **matcher** is anything with ``name: str``, ``higher_is_similar: bool``, ``encode(image) -> template`` and
``compare(a, b) -> float`` (:class:`Matcher`); it may add a vectorised ``compare_all(templates_a,
templates_b) -> ndarray`` (use the module function :func:`compare_all`, which falls back on a double loop).

Built-ins (both distances, ``higher_is_similar = False``; both take an optional shared
:class:`~forensics.impact.segment.Segmenter` so one segmentation serves both):

``masek``  :class:`MasekMatcher` — L. Masek, *Recognition of Human Iris Patterns for Biometric
    Identification* (2003): each row of the 20×240 rubber sheet is filtered along the angle with a 1-D
    Log-Gabor filter (wavelength 18 samples, σ/f = 0.5); the phase of each response is quantised to two bits
    (signs of the real and imaginary parts).  9600 bits.
``ko``     :class:`KoMatcher` — J.-G. Ko, Y.-H. Gil, J.-H. Yoo and K.-I. Chung, "A novel and efficient feature
    extraction method for iris recognition", *ETRI Journal* 29(3), 2007: cells of 3×10 samples of a 30×360
    rubber sheet, cumulative sums of cell-mean deviations in groups of 5 cells, coded up/down/flat.

Both compare by the fractional Hamming distance over bits valid in both masks, minimised over circular
shifts along the angle; :meth:`~MasekMatcher.compare_all` does N×M templates at once on bit-packed 64-bit
words with ``np.bitwise_count`` and gives exactly the values of the pairwise loop.

The other four algorithms of the reference paper (USIT's ``qsw``, ``dct``, ``cr``, ``cb``) are in modules of
their own (:mod:`forensics.impact.qsw`, :mod:`~forensics.impact.dct`, :mod:`~forensics.impact.cr`,
:mod:`~forensics.impact.cb`) and built in by name too.

Matcher specs for :func:`load_matcher`: a built-in name | ``module.path:Class`` | ``path/to/file.py:Class``
| ``cmd:COMMAND`` (an external distance) | ``cmd+sim:COMMAND`` (an external similarity).  See
:class:`ExternalMatcher` for the command protocol.

Matchers travel to worker processes by pickle (the experiment runs on :mod:`forensics._shared.parallel`);
instances of a ``file.py:Class`` travel as the file's path, the class name and their state
(:mod:`forensics._shared.plugins`).
"""
from __future__ import annotations

import math
import shlex
import subprocess
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np

from forensics._shared.plugins import is_class_spec, load_class
from forensics._shared.errors import InputError, UsageError
from forensics.impact.segment import Segmentation, Segmenter


# --------------------------------------------------------------------------- interface
@runtime_checkable
class Matcher(Protocol):
    """What the experiment needs from a recognition system.

    ``encode`` turns an image (``(H, W)`` array as read, e.g. uint8) into a template of any type;
    ``compare`` scores two templates; ``higher_is_similar`` says which way the score points (False for
    distances).  An optional ``compare_all(templates_a, templates_b) -> ndarray`` of shape
    ``(len(a), len(b))`` is used by :func:`compare_all` when present; it must equal the loop of ``compare``.
    """

    name: str
    higher_is_similar: bool

    def encode(self, image: np.ndarray) -> Any: ...

    def compare(self, a: Any, b: Any) -> float: ...


def compare_all(matcher: Any, templates_a: Sequence[Any], templates_b: Sequence[Any]) -> np.ndarray:
    """The ``(len(a), len(b))`` float64 matrix of scores ``matcher.compare(a[i], b[j])``.

    Uses the matcher's own ``compare_all`` when it has one (checked for shape), else a double loop.
    """
    own = getattr(matcher, "compare_all", None)
    shape = (len(templates_a), len(templates_b))
    if callable(own):
        scores = np.asarray(own(templates_a, templates_b), dtype=np.float64)
        if scores.shape != shape:
            raise InputError(f"matcher {getattr(matcher, 'name', matcher)!r}: compare_all returned shape "
                             f"{scores.shape}, expected {shape}")
        return scores
    out = np.empty(shape, dtype=np.float64)
    for i, a in enumerate(templates_a):
        for j, b in enumerate(templates_b):
            out[i, j] = float(matcher.compare(a, b))
    return out


# --------------------------------------------------------------------------- bit-packed iris codes
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


class _IrisCodeMatcher:
    """Shared comparison of the built-ins: masked fractional Hamming distance, minimised over shifts."""

    name: ClassVar[str] = ""
    higher_is_similar: ClassVar[bool] = False
    max_shift: int
    min_valid: float

    def _min_valid_bits(self, code: IrisCode) -> int:
        return math.ceil(self.min_valid * code.n_bits)

    def compare(self, a: IrisCode, b: IrisCode) -> float:
        """Fractional Hamming distance, 0 (same) … 1; about 0.5 or less for different eyes (see the class)."""
        _check_codes(a, b)
        return hamming_distance(a, b, self.max_shift, self._min_valid_bits(a))

    def compare_all(self, templates_a: Sequence[IrisCode], templates_b: Sequence[IrisCode]) -> np.ndarray:
        """Vectorised :meth:`compare` of every pair; equal to the loop exactly."""
        if len(templates_a) == 0 or len(templates_b) == 0:
            return np.ones((len(templates_a), len(templates_b)))
        return hamming_all(templates_a, templates_b, self.max_shift, self._min_valid_bits(templates_a[0]))


# --------------------------------------------------------------------------- Masek
def log_gabor_1d(n: int, wavelength: float, sigma_on_f: float) -> np.ndarray:
    """Masek's 1-D Log-Gabor transfer function over ``n`` FFT bins (positive frequencies only).

    ``G(f) = exp(−(ln(f/f₀))² / (2 (ln σ/f)²))`` for ``0 < f ≤ 1/2`` with ``f₀ = 1/wavelength``, 0 at DC and at
    negative frequencies, so that the filtered signal is analytic and its phase is defined (as ``gaborconvolve``).
    """
    f = np.arange(n) / n
    g = np.zeros(n)
    pos = (f > 0) & (f <= 0.5)
    g[pos] = np.exp(-(np.log(f[pos] * wavelength)) ** 2 / (2 * np.log(sigma_on_f) ** 2))
    return g


class MasekMatcher(_IrisCodeMatcher):
    """Masek's 1-D Log-Gabor iris code with the masked fractional Hamming distance.

    Parameters
    ----------
    segmenter
        Shared segmenter (cache); a new one if None.
    radial, angular
        Rubber-sheet size (Masek: 20×240).
    wavelength, sigma_on_f
        Log-Gabor centre wavelength in angular samples and bandwidth ratio (Masek: 18 and 0.5).
    max_shift
        Circular shifts tried: ``±max_shift`` angular samples (Masek: 8, i.e. ±12° at 240 samples).
    min_valid
        Fraction of the code's bits that must be valid in both masks for a shift to count; if no shift
        has that many, the distance is 1.0.
    min_magnitude
        Bits whose filter response magnitude is below this fraction of the template's median magnitude are
        masked as unreliable (Masek only masks exact zeros; 0 disables).

    Notes
    -----
    Encoding: masked samples of the texture are replaced by the mean of the usable ones (as Masek does, so
    that occlusions do not ring through the filter), every row is filtered at once with ``np.fft``, and each
    angular sample gives two bits (``Re > 0``, ``Im > 0``) sharing the sample's mask.  Layout: one
    :class:`IrisCode` column per angular sample holding ``2 × radial`` bits.
    """

    name: ClassVar[str] = "masek"
    higher_is_similar: ClassVar[bool] = False

    def __init__(self, segmenter: Segmenter | None = None, *, radial: int = 20, angular: int = 240,
                 wavelength: float = 18.0, sigma_on_f: float = 0.5, max_shift: int = 8,
                 min_valid: float = 0.1, min_magnitude: float = 0.0) -> None:
        self.segmenter = segmenter if segmenter is not None else Segmenter()
        self.radial, self.angular = int(radial), int(angular)
        self.wavelength, self.sigma_on_f = float(wavelength), float(sigma_on_f)
        self.max_shift, self.min_valid, self.min_magnitude = int(max_shift), float(min_valid), float(min_magnitude)
        self._filter = log_gabor_1d(self.angular, self.wavelength, self.sigma_on_f)

    def encode_texture(self, texture: np.ndarray, mask: np.ndarray,
                       segmentation: Segmentation | None = None) -> IrisCode:
        """The code of an already normalised ``(radial, angular)`` texture and its usability mask."""
        t = np.asarray(texture, dtype=np.float64)
        usable = np.asarray(mask, dtype=bool)
        fill = float(t[usable].mean()) if usable.any() else 0.0
        t = np.where(usable, t, fill)
        response = np.fft.ifft(np.fft.fft(t, axis=1) * self._filter[None, :], axis=1)
        magnitude = np.abs(response)
        valid = usable & (magnitude > 1e-12 * max(float(magnitude.max()), 1e-300))
        if self.min_magnitude > 0 and valid.any():
            valid &= magnitude >= self.min_magnitude * float(np.median(magnitude[valid]))
        # Column c: [row0 Re, row0 Im, row1 Re, …] — both bits of a sample share its mask.
        bits = np.stack([response.real > 0, response.imag > 0], axis=2).transpose(1, 0, 2)
        vmask = np.stack([valid, valid], axis=2).transpose(1, 0, 2)
        r, a = t.shape
        return IrisCode.from_bits(bits.reshape(a, 2 * r), vmask.reshape(a, 2 * r), segmentation)

    def encode(self, image: np.ndarray) -> IrisCode:
        """Segment (cached), normalise and encode an eye image."""
        texture, mask, seg = self.segmenter.unwrap(image, self.radial, self.angular)
        return self.encode_texture(texture, mask, seg)


# --------------------------------------------------------------------------- Ko et al.
class KoMatcher(_IrisCodeMatcher):
    """Ko, Gil, Yoo & Chung (2007): cumulative-sum iris code with the masked Hamming distance.

    Parameters
    ----------
    segmenter
        Shared segmenter (cache); a new one if None.
    radial, angular
        Rubber-sheet size; default 30×360 so that cells of 3×10 samples give 10 rows × 36 columns of cells
        (10° per cell column).
    cell
        Cell size ``(rows, columns)`` in texture samples (the paper's 3×10).
    group
        Cells per group (the paper's 5).
    max_shift
        Circular shifts tried: ``±max_shift`` cell columns (default 2, ±20°).
    min_valid
        As for :class:`MasekMatcher`.

    Notes
    -----
    Each cell's value is the mean of its usable samples; a cell is masked unless more than half of its
    samples are usable.  Within a group of cells ``X₁…X₅`` with mean ``X̄`` the cumulative sums are
    ``S_k = S_{k−1} + (X_k − X̄)`` (``S₀ = 0``).  With ``k_max``, ``k_min`` the positions of the largest and
    smallest ``S_k`` (k = 1…5), the cells strictly after the first of them up to the second carry the path
    from one extreme to the other: they get code 1 ("up") if the maximum comes later, 2 ("down") if the
    minimum does; all other cells (around the extremes) get 0.  A code is stored as two bits (up, down), so
    "up" against "down" differs by 2 bits and either against 0 by 1.

    *Horizontal* groups (along the angle) are taken at **every** starting cell, circularly — each cell gets
    5 horizontal codes, one per position in a group.  The paper groups fixed blocks of 5; taking all of them
    makes a circular shift of whole cells an exact shift of the code (fixed blocks would regroup the cells
    and change the code), so the Hamming distance can be minimised over shifts as the paper intends.
    *Vertical* groups (along the radius, never shifted) are the paper's fixed blocks of 5 cell rows; cell
    rows beyond the last whole block get no vertical code.  A code is valid only when all cells of its group
    are (a masked cell's mean would distort every cumulative sum of the group).  Each cell column of the
    :class:`IrisCode` holds ``rows × (2·group + 2)`` bits (120 by default; 4320 bits per template).
    """

    name: ClassVar[str] = "ko"
    higher_is_similar: ClassVar[bool] = False

    def __init__(self, segmenter: Segmenter | None = None, *, radial: int = 30, angular: int = 360,
                 cell: tuple[int, int] = (3, 10), group: int = 5, max_shift: int = 2,
                 min_valid: float = 0.1) -> None:
        self.segmenter = segmenter if segmenter is not None else Segmenter()
        self.radial, self.angular = int(radial), int(angular)
        self.cell = (int(cell[0]), int(cell[1]))
        self.group = int(group)
        self.max_shift, self.min_valid = int(max_shift), float(min_valid)
        if self.angular % self.cell[1]:
            raise UsageError(f"ko: angular samples ({self.angular}) must be a multiple of the cell width "
                             f"({self.cell[1]})")
        if self.radial < self.cell[0] or self.group < 2 or self.angular // self.cell[1] < self.group:
            raise UsageError("ko: the texture must hold at least one cell row and one group of cells per row")

    def cells(self, texture: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cell means (of usable samples) and cell validity, ``(cell rows, cell columns)``."""
        ch, cw = self.cell
        rows, cols = texture.shape[0] // ch, texture.shape[1] // cw
        t = np.asarray(texture, dtype=np.float64)[: rows * ch, : cols * cw]
        m = np.asarray(mask, dtype=bool)[: rows * ch, : cols * cw]
        tm = np.where(m, t, 0.0).reshape(rows, ch, cols, cw)
        n = m.reshape(rows, ch, cols, cw).sum(axis=(1, 3))
        s = tm.sum(axis=(1, 3))
        means = s / np.maximum(n, 1)
        return means, n * 2 > ch * cw

    @staticmethod
    def group_codes(x: np.ndarray) -> np.ndarray:
        """Codes (0 flat, 1 up, 2 down) of groups along the last axis of ``x`` (``(…, group)``)."""
        s = np.cumsum(x - x.mean(axis=-1, keepdims=True), axis=-1)
        kmax = np.argmax(s, axis=-1)[..., None]
        kmin = np.argmin(s, axis=-1)[..., None]
        k = np.arange(x.shape[-1])
        lo, hi = np.minimum(kmax, kmin), np.maximum(kmax, kmin)
        between = (k > lo) & (k <= hi)
        return np.where(between, np.where(kmax > kmin, 1, 2), 0).astype(np.uint8)

    def encode_texture(self, texture: np.ndarray, mask: np.ndarray,
                       segmentation: Segmentation | None = None) -> IrisCode:
        """The code of an already normalised ``(radial, angular)`` texture and its usability mask."""
        means, ok = self.cells(texture, mask)
        rows, cols = means.shape
        g = self.group
        # Horizontal: every circular window of g cells; code of cell c at position o comes from window c − o.
        start = np.arange(cols)
        idx = (start[:, None] + np.arange(g)[None, :]) % cols             # (windows, g)
        hcode = self.group_codes(means[:, idx])                            # (rows, windows, g)
        hvalid = np.broadcast_to(ok[:, idx].all(axis=2, keepdims=True), hcode.shape)
        cell_of = idx                                                      # window w, position o → cell
        h_by_cell = np.empty((rows, cols, g), np.uint8)
        hv_by_cell = np.empty((rows, cols, g), bool)
        for o in range(g):
            h_by_cell[:, cell_of[:, o], o] = hcode[:, :, o]
            hv_by_cell[:, cell_of[:, o], o] = hvalid[:, :, o]
        # Vertical: the paper's fixed blocks of g cell rows.
        v_code = np.zeros((rows, cols), np.uint8)
        v_valid = np.zeros((rows, cols), bool)
        for r0 in range(0, rows - g + 1, g):
            v_code[r0:r0 + g] = np.moveaxis(self.group_codes(np.moveaxis(means[r0:r0 + g], 0, -1)), -1, 0)
            v_valid[r0:r0 + g] = ok[r0:r0 + g].all(axis=0, keepdims=True)
        codes = np.concatenate([h_by_cell, v_code[:, :, None]], axis=2)     # (rows, cols, g + 1)
        valid = np.concatenate([hv_by_cell, v_valid[:, :, None]], axis=2)
        bits = np.stack([codes == 1, codes == 2], axis=3)                  # (rows, cols, g + 1, 2)
        vbits = np.stack([valid, valid], axis=3)
        # Angle-major: one IrisCode column per cell column.
        bits = bits.transpose(1, 0, 2, 3).reshape(cols, -1)
        vbits = vbits.transpose(1, 0, 2, 3).reshape(cols, -1)
        return IrisCode.from_bits(bits, vbits, segmentation)

    def encode(self, image: np.ndarray) -> IrisCode:
        """Segment (cached), normalise and encode an eye image."""
        texture, mask, seg = self.segmenter.unwrap(image, self.radial, self.angular)
        return self.encode_texture(texture, mask, seg)


#: Built-in matchers by name: a class, or ``module:Class`` for those in modules of their own (loaded on first
#: use: they import :class:`IrisCode` from here).
BUILTIN_MATCHERS: dict[str, type | str] = {
    "masek": MasekMatcher, "ko": KoMatcher,
    "qsw": "forensics.impact.qsw:QswMatcher", "dct": "forensics.impact.dct:DctMatcher",
    "cr": "forensics.impact.cr:CrMatcher", "cb": "forensics.impact.cb:CbMatcher",
}


# --------------------------------------------------------------------------- external programs
class ExternalMatcher:
    """A matcher that is a program, run once per encode and once per comparison.

    Protocol (``CMD`` is ``command`` split like a shell would, without a shell):

    * ``CMD encode IMAGE.png TEMPLATE`` must write the template file; the image is the array written as an
      8- or 16-bit grey PNG.  The template is kept as the file's bytes.
    * ``CMD compare TEMPLATE_A TEMPLATE_B`` must print one number (the score) on stdout.

    A non-zero exit status, a missing template file, a timeout or an output that is not one number raise
    :class:`~forensics._shared.errors.InputError` naming the command.  There is no batch mode: budget one
    process start per comparison (a few ms in C, ~30 ms for a Python script).

    Parameters
    ----------
    command
        The program and its leading arguments, e.g. ``"python my_matcher.py"``.
    higher_is_similar
        True if the printed score is a similarity, False for a distance.
    name
        Name in results; default ``"cmd:" + command``.
    timeout
        Seconds allowed per call (None: no limit).
    """

    def __init__(self, command: str, higher_is_similar: bool = False, name: str | None = None,
                 timeout: float | None = 60.0) -> None:
        self.command = command
        self.argv = shlex.split(command)
        if not self.argv:
            raise UsageError("cmd: needs a command, e.g. cmd:'python my_matcher.py'")
        self.higher_is_similar = bool(higher_is_similar)
        self.name = name or f"cmd:{command}"
        self.timeout = timeout

    def _run(self, *args: str) -> str:
        try:
            proc = subprocess.run([*self.argv, *args], capture_output=True, text=True, timeout=self.timeout,
                                  check=False)
        except FileNotFoundError as exc:
            raise InputError(f"external matcher '{self.command}': cannot run it ({exc})") from exc
        except subprocess.TimeoutExpired as exc:
            raise InputError(f"external matcher '{self.command}' {args[0]}: no answer within {self.timeout} s") from exc
        if proc.returncode != 0:
            tail = (proc.stderr or proc.stdout).strip().splitlines()
            detail = f": {tail[-1]}" if tail else ""
            raise InputError(f"external matcher '{self.command}' {args[0]} failed with exit status "
                             f"{proc.returncode}{detail}")
        return proc.stdout

    def encode(self, image: np.ndarray) -> bytes:
        """Run ``CMD encode IMAGE TEMPLATE`` and return the template file's bytes."""
        from forensics.io.images import write_image

        img = np.asarray(image)
        if img.dtype not in (np.uint8, np.uint16):
            raise InputError(f"external matcher '{self.command}': images must be uint8 or uint16, got {img.dtype}")
        with tempfile.TemporaryDirectory(prefix="forensics-matcher-") as tmp:
            image_path = Path(tmp) / "image.png"
            template_path = Path(tmp) / "template"
            write_image(image_path, img)
            self._run("encode", str(image_path), str(template_path))
            if not template_path.is_file():
                raise InputError(f"external matcher '{self.command}' encode wrote no template file")
            return template_path.read_bytes()

    def compare(self, a: bytes, b: bytes) -> float:
        """Run ``CMD compare A B`` on the two templates and parse the number it prints."""
        with tempfile.TemporaryDirectory(prefix="forensics-matcher-") as tmp:
            pa, pb = Path(tmp) / "a", Path(tmp) / "b"
            pa.write_bytes(bytes(a))
            pb.write_bytes(bytes(b))
            out = self._run("compare", str(pa), str(pb))
        try:
            value = float(out.strip())
        except ValueError:
            shown = out.strip()[:60] or "nothing"
            raise InputError(f"external matcher '{self.command}' compare printed {shown!r}, not one number") from None
        if math.isnan(value):
            raise InputError(f"external matcher '{self.command}' compare printed NaN")
        return value


# --------------------------------------------------------------------------- loading
SPEC_FORMS = ("a built-in name (" + ", ".join(BUILTIN_MATCHERS) + "), module.path:Class, path/to/file.py:Class, "
              "cmd:COMMAND (distance) or cmd+sim:COMMAND (similarity)")


def _check_matcher(obj: Any, spec: str) -> Any:
    missing = [attr for attr in ("encode", "compare") if not callable(getattr(obj, attr, None))]
    missing += [attr for attr in ("name", "higher_is_similar") if not hasattr(obj, attr)]
    if missing:
        raise UsageError(f"matcher '{spec}' lacks {', '.join(missing)}: a matcher needs encode(image), "
                         "compare(a, b), name and higher_is_similar")
    if not isinstance(obj.name, str) or not obj.name:
        raise UsageError(f"matcher '{spec}': name must be a non-empty string")
    if not isinstance(obj.higher_is_similar, (bool, np.bool_)):
        raise UsageError(f"matcher '{spec}': higher_is_similar must be True or False")
    return obj


def load_matcher(spec: str, segmenter: Segmenter | None = None) -> Matcher:
    """A matcher from a spec string.

    Parameters
    ----------
    spec
        A built-in name (:data:`BUILTIN_MATCHERS`); ``module.path:Class``; ``path/to/file.py:Class``
        (loaded with ``importlib.util.spec_from_file_location``); ``cmd:COMMAND`` (an
        :class:`ExternalMatcher` whose score is a distance) or ``cmd+sim:COMMAND`` (a similarity).  A user's
        class is instantiated with no arguments.
    segmenter
        Shared segmenter for the built-ins (ignored by the others).

    Raises
    ------
    UsageError
        For a spec of none of these forms, a module, file or class that cannot be loaded, or an object
        lacking ``encode``/``compare``/``name``/``higher_is_similar`` (the message names what is missing).
    """
    spec = str(spec).strip()
    if spec in BUILTIN_MATCHERS:
        builtin = BUILTIN_MATCHERS[spec]
        return (load_class(builtin, "matcher") if isinstance(builtin, str) else builtin)(segmenter=segmenter)
    for prefix, similar in (("cmd:", False), ("cmd+sim:", True)):
        if spec.startswith(prefix):
            return ExternalMatcher(spec[len(prefix):].strip(), higher_is_similar=similar, name=spec)
    if not is_class_spec(spec):
        raise UsageError(f"unknown matcher '{spec}'; give {SPEC_FORMS}")
    cls = load_class(spec, "matcher")
    cls_name = cls.__name__
    try:
        obj = cls()
    except Exception as exc:
        raise UsageError(f"matcher '{spec}': {cls_name}() failed ({type(exc).__name__}: {exc}); a matcher class "
                         "must be constructible with no arguments") from exc
    return _check_matcher(obj, spec)


def load_matchers(specs: Sequence[str]) -> list[Matcher]:
    """Matchers for several specs, the built-ins sharing one :class:`Segmenter` (one segmentation per image).

    Raises
    ------
    UsageError
        For a bad spec (see :func:`load_matcher`) or two matchers with the same name.
    """
    segmenter = Segmenter()
    matchers = [load_matcher(s, segmenter=segmenter) for s in specs]
    names = [m.name for m in matchers]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise UsageError(f"matcher names must be unique; {', '.join(dupes)} given more than once")
    return matchers
