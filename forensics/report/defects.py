"""Figures and reports of sensor defects: detection, growth and dating.

Drawing and page layout only: each function takes the result objects of :mod:`forensics.defects`
(:class:`~forensics.defects.detection.DetectionResult`, :class:`~forensics.defects.growth.GrowthResult`,
:class:`~forensics.defects.growth.GrowthModel`, :class:`~forensics.defects.dating.SetDating` /
:class:`~forensics.defects.dating.ImageDating`) and returns a matplotlib figure or a :class:`Report`.
Nothing is re-estimated here; the only numbers computed are display aids (the Garwood error bars of
the plotted cumulative counts).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from forensics.defects.dating import ImageDating, SetDating
from forensics.defects.detection import DetectionResult
from forensics.defects.growth import GrowthModel, GrowthResult
from forensics.report.html import Report, new_figure
from forensics.sensor.catalogue import PARTIAL, STUCK
from forensics.stats.counts import garwood

__all__ = [
    "histogram_figure",
    "defect_map_figure",
    "detection_report",
    "counts_figure",
    "growth_report",
    "set_dating_figure",
    "likelihood_figure",
    "dating_report",
    "truth_counts_figure",
    "defects_demo_report",
]


# =========================================================================== detection
def histogram_figure(result: DetectionResult):
    """The accumulated histogram: pixels above each threshold, log scale, with τ and the normal expectation."""
    fig, ax = new_figure(6.4, 4.0)
    x = result.hist_thresholds
    unit = result.threshold_dict().get("units", "DN")  # ADU/s for a dark series' rates
    ax.step(x, np.maximum(result.hist_counts, 0.5), where="post", label="pixels with d̂ above x")
    ax.plot(x, np.maximum(result.hist_expected, 1e-3), "--", color="C2", label="normal model (robust fit)")
    for fit in result.fits[:1]:
        ax.axvline(fit.tau, color="C3", lw=1.5, label=f"τ = {fit.tau:.4g} {unit}")
    ax.set_yscale("log")
    ax.set_ylim(0.5, max(2.0, float(result.hist_counts.max()) * 2))
    ax.set_xlabel(f"threshold x on d̂ ({unit})")
    ax.set_ylabel("number of pixels with d̂ > x")
    ax.legend(fontsize=8)
    return fig


def defect_map_figure(result: DetectionResult, title: str = ""):
    """Where the defects are, over the analysed region."""
    h, w = result.shape
    fig, ax = new_figure(6.4, 6.4 * h / w + 0.6)
    if result.mask is not None:
        ax.imshow(result.mask, cmap="Greys_r", vmin=-1, vmax=1.5, interpolation="nearest")
    for kind, marker, colour, label in ((PARTIAL, "o", "C0", "partially stuck"), (STUCK, "s", "C3", "stuck")):
        sel = result.kind == kind
        ax.scatter(result.x[sel], result.y[sel], s=18, marker=marker, facecolors="none", edgecolors=colour,
                   label=f"{label} ({int(sel.sum())})")
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_title(title or "defect map (grey: analysed region)", fontsize=9)
    ax.legend(fontsize=8, loc="upper right")
    return fig


def detection_report(result: DetectionResult, title: str = "Defect detection", source: str = "") -> Report:
    """An HTML report of one detection: summary, threshold, accumulated histogram, map, table."""
    rep = Report(title)
    rep.text(f"{source + ': ' if source else ''}{result.n_images} images of {result.shape[1]}×{result.shape[0]}; "
             f"analysed region: {result.mask_spec.describe()} ({result.megapixels:.4g} MP). "
             f"Median kernel q = {result.q}.")
    for w in result.warnings:
        rep.text(w, note=True)
    rep.table(["channel", "center (DN)", "σ = 1.4826·MAD (DN)", "τ (DN)", "pixels"],
              [[f.name, f.center, f.scale, f.tau, f.n_pixels] for f in result.fits])
    rep.text(f"{result.count(PARTIAL)} partially stuck and {result.count(STUCK)} stuck pixels.")
    rep.figure(histogram_figure(result), "accumulated_histogram",
               "Accumulated histogram of d̂ = mean − median_q(mean): pixels above each threshold. Where the "
               "measured curve leaves the normal model is where defects begin; τ is marked.")
    rep.figure(defect_map_figure(result), "defect_map", "Detected defects over the analysed region.")
    rows = result.defect_rows()[:200]
    if rows:
        rep.table(list(rows[0]), [list(r.values()) for r in rows],
                  caption=None if len(result.x) <= 200 else f"first 200 of {len(result.x)}")
    return rep


# =========================================================================== growth
def counts_figure(result: GrowthResult):
    """Cumulative defects per epoch with Garwood 95 % intervals and the constant-rate fit."""
    fig, ax = new_figure(6.4, 4.0)
    t = np.asarray(result.dates)
    for kg, colour in ((result.partial, "C0"), (result.stuck, "C3")):
        cum = np.cumsum([kg.counts[0]] + kg.new)
        if cum.max() == 0:
            continue
        ci = np.array([garwood(int(c)) for c in cum])
        ax.errorbar(t, cum, yerr=[cum - ci[:, 0], ci[:, 1] - cum], fmt="o", color=colour, capsize=3,
                    label=f"{kg.kind}: cumulative count (Garwood 95 %)")
        grid = np.linspace(t[0], t[-1], 50)
        ax.plot(grid, cum[0] + kg.rate.rate * result.area_mp * (grid - t[0]), color=colour, lw=1,
                label=f"{kg.kind}: {kg.rate.rate:.3g} [{kg.rate.ci[0]:.3g}, {kg.rate.ci[1]:.3g}] /MP/yr")
        for lo in (kg.rate.ci[0], kg.rate.ci[1]):
            ax.plot(grid, cum[0] + lo * result.area_mp * (grid - t[0]), color=colour, lw=0.6, ls=":")
    ax.set_xlabel("capture date (year)")
    ax.set_ylabel("defects (first seen by each epoch)")
    ax.legend(fontsize=7)
    return fig


def growth_report(result: GrowthResult, title: str = "Defect growth", epochs: Sequence[Any] = ()) -> Report:
    """The growth estimates (rates, the paper's eq. 16–19, Chapman, trend test) and the counts figure; with
    ``epochs`` (the :class:`~forensics.defects.growth.Epoch` list the result came from), each epoch's
    accumulated histogram and defect map."""
    rep = Report(title)
    th = result.threshold
    rep.text(f"{len(result.dates)} epochs of {result.shape[1]}×{result.shape[0]} images, analysed region "
             f"{result.area_mp:.4g} MP, threshold {'σ = %g' % th['sigma'] if th.get('sigma') else 'τ given'} "
             f"(τ per epoch: {', '.join(f'{v:.4g}' for v in th['tau_per_epoch'])} DN), q = {th['q']}.")
    for w in result.warnings:
        rep.text(w, note=True)
    rows = []
    for kg in (result.partial, result.stuck):
        r = kg.rate
        rows.append([kg.kind, r.count, r.exposure, r.rate, f"[{r.ci[0]:.4g}, {r.ci[1]:.4g}]"])
    rep.table(["kind", "new defects", "MP·years", "rate (/MP/yr)", "95 % interval (Garwood)"], rows)
    p = result.paper
    rep.table(["paper (eq. 16–20)", "n₁", "n₂", "n_match", "γ", "λ_ps (eq. 17)", "λ_s (eq. 18)", "a_ps (eq. 19)"],
              [["first vs last epoch", p.n1, p.n2, p.n_match, p.gamma, p.lambda_ps, p.lambda_s, p.a_ps]])
    if result.partial.chapman:
        c = result.partial.chapman
        rep.text(f"Capture–recapture (Chapman), partially stuck: N̂ = {c.n_hat:.1f} defects at the last epoch "
                 f"(95 % [{c.ci[0]:.1f}, {c.ci[1]:.1f}]), detection efficiency n₂/N̂ = {c.efficiency:.2f}.")
    for kg in (result.partial, result.stuck):
        if kg.trend:
            tr = kg.trend
            rep.text(f"{kg.kind}: test of linear growth (constant rate): LR = {tr.lr_statistic:.2f}, "
                     f"p = {tr.p_value:.3g} → {'consistent' if tr.linear else 'rejected'}; dispersion "
                     f"{tr.dispersion:.2f}.")
    rep.figure(counts_figure(result), "growth_counts", "Cumulative defects against capture date with exact "
               "95 % intervals; lines: constant-rate fit and the rate's interval.")
    for i, ep in enumerate(epochs):
        rep.heading(f"Epoch {ep.date:.2f}: {ep.label}")
        rep.figure(histogram_figure(ep.detection), f"histogram_{i}", "Accumulated histogram of d̂ with τ.")
        rep.figure(defect_map_figure(ep.detection), f"map_{i}", "Detected defects.")
    return rep


# =========================================================================== dating
def set_dating_figure(model: GrowthModel, result: SetDating):
    """Reference counts against date, with the query's estimate and interval."""
    fig, ax = new_figure(6.4, 4.0)
    t = np.asarray(model.dates)
    cum = np.cumsum([model.counts["partial"][0] + model.counts["stuck"][0]]
                    + [a + b for a, b in zip(model.new["partial"], model.new["stuck"])])
    ax.plot(t, cum, "o-", label="reference epochs: defects first seen by then")
    lo, hi = result.interval
    lo_v = lo if lo is not None else min(t[0], result.estimate) - 1
    hi_v = hi if hi is not None else max(t[-1], result.estimate) + 1
    ax.axvspan(lo_v, hi_v, color="C1", alpha=0.25, label=f"query: {result.level:.0%} interval")
    ax.axvline(result.estimate, color="C1", lw=2, label=f"query estimate {result.estimate:.2f}")
    ax.set_xlabel("date (year)")
    ax.set_ylabel("defects")
    ax.legend(fontsize=8)
    return fig


def likelihood_figure(result: ImageDating):
    """Relative likelihood of each onset interval (single-image dating)."""
    fig, ax = new_figure(6.4, 3.6)
    post = result.posterior
    labels = []
    for lo, hi in result.intervals:
        labels.append(f"{'…' if lo is None else f'{lo:.1f}'}–{'…' if hi is None else f'{hi:.1f}'}")
    colours = ["C3" if j == result.best else "C0" for j in range(len(post))]
    ax.bar(range(len(post)), post, color=colours)
    ax.set_xticks(range(len(post)))
    ax.set_xticklabels(labels, rotation=45, ha="right", fontsize=7)
    ax.set_ylabel("relative likelihood")
    ax.set_xlabel("onset interval (date range)")
    return fig


def dating_report(model: GrowthModel, result: SetDating | ImageDating, query: str = "") -> Report:
    """The date of a query set (counts, figure) or image (likelihood of each onset interval)."""
    rep = Report("Dating from sensor defects")
    lo, hi = result.interval
    rng = f"[{'…' if lo is None else f'{lo:.3f}'}, {'…' if hi is None else f'{hi:.3f}'}]"
    rep.text(f"{query + ': ' if query else ''}estimated capture date {result.estimate:.3f} (interval {rng}). "
             f"Reference epochs: {', '.join(f'{d:.2f}' for d in model.dates)}; catalogue of "
             f"{len(model.catalogue)} defects; analysed area {model.area_mp:.4g} MP.")
    for w in result.warnings:
        rep.text(w, note=True)
    if isinstance(result, SetDating):
        rep.text(f"Position: {result.position}. Method: {result.method}.")
        rep.table(["quantity", "value"], [[k, v] for k, v in result.counts.items()])
        rep.figure(set_dating_figure(model, result), "set_dating", "Reference defect counts and the query's date.")
    else:
        rep.figure(likelihood_figure(result), "dating_likelihood",
                   "Relative likelihood of each onset interval (Fridrich–Goljan); red: the maximum.")
        rep.table(["interval", "from", "to", "log-likelihood"],
                  [[j, lo_ if lo_ is not None else "…", hi_ if hi_ is not None else "…", ll]
                   for j, ((lo_, hi_), ll) in enumerate(zip(result.intervals, result.log_likelihood))])
    return rep


# =========================================================================== the demo's defects section
def truth_counts_figure(result: GrowthResult, true_dates: Sequence[float], true_counts: Sequence[int]):
    """Estimated cumulative partially-stuck counts (first appearances) against the simulated truth."""
    fig, ax = new_figure(6.4, 3.2)
    ax.plot(list(true_dates), list(true_counts), "s--", color="0.4", label="true (above τ)")
    cum = np.cumsum([result.partial.counts[0]] + result.partial.new)
    ax.plot(result.dates, cum, "o-", label="estimated (first appearances)")
    ax.set_xlabel("year")
    ax.set_ylabel("partially stuck defects")
    ax.legend(fontsize=8)
    return fig


def defects_demo_report(title: str, intro: str, *, epochs: Sequence[Any], growth: GrowthResult, model: GrowthModel,
                        dated: SetDating, truth: dict[str, Any], query_true: float) -> Report:
    """The demo's defects section: detection at two epochs, the growth rate against the truth, a dated set.

    ``truth`` holds what the simulation knows: ``recall``, ``precision`` (of the last epoch's detection),
    ``true_rate`` (rate above the threshold), ``rate_partial`` (λ for all amplitudes), ``dates`` and
    ``counts`` (true partially-stuck counts above the threshold at the reference epochs).
    """
    det = epochs[-1].detection
    rep = Report(title)
    rep.text(intro)
    rep.heading("Detection at two epochs")
    for ep in (epochs[0], epochs[-1]):
        d = ep.detection
        rep.text(f"{ep.date:.0f}: {d.count()} defects, τ = {d.tau:.4g} DN = median + 5·1.4826·MAD of d̂ over "
                 f"{d.megapixels:.3g} MP (centre 30 % left out).")
    rep.figure(histogram_figure(det), "histogram", "Accumulated histogram of d̂ at the last reference epoch: "
               "pixels above each threshold; the dashed line is the normal model fitted to the bulk.")
    rep.figure(defect_map_figure(det), "map", f"Defects detected at {epochs[-1].date:.0f}.")
    rep.text(f"Against the truth at {epochs[-1].date:.0f}: recall {truth['recall']:.2f} for defects 3σ above τ, "
             f"precision {truth['precision']:.2f}.")
    rep.heading("Growth rate")
    r = growth.partial.rate
    rep.text(f"Partially stuck: {r.rate:.3g} defects/MP/year, exact 95 % interval [{r.ci[0]:.3g}, {r.ci[1]:.3g}] "
             f"(threshold {det.sigma:g}σ); true rate above that threshold {truth['true_rate']:.3g} "
             f"(λ = {truth['rate_partial']:.3g} for all amplitudes). The paper's eq. 17 on the first and last epoch "
             f"gives {growth.paper.lambda_ps:.3g} (γ = {growth.paper.gamma:.2f}).")
    rep.figure(counts_figure(growth), "growth", "Defects first seen by each epoch with Garwood intervals and the "
               "fitted rate.")
    rep.figure(truth_counts_figure(growth, truth["dates"], truth["counts"]), "truth",
               "Estimated and true counts of defects above the threshold.")
    rep.heading("Dating a query set")
    lo, hi = dated.interval
    rep.text(f"The query set was taken in {query_true:g}; estimated {dated.estimate:.2f}, 95 % interval "
             f"[{lo if lo is None else round(lo, 2)}, {hi if hi is None else round(hi, 2)}] ({dated.method}).")
    rep.figure(set_dating_figure(model, dated), "dating", "Reference counts and the query's date with its interval.")
    return rep
