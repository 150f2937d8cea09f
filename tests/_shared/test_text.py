"""printable: untrusted text (file names, manifest fields, EXIF strings) never reaches a terminal raw."""
from __future__ import annotations

import io

from forensics._shared.text import printable


def test_terminal_controls_are_escaped_and_visible_text_kept():
    # ESC (a CSI that clears the screen), CR (overwrites the line), BEL, DEL, C1 CSI, a bidi override
    hostile = "a\x1b[2Jb\rc\x07d\x7fe\x9bf\u202eg"
    out = printable(hostile)
    assert out == "a\\x1b[2Jb\\x0dc\\x07d\\x7fe\\x9bf\\u202eg"
    assert all(ch.isprintable() for ch in out)


def test_newline_tab_and_ordinary_unicode_pass_unchanged():
    text = "Zürich\tcafé 2009–2013 µm\nnext line ✓"
    assert printable(text) == text


def test_undecodable_file_names_print_on_a_strict_utf8_stream():
    name = b"caf\xe9\xff.png".decode("utf-8", "surrogateescape")  # what os.listdir gives for Latin-1 bytes
    out = printable(name)
    assert out == "caf\\xe9\\xff.png"
    stream = io.TextIOWrapper(io.BytesIO(), encoding="utf-8", errors="strict")
    stream.write(out)  # the raw name would raise UnicodeEncodeError here
    stream.flush()
