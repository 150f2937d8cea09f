"""FITS frames, the format sensor measurements come in (astronomy, sensor test benches).

Read through :mod:`astropy.io.fits`, the field's own library, because getting FITS right is more than
decoding pixels: unsigned 16-bit data are stored as signed integers with ``BZERO = 32768`` (a reader that
ignores it, as OpenImageIO does, returns values shifted by 32768), ``BSCALE`` scales, tile-compressed files
(``.fits.fz``) keep their image in an extension, and the header carries the acquisition conditions.

What the header says becomes a frame's metadata, with no manifest needed (a manifest still overrides):

================  ==========================================================================
``captured``      ``DATE-OBS`` (ISO 8601; ``TIME-OBS`` joined when ``DATE-OBS`` is a date only)
``exposure_s``    ``EXPTIME``, else ``EXPOSURE``
``temperature_c`` the *measured* sensor temperature ``CCD-TEMP`` (else ``CCDTEMP``, ``TEMPERAT``);
                  the set point ``SET-TEMP`` is kept as ``set_temperature_c``
``frame_type``    ``IMAGETYP`` (also ``FRAMETYP``, ``OBSTYPE``): bias, dark, flat or light
``device``        ``INSTRUME`` and a serial number where one is given
``gain_e_per_adu`` ``EGAIN`` (else ``GAIN``): the maker's conversion gain, e⁻/ADU
================  ==========================================================================

Integer data stay integer (``uint16`` for the BZERO convention); scaled data (``BSCALE`` ≠ 1) are float32.

Examples
--------
>>> import numpy as np, tempfile, os
>>> from astropy.io import fits
>>> path = os.path.join(tempfile.mkdtemp(), "dark.fits")
>>> hdu = fits.PrimaryHDU(np.full((4, 6), 1016, np.uint16))
>>> hdu.header.update({"EXPTIME": 30.0, "CCD-TEMP": -10.2, "SET-TEMP": -10.0, "IMAGETYP": "Dark Frame"})
>>> hdu.writeto(path)
>>> read_fits(path).data[0, 0], read_fits_header(path).frame_type
(np.uint16(1016), 'dark')
"""
from __future__ import annotations

import datetime as _dt
import os
import re
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from forensics._shared.errors import InputError
from forensics._shared.limits import require_pixels

#: File names read as FITS (case-insensitive; ``.fz`` is tile compression, ``.gz`` whole-file gzip).
FITS_SUFFIXES = (".fits", ".fit", ".fts", ".fits.fz", ".fit.fz", ".fz", ".fits.gz", ".fit.gz", ".fts.gz")
#: The frame types a header can name, and the words acquisition programs use for them.
FRAME_TYPES = ("bias", "dark", "flat", "light")
_TYPE_WORDS = {
    "bias": "bias", "zero": "bias", "offset": "bias",
    "dark": "dark", "thermal": "dark",
    "flat": "flat", "flatfield": "flat", "skyflat": "flat", "domeflat": "flat", "twilight": "flat",
    "light": "light", "object": "light", "science": "light", "sky": "light",
}
_SERIAL_KEYS = ("SERIALNO", "SERIAL", "CAMSER", "CAM-SN", "CAMSN", "DETSERNO", "CCD_SN", "CCDSERNO")
#: Measured and set temperatures differing by more than this (°C) get a warning: the sensor had not settled.
SETPOINT_TOLERANCE_C = 1.0


@dataclass(frozen=True)
class FitsHeader:
    """What a FITS header says about one frame (None where the header does not say).

    ``hdu`` is the index of the image's HDU in the file; ``shape`` is ``(height, width)``; ``dtype`` is the
    dtype :func:`read_fits` returns.
    """

    path: Path
    hdu: int
    shape: tuple[int, int]
    dtype: np.dtype
    captured: _dt.datetime | None = None
    exposure_s: float | None = None
    temperature_c: float | None = None
    set_temperature_c: float | None = None
    frame_type: str | None = None
    instrument: str | None = None
    serial: str | None = None
    gain_e_per_adu: float | None = None
    binning: tuple[int, int] | None = None
    warnings: tuple[str, ...] = field(default=())
    #: why the pixels cannot be read although the header can (the file is shorter than the header says), or None
    truncated: str | None = None

    @property
    def device(self) -> str | None:
        """The device identifier: instrument and serial number where the header gives them."""
        if self.instrument and self.serial:
            return f"{self.instrument} #{self.serial}"
        return self.instrument or (f"#{self.serial}" if self.serial else None)


@dataclass(frozen=True)
class FitsFrame:
    """A frame's pixels (native byte order, ``(height, width)``) and its header."""

    data: np.ndarray
    header: FitsHeader


def is_fits(path: str | os.PathLike) -> bool:
    """Whether a file name is a FITS file's (by its suffix, case-insensitive)."""
    name = Path(path).name.lower()
    return name.endswith(FITS_SUFFIXES)


def _open(path: Path):
    from astropy.io import fits

    if not path.is_file():
        raise InputError(f"{path}: no such file; check the path")
    # our own handle: astropy leaves the file open when it fails part-way (a truncated file), the HDU list closes it
    handle = open(path, "rb")  # noqa: SIM115
    try:
        return fits.open(handle, memmap=False, lazy_load_hdus=False)
    except Warning as exc:  # raised only where the caller made astropy's warnings errors (truncation)
        handle.close()
        raise InputError(f"{path}: cannot read the image data ({_first_line(exc)}); the file may be truncated or "
                         "its header may not match its data") from None
    except (OSError, ValueError, TypeError, IndexError, KeyError) as exc:
        handle.close()
        raise InputError(f"{path}: not a readable FITS file ({_first_line(exc)}); check the file is complete") from None


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def _image_hdu(path: Path, hdul: Any) -> int:
    """The index of the one HDU holding a 2-D image (or a 3-plane colour cube)."""
    candidates = [i for i, hdu in enumerate(hdul)
                  if getattr(hdu, "is_image", False) and (hdu.header.get("NAXIS", 0) or 0) >= 2
                  and all((hdu.header.get(f"NAXIS{k}", 0) or 0) > 0 for k in range(1, hdu.header["NAXIS"] + 1))]
    if not candidates:
        raise InputError(f"{path}: no image in the file (no HDU with a 2-D data array); a FITS frame must hold an image")
    if len(candidates) > 1:
        named = [i for i in candidates if str(hdul[i].name).upper() in ("SCI", "IMAGE", "COMPRESSED_IMAGE")]
        if len(named) == 1:
            return named[0]
        raise InputError(f"{path}: {len(candidates)} image HDUs ({', '.join(str(i) for i in candidates)}); it is not "
                         "clear which is the frame: give one image per file (or name it SCI)")
    return candidates[0]


def _dtype(header: Any) -> np.dtype:
    """The dtype astropy returns for this header (integer data with the unsigned convention stay integer)."""
    bitpix = int(header.get("ZBITPIX", header.get("BITPIX")))
    bscale = float(header.get("BSCALE", 1.0))
    bzero = float(header.get("BZERO", 0.0))
    if bitpix < 0:
        return np.dtype(np.float32 if bitpix == -32 else np.float64)
    signed = {8: np.uint8, 16: np.int16, 32: np.int32, 64: np.int64}[bitpix]
    if bscale == 1.0 and bzero == 0.0:
        return np.dtype(signed)
    if bscale == 1.0 and bitpix > 8 and bzero == 2.0 ** (bitpix - 1):
        return np.dtype({16: np.uint16, 32: np.uint32, 64: np.uint64}[bitpix])
    return np.dtype(np.float32 if bitpix <= 16 else np.float64)


def _shape(path: Path, header: Any) -> tuple[int, int]:
    naxis = int(header["NAXIS"])
    dims = [int(header[f"NAXIS{k}"]) for k in range(1, naxis + 1)]  # FITS order: x (columns) first
    if naxis > 2 and any(d != 1 for d in dims[2:]):
        raise InputError(f"{path}: a data cube of {'×'.join(map(str, dims))} values; give one 2-D frame per file")
    return dims[1], dims[0]


def _number(header: Any, *keys: str) -> float | None:
    for key in keys:
        value = header.get(key)
        if value is None or isinstance(value, bool):
            continue
        try:
            number = float(value)
        except (TypeError, ValueError):
            continue
        if np.isfinite(number):
            return number
    return None


def _text(header: Any, *keys: str) -> str | None:
    for key in keys:
        value = header.get(key)
        if value is not None and str(value).strip():
            return str(value).strip()
    return None


def parse_frame_type(text: str | None) -> str | None:
    """``IMAGETYP``'s value as one of :data:`FRAME_TYPES` (``'Dark Frame'`` → ``'dark'``), None if unknown.

    >>> parse_frame_type("Flat Field"), parse_frame_type("BIAS"), parse_frame_type("Light Frame")
    ('flat', 'bias', 'light')
    """
    if not text:
        return None
    words = re.findall(r"[a-z]+", text.lower())
    joined = "".join(w for w in words if w not in ("frame", "image"))
    if joined in _TYPE_WORDS:
        return _TYPE_WORDS[joined]
    for word in words:
        if word in _TYPE_WORDS:
            return _TYPE_WORDS[word]
    return None


def parse_date_obs(date: str | None, time: str | None = None) -> _dt.datetime | None:
    """``DATE-OBS`` (ISO 8601, or the old ``dd/mm/yy``) joined with ``TIME-OBS`` when it is a date only.

    Times with a zone are converted to UTC and returned naive (FITS times are UTC by the standard).

    >>> parse_date_obs("2017-09-08T21:18:13.698")
    datetime.datetime(2017, 9, 8, 21, 18, 13, 698000)
    >>> parse_date_obs("2017-09-08", "21:18:13")
    datetime.datetime(2017, 9, 8, 21, 18, 13)
    """
    if not date:
        return None
    text = date.strip()
    old = re.fullmatch(r"(\d{2})/(\d{2})/(\d{2})", text)  # the pre-2000 form: dd/mm/yy, 19yy
    if old:
        text = f"19{old.group(3)}-{old.group(2)}-{old.group(1)}"
    if "T" not in text and time and time.strip():
        text = f"{text}T{time.strip()}"
    try:
        when = _dt.datetime.fromisoformat(text[:-1] + "+00:00" if text.endswith("Z") else text)
    except ValueError:
        return None
    if when.tzinfo is not None:
        when = when.astimezone(_dt.timezone.utc).replace(tzinfo=None)
    return when


def _header_info(path: Path, index: int, header: Any) -> FitsHeader:
    measured = _number(header, "CCD-TEMP", "CCDTEMP", "DET-TEMP", "TEMPERAT")
    setpoint = _number(header, "SET-TEMP", "SETTEMP", "CCD-SET")
    notes = []
    if measured is not None and setpoint is not None and abs(measured - setpoint) > SETPOINT_TOLERANCE_C:
        notes.append(f"{path}: the sensor measured {measured:.2f} °C against its set point {setpoint:.2f} °C "
                     f"(more than {SETPOINT_TOLERANCE_C:g} °C apart): it may not have settled")
    xbin, ybin = _number(header, "XBINNING", "XBIN"), _number(header, "YBINNING", "YBIN")
    return FitsHeader(
        path=path,
        hdu=index,
        shape=_shape(path, header),
        dtype=_dtype(header),
        captured=parse_date_obs(_text(header, "DATE-OBS", "DATE_OBS"), _text(header, "TIME-OBS", "UT")),
        exposure_s=_number(header, "EXPTIME", "EXPOSURE", "EXP_TIME"),
        temperature_c=measured,
        set_temperature_c=setpoint,
        frame_type=parse_frame_type(_text(header, "IMAGETYP", "FRAMETYP", "FRAME", "OBSTYPE")),
        instrument=_text(header, "INSTRUME", "CAMERA", "DETECTOR"),
        serial=_text(header, *_SERIAL_KEYS),
        gain_e_per_adu=_number(header, "EGAIN", "E-GAIN", "GAIN"),
        binning=(int(xbin), int(ybin)) if xbin and ybin else None,
        warnings=tuple(notes),
    )


def read_fits_header(path: str | os.PathLike) -> FitsHeader:
    """The metadata of a FITS frame, without decoding its pixels.

    Raises
    ------
    InputError
        The file is missing, not FITS, holds no image or several, or is a data cube.  A file shorter than its
        header says is described, with ``truncated`` saying so (:func:`read_fits` refuses it).
    """
    import astropy.io.fits  # noqa: F401  (imported first: astropy's logger replaces the warnings hook on import)

    path = Path(path)
    with warnings.catch_warnings(record=True) as noted:
        warnings.simplefilter("always")  # astropy's header fix-up notes are kept, not shown; truncation is checked
        hdul = _open(path)
        try:
            index = _image_hdu(path, hdul)
            header = hdul[index].header
            info = _header_info(path, index, header)
        finally:
            hdul.close()
    # astropy finds a file shorter than its headers promise while reading them (and only warns): noted here, so that
    # a header-only look (``forensics info``) names the file that :func:`read_fits` will refuse
    short = next((str(w.message) for w in noted if "truncated" in str(w.message).lower()), None)
    if short is not None:
        note = f"{path}: {_first_line(Exception(short))}: the file is truncated (its pixels cannot be read)"
        info = replace(info, truncated=note)
    require_pixels(info.shape[0] * info.shape[1], str(path))
    return info


def read_fits(path: str | os.PathLike) -> FitsFrame:
    """Read a FITS frame: BZERO/BSCALE applied, integers kept integer, native byte order, ``(height, width)``.

    Raises
    ------
    InputError
        As :func:`read_fits_header`, and for a truncated file or data that do not match the header.
    """
    from astropy.utils.exceptions import AstropyUserWarning

    path = Path(path)
    info = read_fits_header(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error", AstropyUserWarning)  # "File may have been truncated" → refused
        hdul = _open(path)
        try:
            try:
                data = hdul[info.hdu].data
            except (AstropyUserWarning, OSError, ValueError, TypeError) as exc:
                raise InputError(f"{path}: cannot read the image data ({_first_line(exc)}); the file may be "
                                 "truncated or its header may not match its data") from None
            if data is None or data.size != info.shape[0] * info.shape[1]:
                raise InputError(f"{path}: the data ({'none' if data is None else data.shape}) do not match the "
                                 f"header's {info.shape[1]}×{info.shape[0]} frame")
            data = np.asarray(data).reshape(info.shape)
            data = np.ascontiguousarray(data, dtype=data.dtype.newbyteorder("="))
        finally:
            hdul.close()
    if data.dtype != info.dtype:
        data = data.astype(info.dtype) if data.dtype.kind == info.dtype.kind else data
    return FitsFrame(data=data, header=info)
