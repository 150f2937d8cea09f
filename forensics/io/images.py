"""Reading and writing images.

Ordinary images (PNG, TIFF, JPEG, BMP, …) are read through OpenImageIO in
their native dtype; raw camera files (DNG, CR2, NEF, …) through rawpy as the
CFA mosaic with its black and white levels.  Writing is atomic (temporary
file, then rename) and refuses to replace an existing file unless ``force``.
"""
from __future__ import annotations

import contextlib
import datetime as _dt
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from forensics._shared.atomic import mkstemp_like_open, refuse_existing
from forensics._shared.errors import InputError

RAW_EXTENSIONS = frozenset(
    ".dng .cr2 .cr3 .crw .nef .nrw .arw .srf .sr2 .orf .rw2 .raf .pef .srw .3fr .erf .kdc .mos .mrw .x3f .iiq".split()
)
IMAGE_EXTENSIONS = frozenset(".png .tif .tiff .jpg .jpeg .bmp .pgm .ppm .pnm .exr .webp".split()) | RAW_EXTENSIONS
WRITABLE_EXTENSIONS = frozenset(".png .tif .tiff".split())


@dataclass(frozen=True)
class ImageInfo:
    """What a file's header says, without decoding the pixels.

    ``captured`` is a naive :class:`datetime.datetime` (camera local time) or None.
    """

    path: Path
    width: int
    height: int
    channels: int
    dtype: np.dtype
    captured: _dt.datetime | None = None
    exposure_s: float | None = None
    iso: float | None = None
    make: str | None = None
    model: str | None = None
    serial: str | None = None
    orientation: int = 1
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, ...]:
        return (self.height, self.width) if self.channels == 1 else (self.height, self.width, self.channels)


@dataclass(frozen=True)
class RawMosaic:
    """A raw camera frame: the colour-filter-array mosaic, undemosaiced.

    ``cfa_pattern`` is the 2×2 pattern read row-major from the top-left of
    the visible area, e.g. ``"RGGB"``.  ``black_level`` has one entry per
    position of the 2×2 pattern in the same order.
    """

    mosaic: np.ndarray
    black_level: tuple[float, float, float, float]
    white_level: float
    cfa_pattern: str
    info: ImageInfo


def is_raw(path: str | os.PathLike) -> bool:
    """True for file names that rawpy (LibRaw) handles rather than OpenImageIO."""
    return Path(path).suffix.lower() in RAW_EXTENSIONS


def _oiio():
    import OpenImageIO

    return OpenImageIO


def _open_input(path: Path):
    oiio = _oiio()
    if not path.is_file():
        raise InputError(f"{path}: no such file; check the path")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        msg = oiio.geterror().strip().splitlines()
        detail = msg[0] if msg else "unrecognised format"
        raise InputError(f"{path}: cannot read the image ({detail}); check the file is a complete PNG/TIFF/JPEG/BMP or raw file")
    return inp


_DTYPES = {"uint8": np.uint8, "uint16": np.uint16, "half": np.float16, "float": np.float32, "double": np.float64,
           "int8": np.int8, "int16": np.int16, "uint32": np.uint32, "int32": np.int32}


def _exif_datetime(value: Any) -> _dt.datetime | None:
    if not value:
        return None
    text = str(value).strip()
    for fmt in ("%Y:%m:%d %H:%M:%S", "%Y-%m-%d %H:%M:%S", "%Y-%m-%dT%H:%M:%S", "%Y:%m:%d"):
        try:
            return _dt.datetime.strptime(text, fmt)
        except ValueError:
            continue
    return None


def _spec_info(path: Path, spec: Any) -> ImageInfo:
    def get(*names: str) -> Any:
        for name in names:
            value = spec.getattribute(name)
            if value not in (None, ""):
                return value
        return None

    iso = get("Exif:PhotographicSensitivity", "Exif:ISOSpeedRatings", "Exif:ISOSpeed", "ISO")
    if isinstance(iso, (tuple, list)):
        iso = iso[0] if iso else None
    exposure = get("ExposureTime", "Exif:ExposureTime")
    serial = get("Exif:BodySerialNumber", "Exif:SerialNumber", "Nikon:SerialNumber", "Canon:SerialNumber")
    dtype = np.dtype(_DTYPES.get(str(spec.format), np.float32))
    return ImageInfo(
        path=path,
        width=int(spec.width),
        height=int(spec.height),
        channels=int(spec.nchannels),
        dtype=dtype,
        captured=_exif_datetime(get("Exif:DateTimeOriginal", "DateTime", "Exif:DateTimeDigitized")),
        exposure_s=float(exposure) if exposure is not None else None,
        iso=float(iso) if iso is not None else None,
        make=str(get("Make")).strip() if get("Make") else None,
        model=str(get("Model")).strip() if get("Model") else None,
        serial=str(serial).strip() if serial else None,
        orientation=int(get("Orientation") or 1),
    )


def read_info(path: str | os.PathLike) -> ImageInfo:
    """Read a file's size, dtype and capture metadata (EXIF) without decoding its pixels.

    Raises
    ------
    InputError
        If the file is missing or is not a readable image.
    """
    path = Path(path)
    if is_raw(path):
        return read_raw(path).info
    inp = _open_input(path)
    try:
        return _spec_info(path, inp.spec())
    finally:
        inp.close()


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read an image in its native dtype: ``(H, W)`` for grey, ``(H, W, C)`` for colour.

    Raw camera files are returned as their 2-D CFA mosaic (see :func:`read_raw`
    for black/white levels and the CFA pattern).  An alpha channel is dropped.

    Raises
    ------
    InputError
        If the file is missing, corrupt or truncated; the message names the file.
    """
    path = Path(path)
    if is_raw(path):
        return read_raw(path).mosaic
    inp = _open_input(path)
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "unknown")
        failed = pixels is None or bool(inp.has_error)
        detail = inp.geterror().strip().splitlines() if failed else []
    finally:
        inp.close()
    if failed:
        why = detail[0] if detail else "decoding failed"
        raise InputError(f"{path}: cannot read the image, corrupt or truncated ({why}); replace or remove the file")
    pixels = np.asarray(pixels)
    if pixels.ndim == 3 and pixels.shape[2] in (2, 4):
        pixels = pixels[..., :-1]  # drop alpha
    if pixels.ndim == 3 and pixels.shape[2] == 1:
        pixels = pixels[..., 0]
    return np.ascontiguousarray(pixels)


def read_raw(path: str | os.PathLike) -> RawMosaic:
    """Read a raw camera file (DNG, CR2, NEF, …) as its CFA mosaic through rawpy.

    Raises
    ------
    InputError
        If LibRaw cannot open the file.
    """
    import rawpy

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file; check the path")
    try:
        with rawpy.imread(str(path)) as raw:
            mosaic = np.array(raw.raw_image_visible, copy=True)
            desc = raw.color_desc.decode() if isinstance(raw.color_desc, bytes) else str(raw.color_desc)
            pattern = "".join(desc[i] for i in np.asarray(raw.raw_pattern)[:2, :2].ravel())
            black = tuple(float(b) for b in raw.black_level_per_channel)
            order = np.asarray(raw.raw_pattern)[:2, :2].ravel()
            black4 = tuple(black[i] for i in order)
            white = float(raw.white_level)
    except (rawpy.LibRawError, OSError, ValueError) as exc:  # type: ignore[attr-defined]
        raise InputError(f"{path}: cannot read as a raw camera file ({exc}); check the file is complete") from exc
    info = ImageInfo(path=path, width=mosaic.shape[1], height=mosaic.shape[0], channels=1, dtype=mosaic.dtype)
    with contextlib.suppress(InputError):  # EXIF of raw files through OpenImageIO where it can read them
        inp = _open_input(path)
        try:
            meta = _spec_info(path, inp.spec())
            info = ImageInfo(**{**meta.__dict__, "width": info.width, "height": info.height, "channels": 1,
                                "dtype": info.dtype})
        finally:
            inp.close()
    return RawMosaic(mosaic=mosaic, black_level=black4, white_level=white, cfa_pattern=pattern, info=info)


def write_image(
    path: str | os.PathLike,
    image: np.ndarray,
    force: bool = False,
    inputs: tuple[str | os.PathLike, ...] = (),
    metadata: dict[str, Any] | None = None,
) -> Path:
    """Write a uint8 or uint16 image to PNG or TIFF atomically.

    Parameters
    ----------
    path
        Destination; its extension (``.png``, ``.tif``, ``.tiff``) chooses the format.
    image
        ``(H, W)`` or ``(H, W, C)`` array of dtype uint8 or uint16 (TIFF also float32).
    force
        Replace an existing file.
    inputs
        Files that must never be overwritten (raises if ``path`` is one of them).
    metadata
        Extra attributes for the header, e.g. ``{"DateTime": "2009:01:06 14:24:07"}``.
    """
    from forensics._shared.atomic import refuse_inputs

    oiio = _oiio()
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in WRITABLE_EXTENSIONS:
        raise InputError(f"{path}: cannot write {ext or 'files without extension'}; use .png or .tif")
    image = np.asarray(image)
    allowed = (np.uint8, np.uint16, np.float32) if ext != ".png" else (np.uint8, np.uint16)
    if image.dtype.type not in allowed:
        raise InputError(f"{path}: cannot write dtype {image.dtype} to {ext}; convert to uint8 or uint16 first")
    if image.ndim not in (2, 3):
        raise InputError(f"{path}: image must be 2-D or 3-D, got shape {image.shape}")
    refuse_inputs(path, inputs)
    refuse_existing(path, force)
    channels = 1 if image.ndim == 2 else image.shape[2]
    spec = oiio.ImageSpec(image.shape[1], image.shape[0], channels, image.dtype.name if image.dtype != np.float32 else "float")
    for key, value in (metadata or {}).items():
        spec.attribute(key, value)
    if ext in (".tif", ".tiff"):
        spec.attribute("compression", "zip")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = mkstemp_like_open(prefix=f".{path.stem}.", suffix=f".part{ext}", dir=path.parent)  # umask mode
    os.close(fd)
    try:
        out = oiio.ImageOutput.create(tmp)
        if out is None or not out.open(tmp, spec):
            raise InputError(f"{path}: cannot open for writing ({oiio.geterror().strip()})")
        ok = out.write_image(np.ascontiguousarray(image.reshape(image.shape[0], image.shape[1], channels)))
        err = out.geterror()
        out.close()
        if not ok:
            raise InputError(f"{path}: writing failed ({err.strip()})")
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    return path


def bits_dtype(bit_depth: int) -> np.dtype:
    """uint8 for up to 8 bits, uint16 for up to 16."""
    if bit_depth <= 8:
        return np.dtype(np.uint8)
    if bit_depth <= 16:
        return np.dtype(np.uint16)
    raise ValueError(f"bit depth {bit_depth} not supported (1–16)")
