r"""Untrusted text made safe for a terminal.

File names, manifest fields and EXIF strings come from whoever made the data.  Printed raw, an ESC sequence in
one of them can move the cursor, recolour or retitle the terminal, or hide the rest of a line (``\r``); a name
that is not valid UTF-8 (a lone surrogate from :func:`os.fsdecode`) makes ``print`` to a strict stdout raise.
:func:`printable` is the one escaping every command applies to such text before it reaches a terminal.

Examples
--------
>>> printable("a\x1b[2Jb")
'a\\x1b[2Jb'
>>> printable("caf\udce9.png")   # the byte 0xe9 of a Latin-1 file name
'caf\\xe9.png'
>>> printable("line one\nline two\tcolumn")
'line one\nline two\tcolumn'
"""
from __future__ import annotations

import re

# C0 controls except tab and newline, DEL and the C1 controls (which many terminals also obey: CSI is \x9b);
# the bidirectional embeddings, overrides and isolates and the line/paragraph separators, which reorder or
# break what is displayed without being visible themselves; and lone surrogates (undecodable bytes of a
# file name), which cannot be encoded for output at all.
_UNSAFE = re.compile("[\x00-\x08\x0b-\x1f\x7f-\x9f\u2028\u2029\u202a-\u202e\u2066-\u2069\ud800-\udfff]")


def _escape(match: re.Match[str]) -> str:
    code = ord(match.group())
    if 0xDC80 <= code <= 0xDCFF:  # an undecodable byte of a file name (os.fsdecode's surrogateescape): show the byte
        return f"\\x{code - 0xDC00:02x}"
    return f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}"


def printable(text: str) -> str:
    """``text`` with control characters (except newline and tab) and lone surrogates as ``\\xNN``/``\\uNNNN``."""
    return _UNSAFE.sub(_escape, str(text))
