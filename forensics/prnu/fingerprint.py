"""Camera fingerprints (PRNU): streaming maximum-likelihood estimate from many images.

Model (Chen, Fridrich, Goljan & Lukáš 2008): an image ``I`` carries the sensor's
photo-response non-uniformity ``K`` multiplicatively, ``I = I⁰(1 + K) + Θ``, so its
noise residual is ``W = I·K + Ξ``.  From images ``I_1 … I_n`` the maximum-likelihood
estimate is

    K = Σ W_i · I_i / Σ I_i²

computed here image by image: two running sums the size of the frame (float64, so
long sums do not lose precision), whatever the number of images.

Details that follow the reference design (Binghamton camera-fingerprint code):

* ``W`` is the wavelet-stage residual of :func:`forensics.prnu.residual.wavelet_residual`
  at σ = 3 (no per-image zero-mean or DFT Wiener step: those are applied once, to K).
* ``I`` is the grey intensity minus the black level, with the reference's roll-off
  near full scale (``I`` unchanged up to 252/255 of full scale, then
  ``T·exp(−(I − T)²/v)`` with ``T = 252/255`` and ``v = 6/255²`` of full scale), and
  **saturated pixels set to zero**, which removes them from the numerator and the
  denominator alike.  A pixel is saturated when any of its colour channels reaches
  the saturation level (full scale by default); by default its 8 neighbours are
  excluded too, because clipping also distorts the residual next to it.
* After the sums, ``K`` is post-processed like a residual: zero mean on each 2×2 CFA
  sub-lattice, then the DFT Wiener filter with σ = std(K).

Regions (:func:`parse_region`):

``full``
    The whole frame.
``center:N`` (or ``center:HxW``)
    A centred crop whose corner sits on even coordinates, so the CFA phase is kept.
``corners`` (or ``corners:N``, default N = 128)
    The four N×N corner patches of the paper, each processed as an image of its own
    (residual, post-processing) and stored as one 2N×2N mosaic laid out
    ``[[top-left, top-right], [bottom-left, bottom-right]]``.  One array keeps every
    downstream function (NCC, PCE, saving) unchanged; with PCE, use zero shift only,
    since a shifted mosaic would compare unrelated patches.

In every region the pixels are cut out of the frame first and the residual is
computed on the cut-out (cheaper than a full-frame residual; a fingerprint and the
queries matched against it use the same geometry, so the edge effects agree).

Parallel builds: the two sums are sums over images, so they are computed in chunks of
:data:`CHUNK_IMAGES` images — a chunk is one work item of the execution layer
(:mod:`forensics._shared.parallel`), which reads its images itself — and the chunks'
sums are added in chunk order (:func:`build_fingerprints`).  :class:`FingerprintBuilder`
adds images one by one in the same chunks, so a fingerprint has the same bits
whether it was built image by image, in worker processes or on a Dask cluster.
"""
from __future__ import annotations

import copy
import math
import json
import os
import zipfile
import zlib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from forensics import __version__
from forensics._shared.atomic import atomic_file
from forensics._shared.errors import InputError, UsageError
from forensics._shared.jsonsafe import dumps, to_jsonable
from forensics._shared.parallel import Checkpoint, Executor, chunks, resolve
from forensics._shared.progress import Progress, no_progress
from forensics._shared.arrays import GREY_WEIGHTS, full_scale
from forensics.prnu.imageset import ImageSet
from forensics.prnu.region import Region, parse_region
from forensics.prnu.residual import (
    LEVELS,
    WAVELET,
    cfa_residual_and_grey,
    residual_and_grey,
    wiener_dft,
    zero_mean_cfa,
)

__all__ = [
    "Region",
    "parse_region",
    "saturation_mask",
    "intensity",
    "ImageSet",
    "CHUNK_IMAGES",
    "FingerprintSums",
    "FingerprintBuilder",
    "FingerprintJob",
    "Fingerprint",
    "build_fingerprint",
    "build_fingerprints",
    "check_fingerprint",
    "chunk_sums",
    "postprocess",
    "region_content_problem",
    "region_residual_and_intensity",
    "raw_options",
    "query_options",
    "FORMAT",
]

FORMAT = "forensics-fingerprint/1"
#: Roll-off of the intensity weight near full scale (reference: T = 252, v = 6 on 8 bits).
ROLLOFF_T = 252.0 / 255.0
ROLLOFF_V = 6.0 / 255.0**2
#: Images per chunk of the sums (see the module notes): fixed by the estimator, never by the number of
#: workers, so that every way of building a fingerprint adds the same numbers in the same order.
CHUNK_IMAGES = 8

# ----------------------------------------------------------------------------- intensity and saturation


def saturation_mask(image: np.ndarray, level: float | None = None, dilate: int = 1) -> np.ndarray:
    """Pixels where any channel reaches ``level`` (default: the dtype's full scale), grown by ``dilate``.

    Parameters
    ----------
    image : ndarray, (H, W) or (H, W, C)
    level : float, optional
        Saturation level in the image's units.
    dilate : int
        Also mark pixels within this Chebyshev distance of a saturated one (0: none).

    Returns
    -------
    ndarray of bool, (H, W)
    """
    image = np.asarray(image)
    if level is None:
        level = full_scale(image.dtype)
    shape = image.shape[:2]
    if image.size == 0 or not image.max() >= level:  # cheap common case: nothing saturated
        return np.zeros(shape, bool)
    if image.ndim == 3:
        # max over channels by hand: ``(image >= level).any(axis=2)`` is 7× slower
        peak = image[..., 0].copy()
        for c in range(1, image.shape[2]):
            np.maximum(peak, image[..., c], out=peak)
        mask = peak >= level
    else:
        mask = image >= level
    if dilate > 0 and mask.any():
        mask = ndimage.maximum_filter(mask.view(np.uint8), size=2 * dilate + 1, mode="constant").view(bool)
    return mask


def _black_array(black_level: float | Sequence[float], shape: tuple[int, int]) -> float | np.ndarray:
    if np.ndim(black_level) == 0:
        return float(black_level)  # type: ignore[arg-type]
    b = np.asarray(black_level, np.float32).ravel()
    if b.size != 4:
        raise InputError(f"black_level {black_level!r}: give one value or four (one per 2×2 CFA position)")
    tile = b.reshape(2, 2)
    reps = (-(-shape[0] // 2), -(-shape[1] // 2))
    return np.tile(tile, reps)[: shape[0], : shape[1]]


def intensity(
    grey: np.ndarray,
    white_level: float,
    black_level: float | Sequence[float] = 0.0,
    saturated: np.ndarray | None = None,
    rolloff: bool = True,
) -> np.ndarray:
    """The intensity weight ``I`` of the fingerprint estimator (float32, the grey's units).

    ``I = grey − black`` (clipped at 0); with ``rolloff``, above ``T = 252/255`` of the
    full range ``white − black`` it falls as ``T·exp(−(I − T)²/v)``, ``v = 6/255²`` of
    the range squared (the reference's IntenScale); pixels in ``saturated`` are 0.
    ``grey`` is not modified.
    """
    g = np.asarray(grey, dtype=np.float32)
    black = _black_array(black_level, g.shape)
    out = g - black if np.ndim(black) else g - np.float32(black)
    np.maximum(out, 0, out=out)
    rng = float(white_level) - float(np.mean(black))
    if rolloff and rng > 0:
        t = np.float32(ROLLOFF_T * rng)
        over = out > t
        if over.any():
            d = out[over] - t
            out[over] = t * np.exp(-(d * d) / np.float32(ROLLOFF_V * rng * rng))
    if saturated is not None:
        out[saturated] = 0
    return out


def region_content_problem(image: np.ndarray, region: Region | str, *, white_level: float | None = None,
                           black_level: float | Sequence[float] = 0.0, saturation_level: float | None = None,
                           **_: Any) -> str | None:
    """Why the region's pixels of a frame hold no PRNU (constant, black or saturated: :mod:`forensics.io.content`),
    or None.  Levels as :func:`region_residual_and_intensity` (other options are ignored)."""
    from forensics.io.content import content_problem

    image = np.asarray(image)
    region = parse_region(region)
    white = full_scale(image.dtype) if white_level is None else white_level
    pieces = [image[src] for src in region.pieces(image.shape)]
    black = _black_array(black_level, pieces[0].shape[:2])
    return content_problem(pieces, black, white if saturation_level is None else saturation_level)


def region_residual_and_intensity(
    image: np.ndarray,
    region: Region | str,
    sigma: float,
    *,
    white_level: float | None = None,
    black_level: float | Sequence[float] = 0.0,
    saturation_level: float | None = None,
    saturation_dilate: int = 1,
    rolloff: bool = True,
    postprocess: bool = False,
    workers: int | None = None,
    cfa: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Residual ``W`` and intensity ``I`` of one frame over a region (each piece processed on its own).

    Parameters
    ----------
    image : ndarray, (H, W) or (H, W, 3)
    region : Region or str
    sigma : float
        Noise level on an 8-bit scale (3 for fingerprints, 2 for queries).
    white_level, black_level, saturation_level, saturation_dilate, rolloff
        See :func:`intensity` and :func:`saturation_mask`; ``white_level`` defaults
        to the dtype's full scale, ``saturation_level`` to ``white_level``.
    postprocess : bool
        Also apply the zero-mean and DFT Wiener steps to the residual (queries: yes;
        fingerprint accumulation: no).
    workers : int, optional
        Threads.
    cfa : bool
        The frame is a raw CFA mosaic: each colour channel is denoised on its own
        (:func:`~forensics.prnu.residual.cfa_residual_and_grey`).

    Returns
    -------
    (W, I) : two float32 arrays of the region's shape
        New arrays owned by the caller (``W`` may be a view of a slightly larger one).
    """
    region = parse_region(region)
    image = np.asarray(image)
    if image.ndim not in (2, 3):
        raise InputError(f"image of shape {image.shape}: expected (H, W) or (H, W, 3)")
    if white_level is None:
        white_level = full_scale(image.dtype)
    if saturation_level is None:
        saturation_level = white_level
    pieces = region.pieces(image.shape)
    parts = []
    for src in pieces:
        piece = image[src]
        split = cfa_residual_and_grey if cfa else residual_and_grey
        res, grey = split(piece, sigma, white_level=white_level, workers=workers)
        if postprocess:
            res = np.ascontiguousarray(res)
            zero_mean_cfa(res, inplace=True)
            res = wiener_dft(res, workers=workers)
        sat = saturation_mask(piece, saturation_level, saturation_dilate)
        parts.append((res, intensity(grey, white_level, black_level, sat, rolloff)))
        del grey, sat
    if len(parts) == 1:  # no mosaic to assemble: hand the arrays over without a copy
        return parts[0]
    shape = region.shape(image.shape)
    res_all = np.empty(shape, np.float32)
    inten_all = np.empty(shape, np.float32)
    for (res, inten), dst in zip(parts, region.mosaic_slices(image.shape)):
        res_all[dst] = res
        inten_all[dst] = inten
    return res_all, inten_all


def postprocess(k: np.ndarray, region: Region | str, frame_shape: Sequence[int], workers: int | None = None) -> np.ndarray:
    """Zero mean on the CFA sub-lattices, then the DFT Wiener filter (σ = std), piece by piece.

    Returns a new float32 array; ``k`` is not modified.
    """
    region = parse_region(region)
    out = np.array(k, dtype=np.float32, copy=True)
    for dst in region.mosaic_slices(frame_shape):
        piece = np.ascontiguousarray(out[dst])
        zero_mean_cfa(piece, inplace=True)
        out[dst] = wiener_dft(piece, workers=workers)
    return out


# ----------------------------------------------------------------------------- the fingerprint


@dataclass
class Fingerprint:
    """A camera fingerprint with its provenance.

    Attributes
    ----------
    K : ndarray, float32
        The post-processed fingerprint over the region (mosaic for 'corners').
    region : str
        Region spec (:func:`parse_region`).
    sigma : float
        Noise level (8-bit scale) of the residuals it was estimated from.
    files : list of str
        Source of each image, in the order added ('' where none was given).
    n_images : int
    frame_shape : (int, int)
        (height, width) of the source frames, in the orientation they were read.
    parameters : dict
        Everything else needed to reproduce it (estimator, levels, black/white
        levels, saturation rule, library version...).
    """

    K: np.ndarray
    region: str
    sigma: float
    files: list[str]
    n_images: int
    frame_shape: tuple[int, int]
    parameters: dict[str, Any] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        """Shape of ``K`` (the region's shape)."""
        return tuple(self.K.shape)  # type: ignore[return-value]

    def to_dict(self) -> dict[str, Any]:
        """Provenance as JSON-ready data (everything but ``K``)."""
        return {
            "format": FORMAT,
            "region": self.region,
            "sigma": float(self.sigma),
            "files": list(self.files),
            "n_images": int(self.n_images),
            "frame_shape": [int(v) for v in self.frame_shape],
            "shape": [int(v) for v in self.K.shape],
            "parameters": to_jsonable(self.parameters),
        }

    def save(self, path: str | os.PathLike, force: bool = False) -> Path:
        """Write ``K`` and the provenance (JSON) to one ``.npz`` file, atomically.

        Raises
        ------
        UsageError
            If ``path`` exists and ``force`` is false.
        """
        path = Path(path)
        meta = dumps(self.to_dict())
        with atomic_file(path, force=force, mode="wb") as handle:
            # uncompressed: K is noise-like, zlib would gain a few per cent for seconds of CPU
            np.savez(handle, K=np.asarray(self.K, np.float32), meta=np.array(meta))
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> Fingerprint:
        """Read a fingerprint written by :meth:`save`, checked (:func:`check_fingerprint`).

        Raises
        ------
        InputError
            If the file is missing, not a fingerprint, damaged (truncated, metadata missing a key or of the
            wrong type) or inconsistent, or its ``K`` holds no usable pattern.
        """
        path = Path(path)
        if not path.is_file():
            raise InputError(f"{path}: no such fingerprint file; check the path")
        try:
            with open(path, "rb") as handle:  # ours to close, whatever np.load makes of the bytes
                k, meta = _read_npz(handle, path)
        except _READ_ERRORS as exc:
            raise InputError(f"{path}: not a fingerprint file, or a damaged one ({_one_line(exc)}); build it again "
                             "with 'forensics fingerprint build'") from exc
        fields = _metadata(meta, path)
        if tuple(k.shape) != fields.pop("_shape"):
            raise InputError(f"{path}: K has shape {k.shape} but the metadata says {meta['shape']}: a damaged "
                             "fingerprint file; build it again")
        fp = cls(K=k, **fields)
        check_fingerprint(fp, str(path))
        return fp


def _read_npz(handle: Any, path: Path) -> tuple[np.ndarray, Any]:
    """``K`` and the parsed metadata of an open fingerprint file."""
    data = np.load(handle, allow_pickle=False)
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise InputError(f"{path}: a single array, not a fingerprint file; build one with 'forensics fingerprint "
                         "build'")
    with data:
        missing = [key for key in ("K", "meta") if key not in data.files]
        if missing:
            raise InputError(f"{path}: no '{missing[0]}' in the file: not a fingerprint file; build one with "
                             "'forensics fingerprint build'")
        return np.asarray(data["K"], np.float32), json.loads(str(data["meta"][()]))


#: What reading a damaged or foreign ``.npz`` can raise (a truncated zip, a cut member, a wrong type, …).
_READ_ERRORS = (OSError, EOFError, ValueError, KeyError, TypeError, IndexError, zipfile.BadZipFile, zlib.error)


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def _metadata(meta: Any, path: Path) -> dict[str, Any]:
    """The fields of a fingerprint's metadata, each checked for presence and type (one error naming the key)."""
    if not isinstance(meta, dict):
        raise InputError(f"{path}: its metadata is a JSON {type(meta).__name__}, not an object: a damaged fingerprint "
                         "file; build it again")
    if meta.get("format") != FORMAT:
        raise InputError(f"{path}: unknown fingerprint format {meta.get('format')!r} (expected {FORMAT})")

    def field_of(key: str, ok: Callable[[Any], bool], expected: str, default: Any = _MISSING) -> Any:
        if key not in meta:
            if default is not _MISSING:
                return default
            raise InputError(f"{path}: metadata key '{key}' is missing: a damaged fingerprint file; build it again")
        value = meta[key]
        if not ok(value):
            raise InputError(f"{path}: metadata '{key}' is {value!r:.60}, not {expected}: a damaged fingerprint file; "
                             "build it again")
        return value

    def whole(v: Any) -> bool:
        return isinstance(v, int) and not isinstance(v, bool)

    def pair(v: Any) -> bool:
        return isinstance(v, list) and len(v) == 2 and all(whole(x) and x > 0 for x in v)

    region = field_of("region", lambda v: isinstance(v, str) and _parses(v), "a region ('full', 'center:N', 'corners')")
    sigma = field_of("sigma", lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                     and v > 0, "a positive number")
    files = field_of("files", lambda v: isinstance(v, list) and all(isinstance(x, str) for x in v), "a list of names")
    n_images = field_of("n_images", lambda v: whole(v) and v >= 0, "a whole number ≥ 0")
    frame = field_of("frame_shape", pair, "two positive whole numbers")
    field_of("shape", pair, "two positive whole numbers")
    parameters = field_of("parameters", lambda v: isinstance(v, dict), "an object", {})
    return {"region": region, "sigma": float(sigma), "files": list(files), "n_images": int(n_images),
            "frame_shape": (int(frame[0]), int(frame[1])), "parameters": dict(parameters),
            "_shape": tuple(meta["shape"])}


_MISSING = object()


def _parses(spec: str) -> bool:
    try:
        parse_region(spec)
    except (InputError, UsageError):
        return False
    return True


def check_fingerprint(fp: Fingerprint, name: str = "fingerprint") -> None:
    """Refuse a fingerprint that cannot be matched: ``K`` not 2-D, not of its region's shape in its frame,
    holding NaN or infinite values, or constant (no pattern: e.g. built from content-free frames).

    Raises
    ------
    InputError
        Naming ``name`` and what is wrong.
    """
    k = np.asarray(fp.K)
    if k.ndim != 2 or k.size == 0:
        raise InputError(f"{name}: K has shape {k.shape}, not a 2-D array: a damaged fingerprint; build it again")
    try:
        expected = parse_region(fp.region).shape(fp.frame_shape)
    except (InputError, UsageError, TypeError, ValueError) as exc:
        raise InputError(f"{name}: region {fp.region!r} and frame {fp.frame_shape!r} do not agree ({_one_line(exc)}): "
                         "a damaged fingerprint; build it again") from exc
    if tuple(k.shape) != tuple(expected):
        raise InputError(f"{name}: K is {k.shape[0]}×{k.shape[1]} but region {fp.region} of a "
                         f"{fp.frame_shape[0]}×{fp.frame_shape[1]} frame is {expected[0]}×{expected[1]}: a damaged "
                         "fingerprint; build it again")
    bad = int(k.size - np.count_nonzero(np.isfinite(k)))
    if bad:
        raise InputError(f"{name}: K holds {bad} NaN or infinite value(s) of {k.size}: a damaged fingerprint, which "
                         "cannot be matched; build it again")
    if float(k.min()) == float(k.max()):
        raise InputError(f"{name}: K is constant ({float(k.min()):g} everywhere): it holds no pattern (built from "
                         "content-free frames?); build it again from exposed images")


@dataclass
class FingerprintSums:
    """``Σ W·I`` and ``Σ I²`` (float64, the region's shape) and the counts over some images.

    One chunk of a build (what a work item returns, :func:`chunk_sums`) or the running total of a
    :class:`FingerprintBuilder`.  ``files`` names the images in order; ``excluded`` counts the pixels
    with zero weight (saturated); ``skipped`` lists the content-free frames left out, ``(source, why)``
    (:mod:`forensics.io.content`); the frame geometry and pixel type let chunks be checked against each
    other before they are added.
    """

    num: np.ndarray
    den: np.ndarray
    files: list[str]
    excluded: int
    frame_shape: tuple[int, int]
    dtype: np.dtype
    skipped: list[tuple[str, str]] = field(default_factory=list)

    @classmethod
    def zeros(cls, shape: tuple[int, int], frame_shape: tuple[int, int], dtype: np.dtype) -> FingerprintSums:
        """Empty sums over a region of ``shape``."""
        return cls(np.zeros(shape, np.float64), np.zeros(shape, np.float64), [], 0, frame_shape, dtype)

    @property
    def n_images(self) -> int:
        """Number of images summed."""
        return len(self.files)

    @property
    def n_frames(self) -> int:
        """Frames offered: summed and skipped (what fixes the chunks, so they do not depend on the content)."""
        return len(self.files) + len(self.skipped)

    def add(self, other: FingerprintSums) -> None:
        """Add ``other``'s sums to these, in place (the one way partial sums are combined)."""
        self.num += other.num
        self.den += other.den
        self.files.extend(other.files)
        self.excluded += other.excluded
        self.skipped.extend(other.skipped)

    def clear(self) -> None:
        """Back to zero, keeping the arrays (a builder reuses them chunk after chunk)."""
        self.num.fill(0)
        self.den.fill(0)
        self.files = []
        self.excluded = 0
        self.skipped = []


def raw_options(path: str | os.PathLike) -> dict[str, Any]:
    """Builder and query options for frames like the raw file at ``path``: residuals per CFA channel, its black
    level per 2×2 position and its white level (LibRaw's); empty for any other file."""
    from forensics.io.images import is_raw, read_raw

    if not is_raw(path):
        return {}
    raw = read_raw(path)
    return {"cfa": True, "black_level": list(raw.black_level), "white_level": float(raw.white_level)}


def query_options(fingerprint: "Fingerprint") -> dict[str, Any]:
    """The query options a fingerprint was built with that queries must share (raw mosaics: channels, levels)."""
    params = fingerprint.parameters
    if not params.get("residual", {}).get("cfa_channels"):
        return {}
    return {"cfa": True, "black_level": params.get("black_level", 0.0), "white_level": params.get("white_level")}


class FingerprintBuilder:
    """Accumulate ``Σ W·I`` and ``Σ I²`` image by image; memory does not grow with the count.

    Images are summed in chunks of :data:`CHUNK_IMAGES` and the chunks added to a running
    total, exactly as a parallel build adds its work items' sums (:func:`build_fingerprints`),
    so both give the same bits.  Memory: four float64 arrays of the region's size (the
    total and the current chunk).

    Parameters
    ----------
    region : str or Region
        'full', 'center:N' or 'corners' (see the module notes).
    sigma : float
        Residual noise level on an 8-bit scale (3 in the reference).
    white_level : float, optional
        Full scale (default from the first image's dtype).
    black_level : float or 4 floats
        Subtracted from the intensity (raw mosaics; per 2×2 CFA position if four).
    saturation_level : float, optional
        Pixels at or above it (any channel) are excluded; default ``white_level``.
    saturation_dilate : int
        Exclude the neighbours of saturated pixels within this distance too.
    rolloff : bool
        Apply the reference's intensity roll-off near full scale.
    workers : int, optional
        Threads for the residuals.
    cfa : bool
        The frames are raw CFA mosaics: residuals channel by channel (:func:`raw_options` gives this, the black
        levels and the white level of a raw file).

    Examples
    --------
    >>> builder = FingerprintBuilder(region="center:1024")        # doctest: +SKIP
    >>> for path in flat_fields:                                   # doctest: +SKIP
    ...     builder.add(read_image(path), source=str(path))
    >>> fingerprint = builder.result()                             # doctest: +SKIP
    """

    def __init__(
        self,
        region: str | Region = "full",
        sigma: float = 3.0,
        *,
        white_level: float | None = None,
        black_level: float | Sequence[float] = 0.0,
        saturation_level: float | None = None,
        saturation_dilate: int = 1,
        rolloff: bool = True,
        workers: int | None = None,
        cfa: bool = False,
    ) -> None:
        self.region = parse_region(region)
        self.cfa = bool(cfa)
        self.sigma = float(sigma)
        self.white_level = white_level
        self.black_level = black_level
        self.saturation_level = saturation_level
        self.saturation_dilate = int(saturation_dilate)
        self.rolloff = bool(rolloff)
        self.workers = workers
        self._reset()

    def _reset(self) -> None:
        self.frame_shape: tuple[int, int] | None = None
        self._dtype: np.dtype | None = None
        self._total: FingerprintSums | None = None  # every finished chunk
        self._chunk: FingerprintSums | None = None  # the chunk being filled by add()
        self._one_chunk = False  # a work item's builder: one chunk, no running total

    def empty(self) -> FingerprintBuilder:
        """A builder with these settings and no images (each chunk of a parallel build starts from one).

        Raises
        ------
        UsageError
            If this builder already has images (its white level may come from them).
        """
        if self.n_images:
            raise UsageError("a builder that already holds images cannot serve as the settings of a new build")
        fresh = copy.copy(self)
        fresh._reset()
        return fresh

    @property
    def files(self) -> list[str]:
        """Source of each image added so far, in order ('' where none was given)."""
        return [name for sums in (self._total, self._chunk) if sums is not None for name in sums.files]

    @property
    def n_images(self) -> int:
        """Number of images added so far (summed; content-free frames are not)."""
        return sum(s.n_images for s in (self._total, self._chunk) if s is not None)

    @property
    def skipped(self) -> list[tuple[str, str]]:
        """Content-free frames left out so far, ``(source, why)``, in order."""
        return [item for sums in (self._total, self._chunk) if sums is not None for item in sums.skipped]

    @property
    def n_frames(self) -> int:
        """Frames offered so far: summed and left out."""
        return self.n_images + len(self.skipped)

    def _accept(self, shape: tuple[int, int], dtype: np.dtype, name: str) -> None:
        """Take the first frame's geometry and pixel type, or check a later one against them."""
        if self.frame_shape is None:
            self.frame_shape = shape
            self._dtype = dtype
            if self.white_level is None:
                self.white_level = full_scale(dtype)
        elif shape != self.frame_shape:
            hint = " (rotated by 90°? rotate it to the sensor's orientation first)" if shape[::-1] == self.frame_shape else ""
            raise InputError(f"{name}: frame is {shape[0]}×{shape[1]}, the others are "
                             f"{self.frame_shape[0]}×{self.frame_shape[1]}{hint}")
        elif dtype != self._dtype:
            raise InputError(f"{name}: pixel type {dtype} differs from the first image's {self._dtype}")

    def _new_sums(self) -> FingerprintSums:
        assert self.frame_shape is not None and self._dtype is not None
        return FingerprintSums.zeros(self.region.shape(self.frame_shape), self.frame_shape, self._dtype)

    def add(self, image: np.ndarray, source: str | os.PathLike | None = None) -> None:
        """Add one frame ((H, W) or (H, W, 3)); it is not modified.

        Raises
        ------
        InputError
            If its size or pixel type differs from the first frame's.
        """
        image = np.asarray(image)
        name = str(source) if source else f"image #{self.n_frames + 1}"
        if image.ndim not in (2, 3):
            raise InputError(f"{name}: array of shape {image.shape} is not an image")
        self._accept((int(image.shape[0]), int(image.shape[1])), image.dtype, name)
        if self._chunk is None:
            # both accumulators now, so that memory stays flat from the first image on
            self._chunk = self._new_sums()
            if not self._one_chunk:
                self._total = self._new_sums()
        elif self._chunk.n_frames == CHUNK_IMAGES:
            if self._one_chunk:
                raise UsageError(f"a work item sums at most {CHUNK_IMAGES} images")
            self._fold_chunk()
        chunk = self._chunk
        problem = self._content_problem(image)
        if problem is not None:  # left out, and said so in the result: it holds no pattern to estimate
            chunk.skipped.append((name, problem))
            return
        w, i = self._residual_and_intensity(image)
        chunk.excluded += int(np.count_nonzero(i == 0))
        w *= i
        chunk.num += w
        np.multiply(i, i, out=i)
        chunk.den += i
        chunk.files.append(str(source) if source is not None else "")

    def _content_problem(self, image: np.ndarray) -> str | None:
        """Why the frame's pixels in the region hold no pattern (:mod:`forensics.io.content`), or None."""
        return region_content_problem(image, self.region, white_level=self.white_level, black_level=self.black_level,
                                      saturation_level=self.saturation_level)

    def _fold_chunk(self) -> None:
        """Add the filled chunk to the total and start a new one."""
        assert self._total is not None and self._chunk is not None
        self._total.add(self._chunk)
        self._chunk.clear()

    def merge(self, sums: FingerprintSums) -> None:
        """Add the sums of the next chunk of images (computed elsewhere, :func:`chunk_sums`) to the total.

        Chunks must be merged in image order for the bits not to depend on how they were computed.

        Raises
        ------
        InputError
            If the chunk's frames differ in size or pixel type from this builder's.
        """
        name = sums.files[0] if sums.files and sums.files[0] else "a chunk of images"
        self._accept(tuple(sums.frame_shape), sums.dtype, name)  # type: ignore[arg-type]
        if self._total is None:
            self._total = self._new_sums()
        if self._chunk is not None and self._chunk.n_frames:
            self._fold_chunk()
        self._total.add(sums)

    def _residual_and_intensity(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residual W and intensity weight I of one frame over the region (subclasses change W)."""
        return region_residual_and_intensity(
            image, self.region, self.sigma,
            white_level=self.white_level, black_level=self.black_level,
            saturation_level=self.saturation_level, saturation_dilate=self.saturation_dilate,
            rolloff=self.rolloff, postprocess=False, workers=self.workers, cfa=self.cfa,
        )

    def _postprocess(self, raw: np.ndarray) -> np.ndarray:
        """Zero-mean per CFA sub-lattice and DFT Wiener filtering, piece by piece."""
        assert self.frame_shape is not None
        return postprocess(raw, self.region, self.frame_shape, workers=self.workers)

    def _estimator(self) -> dict[str, Any]:
        """How the estimate was made, for the provenance."""
        return {"estimator": "K = sum(W*I) / sum(I^2), then zero-mean per CFA sub-lattice and DFT Wiener",
                "residual": {"wavelet": WAVELET, "levels": LEVELS, "mode": "periodization",
                             "grey_weights": list(GREY_WEIGHTS), "sigma_8bit": self.sigma,
                             "cfa_channels": self.cfa}}

    def raw_estimate(self) -> np.ndarray:
        """``Σ W·I / Σ I²`` before post-processing (0 where no image contributed), float32."""
        if self._total is None:
            raise UsageError("no images added yet; add at least one image before asking for the fingerprint")
        total, chunk = self._total, self._chunk
        k = np.zeros(total.num.shape, np.float32)
        if chunk is None or chunk.n_images == 0:
            np.divide(total.num, total.den, out=k, where=total.den > 0, casting="same_kind")
            return k
        # the open chunk is added last, as a merge would; by blocks of rows, so no full-size temporaries
        step = max(1, (1 << 18) // max(1, k.shape[1]))
        for r in range(0, k.shape[0], step):
            rows = slice(r, r + step)
            num, den = total.num[rows] + chunk.num[rows], total.den[rows] + chunk.den[rows]
            np.divide(num, den, out=k[rows], where=den > 0, casting="same_kind")
        return k

    def result(self, name: str | None = None) -> Fingerprint:
        """The post-processed fingerprint (the builder can keep accumulating afterwards).

        Content-free frames (:mod:`forensics.io.content`) were left out; they are listed in the result's
        ``parameters['excluded_frames']``.

        Parameters
        ----------
        name : str, optional
            The image set's name, for the error below.

        Raises
        ------
        InputError
            Every frame was content-free: there is nothing to estimate a fingerprint from.
        """
        skipped = self.skipped
        if self.n_images == 0 and skipped:
            raise InputError(f"{name or 'the images'}: all {len(skipped)} frame(s) given for the fingerprint are "
                             f"content-free, so there is no pattern to estimate (first, {skipped[0][0]}: {skipped[0][1]});"
                             " give exposed images (20-50 bright, flat, unsaturated ones are best)")
        k = self._postprocess(self.raw_estimate())
        assert self.frame_shape is not None
        excluded = sum(s.excluded for s in (self._total, self._chunk) if s is not None)
        return Fingerprint(
            K=k,
            region=self.region.spec,
            sigma=self.sigma,
            files=self.files,
            n_images=self.n_images,
            frame_shape=self.frame_shape,
            parameters={
                **self._estimator(),
                "dtype": str(self._dtype),
                "white_level": float(self.white_level) if self.white_level is not None else None,
                "black_level": to_jsonable(self.black_level),
                "saturation_level": self.saturation_level,
                "saturation_dilate": self.saturation_dilate,
                "rolloff": self.rolloff,
                "excluded_pixel_fraction": excluded / max(1, self.n_images * k.size),
                "excluded_frames": [{"file": f, "reason": why} for f, why in skipped],
                "forensics_version": __version__,
            },
        )


# ----------------------------------------------------------------------------- building on the execution layer


@dataclass(frozen=True)
class FingerprintJob:
    """One fingerprint to build: the settings (a builder with no images), the image set, which of its images.

    ``builder`` may be any :class:`FingerprintBuilder` (e.g. the median-residual one of
    :mod:`forensics.prnu.ageing`); ``images`` anything with ``load(i)`` and ``sources``
    (an :class:`ImageSet`).
    """

    builder: FingerprintBuilder
    images: ImageSet
    indices: tuple[int, ...]


def chunk_sums(jobs: Sequence[FingerprintJob], item: tuple[int, int, int]) -> tuple[int, FingerprintSums]:
    """Work item of a fingerprint build: the sums over images ``indices[start:stop]`` of job ``j``.

    ``item`` is ``(j, start, stop)``; the images are read here, by index into the job's set.
    Returns ``(j, sums)``.
    """
    j, start, stop = item
    job = jobs[j]
    builder = job.builder.empty()
    builder._one_chunk = True  # the chunk's sums are all that is returned: no total to allocate
    for i in job.indices[start:stop]:
        builder.add(job.images.load(i), source=job.images.sources[i])
    assert builder._chunk is not None
    return j, builder._chunk


def build_fingerprints(
    jobs: Sequence[FingerprintJob],
    *,
    executor: Executor | None = None,
    progress: Progress = no_progress,
    desc: str = "fingerprints",
    checkpoint: Checkpoint | None = None,
) -> list[Fingerprint]:
    """Build several fingerprints at once on the execution layer; one work item per (job, chunk of images).

    Every job's images are cut into chunks of :data:`CHUNK_IMAGES` (so all workers are busy even
    with one fingerprint, and with many), each chunk's sums computed where its item runs, and the
    sums added job by job in chunk order: the fingerprints are bit-identical on every backend and
    to a :class:`FingerprintBuilder` fed the same images one by one.  A job's sums are dropped as
    soon as its fingerprint is complete, so the memory held is about one job's sums plus the
    finished fingerprints.

    Parameters
    ----------
    jobs : sequence of FingerprintJob
    executor : Executor, optional
        Default: in this process.
    progress, desc
        One progress bar counting the chunks.
    checkpoint : Checkpoint, optional
        Finished chunks are saved there (and loaded instead of recomputed when a run resumes).

    Returns
    -------
    list of Fingerprint, in job order

    Raises
    ------
    UsageError
        A job without images, or whose builder already holds images.
    InputError
        Frames of one job differ in size or pixel type, or cannot be read.
    """
    jobs = tuple(jobs)
    if any(len(job.indices) == 0 for job in jobs):
        raise UsageError("no images to build a fingerprint from; give at least one (20-50 flat images are usual)")
    builders: list[FingerprintBuilder | None] = [job.builder.empty() for job in jobs]  # refuses used builders
    items = [(j, c.start, c.stop) for j, job in enumerate(jobs) for c in chunks(len(job.indices), CHUNK_IMAGES)]
    remaining = [len(chunks(len(job.indices), CHUNK_IMAGES)) for job in jobs]
    done: list[Fingerprint | None] = [None] * len(jobs)

    def combine(acc: list[Fingerprint | None], part: tuple[int, FingerprintSums]) -> list[Fingerprint | None]:
        j, sums = part
        builder = builders[j]
        assert builder is not None
        builder.merge(sums)
        remaining[j] -= 1
        if remaining[j] == 0:
            acc[j] = builder.result(jobs[j].images.name)
            builders[j] = None  # free the sums
        return acc

    resolve(executor).reduce(chunk_sums, items, combine, initial=done, shared=jobs, progress=progress, desc=desc,
                             checkpoint=checkpoint)
    return [fp for fp in done if fp is not None]


def _source_name(item: Any) -> str:
    """What the provenance records for an image given as a frame, a path or an array."""
    if hasattr(item, "load"):
        path = getattr(item, "path", None)
        return str(path) if path is not None else ""
    if isinstance(item, (str, os.PathLike)):
        return str(item)
    return ""


def build_fingerprint(
    images: Iterable[Any],
    region: str | Region = "full",
    sigma: float = 3.0,
    *,
    sources: Iterable[str | os.PathLike] | None = None,
    progress: Progress = no_progress,
    total: int | None = None,
    executor: Executor | None = None,
    checkpoint: Checkpoint | None = None,
    name: str | None = None,
    dark: Any = None,
    **options: Any,
) -> Fingerprint:
    """Fingerprint from frames, streamed (one frame in memory at a time per worker).

    Content-free frames (constant, black or saturated: :mod:`forensics.io.content`) are left out and
    listed in ``parameters['excluded_frames']``; when every frame is, an :class:`InputError` names the set.

    Parameters
    ----------
    images : sequence or iterable
        A sequence (list, :class:`ImageSet`, Dataset frames) of image paths, objects with a
        ``load()`` method returning an array and a ``path`` attribute (e.g.
        :class:`forensics.io.dataset.Frame`), or arrays: built in chunks on ``executor``
        (:func:`build_fingerprints`).  Any other iterable (a generator of arrays) is
        consumed here, one frame at a time.  Both give the same bits.
    region, sigma, **options
        As :class:`FingerprintBuilder`.
    sources : iterable of str, optional
        Names recorded in the provenance (default: each item's ``path`` or the path
        itself; '' for arrays).
    progress : callable
        ``progress(iterable, total=None, desc=None)`` (silent by default); counts chunks
        of :data:`CHUNK_IMAGES` images for a sequence.
    total : int, optional
        Number of images of an iterator, for the progress bar.
    executor : Executor, optional
        Where the chunks run (default: this process).  Workers read the images
        themselves, so give paths or dataset frames rather than arrays.
    checkpoint : Checkpoint, optional
        Resume an interrupted build of a sequence (see :func:`build_fingerprints`).
    name : str, optional
        The set's name in messages (default: a Dataset's folder, else 'the images').
    dark : DarkCalibration, optional
        Calibrate every frame as ``frame − offset − rate·exposure`` before its residual
        (:mod:`forensics.prnu.calibration`; raw CCD frames); ``images`` must then be a dataset (folder or
        Dataset), whose frames give their exposure and temperature.  Recorded in
        ``parameters['dark_calibration']``.

    Raises
    ------
    UsageError
        If ``images`` is empty, or an iterator is given with an executor that is not in-process.
    InputError
        Every frame is content-free, frames differ in size or pixel type, or cannot be read.
    """
    from forensics.io.dataset import Dataset

    if dark is not None:
        frames = dark.calibrated_frames(images)
        options.setdefault("white_level", dark.white_level)  # calibrated floats keep the raw frames' full scale
        fp = build_fingerprint(frames, region, sigma, sources=sources, progress=progress, total=total,
                               executor=executor, checkpoint=checkpoint,
                               name=name or str(getattr(images, "root", images)), **options)
        fp.parameters["dark_calibration"] = {**dark.to_dict(), "frames": [f.to_dict() for f in frames]}
        return fp
    builder = FingerprintBuilder(region, sigma, **options)
    names = None if sources is None else [str(s) for s in sources]
    if isinstance(images, (ImageSet, Dataset)) or (
            hasattr(images, "__len__") and hasattr(images, "__getitem__") and not isinstance(images, np.ndarray)):
        label = name or (images.name if isinstance(images, ImageSet) else
                         str(images.root) if isinstance(images, Dataset) else "the images")
        image_set = ImageSet.of(images, label)
        if names is None and not isinstance(images, (ImageSet, Dataset)):
            names = [_source_name(images[i]) for i in range(len(image_set))]  # type: ignore[index]
        if names is not None:
            if len(names) != len(image_set):
                raise UsageError(f"{len(names)} source names for {len(image_set)} images; give one name per image")
            image_set = ImageSet(image_set._loaders, names, image_set.name)
        job = FingerprintJob(builder, image_set, tuple(range(len(image_set))))
        return build_fingerprints([job], executor=executor, progress=progress, desc="fingerprint",
                                  checkpoint=checkpoint)[0]
    if executor is not None and executor.backend != "in-process":
        raise UsageError("an iterator of images is read in this process; give a sequence of paths or frames to "
                         "build a fingerprint on worker processes or a cluster")
    return _build_streamed(builder, images, names, progress, total, name)


def _build_streamed(builder: FingerprintBuilder, images: Iterable[Any], names: list[str] | None,
                    progress: Progress, total: int | None, name: str | None = None) -> Fingerprint:
    """Feed an iterator of frames to ``builder`` one at a time."""
    name_iter = iter(names) if names is not None else None
    for item in progress(images, total=total, desc="fingerprint"):
        source = next(name_iter, None) if name_iter is not None else None
        if hasattr(item, "load"):
            if source is None:
                source = getattr(item, "path", None)
            item = item.load()
        builder.add(item, source=source)
    if builder.n_frames == 0:
        raise UsageError("no images to build a fingerprint from; give at least one (20-50 flat images are usual)")
    return builder.result(name)
