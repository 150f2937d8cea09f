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
"""
from __future__ import annotations

import json
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from forensics import __version__
from forensics._shared.atomic import atomic_file
from forensics._shared.errors import InputError, UsageError
from forensics._shared.progress import Progress, no_progress
from forensics._shared.arrays import GREY_WEIGHTS, full_scale
from forensics.prnu.residual import (
    LEVELS,
    WAVELET,
    residual_and_grey,
    wiener_dft,
    zero_mean_cfa,
)

__all__ = [
    "Region",
    "parse_region",
    "saturation_mask",
    "intensity",
    "FingerprintBuilder",
    "Fingerprint",
    "build_fingerprint",
    "postprocess",
    "region_residual_and_intensity",
    "FORMAT",
]

FORMAT = "forensics-fingerprint/1"
#: Roll-off of the intensity weight near full scale (reference: T = 252, v = 6 on 8 bits).
ROLLOFF_T = 252.0 / 255.0
ROLLOFF_V = 6.0 / 255.0**2

Slices = tuple[slice, slice]


# ----------------------------------------------------------------------------- regions


@dataclass(frozen=True)
class Region:
    """Where in the frame the fingerprint lives.

    Attributes
    ----------
    kind : {'full', 'center', 'corners'}
    size : (int, int) or None
        Crop size (height, width) for 'center'; patch size (N, N) for 'corners'.
    """

    kind: str
    size: tuple[int, int] | None = None

    @property
    def spec(self) -> str:
        """The text form accepted by :func:`parse_region`."""
        if self.kind == "full":
            return "full"
        assert self.size is not None
        h, w = self.size
        text = str(h) if h == w else f"{h}x{w}"
        return f"{self.kind}:{text}"

    def __str__(self) -> str:
        return self.spec

    def pieces(self, frame_shape: Sequence[int]) -> list[Slices]:
        """The (row, column) slices of the frame that make up the region, in mosaic order."""
        fh, fw = int(frame_shape[0]), int(frame_shape[1])
        if self.kind == "full":
            return [(slice(0, fh), slice(0, fw))]
        assert self.size is not None
        h, w = self.size
        if self.kind == "center":
            if h > fh or w > fw:
                raise InputError(f"region {self.spec} does not fit in a {fh}×{fw} frame; choose a smaller crop")
            top = ((fh - h) // 2) & ~1
            left = ((fw - w) // 2) & ~1
            return [(slice(top, top + h), slice(left, left + w))]
        # corners: start coordinates rounded down to even so every patch keeps the CFA phase
        if 2 * h > fh or 2 * w > fw:
            raise InputError(f"region {self.spec}: four {h}×{w} corners do not fit in a {fh}×{fw} frame")
        bottom = (fh - h) & ~1
        right = (fw - w) & ~1
        return [
            (slice(0, h), slice(0, w)),
            (slice(0, h), slice(right, right + w)),
            (slice(bottom, bottom + h), slice(0, w)),
            (slice(bottom, bottom + h), slice(right, right + w)),
        ]

    def shape(self, frame_shape: Sequence[int]) -> tuple[int, int]:
        """Shape of the region's array (the mosaic for 'corners')."""
        if self.kind == "full":
            return int(frame_shape[0]), int(frame_shape[1])
        self.pieces(frame_shape)  # validates the fit
        assert self.size is not None
        h, w = self.size
        return (h, w) if self.kind == "center" else (2 * h, 2 * w)

    def mosaic_slices(self, frame_shape: Sequence[int]) -> list[Slices]:
        """Where each piece goes in the region's array (same order as :meth:`pieces`)."""
        if self.kind != "corners":
            h, w = self.shape(frame_shape)
            return [(slice(0, h), slice(0, w))]
        assert self.size is not None
        h, w = self.size
        return [
            (slice(0, h), slice(0, w)),
            (slice(0, h), slice(w, 2 * w)),
            (slice(h, 2 * h), slice(0, w)),
            (slice(h, 2 * h), slice(w, 2 * w)),
        ]

    def extract(self, array: np.ndarray) -> np.ndarray:
        """The region's pixels of a frame ((H, W) or (H, W, C)) as one new array (mosaic for 'corners')."""
        array = np.asarray(array)
        pieces = self.pieces(array.shape)
        out = np.empty(self.shape(array.shape) + array.shape[2:], array.dtype)
        for src, dst in zip(pieces, self.mosaic_slices(array.shape)):
            out[dst] = array[src]
        return out


_REGION_RE = re.compile(r"^(center|centre|corners)(?::(\d+)(?:[x×](\d+))?)?$")


def parse_region(spec: str | Region) -> Region:
    """Parse ``"full"``, ``"center:N"``, ``"center:HxW"``, ``"corners"`` or ``"corners:N"``.

    Raises
    ------
    UsageError
        For any other text (the message lists the accepted forms).
    """
    if isinstance(spec, Region):
        return spec
    text = str(spec).strip().lower()
    if text == "full":
        return Region("full")
    m = _REGION_RE.match(text)
    if m:
        kind = "center" if m.group(1) in ("center", "centre") else "corners"
        if m.group(2) is None:
            if kind == "center":
                raise UsageError(f"region {spec!r}: give the crop size, e.g. 'center:512'")
            return Region("corners", (128, 128))
        h = int(m.group(2))
        w = int(m.group(3)) if m.group(3) else h
        if kind == "corners" and w != h:
            raise UsageError(f"region {spec!r}: corner patches are square, e.g. 'corners:128'")
        if h < 16 or w < 16:
            raise UsageError(f"region {spec!r}: crops smaller than 16 pixels carry no usable fingerprint")
        return Region(kind, (h, w))
    raise UsageError(f"region {spec!r}: expected 'full', 'center:N' (or 'center:HxW'), or 'corners' / 'corners:N'")


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
        res, grey = residual_and_grey(piece, sigma, white_level=white_level, workers=workers)
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


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    return value


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
            "parameters": _jsonable(self.parameters),
        }

    def save(self, path: str | os.PathLike, force: bool = False) -> Path:
        """Write ``K`` and the provenance (JSON) to one ``.npz`` file, atomically.

        Raises
        ------
        UsageError
            If ``path`` exists and ``force`` is false.
        """
        path = Path(path)
        meta = json.dumps(self.to_dict())
        with atomic_file(path, force=force, mode="wb") as handle:
            # uncompressed: K is noise-like, zlib would gain a few per cent for seconds of CPU
            np.savez(handle, K=np.asarray(self.K, np.float32), meta=np.array(meta))
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> Fingerprint:
        """Read a fingerprint written by :meth:`save`.

        Raises
        ------
        InputError
            If the file is missing, not a fingerprint, or inconsistent.
        """
        path = Path(path)
        if not path.is_file():
            raise InputError(f"{path}: no such fingerprint file; check the path")
        try:
            with np.load(path, allow_pickle=False) as data:
                k = np.asarray(data["K"], np.float32)
                meta = json.loads(str(data["meta"][()]))
        except (OSError, ValueError, KeyError, json.JSONDecodeError) as exc:
            raise InputError(f"{path}: not a fingerprint file ({exc}); build one with FingerprintBuilder") from exc
        if meta.get("format") != FORMAT:
            raise InputError(f"{path}: unknown fingerprint format {meta.get('format')!r} (expected {FORMAT})")
        if list(k.shape) != list(meta.get("shape", [])):
            raise InputError(f"{path}: K has shape {k.shape} but the provenance says {meta.get('shape')}")
        return cls(
            K=k,
            region=meta["region"],
            sigma=float(meta["sigma"]),
            files=list(meta["files"]),
            n_images=int(meta["n_images"]),
            frame_shape=tuple(meta["frame_shape"]),  # type: ignore[arg-type]
            parameters=dict(meta.get("parameters", {})),
        )


class FingerprintBuilder:
    """Accumulate ``Σ W·I`` and ``Σ I²`` image by image; memory does not grow with the count.

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
    ) -> None:
        self.region = parse_region(region)
        self.sigma = float(sigma)
        self.white_level = white_level
        self.black_level = black_level
        self.saturation_level = saturation_level
        self.saturation_dilate = int(saturation_dilate)
        self.rolloff = bool(rolloff)
        self.workers = workers
        self.files: list[str] = []
        self.frame_shape: tuple[int, int] | None = None
        self._dtype: np.dtype | None = None
        self._num: np.ndarray | None = None
        self._den: np.ndarray | None = None
        self._excluded = 0

    @property
    def n_images(self) -> int:
        """Number of images added so far."""
        return len(self.files)

    def add(self, image: np.ndarray, source: str | os.PathLike | None = None) -> None:
        """Add one frame ((H, W) or (H, W, 3)); it is not modified.

        Raises
        ------
        InputError
            If its size or pixel type differs from the first frame's.
        """
        image = np.asarray(image)
        shape = (int(image.shape[0]), int(image.shape[1])) if image.ndim in (2, 3) else None
        name = str(source) if source is not None else f"image #{self.n_images + 1}"
        if shape is None:
            raise InputError(f"{name}: array of shape {image.shape} is not an image")
        if self.frame_shape is None:
            self.frame_shape = shape
            self._dtype = image.dtype
            if self.white_level is None:
                self.white_level = full_scale(image.dtype)
            rshape = self.region.shape(shape)
            self._num = np.zeros(rshape, np.float64)
            self._den = np.zeros(rshape, np.float64)
        elif shape != self.frame_shape:
            hint = " (rotated by 90°? rotate it to the sensor's orientation first)" if shape[::-1] == self.frame_shape else ""
            raise InputError(f"{name}: frame is {shape[0]}×{shape[1]}, the others are "
                             f"{self.frame_shape[0]}×{self.frame_shape[1]}{hint}")
        elif image.dtype != self._dtype:
            raise InputError(f"{name}: pixel type {image.dtype} differs from the first image's {self._dtype}")
        w, i = self._residual_and_intensity(image)
        assert self._num is not None and self._den is not None
        self._excluded += int(np.count_nonzero(i == 0))
        w *= i
        self._num += w
        np.multiply(i, i, out=i)
        self._den += i
        self.files.append(str(source) if source is not None else "")

    def _residual_and_intensity(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residual W and intensity weight I of one frame over the region (subclasses change W)."""
        return region_residual_and_intensity(
            image, self.region, self.sigma,
            white_level=self.white_level, black_level=self.black_level,
            saturation_level=self.saturation_level, saturation_dilate=self.saturation_dilate,
            rolloff=self.rolloff, postprocess=False, workers=self.workers,
        )

    def _postprocess(self, raw: np.ndarray) -> np.ndarray:
        """Zero-mean per CFA sub-lattice and DFT Wiener filtering, piece by piece."""
        assert self.frame_shape is not None
        return postprocess(raw, self.region, self.frame_shape, workers=self.workers)

    def _estimator(self) -> dict[str, Any]:
        """How the estimate was made, for the provenance."""
        return {"estimator": "K = sum(W*I) / sum(I^2), then zero-mean per CFA sub-lattice and DFT Wiener",
                "residual": {"wavelet": WAVELET, "levels": LEVELS, "mode": "periodization",
                             "grey_weights": list(GREY_WEIGHTS), "sigma_8bit": self.sigma}}

    def raw_estimate(self) -> np.ndarray:
        """``Σ W·I / Σ I²`` before post-processing (0 where no image contributed), float32."""
        if self._num is None or self._den is None:
            raise UsageError("no images added yet; add at least one image before asking for the fingerprint")
        k = np.zeros(self._num.shape, np.float32)
        np.divide(self._num, self._den, out=k, where=self._den > 0, casting="same_kind")
        return k

    def result(self) -> Fingerprint:
        """The post-processed fingerprint (the builder can keep accumulating afterwards)."""
        k = self._postprocess(self.raw_estimate())
        assert self.frame_shape is not None
        return Fingerprint(
            K=k,
            region=self.region.spec,
            sigma=self.sigma,
            files=list(self.files),
            n_images=self.n_images,
            frame_shape=self.frame_shape,
            parameters={
                **self._estimator(),
                "dtype": str(self._dtype),
                "white_level": float(self.white_level) if self.white_level is not None else None,
                "black_level": _jsonable(self.black_level),
                "saturation_level": self.saturation_level,
                "saturation_dilate": self.saturation_dilate,
                "rolloff": self.rolloff,
                "excluded_pixel_fraction": self._excluded / max(1, self.n_images * k.size),
                "forensics_version": __version__,
            },
        )


def build_fingerprint(
    images: Iterable[Any],
    region: str | Region = "full",
    sigma: float = 3.0,
    *,
    sources: Iterable[str | os.PathLike] | None = None,
    progress: Progress = no_progress,
    total: int | None = None,
    **options: Any,
) -> Fingerprint:
    """Fingerprint from an iterable of frames, streamed (one frame in memory at a time).

    Parameters
    ----------
    images : iterable
        Arrays, or objects with a ``load()`` method returning one and a ``path``
        attribute (e.g. :class:`forensics.io.dataset.Frame`).
    region, sigma, **options
        As :class:`FingerprintBuilder`.
    sources : iterable of str, optional
        Names recorded in the provenance (default: each item's ``path`` if any).
    progress : callable
        ``progress(iterable, total=None, desc=None)`` (silent by default).
    total : int, optional
        Number of images, for the progress bar.

    Raises
    ------
    UsageError
        If ``images`` is empty.
    """
    builder = FingerprintBuilder(region, sigma, **options)
    names = iter(sources) if sources is not None else None
    if total is None and hasattr(images, "__len__"):
        total = len(images)  # type: ignore[arg-type]
    for item in progress(images, total=total, desc="fingerprint"):
        source = next(names, None) if names is not None else None
        if hasattr(item, "load"):
            if source is None:
                source = getattr(item, "path", None)
            item = item.load()
        builder.add(item, source=source)
    if builder.n_images == 0:
        raise UsageError("no images to build a fingerprint from; give at least one (20-50 flat images are usual)")
    return builder.result()
