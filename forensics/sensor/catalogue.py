"""A device's defect history: every defect's site, kind, amplitude and onset, and the questions asked of it.

*Once defective, always defective*: records are never removed; a site that became partially stuck and later
stuck has two records, and the stuck one wins from its onset (:meth:`DefectCatalogue.effective`).
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

PARTIAL = 0
STUCK = 1
KIND_NAMES = {PARTIAL: "partial", STUCK: "stuck"}
KIND_CODES = {v: k for k, v in KIND_NAMES.items()}



@dataclass
class DefectCatalogue:
    """A device's defect history: one record per defect, arrays of equal length.

    Attributes
    ----------
    x, y
        Column and row of the site.
    kind
        :data:`PARTIAL` (y = i + d) or :data:`STUCK` (y = c).
    amplitude
        d for partially stuck records, c for stuck ones, in output DN.
    onset
        Time the defect appears (decimal year).
    source
        Name of the arrival effect that produced the record.
    extra
        Per-record attributes drawn by other effects (e.g. a dark-current rate),
        arrays of the same length.
    """

    x: np.ndarray
    y: np.ndarray
    kind: np.ndarray
    amplitude: np.ndarray
    onset: np.ndarray
    source: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    @classmethod
    def empty(cls) -> "DefectCatalogue":
        return cls(*(np.zeros(0, dtype=t) for t in (np.int64, np.int64, np.int8, np.float64, np.float64)),
                   source=np.zeros(0, dtype=object))

    def __len__(self) -> int:
        return len(self.x)

    def select(self, mask: np.ndarray) -> "DefectCatalogue":
        """The records where ``mask`` is true (or at the given indices)."""
        return DefectCatalogue(self.x[mask], self.y[mask], self.kind[mask], self.amplitude[mask], self.onset[mask],
                               self.source[mask], {k: v[mask] for k, v in self.extra.items()})

    def active(self, time: float) -> np.ndarray:
        """Boolean mask of the records present at ``time``."""
        return self.onset <= time

    def at(self, time: float) -> "DefectCatalogue":
        """The records present at ``time``."""
        return self.select(self.active(time))

    def effective(self, time: float) -> "DefectCatalogue":
        """One record per defective site at ``time``: the stuck record where a site has one, else its partial record."""
        return self.select(self.effective_index(time))

    def effective_index(self, time: float) -> np.ndarray:
        """Indices of the records :meth:`effective` returns (cached per time: sites, kinds and onsets are treated as
        immutable once a catalogue exists; amplitudes and extras may change)."""
        cache = self.__dict__.setdefault("_effective_cache", {})
        key = (float(time), len(self))
        if key not in cache:
            idx = np.flatnonzero(self.active(time))
            if idx.size:
                x, y, kind = self.x[idx], self.y[idx], self.kind[idx]
                order = np.lexsort((-kind, y, x))  # per site, stuck first
                sites = y[order] * (x.max() + 1) + x[order]
                first = np.ones(len(order), bool)
                first[1:] = sites[1:] != sites[:-1]
                idx = idx[np.sort(order[first])]
            cache[key] = idx
        return cache[key]

    def counts(self, times: Iterable[float], kind: int | None = None) -> np.ndarray:
        """Number of defective sites present at each time (optionally of one kind, after stuck overrides)."""
        out = []
        for t in times:
            eff = self.effective(t)
            out.append(len(eff) if kind is None else int(np.sum(eff.kind == kind)))
        return np.asarray(out)

    def to_rows(self) -> list[dict[str, Any]]:
        """Rows for ``defects.csv``: x, y, kind, amplitude, onset_year, source, extras."""
        rows = []
        for i in range(len(self)):
            row = {"x": int(self.x[i]), "y": int(self.y[i]), "kind": KIND_NAMES[int(self.kind[i])],
                   "amplitude": float(self.amplitude[i]), "onset_year": float(self.onset[i]),
                   "source": str(self.source[i])}
            row.update({k: float(v[i]) for k, v in self.extra.items()})
            rows.append(row)
        return rows

    @classmethod
    def concatenate(cls, parts: Sequence["DefectCatalogue"]) -> "DefectCatalogue":
        if not parts:
            return cls.empty()
        keys = set().union(*(p.extra for p in parts))
        extra = {k: np.concatenate([p.extra.get(k, np.full(len(p), np.nan)) for p in parts]) for k in keys}
        return cls(*(np.concatenate([getattr(p, a) for p in parts]) for a in ("x", "y", "kind", "amplitude", "onset",
                                                                               "source")), extra=extra)

    def resolved(self) -> "DefectCatalogue":
        """Apply *once defective, always defective* to a set of raw arrivals.

        Per site and kind only the earliest record is kept; a partially stuck
        record arriving after the site became stuck is dropped (the site is
        already defective).  The result is sorted by onset.
        """
        if not len(self):
            return self
        order = np.argsort(self.onset, kind="stable")
        cat = self.select(order)
        width = int(cat.x.max()) + 1
        site = cat.y * width + cat.x
        # earliest record per (site, kind): np.unique returns first occurrences in onset order
        _, first = np.unique(site * 2 + cat.kind, return_index=True)
        keep = np.zeros(len(cat), bool)
        keep[first] = True
        # drop partial records whose site already had a stuck record earlier
        is_stuck = keep & (cat.kind == STUCK)
        stuck_site, stuck_onset = site[is_stuck], cat.onset[is_stuck]
        if len(stuck_site):
            by_site = np.argsort(stuck_site)
            stuck_site, stuck_onset = stuck_site[by_site], stuck_onset[by_site]
            pos = np.clip(np.searchsorted(stuck_site, site), 0, len(stuck_site) - 1)
            late = (cat.kind == PARTIAL) & (stuck_site[pos] == site) & (stuck_onset[pos] <= cat.onset)
            keep &= ~late
        return cat.select(keep)
