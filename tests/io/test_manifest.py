"""manifest.csv read strictly: what a hand-edited, foreign or hostile manifest may hold, refused in one line."""
from __future__ import annotations

import os
import threading

import numpy as np
import pytest

from forensics._shared.errors import InputError
from forensics.io.dataset import open_dataset
from forensics.io.images import write_image


def _folder(root, manifest: str | bytes | None = None, n: int = 3):
    root.mkdir(exist_ok=True)
    for i in range(n):
        write_image(root / f"f{i}.png", np.full((8, 10), i, np.uint8))
    if isinstance(manifest, str):
        (root / "manifest.csv").write_text(manifest, encoding="utf-8")
    elif manifest is not None:
        (root / "manifest.csv").write_bytes(manifest)
    return root


def _refused(root, pattern: str) -> str:
    with pytest.raises(InputError, match=pattern) as err:
        open_dataset(root)
    message = str(err.value)
    assert "manifest.csv" in message and "\n" not in message
    return message


# ----------------------------------------------------------------------------- D08: each image once

@pytest.mark.parametrize("second", ["f0.png", "./f0.png", "sub/../f0.png", "alias.png", "hard.png"])
def test_an_image_listed_twice_is_refused_naming_both_lines(tmp_path, second):
    """D08: every row twice turned an EER of 50 % into 35 %; any second name of the same file is the same image."""
    root = _folder(tmp_path / "set", f"file,device\nf0.png,a\nf1.png,a\n{second},a\n")
    (root / "sub").mkdir()
    (root / "alias.png").symlink_to(root / "f0.png")
    os.link(root / "f0.png", root / "hard.png")
    _refused(root, rf"line 4: file '{second}' is already listed on line 2; list each image once")


def test_distinct_images_with_equal_content_are_not_duplicates(tmp_path):
    root = _folder(tmp_path / "set", "file\nf0.png\ncopy.png\n")
    (root / "copy.png").write_bytes((root / "f0.png").read_bytes())
    assert len(open_dataset(root)) == 2  # two files, two frames: only the same file twice is refused


# ----------------------------------------------------------------------------- D09: malformed CSV

def test_an_unterminated_quote_is_refused_at_its_line_not_swallowing_later_rows(tmp_path):
    """D09: a stray quote joined every later row into one field, and `info` counted 1 image of 11."""
    rows = "".join(f"f{i}.png,ok\n" for i in range(1, 3))
    _refused(_folder(tmp_path / "set", 'file,subject\nf0.png,"sky\n' + rows),
             r"line 2: a quoted field runs past the end of the line \(a quote left open\?\)")


def test_a_quoted_field_spanning_lines_is_refused_even_when_closed(tmp_path):
    _refused(_folder(tmp_path / "set", 'file,subject\nf0.png,"two\nlines"\nf1.png,x\n'),
             r"line 2: a quoted field runs past the end of the line")


def test_quoted_fields_on_one_line_are_fine(tmp_path):
    ds = open_dataset(_folder(tmp_path / "set", 'file,subject\n"f0.png","sky, clouds"\r\nf1.png,"say ""hi"""\r\n'))
    assert [f.subject for f in ds] == ["sky, clouds", 'say "hi"']


@pytest.mark.parametrize("manifest, pattern", [
    ("file,device\nf0.png,a,b\n", r"line 2: 3 fields but the header names 2 columns"),
    ("file,device,file\nf0.png,a,f1.png\n", r"line 1: the column 'file' is named twice \(columns 1 and 3\)"),
    ("file,iso,iso\nf0.png,100,200\n", r"line 1: the column 'iso' is named twice"),
    ("file,,device\nf0.png,,a\n", r"line 1: column 2 of the header has no name"),
    ('file,subject\nf0.png,"a"b\n', r"line 2: not valid CSV"),
    ("", r"empty; the first row must name the columns"),
])
def test_malformed_csv_is_refused_naming_the_line(tmp_path, manifest, pattern):
    """D09/D20: more fields than columns, a column named twice (which one would win?), a nameless column."""
    _refused(_folder(tmp_path / "set", manifest), pattern)


def test_short_rows_and_blank_lines_are_allowed(tmp_path):
    ds = open_dataset(_folder(tmp_path / "set", "file,device,subject\nf0.png,a\n\nf1.png\n"))
    assert [(f.device, f.subject) for f in ds] == [("a", None), (None, None)]


# ----------------------------------------------------------------------------- D11/D19: what the file is

@pytest.mark.parametrize("encoding, pattern", [
    ("utf-16", r"the file is UTF-16 text; save it as UTF-8"),
    ("utf-16-le", r"line 1: holds a NUL byte .*save it as UTF-8"),  # no byte-order mark: told by its NULs
    ("latin-1", r"line 3: not UTF-8 text \(byte 0xe9, the line's byte 11; Latin-1"),
    ("cp1252", r"line 3: not UTF-8 text \(byte 0x93"),
])
def test_a_manifest_that_is_not_utf8_is_refused_saying_so(tmp_path, encoding, pattern):
    """D11: a UTF-16 or Latin-1 manifest ended in a UnicodeDecodeError traceback."""
    text = "file,subject\nf0.png,sky\nf1.png,caf\u00e9\n" if encoding != "cp1252" else 'file,subject\nf0.png,x\nf1.png,\u201cq\u201d\n'
    _refused(_folder(tmp_path / "set", text.encode(encoding)), pattern)


def test_a_utf8_byte_order_mark_is_accepted(tmp_path):
    ds = open_dataset(_folder(tmp_path / "set", "\ufefffile,subject\nf0.png,caf\u00e9\n".encode("utf-8")))
    assert ds[0].subject == "caf\u00e9"


def test_a_field_over_the_csv_limit_is_refused_naming_the_line(tmp_path):
    """D11: csv's 131,072-character field limit raised a bare csv.Error."""
    _refused(_folder(tmp_path / "set", "file,subject\nf0.png,ok\nf1.png," + "x" * 140_000 + "\n"),
             r"line 3: not valid CSV \(field larger than field limit \(131072\)\)")


def test_a_line_without_end_is_refused_before_it_fills_memory(tmp_path):
    _refused(_folder(tmp_path / "set", "file\nf0.png\n" + "x," * 600_000), r"line 3: longer than 1,048,576 bytes")


def test_a_manifest_that_is_a_folder_is_refused(tmp_path):
    root = _folder(tmp_path / "set")
    (root / "manifest.csv").mkdir()
    _refused(root, r"manifest.csv: is a folder, not a file")


def test_a_manifest_that_is_a_pipe_is_refused_without_blocking(tmp_path):
    """D19: a FIFO named manifest.csv blocked `info` forever."""
    root = _folder(tmp_path / "set")
    os.mkfifo(root / "manifest.csv")
    outcome: list[str] = []

    def opening() -> None:
        try:
            open_dataset(root)
        except InputError as exc:
            outcome.append(str(exc))

    worker = threading.Thread(target=opening, daemon=True)
    worker.start()
    worker.join(30)
    assert outcome and "manifest.csv: is not a regular file (a pipe" in outcome[0]


# ----------------------------------------------------------------------------- D11: what a row names

def test_rows_naming_what_cannot_be_a_frame_are_refused_naming_line_and_reason(tmp_path):
    """D11: a symlink loop, a name too long and a NUL ended in tracebacks (RuntimeError, OSError, ValueError)."""
    root = _folder(tmp_path / "set")
    (root / "loop.png").symlink_to(root / "loop.png")
    (root / "folder.png").mkdir()
    os.mkfifo(root / "pipe.png")
    cases = {"loop.png": r"line 3: file 'loop.png' is a loop of symbolic links",
             "folder.png": r"line 3: file 'folder.png' is a folder",
             "pipe.png": r"line 3: file 'pipe.png' is not a regular file",
             "a" * 300 + ".png": r"line 3: file 'a{100}… \(304 characters\)' has a name too long",
             "missing.png": r"line 3: file 'missing.png' does not exist"}
    for name, pattern in cases.items():
        (root / "manifest.csv").write_text(f"file\nf0.png\n{name}\n")
        _refused(root, pattern)
    (root / "manifest.csv").write_bytes(b"file\nf0.png\nf\x001.png\n")
    _refused(root, r"line 3: holds a NUL byte")


def test_control_characters_in_refused_values_are_escaped_in_the_message(tmp_path):
    """D22: a manifest field with an ESC sequence must not reach the terminal raw through an error."""
    message = _refused(_folder(tmp_path / "set", "file\n\x1b]0;pwned\x07evil.png\n"), r"does not exist")
    assert "\x1b" not in message and "\x07" not in message and "\\x1b]0;pwned\\x07evil.png" in message


# ----------------------------------------------------------------------------- D20: values in range

@pytest.mark.parametrize("column, value, pattern", [
    ("captured", "0001-01-01", r"'0001-01-01' is not a capture date \(date 0001-01-01 is outside 1975–2200"),
    ("captured", "1970-01-01", r"outside 1975–2200"),
    ("captured", "9999", r"decimal year 9999 is outside 1975–2200"),
    ("captured", "2009-02-30", r"'2009-02-30' is not a capture date"),
    ("temperature_c", "-300", r"'-300' is out of range: give a temperature in °C above absolute zero"),
    ("temperature_c", "-273.15", r"out of range"),
    ("temperature_c", "451", r"out of range: .* at most 150"),
    ("temperature_c", "nan", r"out of range"),
    ("exposure_s", "0", r"'0' is out of range: give an exposure time in seconds, above 0"),
    ("exposure_s", "inf", r"out of range"),
    ("iso", "-100", r"'-100' is out of range"),
    ("black_level", "nan", r"field 'black_level' = 'nan' is out of range: give a black level in DN"),
    ("black_level", "-5", r"out of range"),
    ("black_level", "dark", r"field 'black_level' = 'dark' is not a number"),
])
def test_values_out_of_their_physical_range_are_refused_where_parsed(tmp_path, column, value, pattern):
    """D20/D11: 0001-01-01, −300 °C and black_level=nan were used (or crashed later, with no line named)."""
    _refused(_folder(tmp_path / "set", f"file,{column}\nf0.png,\nf1.png,{value}\n"),
             rf"line 3: field '{column}' = {pattern}" if pattern.startswith("'") else pattern)


@pytest.mark.parametrize("column, value, expected", [
    ("captured", "20090701", 2009.4959), ("captured", "20090701T120000", 2009.4973),
    ("captured", "1975.0", 1975.0), ("captured", "2096-01-01", 2096.0),
    ("temperature_c", "-120", -120.0), ("temperature_c", "150", 150.0),
    ("black_level", "0", "0"), ("exposure_s", "3600", 3600.0),
])
def test_values_in_range_are_read(tmp_path, column, value, expected):
    """D21: the ISO 8601 basic form 20090701 was refused as a decimal year; a cooled CCD at −120 °C is fine."""
    frame = open_dataset(_folder(tmp_path / "set", f"file,{column}\nf0.png,{value}\n"))[0]
    got = frame.get(column)
    assert got == pytest.approx(expected, abs=1e-4) if isinstance(expected, float) else got == expected
