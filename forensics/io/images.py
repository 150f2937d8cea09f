"""Reading and writing images.

Ordinary images (PNG, TIFF, JPEG, BMP, …) are read through OpenImageIO in
their native dtype; raw camera files (DNG, CR2, NEF, …) through rawpy as the
CFA mosaic with its black and white levels; FITS frames (``.fits``, ``.fit``,
``.fts``, compressed ``.fits.fz``) through astropy (:mod:`forensics.io.fits`, which
applies BZERO/BSCALE and checks the file itself).  Every other file is checked before it is
decoded: a regular file (never a pipe, which would block), a header declaring no
more pixels than :func:`~forensics._shared.limits.pixel_limit` and at least 2×2.
Writing is atomic (temporary file, then rename), verified by the library's own
error report, and refuses to replace an existing file unless ``force``.
"""
from __future__ import annotations

import contextlib
import datetime as _dt
import errno
import math
import os
import stat
import sys
import tempfile
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from forensics._shared.atomic import mkstemp_like_open, refuse_existing
from forensics._shared.errors import InputError
from forensics._shared.limits import require_pixels
from forensics._shared.text import printable
from forensics.io.dates import exif_datetime

RAW_EXTENSIONS = frozenset(
    ".dng .cr2 .cr3 .crw .nef .nrw .arw .srf .sr2 .orf .rw2 .raf .pef .srw .3fr .erf .kdc .mos .mrw .x3f .iiq".split()
)
IMAGE_EXTENSIONS = frozenset(".png .tif .tiff .jpg .jpeg .bmp .pgm .ppm .pnm .exr .webp".split()) | RAW_EXTENSIONS
WRITABLE_EXTENSIONS = frozenset(".png .tif .tiff".split())
#: The smallest width and height read: a noise residual, a median or a neighbour comparison needs 2 pixels a side.
MIN_SIDE = 2


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


def _shown(path: str | os.PathLike) -> str:
    """A path as it may be printed: control characters and undecodable bytes escaped."""
    return printable(str(path))


def file_problem(path: str | os.PathLike) -> str | None:
    """What keeps ``path`` from being read as a regular file, as a phrase ("does not exist", "is a folder"), or None.

    Asked before opening, so that a pipe (which would block a reader forever), a folder, a symbolic-link
    loop, a name too long for the file system or one holding a NUL byte is told apart and named, instead
    of failing deep in a library.
    """
    try:
        info = os.stat(path)
    except FileNotFoundError:
        return "does not exist"
    except ValueError:  # an embedded NUL: no file can have this name
        return "has a NUL character in its name, which no file name can hold"
    except OSError as exc:
        reason = {errno.ELOOP: "is a loop of symbolic links", errno.ENAMETOOLONG: "has a name too long for the file system"}
        return reason.get(exc.errno, f"cannot be opened ({exc.strerror})")
    if stat.S_ISDIR(info.st_mode):
        return "is a folder, not a file"
    if not stat.S_ISREG(info.st_mode):
        return "is not a regular file (a pipe, socket or device)"
    return None


def require_regular_file(path: str | os.PathLike, what: str = "image") -> None:
    """Raise :class:`InputError`, naming the file, if it is not a readable regular file (:func:`file_problem`)."""
    problem = file_problem(path)
    if problem is not None:
        raise InputError(f"{_shown(path)}: {problem}; give the path of an existing {what} file")


def _require_utf8_name(path: Path) -> None:
    """OpenImageIO and LibRaw take names as UTF-8: a name holding other bytes cannot be passed to them."""
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:
        raise InputError(f"{_shown(path)}: the path is not valid UTF-8, which the image libraries need to open "
                         "it; rename the file or folder") from None


def _check_header(path: Path, width: int, height: int, channels: int) -> None:
    """Refuse, from the header and before any decoding, an image too large to decode or too small to analyse."""
    require_pixels(width * height * max(channels, 1), _shown(path))  # a 1.5 MB PNG can ask for gigabytes
    if width < MIN_SIDE or height < MIN_SIDE:
        raise InputError(f"{_shown(path)}: the image is {width}×{height} pixels, too small to analyse (at least "
                         f"{MIN_SIDE}×{MIN_SIDE}: every residual and filter compares a pixel with its neighbours); "
                         "remove it from the set")


# libpng prints its errors to the C stderr itself ("libpng error: …") because OpenImageIO's PNG error handler
# returns to it; the same error comes back, once, through geterror().  Those lines are dropped; anything else
# written to fd 2 meanwhile is passed on.  One redirect at a time per process: fd 2 is process-wide.
_STDERR_LOCK = threading.Lock()
_LIBRARY_CHATTER = (b"libpng error:", b"libpng warning:")


@contextlib.contextmanager
def _quiet_native_stderr(active: bool) -> Iterator[None]:
    """While active, send fd 2 to a scratch file; afterwards pass on whatever was not libpng's own chatter."""
    if not active:
        yield
        return
    with _STDERR_LOCK, tempfile.TemporaryFile() as sink:
        try:
            saved = os.dup(2)
        except OSError:  # no stderr at all: nothing to protect
            yield
            return
        with contextlib.suppress(Exception):
            sys.stderr.flush()  # Python's own buffered text goes out before fd 2 moves
        os.dup2(sink.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            kept = [line for line in sink.read().splitlines(keepends=True) if not line.startswith(_LIBRARY_CHATTER)]
            if kept:
                os.write(2, b"".join(kept))


@contextlib.contextmanager
def _image_input(path: Path) -> Iterator[Any]:
    """An open OpenImageIO ImageInput (closed on exit) whose header has been checked (:func:`_check_header`).

    Opened with ``oiio:UnassociatedAlpha``: PNG stores colour unassociated with alpha and OpenImageIO would
    otherwise multiply it by alpha (alpha 128 halves every value, alpha 0 blanks the image); the values read
    are then the file's own.
    """
    oiio = _oiio()
    require_regular_file(path)
    _require_utf8_name(path)
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    with _quiet_native_stderr(path.suffix.lower() == ".png"):
        inp = oiio.ImageInput.open(str(path), config)
        if inp is None:
            msg = oiio.geterror().strip().splitlines()
            detail = msg[0] if msg else "unrecognised format"
            raise InputError(f"{_shown(path)}: cannot read the image ({printable(detail)}); check the file is a "
                             "complete PNG/TIFF/JPEG/BMP or raw file")
        try:
            spec = inp.spec()
            _check_header(path, int(spec.width), int(spec.height), int(spec.nchannels))
            yield inp
        finally:
            inp.close()


def _colour_channels(spec: Any) -> int:
    """Channels without alpha: grey+alpha and RGBA lose their last (alpha) channel, as :func:`read_image` documents."""
    n = int(spec.nchannels)
    return n - 1 if n in (2, 4) else n


_DTYPES = {"uint8": np.uint8, "uint16": np.uint16, "half": np.float16, "float": np.float32, "double": np.float64,
           "int8": np.int8, "int16": np.int16, "uint32": np.uint32, "int32": np.int32}


def _positive(value: Any) -> float | None:
    """A positive finite number, else None.  EXIF writers store 0 (or 0/0) for an exposure time or ISO they do
    not know; 0 s cannot be an exposure, so it is read as unknown — as a missing tag is — not as 0."""
    if isinstance(value, (tuple, list)):
        value = value[0] if value else None
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if math.isfinite(number) and number > 0 else None


def _captured(get: Callable[..., Any], raw: bool) -> _dt.datetime | None:
    """The capture time from EXIF: DateTimeOriginal, else DateTimeDigitized; IFD0 DateTime only for raw files.

    Exif 2.32 defines DateTimeOriginal as when the image data was generated and DateTimeDigitized as
    when it was stored digitally (the same moment in a digital camera), but DateTime (TIFF tag 306) as "the
    date and time the file was changed": every editor, converter — and OpenImageIO's TIFF writer, with the
    current time — rewrites it, so for ordinary images it is a modification time, not a capture date.  A raw
    file is the camera's own record, written once at capture and never re-saved in place, so there DateTime
    is still the capture time when the two EXIF fields are absent.
    """
    for name in ("Exif:DateTimeOriginal", "Exif:DateTimeDigitized") + (("DateTime",) if raw else ()):
        when = exif_datetime(get(name))
        if when is not None:
            return when
    return None


def _spec_info(path: Path, spec: Any) -> ImageInfo:
    def get(*names: str) -> Any:
        for name in names:
            value = spec.getattribute(name)
            if value not in (None, ""):
                return value
        return None

    def text(*names: str) -> str | None:
        value = get(*names)
        return str(value).strip() or None if value is not None else None

    orientation = _positive(get("Orientation"))
    return ImageInfo(
        path=path,
        width=int(spec.width),
        height=int(spec.height),
        channels=_colour_channels(spec),
        dtype=np.dtype(_DTYPES.get(str(spec.format), np.float32)),
        captured=_captured(get, is_raw(path)),
        exposure_s=_positive(get("ExposureTime", "Exif:ExposureTime")),
        iso=_positive(get("Exif:PhotographicSensitivity", "Exif:ISOSpeedRatings", "Exif:ISOSpeed", "ISO")),
        make=text("Make"),
        model=text("Model"),
        serial=text("Exif:BodySerialNumber", "Exif:SerialNumber", "Nikon:SerialNumber", "Canon:SerialNumber"),
        orientation=int(orientation) if orientation is not None and orientation <= 8 else 1,
    )


def fits_info(path: str | os.PathLike) -> ImageInfo:
    """A FITS frame's :class:`ImageInfo`: size, dtype, DATE-OBS, EXPTIME, INSTRUME and serial, and in ``extra`` the
    conditions only FITS carries (``temperature_c``, ``set_temperature_c``, ``frame_type``, ``gain_e_per_adu``,
    ``binning``, ``device``, ``warnings``, ``truncated``; :mod:`forensics.io.fits`)."""
    from forensics.io.fits import read_fits_header

    header = read_fits_header(path)
    extra = {"temperature_c": header.temperature_c, "set_temperature_c": header.set_temperature_c,
             "frame_type": header.frame_type, "gain_e_per_adu": header.gain_e_per_adu,
             "binning": list(header.binning) if header.binning else None, "device": header.device,
             "warnings": list(header.warnings), "truncated": header.truncated}
    return ImageInfo(path=Path(path), width=header.shape[1], height=header.shape[0], channels=1, dtype=header.dtype,
                     captured=header.captured, exposure_s=header.exposure_s, model=header.instrument,
                     serial=header.serial, extra=extra)


def read_info(path: str | os.PathLike) -> ImageInfo:
    """Read a file's size, dtype and capture metadata (EXIF; a FITS frame's header) without decoding its pixels.

    ``channels`` counts colour channels only (an alpha channel is not counted, as :func:`read_image` drops it).

    Raises
    ------
    InputError
        If the file is missing, not a regular file or not a readable image, or its header declares more
        pixels than :func:`~forensics._shared.limits.pixel_limit` or fewer than 2×2.
    """
    from forensics.io.fits import is_fits

    path = Path(path)
    if is_fits(path):  # FITS needs astropy: OpenImageIO ignores BZERO
        return fits_info(path)
    if is_raw(path):
        return read_raw(path).info
    with _image_input(path) as inp:
        return _spec_info(path, inp.spec())


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read an image in its native dtype: ``(H, W)`` for grey, ``(H, W, C)`` for colour.

    Raw camera files are returned as their 2-D CFA mosaic (see :func:`read_raw`
    for black/white levels and the CFA pattern).  An alpha channel is dropped; the colour
    values are the file's own, not multiplied by alpha.

    Raises
    ------
    InputError
        If the file is missing, corrupt or truncated, or its header declares too many pixels to decode
        (:func:`~forensics._shared.limits.pixel_limit`) or fewer than 2×2; the message names the file.
    """
    from forensics.io.fits import is_fits, read_fits

    path = Path(path)
    if is_fits(path):
        return read_fits(path).data
    if is_raw(path):
        return read_raw(path).mosaic
    with _image_input(path) as inp:
        pixels = inp.read_image(0, 0, 0, _colour_channels(inp.spec()), "unknown")
        failed = pixels is None or bool(inp.has_error)
        detail = inp.geterror().strip().splitlines() if failed else []
    if failed:
        why = printable(detail[0]) if detail else "decoding failed"
        raise InputError(f"{_shown(path)}: cannot read the image, corrupt or truncated ({why}); replace or remove the file")
    pixels = np.asarray(pixels)
    if pixels.ndim == 3 and pixels.shape[2] == 1:
        pixels = pixels[..., 0]
    return np.ascontiguousarray(pixels)


def read_raw(path: str | os.PathLike) -> RawMosaic:
    """Read a raw camera file (DNG, CR2, NEF, …) as its CFA mosaic through rawpy.

    Raises
    ------
    InputError
        If LibRaw cannot open the file, or its declared size exceeds
        :func:`~forensics._shared.limits.pixel_limit` (checked before the mosaic is unpacked).
    """
    import rawpy

    path = Path(path)
    require_regular_file(path, "raw camera")
    _require_utf8_name(path)
    try:
        with rawpy.imread(str(path)) as raw:  # opens and reads the header; the mosaic is unpacked on first use
            sizes = raw.sizes
            _check_header(path, int(sizes.raw_width), int(sizes.raw_height), 1)
            mosaic = np.array(raw.raw_image_visible, copy=True)
            desc = raw.color_desc.decode() if isinstance(raw.color_desc, bytes) else str(raw.color_desc)
            pattern = "".join(desc[i] for i in np.asarray(raw.raw_pattern)[:2, :2].ravel())
            black = tuple(float(b) for b in raw.black_level_per_channel)
            order = np.asarray(raw.raw_pattern)[:2, :2].ravel()
            black4 = tuple(black[i] for i in order)
            white = float(raw.white_level)
    except (rawpy.LibRawError, OSError, ValueError) as exc:  # type: ignore[attr-defined]
        raise InputError(f"{_shown(path)}: cannot read as a raw camera file ({printable(str(exc))}); "
                         "check the file is complete") from exc
    info = ImageInfo(path=path, width=mosaic.shape[1], height=mosaic.shape[0], channels=1, dtype=mosaic.dtype)
    with contextlib.suppress(InputError):  # EXIF of raw files through OpenImageIO where it can read them
        with _image_input(path) as inp:
            meta = _spec_info(path, inp.spec())
        info = ImageInfo(**{**meta.__dict__, "width": info.width, "height": info.height, "channels": 1,
                            "dtype": info.dtype})
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
        Extra attributes for the header, e.g. ``{"Exif:DateTimeOriginal": "2009:01:06 14:24:07"}``.  Nothing
        else is dated: OpenImageIO's TIFF writer would stamp the write time as ``DateTime``, which readers
        take for a capture date, so an empty one is written unless ``metadata`` gives it.

    Raises
    ------
    OSError
        The image library reported a failure (a full disk, the file size limit): the temporary file is
        removed and nothing appears at ``path``.  The message names the file and the reason.
    """
    from forensics._shared.atomic import refuse_inputs

    oiio = _oiio()
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in WRITABLE_EXTENSIONS:
        raise InputError(f"{_shown(path)}: cannot write {ext or 'files without extension'}; use .png or .tif")
    image = np.asarray(image)
    allowed = (np.uint8, np.uint16, np.float32) if ext != ".png" else (np.uint8, np.uint16)
    if image.dtype.type not in allowed:
        raise InputError(f"{_shown(path)}: cannot write dtype {image.dtype} to {ext}; convert to uint8 or uint16 first")
    if image.ndim not in (2, 3):
        raise InputError(f"{_shown(path)}: image must be 2-D or 3-D, got shape {image.shape}")
    refuse_inputs(path, inputs)
    refuse_existing(path, force)
    channels = 1 if image.ndim == 2 else image.shape[2]
    spec = oiio.ImageSpec(image.shape[1], image.shape[0], channels, image.dtype.name if image.dtype != np.float32 else "float")
    if ext in (".tif", ".tiff"):
        spec.attribute("compression", "zip")
        spec.attribute("DateTime", "")  # empty: not written, instead of the write time (see ``metadata``)
        # OpenImageIO (3.2) counts IFD0 tags (Orientation, DateTime) as Exif data and, given no true Exif
        # field, writes an empty Exif directory that libtiff refuses ("failed TIFFWriteCustomDirectory()"):
        # an error report on every write, which would hide a real one.  Write the Exif directory only when
        # there is something to put in it.
        spec.attribute("tiff:write_exif", int(any(_is_exif_field(key) for key in (metadata or {}))))
    for key, value in (metadata or {}).items():
        spec.attribute(key, value)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = mkstemp_like_open(prefix=f".{path.stem}.", suffix=f".part{ext}", dir=path.parent)  # umask mode
    os.close(fd)
    try:
        _write_verified(tmp, spec, np.ascontiguousarray(image.reshape(image.shape[0], image.shape[1], channels)), path)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    return path


def _is_exif_field(name: str) -> bool:
    """Whether OpenImageIO writes the attribute ``name`` into a TIFF's Exif directory (rather than IFD0)."""
    return name.startswith(("Exif:", "GPS:")) or name in ("ExposureTime", "FNumber")


def _write_verified(tmp: str, spec: Any, pixels: np.ndarray, path: Path) -> None:
    """Write ``pixels`` to ``tmp``; raise :class:`OSError` if OpenImageIO reports any error.

    Its flags are not enough: the PNG writer returns true from ``write_image`` and ``close`` after a short
    write (a full disk, ``ulimit -f``) and leaves the reason in ``geterror()``, so the error text of the
    output, after writing and after closing (which writes the last chunks), and the thread's global error
    are all checked.
    """
    oiio = _oiio()
    oiio.geterror()  # discard a stale message of an earlier call in this thread: only this write's count
    out = oiio.ImageOutput.create(tmp)
    if out is None:
        raise _write_failure(path, tmp, oiio.geterror())
    opened = bool(out.open(tmp, spec))
    written = opened and bool(out.write_image(pixels))
    reports = [out.geterror()]
    closed = bool(out.close())
    reports += [out.geterror(), oiio.geterror()]
    text = "\n".join(r for r in reports if r and r.strip())
    if not (opened and written and closed) or text:
        raise _write_failure(path, tmp, text)
    incomplete = _incomplete(tmp, pixels)
    if incomplete:
        raise _write_failure(path, tmp, incomplete, source="")


_PNG_END = b"\0\0\0\0IEND\xaeB`\x82"  # the IEND chunk: length 0, type, CRC — the last 12 bytes of every PNG


def _incomplete(tmp: str, pixels: np.ndarray) -> str:
    """Why the closed file ``tmp`` is not whole, or "" if it is.

    Needed besides the error text: the writers buffer their last bytes and flush them when the file is
    closed, and a short write there (the size limit or the disk reached just then) is reported by no one.
    A PNG is written front to back, and once a write has failed every later one fails too, so a PNG cut
    short lacks its final IEND chunk: checking its last 12 bytes is enough.  libtiff rewrites its directory
    in place, so a TIFF cut short in its last strip can still open with the right size: a TIFF is read back
    and compared (a deflate decode, a fraction of the time the encode took).
    """
    if tmp.lower().endswith(".png"):
        with open(tmp, "rb") as handle:
            handle.seek(max(os.fstat(handle.fileno()).st_size - len(_PNG_END), 0))
            return "" if handle.read() == _PNG_END else "the file ends before the PNG's final chunk"
    oiio = _oiio()
    inp = oiio.ImageInput.open(tmp)
    if inp is None:
        return oiio.geterror() or "the file written cannot be opened"
    try:
        back = inp.read_image(0, 0, 0, int(inp.spec().nchannels), "unknown")
        error = inp.geterror()
    finally:
        inp.close()
    if error or back is None:
        return error or "the file written cannot be read back"
    same = np.array_equal(np.asarray(back).reshape(pixels.shape), pixels, equal_nan=pixels.dtype.kind == "f")
    return "" if same else "the file written reads back different"


def _write_failure(path: Path, tmp: str, library_text: str, source: str = "OpenImageIO: ") -> OSError:
    """The one-line error of a failed write: the file, the likely cause and what to do, and the first line of
    what the library (or the check of the file's end, ``source=""``) reported."""
    first = next((line.strip() for line in library_text.splitlines() if line.strip()), "no reason given")
    code, cause, remedy = _likely_cause(tmp)
    return OSError(code, f"writing the image failed: {cause} ({source}{printable(first)}); {remedy}", _shown(path))


def _likely_cause(tmp: str) -> tuple[int, str, str]:
    """Why a write most likely failed, told from the size limit and the free space (the library gives no errno)."""
    with contextlib.suppress(OSError, ImportError, ValueError):
        import resource

        soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
        if soft != resource.RLIM_INFINITY and os.path.getsize(tmp) >= soft:
            return errno.EFBIG, f"the file size limit of {soft:,} bytes was reached", "raise it (ulimit -f) and run again"
        fs = os.statvfs(os.path.dirname(tmp) or ".")
        if fs.f_bavail * fs.f_frsize < 2**20:
            return errno.ENOSPC, "the disk is full", "free space and run again"
    return errno.EIO, "the image library could not write the file", "check the disk and run again"


def bits_dtype(bit_depth: int) -> np.dtype:
    """uint8 for up to 8 bits, uint16 for up to 16."""
    if bit_depth <= 8:
        return np.dtype(np.uint8)
    if bit_depth <= 16:
        return np.dtype(np.uint16)
    raise ValueError(f"bit depth {bit_depth} not supported (1–16)")
