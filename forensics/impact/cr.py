"""Rathgeb and Uhl's local intensity variations: USIT's ``cr`` iris code.

C. Rathgeb and A. Uhl, "Secure iris recognition based on local intensity variations", *Proc. Int. Conf. on
Image Analysis and Recognition (ICIAR 2010)*, Springer LNCS 6112, 266–275 — the paper USIT's ``cr`` cites.
(USIT's other Rathgeb–Uhl algorithm, ``cb``, is the context-based one: :mod:`forensics.impact.cb`.)

The published method, as implemented here:

1. The normalised texture (USIT: 64 × 512) is smoothed (USIT: a 3 × 3 Gaussian, σ = 0.8) and its contrast
   equalised (USIT: adaptive histogram equalisation on 8 × 2 tiles, :func:`~forensics.impact.texture.equalise`).
2. It is cut into horizontal stripes of ``stripe`` = 3 rows (21 stripes).  In every stripe two *pixel
   paths* run along the angle, starting in the middle row at the first column: at each step the path moves
   to the next column, into the same row or one row up or down, whichever holds the brightest pixel — the
   *light* path — or the darkest — the *dark* path; it leaves its row only for a neighbour strictly brighter
   (darker) than both other candidates.  The paths follow local intensity variations (crypts, furrows).
3. Each path is smoothed (USIT's two passes, sequential along the angle): a single sample that leaves and
   returns to a row is flattened, then any excursion of up to three samples between two equal samples.
4. A path's row (0, 1, 2) is coded with two bits ``00``, ``01``, ``11``, so the Hamming distance between
   codes counts rows of difference.  Templates are compared by the masked fractional Hamming distance
   minimised over circular shifts (``max_shift`` = 17 columns = ±12°, this project's range for 512-column
   codes; a path's first columns depend on its fixed start, but paths re-join within a few columns).

Code: 21 stripes × 2 paths × 2 bits × 512 columns = 43,008 bits, one IrisCode column per angular sample.
A path sample is valid when at least 2 of the 3 texture samples of its column of the stripe are usable.
USIT's ``cr`` codes carry no mask.
"""
from __future__ import annotations

from typing import ClassVar

import numpy as np
from scipy import ndimage

from forensics._shared.errors import UsageError
from forensics.impact.iriscode import IrisCode, IrisCodeMatcher
from forensics.impact.segment import Segmentation, Segmenter
from forensics.impact.texture import TEXTURE_SHAPE, cell_validity, equalise, fill_unusable

__all__ = ["CrMatcher", "pixel_paths", "smooth_paths"]


# A map of the rows {0, 1, 2} to themselves is coded as one number m(0) + 3 m(1) + 9 m(2) (0 … 26), so that
# composing maps and applying them are look-ups in two small tables.
_APPLY = np.array([[(code // 3 ** s) % 3 for s in range(3)] for code in range(27)], np.uint8)   # [map, row]
_COMPOSE = np.array([[sum(int(_APPLY[g, _APPLY[f, s]]) * 3 ** s for s in range(3)) for f in range(27)]
                     for g in range(27)], np.uint8)                                            # [g, f] = g ∘ f
_COMPOSE_FLAT = _COMPOSE.ravel()


def _code(maps: np.ndarray) -> np.ndarray:
    """``(…, 3)`` row maps → their codes (…)."""
    return (maps[..., 0] + 3 * maps[..., 1] + 9 * maps[..., 2]).astype(np.uint8)


def _run(maps: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Rows ``(paths, steps + 1)`` of a sequence that starts in ``start`` and moves by the coded ``maps``
    ``(paths, steps)``, evaluated for all steps at once: a prefix scan of compositions (log₂ steps of them)."""
    prefix = maps.copy()                                    # prefix[:, j]: the map from step 0 to after step j
    d = 1
    while d < prefix.shape[1]:
        prefix[:, d:] = np.take(_COMPOSE_FLAT, 27 * prefix[:, d:].astype(np.intp) + prefix[:, :-d])
        d *= 2
    rows = np.empty((maps.shape[0], maps.shape[1] + 1), np.intp)
    rows[:, 0] = start
    rows[:, 1:] = _APPLY[prefix, np.asarray(start)[:, None]]
    return rows


def _steps(nxt: np.ndarray) -> np.ndarray:
    """Coded transition maps ``(paths, columns)``: where a path in each row moves, from the next column's values.

    ``nxt`` is ``(paths, 3, columns)``; a path moves up (down) only to a value strictly greater than the same
    row's and the other neighbour's.
    """
    n_paths, _, n_cols = nxt.shape
    lo = np.full((n_paths, 1, n_cols), -np.inf)
    padded = np.concatenate([lo, nxt, lo], axis=1)               # rows −1 … 3, the outside never wins
    maps = np.empty((n_paths, n_cols, 3), np.intp)
    for s in range(3):
        up, same, down = padded[:, s], padded[:, s + 1], padded[:, s + 2]
        go_up = (up > same) & (up > down)
        go_down = (down > same) & (down > up)
        maps[:, :, s] = s - go_up.astype(np.intp) + go_down.astype(np.intp)
    return _code(maps)


def pixel_paths(values: np.ndarray, start: int = 1) -> np.ndarray:
    """Rows ``(paths, columns)`` taken by the maximising paths through ``values`` of shape ``(paths, 3, columns)``.

    The path starts in row ``start`` at column 0 and moves column by column (see :func:`_steps`).  The
    sequence of moves is a composition of per-column maps of {0, 1, 2}; it is evaluated for all columns at
    once by a prefix scan instead of a loop over columns.
    """
    v = np.asarray(values, dtype=np.float64)
    return _run(_steps(v[:, :, 1:]), np.full(v.shape[0], start))


def smooth_paths(rows: np.ndarray) -> np.ndarray:
    """USIT's smoothing of paths ``(paths, columns)``: isolated excursions flattened.

    First pass, left to right: a sample whose (already smoothed) left neighbour equals its right neighbour
    takes their value — a map of the left neighbour's row, so the pass is a prefix scan like the paths.
    Second pass, left to right: where the (current) sample two to the left equals the one two to the right,
    the three between them take that value; sequential along the angle as in USIT, vectorised over paths.
    """
    f = np.array(rows, dtype=np.intp, copy=True)
    n = f.shape[1]
    if n >= 3:
        left = np.arange(3)[None, None, :]                   # the candidate row of the left neighbour
        maps = np.where(left == f[:, 2:, None], left, f[:, 1:-1, None])    # (paths, n − 2, 3)
        f[:, :-1] = _run(_code(maps), f[:, 0])
    for i in range(2, n - 2):
        same = f[:, i - 2] == f[:, i + 2]
        f[:, i - 1:i + 2] = np.where(same[:, None], f[:, i - 2, None], f[:, i - 1:i + 2])
    return f


class CrMatcher(IrisCodeMatcher):
    """Rathgeb & Uhl (ICIAR 2010) through USIT's ``cr``: light and dark pixel paths, Hamming distance.

    Parameters
    ----------
    segmenter
        Shared segmenter (cache); a new one if None.
    radial, angular
        Rubber-sheet size (USIT: 64 × 512).
    stripe
        Rows per stripe (3; the path code is written for three rows).
    blur_sigma
        Gaussian smoothing before the equalisation (USIT's 3 × 3 kernel: σ = 0.8, radius 1).
    tiles
        Equalisation tiles ``(rows, columns)`` (USIT: 2 × 8).
    max_shift
        Circular shifts tried, ``±max_shift`` columns.
    min_valid
        Fraction of the code's bits that must be valid in both masks for a shift to count.
    """

    name: ClassVar[str] = "cr"
    higher_is_similar: ClassVar[bool] = False

    def __init__(self, segmenter: Segmenter | None = None, *, radial: int = TEXTURE_SHAPE[0],
                 angular: int = TEXTURE_SHAPE[1], stripe: int = 3, blur_sigma: float = 0.8,
                 tiles: tuple[int, int] = (2, 8), max_shift: int = 17, min_valid: float = 0.1) -> None:
        self.segmenter = segmenter if segmenter is not None else Segmenter()
        self.radial, self.angular = int(radial), int(angular)
        self.stripe, self.blur_sigma = int(stripe), float(blur_sigma)
        self.tiles = (int(tiles[0]), int(tiles[1]))
        self.max_shift, self.min_valid = int(max_shift), float(min_valid)
        if self.stripe != 3:
            raise UsageError(f"cr: stripes of {self.stripe} rows; the path code is defined for 3")
        if self.radial < self.stripe or self.angular < 8:
            raise UsageError(f"cr: a {self.radial} × {self.angular} texture is too small")

    def enhanced(self, texture: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """The smoothed, equalised texture the paths run through (float32 in [0, 1])."""
        t = fill_unusable(texture, mask)
        # Radius 1 (USIT's 3 × 3 kernel), circular along the angle.
        t = ndimage.gaussian_filter(t, self.blur_sigma, mode=("reflect", "wrap"), truncate=1.0 / self.blur_sigma)
        return equalise(t, np.ones(t.shape, bool), self.tiles)

    def paths(self, texture: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Smoothed rows of the light and dark paths ``(2, stripes, angular)`` and their validity ``(stripes, angular)``."""
        e = self.enhanced(texture, mask)
        n = self.radial // self.stripe
        v = e[: n * self.stripe].reshape(n, self.stripe, -1)
        rows = pixel_paths(np.concatenate([v, -v]))                      # light paths, then dark ones
        rows = smooth_paths(rows).reshape(2, n, -1)
        valid = cell_validity(np.asarray(mask, bool)[: n * self.stripe], (self.stripe, 1))
        return rows, valid

    def encode_texture(self, texture: np.ndarray, mask: np.ndarray,
                       segmentation: Segmentation | None = None) -> IrisCode:
        """The code of an already normalised ``(radial, angular)`` texture and its usability mask."""
        rows, valid = self.paths(texture, mask)
        bits = np.stack([rows >= 1, rows >= 2], axis=0)                 # (2 bits, 2 paths, stripes, angular)
        vmask = np.broadcast_to(valid, bits.shape)
        cols = rows.shape[-1]
        return IrisCode.from_bits(bits.transpose(3, 0, 1, 2).reshape(cols, -1),
                                  vmask.transpose(3, 0, 1, 2).reshape(cols, -1), segmentation)

    def mask_groups(self) -> np.ndarray:
        """A column's bits (2 bits × 2 paths × stripes) share the mask of their stripe."""
        return np.tile(np.arange(self.radial // self.stripe), 4)

    def encode(self, image: np.ndarray) -> IrisCode:
        """Segment (cached), normalise and encode an eye image."""
        texture, mask, seg = self.segmenter.unwrap(image, self.radial, self.angular)
        return self.encode_texture(texture, mask, seg)
