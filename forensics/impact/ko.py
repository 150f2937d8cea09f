"""Ko et al.'s cumulative-sum iris code.

J.-G. Ko, Y.-H. Gil, J.-H. Yoo and K.-I. Chung, "A novel and efficient feature extraction method for iris
recognition", *ETRI Journal* 29(3), 2007; USIT's ``ko``.
"""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from forensics._shared.errors import UsageError
from forensics.impact.iriscode import IrisCode, IrisCodeMatcher
from forensics.impact.segment import Segmentation, Segmenter


class KoMatcher(IrisCodeMatcher):
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
