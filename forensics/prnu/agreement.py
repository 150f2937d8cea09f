"""Agreement of a clustering with known labels: purity, inverse purity (completeness) and the adjusted Rand
index (SciPy has none of them), for measuring :func:`forensics.prnu.cluster.cluster_images` on data with
known devices.  An unattributed image (label None) is a cluster of its own.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from forensics._shared.errors import UsageError

__all__ = ["adjusted_rand_index", "completeness", "purity"]


def _contingency(truth: Sequence[Any], labels: Sequence[Any]) -> np.ndarray:
    """Counts of (true class, cluster); a label None is a cluster of its own (an unattributed image)."""
    if len(truth) != len(labels):
        raise UsageError(f"{len(truth)} true labels for {len(labels)} cluster labels; give one of each per image")
    own = [("__single__", i) if lab is None else ("__label__", lab) for i, lab in enumerate(labels)]
    _, t = np.unique(np.array([str(x) for x in truth], dtype=object), return_inverse=True)
    cluster_ids: dict[Any, int] = {}
    c = np.array([cluster_ids.setdefault(key, len(cluster_ids)) for key in own])
    table = np.zeros((int(t.max()) + 1 if len(t) else 0, len(cluster_ids)), np.int64)
    np.add.at(table, (t, c), 1)
    return table


def purity(truth: Sequence[Any], labels: Sequence[Any]) -> float:
    """Share of images whose cluster's majority class is their own class: ``Σ_c max_k n_ck / n``.

    ``labels`` None marks an unattributed image, counted as a cluster of its own (always pure).
    """
    table = _contingency(truth, labels)
    return float(table.max(axis=0).sum() / max(1, table.sum()))


def completeness(truth: Sequence[Any], labels: Sequence[Any]) -> float:
    """Inverse purity: share of images in their class's largest cluster, ``Σ_k max_c n_ck / n``.

    An unattributed image (label None) is a cluster of its own, so leaving images out lowers it.
    """
    table = _contingency(truth, labels)
    return float(table.max(axis=1).sum() / max(1, table.sum()))


def adjusted_rand_index(truth: Sequence[Any], labels: Sequence[Any]) -> float:
    """Hubert & Arabie's adjusted Rand index (1: identical partitions, about 0: chance agreement).

    Unattributed images (label None) are singletons.  Two partitions that are both all singletons (or
    both one cluster) agree perfectly: 1.
    """
    table = _contingency(truth, labels)
    n = int(table.sum())

    def pairs(x: np.ndarray) -> float:
        return float((x * (x - 1) // 2).sum())

    index = pairs(table)
    a, b = pairs(table.sum(axis=1)), pairs(table.sum(axis=0))
    total = n * (n - 1) / 2
    expected = a * b / total if total else 0.0
    top = (a + b) / 2
    if top == expected:
        return 1.0
    return float((index - expected) / (top - expected))
