"""Monro et al.'s DCT iris code: USIT's ``dct`` (with its comparator ``dctc``).

D. M. Monro, S. Rakshit and D. Zhang, "DCT-based iris recognition", *IEEE Transactions on Pattern Analysis
and Machine Intelligence* 29(4), 2007, 586–595.

The published method, as implemented here:

1. The normalised iris is divided into overlapping *angular patches*: ``patch`` = 8 radial × 12 angular
   samples, overlapping by half in both directions (steps of 4 rows and 6 columns), slanted by 45° in the
   normalised image (each row of a patch, going outwards, starts one column further back along the angle —
   ``slant`` = 1 column per row; USIT's default shear is 2 columns per row, its tables also offer 45°).
   USIT skips the 3 rows nearest the pupil and takes 12 rows of patches (rows 3 … 54 of 64).
2. Each patch is averaged across its width with a Hanning window into a radial 1-D patch vector, which is
   windowed by a Hanning window along its length and transformed by the 1-D DCT-II.
3. The differences between the DCT coefficients of angularly adjacent patches are taken, and the code is
   their zero crossings: bit ``1`` where the coefficient increases from one patch to the next, ``0`` where
   it decreases.  USIT keeps the first three coefficients (``coefficients = (0, 1, 2)``); each forms its own
   bit plane of 12 rows × 86 patches.  (USIT's ``dct`` instead sets a bit where the difference changes sign
   between consecutive patch pairs; we follow the paper's wording.)
4. Comparison is Monro et al.'s *product of sum*: the fractional Hamming distance of each bit plane,
   combined by their geometric mean, minimised over relative rotations.

Texture size: USIT's 64 rows, but 516 rather than 512 angular samples, so that 86 patch steps of 6 columns
close the circle exactly: a rotation by whole patches is then an exact roll of the code.  Rotations by a
fraction of a patch are handled as USIT does, by encoding the texture also rotated by 2 and 4 columns
(``offsets``) and comparing every rotated version of one template with the unrotated other; together with
shifts of ``±max_shift`` patches this covers every even rotation up to ±(6 · max_shift + 4) columns —
±16 columns = ±11.2° with the default ``max_shift = 2`` (USIT compares ±24 of 512 columns in steps of 4).

Masks: a patch is usable when more than half of its (slanted) samples are; a bit when both patches of its
difference are.  USIT's ``dctc`` ignores masks.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np
from scipy.fft import dct as _dct

from forensics._shared.errors import InputError, UsageError
from forensics.impact.iriscode import IrisCode, hamming_distance, hamming_planes
from forensics.impact.segment import Segmentation, Segmenter
from forensics.impact.texture import fill_unusable

__all__ = ["DctMatcher", "DctTemplate", "patch_coefficients"]


@dataclass(frozen=True, eq=False)
class DctTemplate:
    """A Monro code: ``codes[o][c]`` is the bit plane of coefficient ``c`` of the texture rotated by offset ``o``.

    Every plane is an :class:`~forensics.impact.iriscode.IrisCode` with one column per patch (angle) and
    one bit per patch row.  ``codes[0]`` is the unrotated texture.
    """

    codes: tuple[tuple[IrisCode, ...], ...]
    offsets: tuple[int, ...]
    segmentation: Segmentation | None = None

    def code_only(self) -> DctTemplate:
        """The planes and offsets without any segmentation: all that the comparison reads."""
        return replace(self, codes=tuple(tuple(c.code_only() for c in row) for row in self.codes), segmentation=None)


def _hann(n: int) -> np.ndarray:
    """A Hanning window of ``n`` non-zero weights (the ``n`` inner points of one of ``n + 2``)."""
    return np.hanning(n + 2)[1:-1]


def patch_coefficients(texture: np.ndarray, mask: np.ndarray, *, first_row: int = 3, patch_rows: int = 12,
                       patch: tuple[int, int] = (8, 12), slant: int = 1,
                       coefficients: tuple[int, ...] = (0, 1, 2)) -> tuple[np.ndarray, np.ndarray]:
    """DCT coefficients of the overlapping slanted patches, and the patches' usability.

    Returns ``(coeffs, usable)``: ``coeffs`` of shape ``(len(coefficients), patch_rows, n_patches)`` and
    ``usable`` of shape ``(patch_rows, n_patches)``, with ``n_patches = angular / (patch width / 2)``.
    """
    ph, pw = int(patch[0]), int(patch[1])
    sh, sw = ph // 2, pw // 2
    t = fill_unusable(texture, mask).astype(np.float64)
    m = np.asarray(mask, dtype=bool)
    rows, cols = t.shape
    used = (patch_rows + 1) * sh
    if first_row + used > rows:
        raise UsageError(f"dct: {patch_rows} rows of {ph}-row patches from row {first_row} need {first_row + used} "
                         f"texture rows, the texture has {rows}")
    if cols % sw:
        raise UsageError(f"dct: {cols} angular samples are not a whole number of patch steps ({sw})")
    band = slice(first_row, first_row + used)
    # Slant: row y of the band moves y·slant columns along the angle, so upright patches of the sheared band
    # are slanted ones of the texture.
    shift = slant * np.arange(used)
    cidx = (np.arange(cols)[None, :] - shift[:, None]) % cols
    rsel = np.arange(used)[:, None]
    sheared = t[band][rsel, cidx]
    smask = m[band][rsel, cidx].astype(np.float64)
    n_patches = cols // sw
    pcols = (np.arange(n_patches)[:, None] * sw + np.arange(pw)[None, :]) % cols      # (patches, pw)
    ww, wh = _hann(pw), _hann(ph)
    across = sheared[:, pcols] @ ww                                                   # (used rows, patches)
    counts = smask[:, pcols].sum(axis=2)                                              # usable per row and patch
    prow = np.arange(patch_rows)[:, None] * sh + np.arange(ph)[None, :]               # (patch rows, ph)
    vectors = across[prow] * wh[None, :, None]                                        # (patch rows, ph, patches)
    coeffs = _dct(vectors, type=2, norm="ortho", axis=1)[:, list(coefficients), :].transpose(1, 0, 2)
    usable = counts[prow].sum(axis=1) * 2 > ph * pw
    return coeffs, usable


class DctMatcher:
    """Monro, Rakshit & Zhang (2007) through USIT's ``dct``: differences of patch DCT coefficients.

    Parameters
    ----------
    segmenter
        Shared segmenter (cache); a new one if None.
    radial, angular
        Rubber-sheet size: 64 × 516 (USIT's 64 rows; 516 = 86 patch steps, see the module notes).
    first_row, patch_rows, patch, slant, coefficients
        Patch layout (module notes): USIT's 3, 12, 8 × 12, and the first three DCT coefficients; Monro's 45°.
    offsets
        Sub-patch rotations (columns) encoded into every template (0, 2, 4).
    max_shift
        Whole-patch shifts tried, ``±max_shift``.
    min_valid
        Fraction of a bit plane's bits that must be valid in both templates for a rotation to count; a
        rotation where some plane has fewer counts as distance 1 in that plane.
    """

    name: ClassVar[str] = "dct"
    higher_is_similar: ClassVar[bool] = False

    def __init__(self, segmenter: Segmenter | None = None, *, radial: int = 64, angular: int = 516,
                 first_row: int = 3, patch_rows: int = 12, patch: tuple[int, int] = (8, 12), slant: int = 1,
                 coefficients: tuple[int, ...] = (0, 1, 2), offsets: tuple[int, ...] = (0, 2, 4),
                 max_shift: int = 2, min_valid: float = 0.1) -> None:
        self.segmenter = segmenter if segmenter is not None else Segmenter()
        self.radial, self.angular = int(radial), int(angular)
        self.first_row, self.patch_rows = int(first_row), int(patch_rows)
        self.patch = (int(patch[0]), int(patch[1]))
        self.slant = int(slant)
        self.coefficients = tuple(int(c) for c in coefficients)
        self.offsets = tuple(int(o) for o in offsets)
        self.max_shift, self.min_valid = int(max_shift), float(min_valid)
        if not self.coefficients or min(self.coefficients) < 0 or max(self.coefficients) >= self.patch[0]:
            raise UsageError(f"dct: coefficients must lie in 0 … {self.patch[0] - 1}, got {self.coefficients}")
        if not self.offsets or self.offsets[0] != 0 or len(set(self.offsets)) != len(self.offsets):
            raise UsageError(f"dct: offsets must start with 0 and be distinct, got {self.offsets}")
        # Checks the layout against the texture size.
        patch_coefficients(np.zeros((self.radial, self.angular)), np.ones((self.radial, self.angular), bool),
                           **self._layout())

    def _layout(self) -> dict:
        return {"first_row": self.first_row, "patch_rows": self.patch_rows, "patch": self.patch,
                "slant": self.slant, "coefficients": self.coefficients}

    # ------------------------------------------------------------------ encoding
    def _planes(self, texture: np.ndarray, mask: np.ndarray, segmentation: Segmentation | None
                ) -> tuple[IrisCode, ...]:
        coeffs, usable = patch_coefficients(texture, mask, **self._layout())
        rising = np.roll(coeffs, -1, axis=2) > coeffs                   # (coefficients, rows, patches)
        valid = usable & np.roll(usable, -1, axis=1)
        # One IrisCode per coefficient, angle-major: column p holds the patch rows' bits.
        return tuple(IrisCode.from_bits(plane.T, valid.T, segmentation) for plane in rising)

    def encode_texture(self, texture: np.ndarray, mask: np.ndarray,
                       segmentation: Segmentation | None = None) -> DctTemplate:
        """The template of an already normalised ``(radial, angular)`` texture and its usability mask."""
        t, m = np.asarray(texture), np.asarray(mask, dtype=bool)
        codes = tuple(self._planes(np.roll(t, o, axis=1), np.roll(m, o, axis=1), segmentation) for o in self.offsets)
        return DctTemplate(codes, self.offsets, segmentation)

    def encode(self, image: np.ndarray) -> DctTemplate:
        """Segment (cached), normalise and encode an eye image."""
        texture, mask, seg = self.segmenter.unwrap(image, self.radial, self.angular)
        return self.encode_texture(texture, mask, seg)

    # ------------------------------------------------------------------ comparison
    def _rotations(self) -> list[tuple[int, int, int]]:
        """``(offset index of a, offset index of b, patch shift of b)``: every rotated version of one template
        against the unrotated other, each at every whole-patch shift (a set symmetric in a and b)."""
        pairs = [(0, 0)] + [(k, 0) for k in range(1, len(self.offsets))] + [(0, k) for k in range(1, len(self.offsets))]
        return [(ka, kb, q) for ka, kb in pairs for q in range(-self.max_shift, self.max_shift + 1)]

    def _check(self, t: object) -> DctTemplate:
        if not isinstance(t, DctTemplate):
            raise InputError(f"dct templates expected, got {type(t).__name__}")
        if t.offsets != self.offsets or len(t.codes[0]) != len(self.coefficients):
            raise InputError("dct templates of a different layout; encode both with the same matcher settings")
        return t

    def _min_valid_bits(self, t: DctTemplate) -> int:
        return math.ceil(self.min_valid * t.codes[0][0].n_bits)

    def _product_of_sum(self, planes: Sequence[np.ndarray | float]) -> np.ndarray:
        """Geometric mean of the per-plane Hamming distances (the same operations for one pair and for a matrix)."""
        prod = np.asarray(planes[0], dtype=np.float64)
        for p in planes[1:]:
            prod = prod * p
        return np.power(prod, 1.0 / len(planes))

    def compare(self, a: DctTemplate, b: DctTemplate) -> float:
        """Product-of-sum Hamming distance minimised over rotations: 0 (same) … 1."""
        a, b = self._check(a), self._check(b)
        need = self._min_valid_bits(a)
        best = 1.0
        for ka, kb, q in self._rotations():
            planes = [hamming_distance(pa, pb.shifted(q), 0, need) for pa, pb in zip(a.codes[ka], b.codes[kb])]
            best = min(best, float(self._product_of_sum(planes)))
        return best

    def compare_all(self, templates_a: Sequence[DctTemplate], templates_b: Sequence[DctTemplate]) -> np.ndarray:
        """Vectorised :meth:`compare` of every pair (bit-packed, :func:`~forensics.impact.iriscode.hamming_planes`
        per rotation pair: every plane at every shift); equal to the loop exactly."""
        out = np.ones((len(templates_a), len(templates_b)))
        if len(templates_a) == 0 or len(templates_b) == 0:
            return out
        ta = [self._check(t) for t in templates_a]
        tb = [self._check(t) for t in templates_b]
        need = self._min_valid_bits(ta[0])
        # Per rotation pair every plane at every whole-patch shift at once (hamming_planes: the planes share one
        # mask, so the valid bits are counted once, and each code is packed once per pair, not per shift); rows
        # in blocks so that the (shifts, planes, rows, columns) distances stay below ~64 MB.
        shifts = list(range(-self.max_shift, self.max_shift + 1))
        rows = max(1, 2**23 // (len(shifts) * len(self.coefficients) * len(tb)))
        for i0 in range(0, len(ta), rows):
            best = out[i0:i0 + rows]
            for ka, kb in dict.fromkeys((ka, kb) for ka, kb, _ in self._rotations()):
                planes = hamming_planes([t.codes[ka] for t in ta[i0:i0 + rows]], [t.codes[kb] for t in tb], shifts,
                                        need)
                for k in range(len(shifts)):
                    np.minimum(best, self._product_of_sum(list(planes[k])), out=best)
        return out
