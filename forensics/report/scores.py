"""Figures of score statistics: DET curves and genuine/impostor score histograms.

Drawing only: every number comes from :mod:`forensics.stats.scores` (``det_curve``, ``eer``); the
functions draw on a matplotlib Axes the caller made with :func:`forensics.report.html.new_figure`.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from forensics.stats.scores import DetCurve, EerResult, as_scores

__all__ = ["plot_det", "plot_score_histograms"]


_DET_TICKS = (0.0001, 0.001, 0.01, 0.02, 0.05, 0.1, 0.2, 0.4, 0.6, 0.8, 0.9, 0.95, 0.98, 0.99, 0.999, 0.9999)


def _percent_label(p: float) -> str:
    return f"{100 * p:g}"


def plot_det(
    ax: Any,
    curve: DetCurve,
    *,
    label: str | None = None,
    eer_point: EerResult | float | None = None,
    **line_kwargs: Any,
) -> Any:
    """Draw a DET curve on a matplotlib Axes (probit axes labelled in percent).

    Parameters
    ----------
    ax : matplotlib.axes.Axes
        Where to draw; no pyplot state is used.
    curve : DetCurve
        From :func:`det_curve`.
    label : str, optional
        Legend label of the curve.
    eer_point : EerResult or float, optional
        Marks the EER on the diagonal.
    **line_kwargs
        Passed to ``ax.plot``.

    Returns
    -------
    matplotlib.lines.Line2D
        The curve.
    """
    from scipy.stats import norm

    (line,) = ax.plot(curve.far_probit, curve.frr_probit, label=label, **line_kwargs)
    if eer_point is not None:
        e = eer_point.eer if isinstance(eer_point, EerResult) else float(eer_point)
        if 0.0 < e < 1.0:
            z = float(norm.ppf(e))
            ax.plot([z], [z], "o", color=line.get_color(), markersize=5)
    both = np.concatenate([curve.far_probit, curve.frr_probit])
    lo = float(np.min(both, initial=np.inf))
    hi = float(np.max(both, initial=-np.inf))
    ticks = [p for p in _DET_TICKS if (lo - 0.5) <= norm.ppf(p) <= (hi + 0.5)] or list(_DET_TICKS)
    z = norm.ppf(ticks)
    for set_ticks, set_labels in ((ax.set_xticks, ax.set_xticklabels), (ax.set_yticks, ax.set_yticklabels)):
        set_ticks(z)
        set_labels([_percent_label(p) for p in ticks])
    ax.plot([z[0], z[-1]], [z[0], z[-1]], ls=":", color="0.6", lw=0.8)
    ax.set_xlabel("False accept rate (%)")
    ax.set_ylabel("False reject rate (%)")
    ax.grid(True, alpha=0.3)
    return line


def plot_score_histograms(
    ax: Any,
    genuine: ArrayLike,
    impostor: ArrayLike,
    threshold: float | None = None,
    *,
    bins: int = 60,
) -> None:
    """Genuine and impostor score densities on shared bins, with an optional threshold line.

    Parameters
    ----------
    ax : matplotlib.axes.Axes
        Where to draw; no pyplot state is used.
    genuine, impostor : array_like
        Same-source and different-source scores.
    threshold : float, optional
        Drawn as a vertical dashed line (e.g. ``eer(...).threshold``).
    bins : int
        Number of shared bins over the finite score range.
    """
    g = as_scores(genuine, "genuine")
    i = as_scores(impostor, "impostor")
    pooled_finite = [x[np.isfinite(x)] for x in (g, i)]
    lo = min((float(x.min()) for x in pooled_finite if x.size), default=0.0)
    hi = max((float(x.max()) for x in pooled_finite if x.size), default=1.0)
    if hi <= lo:
        lo, hi = lo - 0.5, hi + 0.5
    edges = np.linspace(lo, hi, bins + 1)
    for x, name, color in ((g, "genuine", "C0"), (i, "impostor", "C3")):
        counts, _ = np.histogram(x, bins=edges, density=True)
        ax.stairs(counts, edges, label=f"{name} (n={x.size:,})", color=color, fill=False)
    if threshold is not None and math.isfinite(threshold):
        ax.axvline(threshold, ls="--", color="0.3", lw=1, label=f"threshold {threshold:.4g}")
    ax.set_xlabel("score")
    ax.set_ylabel("density")
    ax.legend(frameon=False)
