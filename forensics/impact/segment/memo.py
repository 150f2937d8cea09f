"""Exact reuse of a segmentation's costly steps between images that differ in a few pixels.

An aged image equals the image of the same eye at the sensor's previous age except where a defect appeared or
grew: a handful of pixels.  Its segmentation cannot simply be copied — every step reads whole-image statistics
(luminance percentiles, Canny's quantile thresholds), and a defect can move them — but most steps' *inputs*
come out byte-identical anyway: the thresholded dark map the pupil's Hough transform reads, the edge pixels and
weights the limbus's Hough transform reads, the ray profiles a limbus fit reads are unchanged unless a new
defect lies where they look.  The costly steps are pure functions of those inputs, so where the inputs are
byte-identical the result is.

:class:`StepMemo` makes that exact by construction: a step's result is looked up by the
:func:`~forensics._shared.digest.content_digest` of the step (its module and name) and of *everything* it
receives — every array's dtype, shape, strides and bytes, every number's exact bits.  The cheap
steps that make those inputs are always computed; a costly step is computed whenever its inputs differ in a
single bit, and then its new result is kept.  A segmentation run with a memo returns the same bits as one run
without (``tests/impact/test_segment_memo.py``: real and synthetic eyes, aged by several sensors).

A memo is made per image from the entries of the same eye's previous segmentation (``before``) and collects
the entries this segmentation used (:attr:`StepMemo.entries`), which the next age starts from.  Entries are
valid for the code that made them: they live within one run (and its checkpoints), like the templates.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, TypeVar

from forensics._shared.digest import content_digest

T = TypeVar("T")


class StepMemo:
    """Results of a segmentation's costly steps, keyed by the exact content of everything each step receives.

    Parameters
    ----------
    before
        Entries of an earlier segmentation (:attr:`entries`), typically of the same eye at the previous age.

    Attributes
    ----------
    entries
        ``{digest: result}`` of every step this memo's segmentation ran or reused (to start the next one from).
    hits, misses
        Steps reused and computed.
    """

    def __init__(self, before: Mapping[bytes, Any] | None = None) -> None:
        self._before = before if before is not None else {}
        self.entries: dict[bytes, Any] = {}
        self.hits = 0
        self.misses = 0

    def __call__(self, step: Callable[..., T], *args: Any) -> T:
        """``step(*args)``, or its stored result when ``step`` already ran on byte-identical ``args``.

        A result is stored as it is: steps return immutable values (tuples of numbers), which nobody alters.
        """
        key = content_digest((step.__module__, step.__qualname__, args))
        if key is None:                      # an argument the digest cannot see into: never reused
            self.misses += 1
            return step(*args)
        if key in self.entries:
            return self.entries[key]
        if key in self._before:
            value = self._before[key]
            self.hits += 1
        else:
            value = step(*args)
            self.misses += 1
        self.entries[key] = value
        return value


def remembered(memo: StepMemo | None, step: Callable[..., T], *args: Any) -> T:
    """``step(*args)`` through ``memo`` when there is one."""
    return step(*args) if memo is None else memo(step, *args)
