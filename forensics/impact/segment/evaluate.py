"""Segmentations against hand-checked boundary circles: the hit rate.

A boundary is *hit* when the found circle's centre lies within ``centre_tol`` pixels of the marked one and its
radius within ``radius_tol`` (a fraction) of the marked radius — issue 29's criterion (3 px, 10 %).  Marks are
read from a CSV with the columns of ``tests/impact/data/iitd_marks.csv`` (``file``, ``pupil_x``, ``pupil_y``,
``pupil_r``, ``iris_x``, ``iris_y``, ``iris_r`` and optionally ``limbus`` = ``clear`` | ``uncertain``).
"""
from __future__ import annotations

import csv
import math
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from forensics._shared.errors import InputError
from forensics.impact.segment.common import Circle, Segmentation

MARK_COLUMNS = ("file", "pupil_x", "pupil_y", "pupil_r", "iris_x", "iris_y", "iris_r")


@dataclass(frozen=True)
class BoundaryMark:
    """Hand-checked pupil and limbus circles of one image; ``limbus_clear`` False when the limbus is faint."""

    file: str
    pupil: Circle
    iris: Circle
    limbus_clear: bool = True


def read_marks(path: str | Path) -> list[BoundaryMark]:
    """The marks in a CSV file (see the module docstring).

    Raises
    ------
    InputError
        For a missing file or column, or a value that is not a positive finite number (radii) or a number.
    """
    path = Path(path)
    try:
        with path.open(newline="") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise InputError(f"{path}: cannot read the marks ({exc.strerror or exc})") from None
    if not rows:
        raise InputError(f"{path}: no marks (an empty file or only a header)")
    missing = [c for c in MARK_COLUMNS if c not in rows[0]]
    if missing:
        raise InputError(f"{path}: missing column(s) {', '.join(missing)}; expected {', '.join(MARK_COLUMNS)}")
    marks = []
    for line, row in enumerate(rows, start=2):
        try:
            values = [float(row[c]) for c in MARK_COLUMNS[1:]]
        except (TypeError, ValueError):
            raise InputError(f"{path}, line {line}: a circle value is not a number") from None
        if not all(math.isfinite(v) for v in values) or values[2] <= 0 or values[5] <= 0:
            raise InputError(f"{path}, line {line}: circles need finite centres and positive radii")
        clear = (row.get("limbus") or "clear").strip().lower() != "uncertain"
        marks.append(BoundaryMark(row["file"], tuple(values[:3]), tuple(values[3:]), clear))
    return marks


def circle_error(found: Circle, truth: Circle) -> tuple[float, float]:
    """``(centre distance in pixels, |radius difference| / true radius)``."""
    return (math.hypot(found[0] - truth[0], found[1] - truth[1]), abs(found[2] - truth[2]) / truth[2])


def is_hit(found: Circle, truth: Circle, centre_tol: float = 3.0, radius_tol: float = 0.1) -> bool:
    """Whether ``found`` is within ``centre_tol`` px of ``truth``'s centre and ``radius_tol`` of its radius."""
    d, r = circle_error(found, truth)
    return d <= centre_tol and r <= radius_tol


@dataclass(frozen=True)
class ImageHit:
    """One image: the errors of both boundaries, whether each was hit, and the segmentation's own verdict."""

    file: str
    pupil_centre: float
    pupil_radius: float
    limbus_centre: float
    limbus_radius: float
    pupil_hit: bool
    limbus_hit: bool
    limbus_clear: bool
    ok: bool
    reason: str


@dataclass
class HitRates:
    """Hit counts of a segmentation on a set of marks."""

    centre_tol: float
    radius_tol: float
    images: list[ImageHit] = field(default_factory=list)

    @property
    def n(self) -> int:
        return len(self.images)

    def rate(self, boundary: str, clear_only: bool = False) -> tuple[int, int]:
        """``(hits, images)`` for ``boundary`` = ``"pupil"``, ``"limbus"`` or ``"both"``."""
        pool = [i for i in self.images if i.limbus_clear or not clear_only]
        if boundary == "pupil":
            hits = sum(i.pupil_hit for i in pool)
        elif boundary == "limbus":
            hits = sum(i.limbus_hit for i in pool)
        elif boundary == "both":
            hits = sum(i.pupil_hit and i.limbus_hit for i in pool)
        else:
            raise ValueError(f"boundary must be pupil, limbus or both, not {boundary!r}")
        return hits, len(pool)

    def misses(self) -> list[ImageHit]:
        """Images where a boundary was missed."""
        return [i for i in self.images if not (i.pupil_hit and i.limbus_hit)]

    def flagged(self) -> tuple[int, int]:
        """``(misses the segmentation flagged as failed, misses)``."""
        misses = self.misses()
        return sum(not i.ok for i in misses), len(misses)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"centre_tol": self.centre_tol, "radius_tol": self.radius_tol, "n": self.n}
        for boundary in ("pupil", "limbus", "both"):
            hits, n = self.rate(boundary)
            out[boundary] = {"hits": hits, "n": n, "rate": hits / n if n else None}
        hits, n = self.rate("limbus", clear_only=True)
        out["limbus_clear"] = {"hits": hits, "n": n, "rate": hits / n if n else None}
        out["images"] = [asdict(i) for i in self.images]
        return out


def hit_rates(segmentations: Mapping[str, Segmentation], marks: Iterable[BoundaryMark], centre_tol: float = 3.0,
              radius_tol: float = 0.1) -> HitRates:
    """Compare segmentations (by file name) with marks; images without a segmentation are skipped.

    Raises
    ------
    InputError
        When no mark has a segmentation (the file names do not match).
    """
    result = HitRates(centre_tol, radius_tol)
    for mark in marks:
        seg = segmentations.get(mark.file)
        if seg is None:
            continue
        pc, pr = circle_error(seg.pupil, mark.pupil)
        lc, lr = circle_error(seg.iris, mark.iris)
        result.images.append(ImageHit(mark.file, pc, pr, lc, lr, pc <= centre_tol and pr <= radius_tol,
                                      lc <= centre_tol and lr <= radius_tol, mark.limbus_clear, seg.ok,
                                      seg.reason))
    if not result.images:
        raise InputError("no segmentation matches a marked file name; check that the marks describe these images")
    return result
