"""Bounds on what one request may allocate: estimate first, refuse with one line naming the limit.

A command asked for something enormous — a median window of 99,999 pixels, a 100,000 × 100,000 scene, a
million ages, a small PNG that decodes to gigabytes — must say so before it allocates, not be killed by the
kernel half-way with its outputs half-written.  Three limits, each overridable by an environment variable:

* :func:`memory_limit` — the working memory one step of a command may ask for
  (``FORENSICS_MEMORY_LIMIT``, e.g. ``64G``; default 80 % of this machine's physical memory);
* :func:`pixel_limit` — the pixels of one decoded image (``FORENSICS_MAX_PIXELS``, default 400 million:
  above the largest single sensors made, below what a decompression bomb asks for);
* :func:`age_limit` — the sample ages one request may ask for (``FORENSICS_MAX_AGES``, default 1,000):
  every age is a folder of images (``simulate age``) or a round of the experiment (``impact``), so
  ``--years 0:1e6:1`` would make a million of them; the paper's designs use 13.

Examples
--------
>>> require_memory(10 * 2**20, "a 10 MiB buffer")   # fine
>>> parse_size("1.5G")
1610612736
"""
from __future__ import annotations

import os
import re

from forensics._shared.errors import InputError, UsageError

MEMORY_ENV = "FORENSICS_MEMORY_LIMIT"
PIXELS_ENV = "FORENSICS_MAX_PIXELS"
DEFAULT_MAX_PIXELS = 400_000_000
AGES_ENV = "FORENSICS_MAX_AGES"
DEFAULT_MAX_AGES = 1_000
_UNITS = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def parse_size(text: str) -> int:
    """Bytes of a size written as ``123``, ``512M``, ``1.5G``, ``2T`` (binary units, optional ``B``/``iB``)."""
    match = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([KMGT]?)(?:i?B)?\s*", text, flags=re.IGNORECASE)
    if not match:
        raise ValueError(f"'{text}' is not a size (e.g. 512M, 8G)")
    return int(float(match.group(1)) * _UNITS[match.group(2).upper()])


def physical_memory() -> int:
    """Bytes of physical memory of this machine (0 where it cannot be told)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        return 0


def memory_limit() -> int:
    """The memory one step may ask for: ``FORENSICS_MEMORY_LIMIT`` if set, else 80 % of physical memory."""
    text = os.environ.get(MEMORY_ENV)
    if text:
        try:
            return parse_size(text)
        except ValueError as exc:
            raise UsageError(f"{MEMORY_ENV}={text}: {exc}") from None
    total = physical_memory()
    return int(0.8 * total) if total else 2**63 - 1


def pixel_limit() -> int:
    """The most pixels one decoded image may have: ``FORENSICS_MAX_PIXELS`` if set, else 400 million."""
    text = os.environ.get(PIXELS_ENV)
    if not text:
        return DEFAULT_MAX_PIXELS
    try:
        value = int(float(text))
    except ValueError:
        raise UsageError(f"{PIXELS_ENV}={text}: not a number of pixels (e.g. 1e9)") from None
    if value < 1:
        raise UsageError(f"{PIXELS_ENV}={text}: must be at least 1")
    return value


def age_limit() -> int:
    """The most sample ages one request may ask for: ``FORENSICS_MAX_AGES`` if set, else 1,000."""
    text = os.environ.get(AGES_ENV)
    if not text:
        return DEFAULT_MAX_AGES
    try:
        value = int(float(text))
    except (ValueError, OverflowError):
        raise UsageError(f"{AGES_ENV}={text}: not a number of ages (e.g. 5000)") from None
    if value < 1:
        raise UsageError(f"{AGES_ENV}={text}: must be at least 1")
    return value


def require_ages(n_ages: float, what: str) -> None:
    """Raise :class:`UsageError` if a request for ``n_ages`` sample ages exceeds :func:`age_limit`.

    ``n_ages`` may be a float (``inf`` included), so that it can be checked before a list is built.
    """
    limit = age_limit()
    if not n_ages <= limit:
        finite = n_ages < 1e15
        count = f"{n_ages:,.0f}" if finite else f"{n_ages:.3g}"
        raise UsageError(f"{what} asks for {count} ages, more than the limit of {limit:,} (each age is a "
                         f"folder of images or a round of the experiment); ask for fewer, or if you mean it, "
                         f"raise the limit with {AGES_ENV} (e.g. {AGES_ENV}={int(n_ages) if finite else limit * 10})")


def _gib(nbytes: float) -> str:
    return f"{nbytes / 2**30:.1f} GiB"


def require_memory(nbytes: float, what: str, error: type[Exception] = UsageError) -> None:
    """Raise ``error`` (a one-line message) if ``nbytes`` exceed :func:`memory_limit`.

    ``what`` names the request as the user made it (``"--q 99999 (a 199,999-pixel median window)"``).
    """
    limit = memory_limit()
    if nbytes > limit:
        raise error(f"{what} needs about {_gib(nbytes)} of memory, more than the limit of {_gib(limit)}; ask for "
                    f"less, or raise the limit with {MEMORY_ENV} (e.g. {MEMORY_ENV}=64G) on a larger machine")


def require_pixels(n_pixels: int, where: str) -> None:
    """Raise :class:`InputError` if one image of ``n_pixels`` exceeds :func:`pixel_limit` (``where`` names the file)."""
    limit = pixel_limit()
    if n_pixels > limit:
        raise InputError(f"{where}: the image has {n_pixels:,} pixels, more than the limit of {limit:,} for one "
                         f"image (a damaged or malicious file?); if it is genuine, raise the limit with {PIXELS_ENV}")
