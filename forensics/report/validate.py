"""Figures and the report of a validation run on simulated ground truth (:mod:`forensics.validate`).

Drawing only: every number comes from the :class:`~forensics.validate.trials.ValidationResult`; the
grey reference curve of the recall figure is the normal model's expectation Φ(a/σ − τ/σ).
"""
from __future__ import annotations

import numpy as np
from scipy import stats

from forensics.report.html import Report, new_figure
from forensics.validate.trials import ACCEPT_COVERAGE, NOMINAL, ValidationResult

__all__ = ["coverage_figure", "recall_figure", "validation_report"]


def coverage_figure(result: ValidationResult):
    """Observed coverage / proportions with exact 95 % intervals, against the acceptance band."""
    props = [m for m in result.metrics if m.ci is not None and 0 <= m.value <= 1 and "bias" not in m.name]
    fig, ax = new_figure(7.0, 0.5 + 0.45 * max(len(props), 1))
    for i, m in enumerate(props):
        colour = "C2" if m.passed else ("C3" if m.passed is False else "C0")
        ax.errorbar([m.value], [i], xerr=[[m.value - m.ci[0]], [m.ci[1] - m.value]], fmt="o", color=colour,
                    capsize=3)
    ax.axvspan(*ACCEPT_COVERAGE, color="C2", alpha=0.15, label="coverage acceptance [0.92, 0.98]")
    ax.axvline(NOMINAL, color="C2", lw=1)
    ax.set_yticks(range(len(props)))
    ax.set_yticklabels([m.name for m in props], fontsize=7)
    ax.set_xlim(min(0.5, min((m.ci[0] for m in props), default=0.5)) - 0.02, 1.01)
    ax.set_xlabel("proportion over trials (exact 95 % interval)")
    ax.legend(fontsize=7, loc="lower left")
    return fig


def recall_figure(result: ValidationResult):
    """Detection recall against amplitude (σ units of d̂), with the normal-model expectation Φ(a/σ − τ/σ)."""
    curve = result.curves.get("recall_vs_amplitude_sigma", [])
    fig, ax = new_figure(6.4, 3.6)
    xs = [c[0] for c in curve if c[2] is not None]
    ys = [c[2] for c in curve if c[2] is not None]
    ax.plot(xs, ys, "o-")
    ax.axvline(result.settings.sigma, color="C3", lw=1, label=f"τ = {result.settings.sigma:g}σ")
    ax.axvline(result.settings.amp_sigma, color="C2", lw=1, ls="--", label=f"{result.settings.amp_sigma:g}σ")
    x = np.linspace(0, 16, 200)
    ax.plot(x, stats.norm.cdf(x - result.settings.sigma), color="0.5", lw=0.8, label="Φ(a/σ − τ/σ)")
    ax.set_xlabel("defect amplitude / σ of d̂")
    ax.set_ylabel("recall")
    ax.legend(fontsize=8)
    return fig


def validation_report(result: ValidationResult) -> Report:
    """The metrics table and the coverage (and, for defects, recall) figures of a validation run."""
    rep = Report(f"Validation on simulated ground truth: {result.what}")
    s = result.settings
    rep.text(f"{result.trials} trials, seed {result.seed}; sensor {s.sensor} ({s.bit_depth}-bit, "
             f"{s.shape[1]}×{s.shape[0]}, rates ×{s.rate_scale():.4g}, read noise {s.read_noise:g} DN), "
             f"{s.images} images per epoch, q = {s.q}, τ = {s.sigma:g}σ.")
    rep.table(["quantity", "trials", "value", "95 % interval", "acceptance", ""], result.table())
    rep.figure(coverage_figure(result), "coverage", "Coverage and proportions with exact 95 % intervals; green band: "
               "the acceptance range for interval coverage.")
    if result.what == "defects":
        rep.figure(recall_figure(result), "recall", "Detection recall against amplitude in units of σ of d̂, with "
                   "the normal-model expectation Φ(a/σ − τ/σ).")
    return rep
