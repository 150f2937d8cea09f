"""Multiple testing: Holm's step-down adjustment (scipy has Benjamini–Hochberg, ``false_discovery_control``,
but no family-wise step-down method)."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def holm_adjusted(p: Sequence[float]) -> np.ndarray:
    """Holm's step-down adjusted p-values (Scand. J. Statist. 6, 1979): the family-wise error rate is held at
    α by rejecting where the adjusted value is below α.

    Examples
    --------
    >>> holm_adjusted([0.01, 0.04, 0.03]).round(3).tolist()
    [0.03, 0.06, 0.06]
    """
    p = np.asarray(p, float)
    order = np.argsort(p, kind="stable")
    m = p.size
    adj = np.empty(m)
    running = 0.0
    for rank, j in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p[j]))
        adj[j] = running
    return adj
