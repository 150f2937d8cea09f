"""``manifest.csv``: read strictly, one row per image, every value checked where it is parsed; and written.

A manifest is often written by another tool, edited by hand, and read by many machines, so nothing in it is
taken on trust.  It must be a regular UTF-8 file (a pipe would block the reader, a folder cannot be read)
holding well-formed CSV: a header naming each column once, no row with more fields than the header, no quoted
field running past the end of its line (an unterminated quote would otherwise swallow every later row).
Each image may be listed once (a duplicated row would be counted twice by every statistic), must be a
regular file inside the folder (unless ``allow_outside``), and every value must parse and lie in its
physical range.  Each refusal is one :class:`InputError` naming the manifest, the line and the field.
"""
from __future__ import annotations

import csv
import math
import os
import stat
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

from forensics._shared.errors import InputError
from forensics._shared.text import printable
from forensics.io.dates import FIRST_YEAR, LAST_YEAR, parse_captured
from forensics.io.images import file_problem

MANIFEST = "manifest.csv"
STANDARD_COLUMNS = ("file", "device", "captured", "exposure_s", "iso", "temperature_c", "subject")

#: Absolute zero in °C: no temperature lies below it.
ABSOLUTE_ZERO_C = -273.15
#: The hottest temperature accepted (°C): the top of the widest qualification range of electronics
#: (AEC-Q100 grade 0, automotive, −40 … +150 °C).  No working image sensor records a frame hotter than this;
#: a larger value is a typo or a Fahrenheit/Kelvin reading.
HOTTEST_C = 150.0
# Physical range of each numeric column: (lowest, highest, whether the lowest itself is allowed, what it is).
_RANGES = {
    "exposure_s": (0.0, math.inf, False, "an exposure time in seconds, above 0"),
    "iso": (0.0, math.inf, False, "an ISO sensitivity, above 0"),
    "temperature_c": (ABSOLUTE_ZERO_C, HOTTEST_C, False,
                      f"a temperature in °C above absolute zero ({ABSOLUTE_ZERO_C}) and at most {HOTTEST_C:g}"),
    "black_level": (0.0, math.inf, True, "a black level in DN, 0 or more"),
}
_UTF16_BOMS = (b"\xff\xfe", b"\xfe\xff")
#: The longest line read (bytes): above csv's 131,072-character field limit, far above any real row.
_LONGEST_LINE = 2**20
#: Characters of a field quoted in an error message; a longer value is cut (a message stays one readable line).
_SHOWN_CHARS = 100


def _quoted(text: str) -> str:
    """``text`` as an error message shows it: escaped (:func:`printable`), cut to :data:`_SHOWN_CHARS`."""
    cut = text if len(text) <= _SHOWN_CHARS else f"{text[:_SHOWN_CHARS]}… ({len(text):,} characters)"
    return f"'{printable(cut)}'"


@dataclass(frozen=True)
class ManifestRow:
    """One checked row: the image's path and the values the manifest gives (None where it gives none)."""

    line: int
    path: Path
    file: str
    device: str | None = None
    subject: str | None = None
    captured: float | None = None
    exposure_s: float | None = None
    iso: float | None = None
    temperature_c: float | None = None
    extra: dict[str, str] = field(default_factory=dict)


def read_manifest(root: Path, manifest: Path, allow_outside: bool = False) -> list[ManifestRow]:
    """Read and check ``manifest`` of the dataset folder ``root`` completely (see the module docstring).

    Raises
    ------
    InputError
        Naming the manifest, the line and the field, and what to do.
    """
    shown = printable(str(manifest))
    with _open_regular(manifest, shown) as handle:
        records = _records(_decoded_lines(handle, shown), shown)
        header = _header(next(records, None), shown)
        rows: list[ManifestRow] = []
        first_line: dict[tuple[int, int], int] = {}
        for line, record in records:
            if len(record) > len(header):
                raise InputError(f"{shown}, line {line}: {len(record)} fields but the header names {len(header)} "
                                 "columns; quote a field that holds a comma, or add the column to the header")
            values = dict(zip(header, [v.strip() for v in record] + [""] * (len(header) - len(record))))
            row = _row(root, f"{shown}, line {line}", line, values, allow_outside)
            found = os.stat(row.path)  # one image under two names (./f.png, a/../f.png, a link) is one file
            key = (found.st_dev, found.st_ino)
            if key in first_line:
                raise InputError(f"{shown}, line {line}: file {_quoted(row.file)} is already listed on line "
                                 f"{first_line[key]}; list each image once (a second row would count it twice)")
            first_line[key] = line
            rows.append(row)
    if not rows:
        raise InputError(f"{shown}: no rows; list one image per row under the header")
    return rows


def _open_regular(manifest: Path, shown: str) -> BinaryIO:
    """Open ``manifest`` for reading if it is a regular file.  Opened without blocking and checked on the open
    descriptor, so a pipe put in its place (even between a check and the open) cannot hang the reader."""
    problem = file_problem(manifest)
    if problem is None:
        try:
            fd = os.open(manifest, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
        except OSError as exc:
            raise InputError(f"{shown}: cannot be opened ({exc.strerror}); check its permissions") from None
        if stat.S_ISREG(os.fstat(fd).st_mode):
            return os.fdopen(fd, "rb")
        os.close(fd)
        problem = "is not a regular file"
    raise InputError(f"{shown}: {problem}; a manifest is a UTF-8 CSV file")


def _decoded_lines(handle: BinaryIO, shown: str) -> Iterator[str]:
    """The file's lines as text, refusing anything but UTF-8 (a byte-order mark is allowed), NUL bytes, and a
    line longer than :data:`_LONGEST_LINE` (no manifest row needs one; a file without line ends is no manifest)."""
    for number, raw in enumerate(iter(lambda: handle.readline(_LONGEST_LINE + 1), b""), start=1):
        if len(raw) > _LONGEST_LINE:
            raise InputError(f"{shown}, line {number}: longer than {_LONGEST_LINE:,} bytes; a manifest has one short "
                             "row per image")
        if number == 1:
            if raw.startswith(_UTF16_BOMS):
                raise InputError(f"{shown}: the file is UTF-16 text; save it as UTF-8 (e.g. 'CSV UTF-8' in a "
                                 "spreadsheet, or iconv -f UTF-16 -t UTF-8)")
            raw = raw.removeprefix(b"\xef\xbb\xbf")
        if b"\0" in raw:
            raise InputError(f"{shown}, line {number}: holds a NUL byte (UTF-16 or binary data?); a manifest is "
                             "UTF-8 text: save it as UTF-8")
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise InputError(f"{shown}, line {number}: not UTF-8 text (byte 0x{raw[exc.start]:02x}, the line's byte "
                             f"{exc.start + 1}; Latin-1 or another code page?); save the manifest as UTF-8") from None
        yield text


def _records(lines: Iterable[str], shown: str) -> Iterator[tuple[int, list[str]]]:
    """CSV records with the line each starts on; blank lines skipped.

    A record must end on the line where it starts: the csv module lets a quoted field run on over line ends,
    so one stray quote would silently join every later row into one field.  No manifest value (a path, a
    date, a number, a short text) holds a line break, so a record spanning lines is refused, naming the
    line of the quote.  Fields are limited to the csv module's 131,072 characters.
    """
    reader = csv.reader(lines, strict=True)
    start = 1
    open_quote = (f"{shown}, line {{}}: a quoted field runs past the end of the line (a quote left open?); close "
                  "the quote, or remove the line break inside it")
    try:
        for record in reader:
            if reader.line_num > start:
                raise InputError(open_quote.format(start))
            if record:
                yield start, record
            start = reader.line_num + 1
    except csv.Error as exc:
        if reader.line_num > start:  # the file ended inside a quoted field that began on line ``start``
            raise InputError(open_quote.format(start)) from None
        raise InputError(f"{shown}, line {start}: not valid CSV ({exc}); fix the line") from None


def _header(first: tuple[int, list[str]] | None, shown: str) -> list[str]:
    """The column names: present, each named, each once, with a ``file`` column."""
    if first is None:
        raise InputError(f"{shown}: empty; the first row must name the columns (file, captured, …)")
    line, record = first
    names = [name.strip() for name in record]
    for index, name in enumerate(names):
        if not name:
            raise InputError(f"{shown}, line {line}: column {index + 1} of the header has no name; name it or "
                             "delete the column")
        if name in names[:index]:
            raise InputError(f"{shown}, line {line}: the column {_quoted(name)} is named twice (columns "
                             f"{names.index(name) + 1} and {index + 1}); keep one")
    if "file" not in names:
        raise InputError(f"{shown}: the header has no 'file' column; the first row must name the columns "
                         "(file, captured, …)")
    return names


def _row(root: Path, where: str, line: int, values: dict[str, str], allow_outside: bool) -> ManifestRow:
    """One row's image path and values, each checked."""
    name = values.get("file", "")
    path = _image_path(root, where, name, allow_outside)
    numbers = {column: _number(where, column, values.get(column, "")) for column in _RANGES}
    return ManifestRow(
        line=line,
        path=path,
        file=name,
        device=values.get("device") or None,
        subject=values.get("subject") or None,
        captured=_captured(where, values.get("captured", "")),
        exposure_s=numbers["exposure_s"],
        iso=numbers["iso"],
        temperature_c=numbers["temperature_c"],
        extra={k: v for k, v in values.items() if k not in STANDARD_COLUMNS},
    )


def _image_path(root: Path, where: str, name: str, allow_outside: bool) -> Path:
    """The path a row names, refused unless it is a regular file (inside the folder unless ``allow_outside``)."""
    if not name:
        raise InputError(f"{where}: field 'file' is empty; give the image's path relative to the folder")
    shown = _quoted(name)
    path = root / name
    problem = file_problem(path)
    if problem is not None:
        raise InputError(f"{where}: file {shown} {problem} in {printable(str(root))}; fix the row or add the file")
    if not allow_outside and not path.resolve().is_relative_to(root.resolve()):
        raise InputError(f"{where}: file {shown} lies outside the dataset folder {printable(str(root))} (absolute "
                         "path, '..' or a link leaving it); move it into the folder or pass --allow-outside")
    return path


def _number(where: str, column: str, text: str) -> float | None:
    """A numeric field, None when empty; refused unless a finite number in the column's physical range."""
    if not text:
        return None
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"{where}: field '{column}' = {_quoted(text)} is not a number") from None
    low, high, low_allowed, meaning = _RANGES[column]
    if not (math.isfinite(value) and (value >= low if low_allowed else value > low) and value <= high):
        raise InputError(f"{where}: field '{column}' = {_quoted(text)} is out of range: give {meaning}")
    return value


def _captured(where: str, text: str) -> float | None:
    """The ``captured`` field as a decimal year, None when empty (:func:`~forensics.io.dates.parse_captured`)."""
    if not text:
        return None
    try:
        return parse_captured(text)
    except ValueError as exc:
        raise InputError(
            f"{where}: field 'captured' = {_quoted(text)} is not a capture date ({printable(str(exc))}): give an "
            f"ISO 8601 date or datetime or a decimal year between {FIRST_YEAR:.0f} and {LAST_YEAR:.0f} (e.g. "
            "2009-07-01, 20090701, 2009-07-01T12:30:00 or 2009.5)"
        ) from None


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
