"""Datasets: a folder of images with an optional ``manifest.csv``.

The manifest has a header row and the columns

============== =========================================================
``file``       required; path of the image relative to the folder
``device``     device identifier (free text; from EXIF make, model and body serial when
               the manifest has none and the file has a serial)
``captured``   ISO-8601 date or datetime (``2009-07-01``, ``2009-07-01T12:30:00``)
               or a decimal year (``2009.5``)
``exposure_s`` exposure time in seconds (0 for a bias frame)
``iso``        ISO sensitivity
``temperature_c`` sensor or ambient temperature in °C
``subject``    what the frame shows (free text); ``dark`` (any case) means the frame
               was taken without light (lens capped, shutter closed): the model check
               uses such frames as zero light
``black_level`` the readout's black level in DN, when known (e.g. from the camera's raw
               metadata); the model check then uses it instead of estimating it
``light``      the light level of a calibration frame (free text, e.g. the irradiance of a
               photon-transfer series): frames that differ only in it are different
               conditions for the model check
============== =========================================================

Any other column is kept in :attr:`Frame.extra`.  A value missing from the
manifest (or every value, when there is no manifest) is taken from the image's
EXIF where the file has it, or from a FITS frame's header: ``captured`` from
DATE-OBS, ``exposure_s`` from EXPTIME (0 for a bias), ``temperature_c`` from the
measured CCD-TEMP, ``subject`` from IMAGETYP (bias and dark frames are ``dark``,
flats ``flat``, lights ``light``), ``device`` from INSTRUME and its serial, and
the further columns ``frame_type`` (bias, dark, flat, light), ``set_temperature_c``
(SET-TEMP) and ``gain_e_per_adu`` (EGAIN).  Without a manifest, every image file
directly in the folder is used, in name order.

Frames are loaded lazily: iterating over a dataset never holds more than one
image in memory.
"""
from __future__ import annotations

import csv
import datetime as _dt
import math
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from forensics._shared.errors import InputError
from forensics.io.fits import is_fits
from forensics.io.images import IMAGE_EXTENSIONS, ImageInfo, read_image, read_info
from forensics._shared.progress import Progress, no_progress

MANIFEST = "manifest.csv"
#: The ``subject`` of frames taken without light (compared case-insensitively).
DARK_SUBJECT = "dark"
#: A FITS frame type (IMAGETYP) as a ``subject``: biases and darks are both taken without light (a bias is a dark
#: frame of exposure 0, ``exposure_s`` = 0); the column ``frame_type`` keeps them apart.
FRAME_SUBJECTS = {"bias": DARK_SUBJECT, "dark": DARK_SUBJECT, "flat": "flat", "light": "light"}
#: The optional manifest column that tells light levels apart (an extra column: kept in :attr:`Frame.extra`).
LIGHT_COLUMN = "light"
STANDARD_COLUMNS = ("file", "device", "captured", "exposure_s", "iso", "temperature_c", "subject")
_NUMERIC = ("exposure_s", "iso", "temperature_c")


def is_dark_subject(subject: str | None) -> bool:
    """Whether a frame's ``subject`` says it was taken without light (:data:`DARK_SUBJECT`)."""
    return subject is not None and subject.strip().lower() == DARK_SUBJECT


def split_epochs(times: np.ndarray, gap_years: float) -> tuple[np.ndarray, np.ndarray]:
    """Split capture times into epochs: a new epoch starts after a gap longer than ``gap_years``.

    Returns
    -------
    epoch : ndarray of int
        The epoch index of every time, numbered in time order.
    epoch_times : ndarray
        Each epoch's median capture time.
    """
    times = np.asarray(times, float)
    if times.size == 0:
        return np.zeros(0, int), np.zeros(0)
    order = np.argsort(times, kind="stable")
    epoch = np.zeros(len(times), int)
    current = 0
    for prev, nxt in zip(order[:-1], order[1:]):
        if times[nxt] - times[prev] > gap_years:
            current += 1
        epoch[nxt] = current
    epoch_times = np.array([float(np.median(times[epoch == e])) for e in range(current + 1)])
    return epoch, epoch_times


def decimal_year(when: _dt.datetime | _dt.date) -> float:
    """Convert a date or datetime to a decimal year (2009-07-02T12:00 → 2009.5)."""
    if not isinstance(when, _dt.datetime):
        when = _dt.datetime(when.year, when.month, when.day)
    if when.tzinfo is not None:
        when = when.astimezone(_dt.timezone.utc).replace(tzinfo=None)
    start = _dt.datetime(when.year, 1, 1)
    end = _dt.datetime(when.year + 1, 1, 1)
    return when.year + (when - start).total_seconds() / (end - start).total_seconds()


def from_decimal_year(year: float) -> _dt.datetime:
    """Inverse of :func:`decimal_year` (to the second)."""
    whole = int(math.floor(year))
    start = _dt.datetime(whole, 1, 1)
    length = (_dt.datetime(whole + 1, 1, 1) - start).total_seconds()
    return start + _dt.timedelta(seconds=round((year - whole) * length))


def parse_captured(text: str) -> float:
    """Parse a ``captured`` value (ISO-8601 date/datetime or decimal year) into a decimal year.

    Raises
    ------
    ValueError
        If the text is neither form.
    """
    text = text.strip()
    try:
        year = float(text)
    except ValueError:
        pass
    else:
        if not (1000 <= year <= 3000):
            raise ValueError(f"decimal year {text} out of range")
        return year
    normalised = text[:-1] + "+00:00" if text.endswith("Z") else text
    try:
        return decimal_year(_dt.datetime.fromisoformat(normalised))
    except ValueError:
        return decimal_year(_dt.date.fromisoformat(text))


@dataclass
class Frame:
    """One image of a dataset and what is known about it.

    Manifest values take precedence; missing ones are read from EXIF on first
    access of :attr:`captured`, :attr:`exposure_s` or :attr:`iso`.
    ``captured`` is a decimal year.
    """

    path: Path
    file: str
    device: str | None = None
    subject: str | None = None
    temperature_c: float | None = None
    extra: dict[str, str] = field(default_factory=dict)
    _captured: float | None = None
    _exposure_s: float | None = None
    _iso: float | None = None
    _exif: ImageInfo | None = field(default=None, repr=False)
    _exif_done: bool = field(default=False, repr=False)

    def info(self) -> ImageInfo:
        """Header and EXIF of the file (read once, then cached); fills values the manifest lacks."""
        if not self._exif_done:
            info = read_info(self.path)
            if self._captured is None and info.captured is not None:
                self._captured = decimal_year(info.captured)
            if self._exposure_s is None:
                self._exposure_s = info.exposure_s
            if self._iso is None:
                self._iso = info.iso
            if self.device is None and info.extra.get("device"):  # FITS: INSTRUME and its serial
                self.device = info.extra["device"]
            elif self.device is None and info.serial:  # a body serial identifies a device; make/model alone do not
                self.device = f"{info.make or ''} {info.model or ''} #{info.serial}".strip()
            if "frame_type" in info.extra:
                self._take_fits(info.extra)
            self._exif, self._exif_done = info, True
        assert self._exif is not None
        return self._exif

    def _take_fits(self, extra: dict[str, Any]) -> None:
        """A FITS header's conditions where the manifest gives none: the measured temperature, the frame type as the
        ``subject`` (bias and dark frames are ``dark``: taken without light) and as ``frame_type``, the set point
        and the gain as further columns."""
        if self.temperature_c is None and extra.get("temperature_c") is not None:
            self.temperature_c = float(extra["temperature_c"])
        kind = extra.get("frame_type")
        if self.subject is None and kind:
            self.subject = FRAME_SUBJECTS.get(kind, kind)
        for column in ("frame_type", "set_temperature_c", "gain_e_per_adu"):
            if not self.extra.get(column) and extra.get(column) is not None:
                self.extra[column] = str(extra[column])

    def _value(self, name: str) -> float | None:
        if getattr(self, name) is None and not self._exif_done:
            self.info()
        return getattr(self, name)

    @property
    def captured(self) -> float | None:
        """Capture time as a decimal year (manifest, else EXIF), or None."""
        return self._value("_captured")

    @property
    def exposure_s(self) -> float | None:
        """Exposure time in seconds (manifest, else EXIF), or None."""
        return self._value("_exposure_s")

    @property
    def iso(self) -> float | None:
        """ISO sensitivity (manifest, else EXIF), or None."""
        return self._value("_iso")

    def load(self) -> np.ndarray:
        """Decode the image (native dtype)."""
        return read_image(self.path)

    def get(self, name: str) -> Any:
        """A field by manifest column name (standard or extra)."""
        if name in ("captured", "exposure_s", "iso"):
            return getattr(self, name)
        if name in ("device", "subject", "temperature_c") and getattr(self, name) is None and not self._exif_done:
            self.info()
        if name in ("file", "device", "subject", "temperature_c"):
            return getattr(self, name)
        if name not in self.extra and not self._exif_done:
            self.info()  # a FITS header's further columns (frame_type, set_temperature_c, gain_e_per_adu)
        return self.extra.get(name)


@dataclass
class Dataset:
    """A list of frames rooted at a folder.  Slicing and grouping give sub-datasets."""

    root: Path
    frames: list[Frame]
    has_manifest: bool = False

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self) -> Iterator[Frame]:
        return iter(self.frames)

    def __getitem__(self, index: int | slice) -> Any:
        if isinstance(index, slice):
            return replace(self, frames=self.frames[index])
        return self.frames[index]

    def subset(self, indices: Any) -> "Dataset":
        """The frames at ``indices`` (a sequence of ints or a boolean mask)."""
        idx = np.arange(len(self.frames))[np.asarray(indices)]
        return replace(self, frames=[self.frames[i] for i in idx])

    def images(self, progress: Progress = no_progress, desc: str | None = None) -> Iterator[np.ndarray]:
        """Yield each frame's pixels in turn (one image in memory at a time)."""
        for frame in progress(self.frames, total=len(self.frames), desc=desc):
            yield frame.load()

    def shape(self) -> tuple[int, ...]:
        """The common image shape, from the file headers.

        Raises
        ------
        InputError
            If the frames do not all have the same size, naming the first that differs.
        """
        if not self.frames:
            raise InputError(f"{self.root}: dataset has no images")
        infos = [frame.info() for frame in self.frames]
        sizes = [(i.width, i.height, i.channels) for i in infos]
        common = max(set(sizes), key=sizes.count)  # the majority size; the odd ones are named
        for info, size in zip(infos, sizes):
            if size != common:
                raise InputError(
                    f"{info.path}: size {size[0]}×{size[1]}×{size[2]} differs from the other images' "
                    f"{common[0]}×{common[1]}×{common[2]}; a dataset's images must all have one size"
                )
        return infos[0].shape

    def group_by(self, key: str | Callable[[Frame], Any]) -> dict[Any, "Dataset"]:
        """Split into sub-datasets by a manifest column name or a function of the frame, in first-seen order."""
        getter = (lambda f: f.get(key)) if isinstance(key, str) else key
        groups: dict[Any, list[Frame]] = {}
        for frame in self.frames:
            groups.setdefault(getter(frame), []).append(frame)
        return {k: replace(self, frames=v) for k, v in groups.items()}

    def conditions(self) -> dict[tuple[Any, ...], "Dataset"]:
        """Group by acquisition condition: (exposure_s, iso, temperature_c, subject)."""
        return self.group_by(lambda f: (f.exposure_s, f.iso, f.temperature_c, f.subject))

    def epochs(self, gap_years: float = 0.25) -> list["Dataset"]:
        """Split by capture time into epochs: a new epoch starts after a gap longer than ``gap_years``."""
        times = self.captured_times()
        epoch, epoch_times = split_epochs(times, gap_years)
        order = np.argsort(times, kind="stable")  # frames in time order within each epoch
        return [self.subset(order[epoch[order] == e]) for e in range(len(epoch_times))]

    def captured_times(self) -> np.ndarray:
        """Every frame's capture time (decimal years).

        Raises
        ------
        InputError
            Naming the first frame without a ``captured`` value in the manifest or EXIF.
        """
        times = []
        for frame in self.frames:
            when = frame.captured
            if when is None:
                raise InputError(
                    f"{frame.path}: no capture date: the field 'captured' is missing from "
                    f"{self.root / MANIFEST} and from the file's EXIF; add a 'captured' column"
                )
            times.append(when)
        return np.asarray(times, dtype=float)

    def epoch(self) -> float:
        """The dataset's capture epoch: the median capture time (decimal year)."""
        return float(np.median(self.captured_times()))

    def devices(self) -> list[str | None]:
        """The distinct device identifiers, in first-seen order."""
        return list(self.group_by("device"))


def list_images(folder: Path) -> list[Path]:
    """Image files directly in ``folder`` (by extension; FITS by its whole suffix, e.g. ``.fits.fz``), hidden files
    skipped, in name order."""
    return sorted(
        p for p in folder.iterdir()
        if p.is_file() and not p.name.startswith(".") and (p.suffix.lower() in IMAGE_EXTENSIONS or is_fits(p))
    )


def open_dataset(folder: str | os.PathLike, allow_outside: bool = False) -> Dataset:
    """Open a dataset folder (see the module docstring for the format).

    Nothing is decoded here; the manifest is validated completely.  A manifest is often written by another
    tool and read by many machines, so a row naming a file outside the folder — an absolute path, ``../``,
    or a symbolic link that leaves it — is refused unless ``allow_outside`` (``--allow-outside``).  A folder
    without a manifest is the user's own listing and is taken as it is.

    Raises
    ------
    InputError
        The folder is missing or empty, or the manifest lacks ``file``, names a
        file that does not exist, or holds a value that does not parse; the
        message names the file, row and field.
    """
    root = Path(folder)
    if not root.is_dir():
        raise InputError(f"{root}: not a folder; a dataset is a folder of images with an optional manifest.csv")
    manifest = root / MANIFEST
    if not manifest.exists():
        paths = list_images(root)
        if not paths:
            raise InputError(f"{root}: no images found; add PNG/TIFF/JPEG/BMP/raw/FITS files or a manifest.csv")
        frames = [Frame(path=p, file=p.name) for p in paths]
        for frame in frames:
            if is_fits(frame.path):  # the header is the manifest: its conditions are read now (no pixels decoded)
                frame.info()
        return Dataset(root, frames, has_manifest=False)
    return Dataset(root, _read_manifest(root, manifest, allow_outside), has_manifest=True)


def _read_manifest(root: Path, manifest: Path, allow_outside: bool = False) -> list[Frame]:
    with open(manifest, newline="", encoding="utf-8-sig") as handle:
        reader = csv.DictReader(handle)
        header = [h.strip() for h in (reader.fieldnames or [])]
        if "file" not in header:
            raise InputError(f"{manifest}: the header has no 'file' column; the first row must name the columns (file, captured, …)")
        reader.fieldnames = header
        frames = []
        for row_number, row in enumerate(reader, start=2):
            frames.append(_frame_from_row(root, manifest, row_number, row, allow_outside))
    if not frames:
        raise InputError(f"{manifest}: no rows; list one image per row under the header")
    return frames


def _frame_from_row(root: Path, manifest: Path, row_number: int, row: dict[str, Any],
                    allow_outside: bool = False) -> Frame:
    where = f"{manifest}, line {row_number}"
    values = {k: (v or "").strip() for k, v in row.items() if k is not None}
    name = values.get("file", "")
    if not name:
        raise InputError(f"{where}: field 'file' is empty; give the image's path relative to the folder")
    path = root / name
    if not allow_outside and not _inside(root, path):
        raise InputError(f"{where}: file '{name}' lies outside the dataset folder {root} (absolute path, '..' or a "
                         "link leaving it); move it into the folder or pass --allow-outside")
    if not path.is_file():
        raise InputError(f"{where}: file '{name}' does not exist in {root}; fix the row or add the file")
    numbers: dict[str, float | None] = {}
    for column in _NUMERIC:
        text = values.get(column, "")
        if not text:
            numbers[column] = None
            continue
        try:
            numbers[column] = float(text)
        except ValueError:
            raise InputError(f"{where}: field '{column}' = '{text}' is not a number") from None
        value = numbers[column]
        # an exposure of 0 is a bias frame; an ISO must be positive; a temperature may be anything
        out_of_range = (column == "iso" and value <= 0) or (column == "exposure_s" and value < 0)  # type: ignore[operator]
        if not math.isfinite(value) or out_of_range:  # type: ignore[arg-type]
            raise InputError(f"{where}: field '{column}' = '{text}' is out of range")
    captured = None
    if values.get("captured"):
        try:
            captured = parse_captured(values["captured"])
        except ValueError:
            raise InputError(
                f"{where}: field 'captured' = '{values['captured']}' is not an ISO-8601 date or datetime "
                "or a decimal year (e.g. 2009-07-01, 2009-07-01T12:30:00 or 2009.5)"
            ) from None
    extra = {k: v for k, v in values.items() if k not in STANDARD_COLUMNS}
    return Frame(
        path=path,
        file=name,
        device=values.get("device") or None,
        subject=values.get("subject") or None,
        temperature_c=numbers["temperature_c"],
        extra=extra,
        _captured=captured,
        _exposure_s=numbers["exposure_s"],
        _iso=numbers["iso"],
    )


def _inside(root: Path, path: Path) -> bool:
    """Whether ``path`` (symbolic links followed) lies inside ``root``."""
    return path.resolve().is_relative_to(root.resolve())


def write_manifest(path: str | os.PathLike, rows: list[dict[str, Any]], force: bool = False) -> Path:
    """Write a ``manifest.csv`` atomically from a list of row dicts (standard columns first)."""
    from forensics._shared.atomic import atomic_file

    columns = [c for c in STANDARD_COLUMNS if any(c in r for r in rows)]
    columns += sorted({k for r in rows for k in r} - set(columns))
    with atomic_file(path, force=force, mode="w") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns, lineterminator="\n")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: _manifest_value(v) for k, v in row.items()})
    return Path(path)


def _manifest_value(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(round(value, 6)) if not value.is_integer() else f"{value:.1f}"
    return str(value)
