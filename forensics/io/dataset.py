"""Datasets: a folder of images with an optional ``manifest.csv``.

The manifest has a header row and the columns

============== =========================================================
``file``       required; path of the image relative to the folder
``device``     device identifier (free text; from EXIF make, model and body serial when
               the manifest has none and the file has a serial)
``captured``   ISO 8601 date or datetime (``2009-07-01``, ``20090701``,
               ``2009-07-01T12:30:00``) or a decimal year (``2009.5``), between 1975 and
               2200 (:mod:`forensics.io.dates` says why)
``exposure_s`` exposure time in seconds (0 for a bias frame, else above 0)
``iso``        ISO sensitivity (above 0)
``temperature_c`` sensor or ambient temperature in °C (above absolute zero, at most 150)
``subject``    what the frame shows (free text); ``dark`` (any case) means the frame
               was taken without light (lens capped, shutter closed): the model check
               uses such frames as zero light
``black_level`` the readout's black level in DN (0 or more), when known (e.g. from the camera's raw
               metadata); the model check then uses it instead of estimating it
``light``      the light level of a calibration frame (free text, e.g. the irradiance of a
               photon-transfer series): frames that differ only in it are different
               conditions for the model check
============== =========================================================

Any other column is kept in :attr:`Frame.extra`.  The manifest is read strictly
(:mod:`forensics.io.manifest`): UTF-8, well-formed CSV, each column and each image
named once, every value in its range.  A value missing from the
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

import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from forensics._shared.errors import InputError
from forensics._shared.progress import Progress, no_progress
from forensics._shared.text import printable
from forensics.io.dates import decimal_year
from forensics.io.fits import is_fits
from forensics.io.images import IMAGE_EXTENSIONS, ImageInfo, read_image, read_info
from forensics.io.manifest import MANIFEST, ManifestRow, read_manifest

# Moved to forensics.io.dates and forensics.io.manifest; still importable from here, where callers find them.
from forensics.io.dates import from_decimal_year, parse_captured  # noqa: E402,F401  (re-exported)
from forensics.io.manifest import STANDARD_COLUMNS, write_manifest  # noqa: E402,F401  (re-exported)
#: The ``subject`` of frames taken without light (compared case-insensitively).
DARK_SUBJECT = "dark"
#: A FITS frame type (IMAGETYP) as a ``subject``: biases and darks are both taken without light (a bias is a dark
#: frame of exposure 0, ``exposure_s`` = 0); the column ``frame_type`` keeps them apart.
FRAME_SUBJECTS = {"bias": DARK_SUBJECT, "dark": DARK_SUBJECT, "flat": "flat", "light": "light"}
#: The optional manifest column that tells light levels apart (an extra column: kept in :attr:`Frame.extra`).
LIGHT_COLUMN = "light"


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
        columns = ["frame_type", "set_temperature_c", "gain_e_per_adu", "binning"]
        if self.temperature_c is None and extra.get("temperature_c") is not None:
            self.temperature_c = float(extra["temperature_c"])
        elif self.temperature_c is not None:
            # the manifest's temperature overrides the header's, and the header's set point belongs to the header's
            columns.remove("set_temperature_c")
        kind = extra.get("frame_type")
        if self.subject is None and kind:
            self.subject = FRAME_SUBJECTS.get(kind, kind)
        for column in columns:
            if not self.extra.get(column) and extra.get(column) is not None:
                value = extra[column]
                self.extra[column] = "x".join(map(str, value)) if column == "binning" else str(value)

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


def nominal_temperature(frame: Frame) -> float | None:
    """The temperature a frame was taken *at* as a condition: its set point where it has one, else the measured one.

    Examples
    --------
    >>> from pathlib import Path
    >>> nominal_temperature(Frame(Path("d.fits"), "d.fits", temperature_c=-9.79, extra={"set_temperature_c": "-10"}))
    -10.0
    >>> nominal_temperature(Frame(Path("d.png"), "d.png", temperature_c=25.0, extra={"set_temperature_c": ""}))
    25.0
    """
    setpoint = set_point(frame)
    return frame.temperature_c if setpoint is None else setpoint


def set_point(frame: Frame) -> float | None:
    """The frame's temperature set point (``set_temperature_c``) in °C, or None where it has none or it is not a
    number (then it is only a label, and the measured temperature stands)."""
    value = frame.get("set_temperature_c")
    if value in (None, ""):
        return None
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


def binning(frame: Frame) -> tuple[int, int] | None:
    """The frame's on-chip binning ``(x, y)`` — FITS XBINNING/YBINNING, or a manifest column ``binning`` such as
    ``2x2`` or ``2`` — or None where it is not stated (unknown, not assumed 1×1).

    Examples
    --------
    >>> from pathlib import Path
    >>> binning(Frame(Path("d.fit"), "d.fit", extra={"binning": "2x2"})), binning(Frame(Path("d.png"), "d.png"))
    ((2, 2), None)
    """
    value = str(frame.get("binning") or "").strip().lower()
    if not value:
        return None
    try:
        parts = [int(float(v)) for v in value.replace("×", "x").split("x")]
    except ValueError:
        raise InputError(f"{printable(str(frame.path))}: binning {value!r} is not a binning; write it as 2x2 (or 2), "
                         "or leave it empty") from None
    if len(parts) == 1:
        parts *= 2
    if len(parts) != 2 or min(parts) < 1:
        raise InputError(f"{printable(str(frame.path))}: binning {value!r} is not a binning; write it as 2x2 (or 2), "
                         "or leave it empty")
    return parts[0], parts[1]


def common_binning(named: Sequence[tuple[str, tuple[int, int] | None]]) -> tuple[int, int] | None:
    """The binning ``(x, y)`` that every frame stating one shares (frames that state none are unknown and do not
    count), or None when none states one.

    Raises
    ------
    InputError
        Two frames state different binnings, naming one of each: a binned pixel sums the charge of x·y pixels, so
        its dark rate, noise and defects mean something else, and one analysis cannot mix them.
    """
    stated = [(name, b) for name, b in named if b is not None]
    if not stated:
        return None
    bins = [b for _, b in stated]
    common = max(dict.fromkeys(bins), key=bins.count)  # the majority binning (ties: the first); another is named
    odd = next((name, b) for name, b in stated if b != common) if len(set(bins)) > 1 else None
    if odd is not None:
        other = next(name for name, b in stated if b == common)
        more = bins.count(common) - 1
        raise InputError(f"{printable(odd[0])}: binned {odd[1][0]}×{odd[1][1]} but {printable(other)}"
                         f"{f' and {more} more frames are' if more else ' is'} binned {common[0]}×{common[1]}; "
                         "a binned pixel sums the charge of "
                         "several, so frames of different binnings cannot be analysed together: put each binning "
                         "in its own folder")
    return common


def temperature_groups(set_points: Sequence[float | None], measured: Sequence[float | None],
                       tolerance: float) -> list[tuple[str, float | None]]:
    """Per frame, the temperature group it belongs to in a dark series: ``("set", set point)`` (rounded to 0.1 °C)
    for a frame with a set point; for the others a cluster of measured temperatures, ``("measured", centre)`` —
    sorted readings split where they jump by more than ``tolerance`` °C, the centre the cluster's median rounded
    to 0.1 °C; ``("unknown", None)`` for a frame with neither.  (``defects detect`` groups its frames so and
    ``forensics info`` lists them so: one rule.)

    Examples
    --------
    >>> temperature_groups([None, None, None, -10.0], [-10.1, -4.9, -9.95, -9.8], 1.0)
    [('measured', -10.0), ('measured', -4.9), ('measured', -10.0), ('set', -10.0)]
    """
    keys: dict[int, tuple[str, float | None]] = {}
    loose = []
    for i, (sp, t) in enumerate(zip(set_points, measured)):
        if sp is not None:
            keys[i] = ("set", round(float(sp), 1))
        elif t is not None:
            loose.append(i)
        else:
            keys[i] = ("unknown", None)
    loose.sort(key=lambda i: measured[i])  # type: ignore[arg-type, return-value]
    cluster: list[int] = []
    for i in loose + [None]:  # type: ignore[list-item]
        if cluster and (i is None or measured[i] - measured[cluster[-1]] > tolerance):  # type: ignore[operator]
            centre = round(float(np.median([measured[j] for j in cluster])), 1)
            keys.update({j: ("measured", centre) for j in cluster})
            cluster = []
        if i is not None:
            cluster.append(i)
    return [keys[i] for i in range(len(set_points))]


@dataclass
class Dataset:
    """A list of frames rooted at a folder.  Slicing and grouping give sub-datasets."""

    root: Path
    frames: list[Frame]
    has_manifest: bool = False
    #: A directory of the frames decoded once (:func:`forensics.io.framecache.frame_cache`), or None: readers that
    #: take parts of frames (a tile) map the decoded frame instead of decoding the file.
    frame_cache: str | None = None

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
            If the frames do not all have the same size, naming the first that differs, or state different
            binnings (:meth:`binning`).
        """
        if not self.frames:
            raise InputError(f"{printable(str(self.root))}: dataset has no images")
        infos = [frame.info() for frame in self.frames]
        self.binning()  # before the sizes: a frame of another binning is named as such, not as another size
        sizes = [(i.width, i.height, i.channels) for i in infos]
        common = max(set(sizes), key=sizes.count)  # the majority size; the odd ones are named
        for info, size in zip(infos, sizes):
            if size != common:
                raise InputError(
                    f"{printable(str(info.path))}: size {size[0]}×{size[1]}×{size[2]} differs from the other images' "
                    f"{common[0]}×{common[1]}×{common[2]}; a dataset's images must all have one size"
                )
        return infos[0].shape

    def binning(self) -> tuple[int, int] | None:
        """The frames' common on-chip binning (:func:`common_binning`; None where none states one).

        Raises
        ------
        InputError
            Two frames state different binnings, naming one of each.
        """
        return common_binning([(str(f.path), binning(f)) for f in self.frames])

    def group_by(self, key: str | Callable[[Frame], Any]) -> dict[Any, "Dataset"]:
        """Split into sub-datasets by a manifest column name or a function of the frame, in first-seen order."""
        getter = (lambda f: f.get(key)) if isinstance(key, str) else key
        groups: dict[Any, list[Frame]] = {}
        for frame in self.frames:
            groups.setdefault(getter(frame), []).append(frame)
        return {k: replace(self, frames=v) for k, v in groups.items()}

    def conditions(self) -> dict[tuple[Any, ...], "Dataset"]:
        """Group by acquisition condition: (exposure_s, iso, temperature, subject).

        The temperature is the frame's set point (``set_temperature_c``, from FITS's SET-TEMP or the manifest)
        where it has one, else its measured ``temperature_c``: a cooled sensor's thermistor reads in steps
        around its set point (−10.20 and −9.79 °C for one −10 °C run), and those readings are one condition,
        not several.
        """
        return self.group_by(lambda f: (f.exposure_s, f.iso, nominal_temperature(f), f.subject))

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
                    f"{printable(str(frame.path))}: no capture date: the field 'captured' is missing from "
                    f"{printable(str(self.root / MANIFEST))} and the file's EXIF has none (or an implausible one); "
                    "add a 'captured' column"
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
        The folder is missing or empty, or the manifest is not a UTF-8 CSV file, lacks ``file``, names a
        file twice or one that does not exist, or holds a value that does not parse or is out of range;
        the message names the file, line and field (:func:`~forensics.io.manifest.read_manifest`).
    """
    root = Path(folder)
    if not root.exists():
        raise InputError(f"{printable(str(root))}: does not exist; check the path (a dataset is a folder of images "
                         "with an optional manifest.csv)")
    if not root.is_dir():
        raise InputError(f"{printable(str(root))}: not a folder; a dataset is a folder of images with an optional "
                         "manifest.csv")
    manifest = root / MANIFEST
    if not os.path.lexists(manifest):
        paths = list_images(root)
        if not paths:
            raise InputError(f"{printable(str(root))}: no images found; add PNG/TIFF/JPEG/BMP/raw/FITS files or a "
                             "manifest.csv")
        return Dataset(root, _with_fits_headers([Frame(path=p, file=p.name) for p in paths]), has_manifest=False)
    frames = [_frame(row) for row in read_manifest(root, manifest, allow_outside)]
    return Dataset(root, _with_fits_headers(frames), has_manifest=True)


def _with_fits_headers(frames: list[Frame]) -> list[Frame]:
    """FITS frames with their header's conditions read now (no pixels decoded), filling what the manifest (if any)
    leaves empty: grouping by condition reads the fields directly, so they must be there before any grouping."""
    for frame in frames:
        if is_fits(frame.path):
            frame.info()
    return frames


def _frame(row: ManifestRow) -> Frame:
    return Frame(path=row.path, file=row.file, device=row.device, subject=row.subject,
                 temperature_c=row.temperature_c, extra=row.extra, _captured=row.captured,
                 _exposure_s=row.exposure_s, _iso=row.iso)
