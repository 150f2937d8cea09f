"""Exact masked Hamming counts of all pairs at every circular shift, by cross-correlation in the frequency domain.

For codes ``a``, ``b`` (0/1 bits cleared outside their masks ``mₐ``, ``m_b``) and a shift ``s`` of ``b`` along
the angle, the masked Hamming distance of :func:`~forensics.impact.iriscode.hamming_distance` is
``diff(s) / valid(s)`` with

    valid(s) = Σ mₐ · m_b(s)            diff(s) = Σ mₐ m_b(s) (a ⊕ b(s)) = Σ a (m_b(s) − 2 b(s)) + mₐ b(s)

(the sums run over every bit of every column; ``a ⊕ b = a + b − 2ab`` for bits, and ``a mₐ = a``).  Both are
circular cross-correlations along the angle of a few rows per template, so the rows are Fourier-transformed
once per template and every pair's correlations at *all* shifts are a sum over rows of products of spectra:
one matrix product per frequency (BLAS), then a small real matrix that turns the spectra into the values at the
``2 · max_shift + 1`` shifts wanted.  Bit-packed Hamming distances (:func:`~forensics.impact.iriscode.hamming_all`)
cost bits × shifts word operations per pair; this costs rows × frequencies multiply-adds, far fewer for long
codes tried at many shifts (``cr``: 43,008 bits at 35 shifts).

**Mask groups.** Bits of a column whose mask bit is the same in every template (both phase bits of a Masek
sample, the four path bits of a ``cr`` stripe) form a *group*: the group shares one mask row, and its ``diff``
terms ``mₐ Σ b`` collapse into one row — ``bits + groups`` rows per template instead of ``2 × bits``.  The
groups are the matcher's layout (``IrisCodeMatcher.mask_groups``), checked against the codes (codes that break
them, e.g. made by hand, are correlated bit by bit, still exactly).

**Exactness.**  The correlations are integers; the floating-point values are rounded to the nearest integer and
then divided exactly as :func:`~forensics.impact.iriscode.hamming_all` does, so the distances are the pairwise
loop's bit for bit as long as every rounding error is below 0.5.  In float64 the error of the whole computation
is bounded by about ``2 (2 γ + (K + F) u) Σ_k ‖a_k‖₂ ‖b_k‖₂`` (``u`` = 2⁻⁵³, ``γ ≈ 10 u log₂ N`` for the FFT of
``N`` columns, ``K`` rows, ``F`` frequencies; rows hold values of magnitude ≤ group size): for ``cr`` (512
columns, 105 + 21 rows) ≈ 10⁻⁸, seven orders of magnitude below 0.5 (measured: ≈ 10⁻¹⁰).  As a guard against
a layout this bound does not cover, a block whose values are not all within 10⁻³ of integers is handed back
empty, and :func:`~forensics.impact.iriscode.hamming_all_spectral` computes it bit by bit instead.
"""
from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING

import numpy as np
import scipy.fft
from threadpoolctl import ThreadpoolController

if TYPE_CHECKING:
    from forensics.impact.iriscode import IrisCode

__all__ = ["shift_counts"]

#: Largest distance from an integer accepted for a correlation (see the module's note on exactness).
_TOLERANCE = 1e-3
#: Templates transformed at once (their rows stay in cache through the FFT along the non-contiguous columns).
_FFT_TEMPLATES = 8


def _unpacked(codes: Sequence[IrisCode]) -> tuple[np.ndarray, np.ndarray]:
    """Bits (cleared outside the mask) and masks, ``(n, columns, bits_per_column)`` uint8."""
    n_bits = codes[0].bits_per_column
    bits = np.unpackbits(np.stack([c.bits for c in codes]), axis=2, count=n_bits)
    mask = np.unpackbits(np.stack([c.mask for c in codes]), axis=2, count=n_bits)
    return bits & mask, mask


def _group_layout(groups: np.ndarray | None, n_bits: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(group of each bit, first bit of each group, group sizes)``; every bit its own group if None."""
    g = np.arange(n_bits) if groups is None else np.asarray(groups, dtype=np.intp)
    if g.shape != (n_bits,) or g.min() < 0:
        raise ValueError(f"mask groups must give a group ≥ 0 for each of the {n_bits} bits of a column")
    sizes = np.bincount(g)
    if (sizes == 0).any():
        raise ValueError("mask groups must be numbered 0 … G − 1 without gaps")
    first = np.array([np.flatnonzero(g == k)[0] for k in range(sizes.size)])
    return g, first, sizes


def _groups_hold(codes: Sequence[IrisCode], layout: tuple[np.ndarray, np.ndarray, np.ndarray]) -> bool:
    """Whether every bit of every code has the mask bit of its group's first bit."""
    g, first, _ = layout
    n_bits = codes[0].bits_per_column
    for c in codes:
        mask = np.unpackbits(c.mask, axis=1, count=n_bits)
        if not np.array_equal(mask, mask[:, first][:, g]):
            return False
    return True


def _time_rows(codes: Sequence[IrisCode], layout: tuple[np.ndarray, np.ndarray, np.ndarray], side: str
               ) -> np.ndarray:
    """The rows to correlate, columns outermost: side "a" ``(columns, n, rows)`` with rows ``[a_k…, mₐ_g…]``;
    side "b" ``(columns, rows, n)`` with rows ``[m_b,g(k) − 2 b_k…, Σ_{k∈g} b_k…, m_b,g…]`` (float64)."""
    g, first, sizes = layout
    bits, mask = _unpacked(codes)
    group_mask = mask[:, :, first]                 # the groups hold (checked by shift_counts)
    if side == "a":
        return np.concatenate([bits, group_mask], axis=2).transpose(1, 0, 2).astype(np.float64, order="C")
    # Written straight into the (columns, rows, n) layout; the group sums as one product with the groups'
    # indicator matrix (small integers: exact in float64): 0.42 ms per cr template against 0.67 for a reduceat
    # over the reordered bits and a transposing copy.
    n, columns, n_bits = bits.shape
    n_groups = sizes.size
    indicator = np.zeros((n_bits, n_groups))
    indicator[np.arange(n_bits), g] = 1.0
    bits_t = bits.transpose(1, 2, 0)                                  # (columns, bits, n) views
    mask_t = group_mask.transpose(1, 2, 0)
    rows = np.empty((columns, n_bits + 2 * n_groups, n))
    np.multiply(bits_t, -2.0, out=rows[:, :n_bits])
    rows[:, :n_bits] += mask_t[:, g]
    np.matmul(indicator.T, bits_t.astype(np.float64), out=rows[:, n_bits:n_bits + n_groups])
    rows[:, n_bits + n_groups:] = mask_t
    return rows


def _spectra(codes: Sequence[IrisCode], layout: tuple[np.ndarray, np.ndarray, np.ndarray], side: str,
             buffers: Sequence[np.ndarray] | None = None) -> tuple[np.ndarray, ...]:
    """Real-split spectra of the ``diff`` and ``valid`` rows (:func:`_time_rows`) of ``codes`` for one side.

    Side "a": for the diff rows and the valid rows ``[size_g · mₐ_g…]``, two ``(F, n, 2K)`` arrays each,
    ``[Re, Im]`` and ``[−Im, Re]``.  Side "b": for the diff rows and the valid rows ``[m_b,g…]``, one
    ``(F, 2K, n)`` array ``[Re; Im]``.  An a-side row of the first kind times a b-side column is the real part
    of ``conj(a) b``, of the second kind its imaginary part.  Returns ``(diff_re, diff_im, valid_re,
    valid_im)`` for "a" and ``(diff, valid)`` for "b"; all C-contiguous, as BLAS wants them.  With ``buffers``
    (flat float64 arrays from :func:`_buffers`, one per array returned) the arrays are views of their first
    elements: one allocation serves every chunk of a comparison.
    """
    n, n_freq, n_valid = len(codes), codes[0].columns // 2 + 1, layout[2].size
    n_diff = codes[0].bits_per_column + (0 if side == "a" else n_valid)
    sizes = layout[2].astype(np.float64)
    shapes = _spectra_shapes(n, n_freq, n_diff, n_valid, side)
    if buffers is None:
        buffers = _buffers(shapes)
    out = [b[:int(np.prod(shape))].reshape(shape) for b, shape in zip(buffers, shapes, strict=True)]
    # A few templates at a time, so that their rows stay in cache from unpacking to the split spectra.
    for i0 in range(0, n, _FFT_TEMPLATES):
        i = slice(i0, min(i0 + _FFT_TEMPLATES, n))
        spec = scipy.fft.rfft(_time_rows(codes[i], layout, side), axis=0)
        if side == "a":                                                                 # (F, n_i, rows)
            valid = spec[:, :, n_diff:] * sizes
            for (re, im), part in zip(((0, 1), (2, 3)), (spec, valid)):
                k = part.shape[2]
                out[re][:, i, :k], out[re][:, i, k:] = part.real, part.imag
                np.negative(part.imag, out=out[im][:, i, :k])
                out[im][:, i, k:] = part.real
        else:                                                                           # (F, rows, n_i)
            for o, part in zip(out, (spec[:, :n_diff], spec[:, n_diff:])):
                k = part.shape[1]
                o[:, :k, i], o[:, k:, i] = part.real, part.imag
    return tuple(out)


def _spectra_shapes(n: int, n_freq: int, n_diff: int, n_valid: int, side: str) -> list[tuple[int, int, int]]:
    """Shapes of :func:`_spectra`'s arrays for ``n`` templates."""
    if side == "a":
        return [(n_freq, n, 2 * k) for k in (n_diff + n_valid, n_diff + n_valid, n_valid, n_valid)]
    return [(n_freq, 2 * k, n) for k in (n_diff, n_valid)]


def _buffers(shapes: Sequence[tuple[int, ...]]) -> list[np.ndarray]:
    """Flat float64 buffers holding arrays of ``shapes``.  Allocated once per comparison and reused chunk after
    chunk: a fresh allocation this large is new pages, and a first touch of a page costs more than the
    arithmetic that fills it (measured 0.5–7 µs per 4 KiB page on the development machine)."""
    return [np.empty(int(np.prod(shape))) for shape in shapes]


def _inverse(columns: int, n_freq: int, max_shift: int) -> np.ndarray:
    """``(shifts, 2F)`` real matrix from ``[Re; Im]`` of a cross-spectrum to the correlation at each shift.

    ``r(s) = Σ_c x[c] y[c − s] = (1/N) Σ_f w_f Re(conj(X_f) Y_f e^{−2πi f s / N})`` over the ``F`` frequencies of
    a real FFT (``w`` = 2 except at 0 and at N/2): the shift of ``y`` by ``s`` is ``np.roll(y, s)``.
    """
    f = np.arange(n_freq)
    w = np.full(n_freq, 2.0)
    w[0] = 1.0
    if columns % 2 == 0:
        w[-1] = 1.0
    theta = 2 * np.pi * np.outer(np.arange(-max_shift, max_shift + 1), f) / columns
    return np.concatenate([w * np.cos(theta), w * np.sin(theta)], axis=1) / columns


def _correlate(a_re: np.ndarray, a_im: np.ndarray, b: np.ndarray, inverse: np.ndarray, buffer: np.ndarray
               ) -> np.ndarray:
    """``(shifts, na, nb)`` correlations from a-side ``(F, na, 2K)`` and b-side ``(F, 2K, nb)`` spectra."""
    n_freq, na, nb = a_re.shape[0], a_re.shape[1], b.shape[2]
    products = buffer[: 2 * n_freq * na * nb].reshape(2, n_freq, na, nb)
    for f in range(n_freq):                      # one BLAS product per frequency (faster than a stacked matmul)
        np.matmul(a_re[f], b[f], out=products[0, f])
        np.matmul(a_im[f], b[f], out=products[1, f])
    return (inverse @ products.reshape(2 * n_freq, na * nb)).reshape(-1, na, nb)


def _rounded(values: np.ndarray) -> tuple[np.ndarray, bool]:
    r = np.rint(values)
    return r, bool(np.abs(values - r).max(initial=0.0) <= _TOLERANCE)


def shift_counts(codes_a: Sequence[IrisCode], codes_b: Sequence[IrisCode], max_shift: int,
                 groups: np.ndarray | None = None, memory: int = 640 * 2**20
                 ) -> Iterator[tuple[slice, slice, np.ndarray | None, np.ndarray | None]]:
    """Blocks ``(rows, cols, diff, valid)`` of the exact counts at every shift ``−max_shift … max_shift``.

    ``diff`` and ``valid`` are float64 ``(shifts, rows, cols)`` arrays of integers: the masked disagreeing and
    valid bits of ``codes_a[rows]`` against ``codes_b[cols]`` rolled by each shift (``IrisCode.shifted``).
    ``groups`` (see the module's note) is used only if it holds for every code, else each bit is its own group.
    Both are None for a block whose values were not all within 10⁻³ of integers (see the module's note; not
    seen in practice): the caller computes that block another way.  All codes must share one layout (the
    caller checks).  Working memory at most about ``memory`` bytes: half for the spectra of ``codes_a`` (each
    computed once if they fit: 308 ``cr`` templates at the default), an eighth each for a chunk of
    ``codes_b``'s and for the products.
    """
    na, nb = len(codes_a), len(codes_b)
    if na == 0 or nb == 0:
        return
    first = codes_a[0]
    columns, n_bits = first.columns, first.bits_per_column
    layout = _group_layout(groups, n_bits)
    if groups is not None and not (_groups_hold(codes_a, layout) and _groups_hold(codes_b, layout)):
        layout = _group_layout(None, n_bits)                 # not this matcher's codes: every bit its own group
    n_freq = columns // 2 + 1
    inverse = _inverse(columns, n_freq, max_shift)
    per_template = n_freq * 2 * (n_bits + 2 * layout[2].size) * 8       # bytes of one template's b-side spectra
    chunk_a = int(max(1, min(na, memory // 2 // (2 * per_template))))   # the a side holds two arrays per part
    chunk_b = int(max(1, min(nb, 128, memory // 8 // per_template)))
    # Products of a sub-block of a's rows with the b chunk: 2F values per pair.
    sub_a = int(max(1, min(chunk_a, memory // 8 // (2 * n_freq * 8 * chunk_b))))
    buffer = np.empty(2 * n_freq * sub_a * chunk_b)
    # The products are hundreds of mid-sized BLAS calls: on several BLAS threads they cost several times the
    # CPU of one thread (threads spin between calls, worse when other processes share the cores), so each block
    # runs on one, as in the experiment's worker processes; parallelism belongs to the caller's workers.
    blas = ThreadpoolController()
    n_diff_b = n_bits + layout[2].size
    a_buffers = _buffers(_spectra_shapes(chunk_a, n_freq, n_bits, layout[2].size, "a"))
    b_buffers = _buffers(_spectra_shapes(chunk_b, n_freq, n_diff_b, layout[2].size, "b"))
    for i0 in range(0, na, chunk_a):
        a_diff_re, a_diff_im, a_valid_re, a_valid_im = _spectra(codes_a[i0:min(i0 + chunk_a, na)], layout, "a",
                                                                a_buffers)
        for j0 in range(0, nb, chunk_b):
            cols_b = slice(j0, min(j0 + chunk_b, nb))
            b_diff, b_valid = _spectra(codes_b[cols_b], layout, "b", b_buffers)
            for k0 in range(0, a_diff_re.shape[1], sub_a):
                k = slice(k0, min(k0 + sub_a, a_diff_re.shape[1]))
                with blas.limit(limits=1, user_api="blas"):
                    diff, diff_ok = _rounded(_correlate(a_diff_re[:, k], a_diff_im[:, k], b_diff, inverse, buffer))
                    valid, valid_ok = _rounded(_correlate(a_valid_re[:, k], a_valid_im[:, k], b_valid, inverse,
                                                          buffer))
                rows_a = slice(i0 + k.start, i0 + k.stop)
                if diff_ok and valid_ok:
                    yield rows_a, cols_b, diff, valid
                else:
                    yield rows_a, cols_b, None, None
