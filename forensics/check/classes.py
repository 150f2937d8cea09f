"""Pixel classes (normal, partially stuck, stuck) and the checker's shared constants."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from forensics.io.dataset import is_dark_subject
from forensics.sensor.catalogue import PARTIAL, STUCK, DefectCatalogue

CLASSES = ("normal", "partial", "stuck")
NORMAL, PART, STK = 0, 1, 2
CHANNELS = ("pixel", "variance", "growth", "spatial")
#: Variance of rounding to integer DN.
QUANT_VAR = 1.0 / 12.0


def class_maps(catalogue: DefectCatalogue, shape: tuple[int, int], times: Sequence[float]) -> np.ndarray:
    """Pixel class (NORMAL / PART / STK) at each time, from a catalogue (stuck overrides)."""
    out = np.zeros((len(times), *shape), np.int8)
    for i, t in enumerate(times):
        eff = catalogue.effective(t)
        out[i][eff.y[eff.kind == PARTIAL], eff.x[eff.kind == PARTIAL]] = PART
        out[i][eff.y[eff.kind == STUCK], eff.x[eff.kind == STUCK]] = STK
    return out


def dark_groups(groups: Sequence) -> np.ndarray:
    """Boolean per group: taken without light (the manifest's ``subject`` is ``dark``), so its light is known
    to be zero and its prediction does not use the scene estimate."""
    return np.array([is_dark_subject(g.subject) for g in groups], bool)

