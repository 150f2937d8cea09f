"""Conventions shared by the re-implementations of USIT's feature extractors (``qsw``, ``dct``, ``cr``, ``cb``).

USIT (University of Salzburg Iris Toolkit; C. Rathgeb, A. Uhl, P. Wild, H. Hofbauer, "Design Decisions for
an Iris Recognition SDK", *Handbook of Iris Recognition*, 2nd ed., Springer 2016) hands every feature
extractor the same rubber-sheet texture: 512 angular × 64 radial samples, row 0 at the pupil boundary,
8-bit grey.  Here the texture comes from the shared :class:`~forensics.impact.segment.Segmenter` (one
segmentation per image for all matchers) with its usability mask; the helpers below are the small steps
several extractors share: filling unusable samples before filtering, USIT's contrast enhancement, and the
validity of cells of samples.
"""
from __future__ import annotations

import numpy as np
from skimage.exposure import equalize_adapthist

__all__ = ["TEXTURE_SHAPE", "cell_validity", "equalise", "fill_unusable"]

#: USIT's rubber-sheet size, ``(radial, angular)``.
TEXTURE_SHAPE = (64, 512)


def fill_unusable(texture: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Float32 copy of ``texture`` with unusable samples (``mask`` False) set to the mean of the usable ones.

    As Masek does before filtering: a constant fill neither rings through a filter nor creates structure of
    its own; codes taken from filled samples are masked by the callers anyway.  An all-unusable texture
    becomes zeros.
    """
    t = np.asarray(texture, dtype=np.float32)
    usable = np.asarray(mask, dtype=bool)
    if t.shape != usable.shape:
        raise ValueError(f"texture {t.shape} and mask {usable.shape} differ in shape")
    fill = float(t[usable].mean()) if usable.any() else 0.0
    return np.where(usable, t, np.float32(fill)).astype(np.float32)


def equalise(texture: np.ndarray, mask: np.ndarray, tiles: tuple[int, int] = (2, 8)) -> np.ndarray:
    """USIT's texture enhancement: adaptive histogram equalisation on a grid of ``tiles`` (rows, columns).

    USIT equalises the 64×512 texture with its own CLAHE at a clip factor of 1, i.e. without clipping
    (plain adaptive histogram equalisation), on 8 × 2 tiles of 64 × 32 samples in ``cr`` (its segmenters'
    ``-e`` option does the same with tiles sized from the eye image).
    ``skimage.exposure.equalize_adapthist`` with ``clip_limit=1`` is the same operation (contextual regions
    with bilinear interpolation of the tile mappings).  Unusable samples are filled
    first (:func:`fill_unusable`) so that eyelids and reflections do not take part in the histograms as
    themselves.  Returns float32 in [0, 1]; a flat texture is returned as 0.5 everywhere.
    """
    t = fill_unusable(texture, mask)
    lo, hi = float(t.min()), float(t.max())
    if hi - lo <= 1e-12:
        return np.full(t.shape, 0.5, np.float32)
    rows, cols = t.shape
    kernel = (max(rows // int(tiles[0]), 1), max(cols // int(tiles[1]), 1))
    scaled = (t - lo) / (hi - lo)
    return equalize_adapthist(scaled, kernel_size=kernel, clip_limit=1.0, nbins=256).astype(np.float32)


def cell_validity(mask: np.ndarray, cell: tuple[int, int]) -> np.ndarray:
    """Whether more than half of the samples of each ``cell`` (rows, columns) are usable.

    ``mask`` is cropped to whole cells; the result has shape ``(rows // cell[0], columns // cell[1])``.
    """
    m = np.asarray(mask, dtype=bool)
    ch, cw = int(cell[0]), int(cell[1])
    r, c = m.shape[0] // ch, m.shape[1] // cw
    counts = m[: r * ch, : c * cw].reshape(r, ch, c, cw).sum(axis=(1, 3))
    return counts * 2 > ch * cw
