"""Capture dates: decimal years, the forms a manifest may use, EXIF date strings, and the plausible range.

A capture date is kept as a decimal year (2009-07-02T12:00 → 2009.5).  A manifest writes it as an ISO 8601
date or datetime, extended (``2009-07-01``, ``2009-07-01T12:30:00``) or basic (``20090701``,
``20090701T123000``), or as a decimal year (``2009.5``); EXIF writes ``2009:07:01 12:30:00``.

Every date is checked against :data:`FIRST_YEAR` … :data:`LAST_YEAR` where it is parsed, so that a typo or an
unset camera clock (``0001-01-01``, ``1970-01-01``) never enters an epoch split, a growth fit or a dating.
"""
from __future__ import annotations

import datetime as _dt
import math
from typing import Any

#: The earliest plausible capture date (decimal year).  The first digital camera (S. Sasson's prototype at
#: Kodak) took its first image in December 1975; no image sensor recorded a dated file before.  Earlier
#: dates in files come from clocks that were never set or were reset: 0001-01-01, the Unix epoch 1970-01-01.
FIRST_YEAR = 1975.0
#: The latest plausible capture date (decimal year, exclusive).  Not "now": simulated ageing writes capture
#: dates decades ahead on purpose (``simulate age`` starts at 2000 and its default series reaches 2096), so
#: the bound leaves a century beyond today's sensors and still refuses typos such as 20090 or 9999.
LAST_YEAR = 2200.0

_EXIF_FORMATS = ("%Y:%m:%d %H:%M:%S", "%Y-%m-%d %H:%M:%S", "%Y-%m-%dT%H:%M:%S", "%Y:%m:%d")


def decimal_year(when: _dt.datetime | _dt.date) -> float:
    """Convert a date or datetime to a decimal year (2009-07-02T12:00 → 2009.5); aware times in UTC."""
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


def is_plausible(year: float) -> bool:
    """Whether a decimal year lies in the plausible range of capture dates (:data:`FIRST_YEAR` … :data:`LAST_YEAR`)."""
    return math.isfinite(year) and FIRST_YEAR <= year < LAST_YEAR


def _range_text() -> str:
    return f"{FIRST_YEAR:.0f}–{LAST_YEAR:.0f}"


def parse_captured(text: str) -> float:
    """Parse a ``captured`` value (ISO 8601 date/datetime, extended or basic, or a decimal year) to a decimal year.

    Raises
    ------
    ValueError
        If the text is neither form, or the date lies outside the plausible range (:func:`is_plausible`).
    """
    text = text.strip()
    try:
        year: float | None = float(text)
    except ValueError:
        year = None
    if year is not None and is_plausible(year):
        return year
    try:
        # fromisoformat (Python ≥ 3.11) reads both the extended and the basic form, and a trailing Z
        when = _dt.datetime.fromisoformat(text) if "T" in text or " " in text else _dt.date.fromisoformat(text)
    except ValueError:
        if year is not None:  # a number, but neither a plausible year nor a basic date such as 20090701
            raise ValueError(f"decimal year {text} is outside {_range_text()}") from None
        raise
    value = decimal_year(when)
    if not is_plausible(value):
        raise ValueError(f"date {text} is outside {_range_text()}, the plausible range for a digital image")
    return value


def exif_datetime(value: Any) -> _dt.datetime | None:
    """An EXIF date string (``2009:07:01 12:30:00``) as a naive datetime; None if absent, unreadable or implausible.

    Cameras write ``0000:00:00 00:00:00`` or blanks when the date is unknown, and a reset clock writes its
    epoch: such values say nothing about the capture time, so they are unknown rather than an error.
    """
    if not value:
        return None
    text = str(value).strip()
    for fmt in _EXIF_FORMATS:
        try:
            when = _dt.datetime.strptime(text, fmt)
        except ValueError:
            continue
        return when if is_plausible(decimal_year(when)) else None
    return None
