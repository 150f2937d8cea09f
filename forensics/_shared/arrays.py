"""Array helpers used by every domain: full scale of a pixel type and the two grey conversions.

Two grey conversions exist because two uses need different things:

* :func:`grey_luma` (BT.601 luma) is what the PRNU reference design correlates: the fingerprint lives
  in the luminance the camera's pipeline produced, weighted as the eye and JPEG weight it.
* :func:`grey_mean` (equal channel weights) is what defect statistics need: a defect adds the same
  offset to every channel it touches, and the plain mean keeps that offset in DN, so amplitudes and
  thresholds stay in the units of the data.
"""
from __future__ import annotations

import numpy as np

from forensics._shared.errors import InputError

#: ITU-R BT.601 luma weights (R, G, B).
GREY_WEIGHTS: tuple[float, float, float] = (0.299, 0.587, 0.114)


def full_scale(dtype: np.dtype | type) -> float:
    """The full-scale pixel value of a container type: the integer maximum, or 1.0 for floats and bools.

    Raises
    ------
    InputError
        For types that are not pixels (complex, strings, objects).
    """
    dtype = np.dtype(dtype)
    if dtype.kind in "ui":
        return float(np.iinfo(dtype).max)
    if dtype.kind in "fb":
        return 1.0
    raise InputError(f"unsupported pixel type {dtype}; expected integer or floating-point pixels")


def infer_full_scale(dtype: np.dtype | type, maximum: float) -> float:
    """Full scale of the *data* in a container: 255 for 8-bit; for wider integer containers the smallest
    of 10/12/14/16 bits that holds ``maximum`` (raw data are commonly 12- or 14-bit in 16-bit files);
    1.0 for floats.  Use :func:`full_scale` when the container itself is the scale."""
    dtype = np.dtype(dtype)
    if dtype == np.uint8:
        return 255.0
    if dtype.kind in "ui":
        for bits in (10, 12, 14, 16):
            if maximum <= 2**bits - 1:
                return float(2**bits - 1)
        return float(np.iinfo(dtype).max)
    return 1.0


def _channels(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (3, 4)):
        raise InputError(f"image of shape {image.shape}: expected (H, W) grey or raw mosaic, or (H, W, 3) colour")
    return image


def grey_luma(image: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """BT.601 luma of an RGB image as float32 (a 2-D image is returned as float32 unchanged).

    Parameters
    ----------
    image : ndarray, (H, W) or (H, W, 3|4)
        Any integer or float dtype; a 4th (alpha) channel is ignored.
    out : ndarray, optional
        float32 array of shape (H, W) to write into (may be a view).

    Returns
    -------
    ndarray, float32, (H, W), in the input's units (no rescaling).
    """
    image = _channels(image)
    if out is None:
        out = np.empty(image.shape[:2], np.float32)
    if image.ndim == 2:
        out[...] = image
        return out
    w = [np.float32(v) for v in GREY_WEIGHTS]
    np.multiply(image[..., 0], w[0], out=out, dtype=np.float32, casting="unsafe")
    tmp = np.empty(out.shape, np.float32)
    for c in (1, 2):
        np.multiply(image[..., c], w[c], out=tmp, dtype=np.float32, casting="unsafe")
        out += tmp
    return out


def grey_mean(image: np.ndarray, dtype: np.dtype | type = np.float32) -> np.ndarray:
    """Equal-weight mean over the colour channels (the first three), as ``dtype``; 2-D input is converted.

    float32 (the default) is exact for one 16-bit frame; statistics accumulated over many frames (means
    of stacks) pass ``np.float64`` to keep their precision.
    """
    image = _channels(image)
    if image.ndim == 2:
        return image.astype(dtype, copy=False)
    return image[..., :3].mean(axis=2, dtype=dtype)


def bits_full_scale(bit_depth: int) -> float:
    """Full scale of ``bit_depth``-bit data: 2**bits − 1 (255 for 8 bits, 4095 for 12)."""
    return float(2**int(bit_depth) - 1)
