"""Optional progress reporting for long loops.

Library functions that loop over many images take a ``progress`` argument: a
callable ``progress(iterable, total=None, desc=None)`` that returns an
iterable yielding the same items.  The default, :func:`no_progress`, is the
identity, so the library never prints; the command layer passes
:func:`tqdm_progress` when stderr is a terminal.
"""
from __future__ import annotations

import sys
from collections.abc import Callable, Iterable, Iterator
from typing import Any, TypeVar

T = TypeVar("T")
Progress = Callable[..., Iterable[Any]]


def no_progress(iterable: Iterable[T], total: int | None = None, desc: str | None = None) -> Iterable[T]:
    """Return ``iterable`` unchanged (the library's default: silent)."""
    return iterable


def tqdm_progress(iterable: Iterable[T], total: int | None = None, desc: str | None = None) -> Iterator[T]:
    """Wrap ``iterable`` in a tqdm bar on stderr."""
    from tqdm import tqdm

    return iter(tqdm(iterable, total=total, desc=desc, file=sys.stderr, leave=False, dynamic_ncols=True))


def choose_progress(quiet: bool = False) -> Progress:
    """A bar on stderr when it is a terminal and not ``quiet``; otherwise silence."""
    if quiet or not sys.stderr.isatty():
        return no_progress
    return tqdm_progress
