"""Untrusted text made safe for a terminal.

File names, manifest fields and EXIF strings come from whoever made the data.  Printed raw, an escape
sequence in one of them (``ESC [ 2 J``, a carriage return, a right-to-left override) can clear the screen,
overwrite what was printed before or disguise a name.  :func:`printable` is applied to everything the
command prints for a human; JSON output needs nothing more (``json`` escapes control characters itself).

Examples
--------
>>> printable("photo\\x1b[2J.png")
'photo\\\\x1b[2J.png'
>>> printable("two\\nlines\\tkept")
'two\\nlines\\tkept'
"""
from __future__ import annotations

import unicodedata

# Newline and tab lay out the tool's own tables and messages; every other control character is escaped.
_KEPT = frozenset("\n\t")
# Format characters that reorder or hide text on a terminal (bidirectional overrides and isolates).
_BIDI = frozenset("\u200e\u200f\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069")


def _escape(char: str) -> str:
    code = ord(char)
    if 0xDC80 <= code <= 0xDCFF:  # a byte of a non-UTF-8 file name (os.fsdecode's surrogateescape)
        return f"\\x{code - 0xDC00:02x}"
    if code <= 0xFF:
        return f"\\x{code:02x}"
    return f"\\u{code:04x}"


def printable(text: str) -> str:
    """``text`` with control characters (except newline and tab), lone surrogates and bidirectional
    overrides replaced by ``\\xNN`` / ``\\uNNNN`` escapes, so that it shows as written on a terminal."""
    text = str(text)
    if text.isprintable():  # the common case: nothing to do
        return text
    return "".join(
        _escape(c) if c not in _KEPT and (unicodedata.category(c) in ("Cc", "Cs") or c in _BIDI) else c
        for c in text
    )
