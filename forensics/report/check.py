"""The model check's report: tables, residual maps, residuals against every covariate, defect counts against
time with the model's band, Ripley's L with its envelope (it draws a :class:`~forensics.check.CheckResult`,
never recomputes)."""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from forensics.check.classes import CHANNELS, CLASSES
from forensics.check.diagnosis import FLAG_DBIC
from forensics.check.result import CheckResult
from forensics.check.select import SelectionResult
from forensics.check.tiles import TiledCheck, tile_dispersion
from forensics.report.html import Report, new_figure
from forensics.sensor.catalogue import PARTIAL, STUCK


def _label(ax: Any, xlabel: str, ylabel: str, title: str) -> None:
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)


def _symlog(v: float) -> float:
    return math.copysign(math.log10(1 + abs(v)), v)


def check_report(result: CheckResult, title: str = "Model check") -> Report:
    """An HTML report of a check: tables, residual maps, residuals against every covariate, defect counts
    against time with the model's band, Ripley's L with its envelope; with a baseline, before and after side by
    side."""
    rep = Report(title)
    _check_sections(rep, result)
    return rep


def _check_sections(rep: Report, result: CheckResult) -> None:
    """Every section of :func:`check_report`, added to ``rep``."""
    runs = [("before", result.baseline), ("after", result)] if result.baseline is not None else [("model", result)]
    _summary(rep, result, runs)
    _numbers(rep, result, runs)
    _residual_maps(rep, result, runs)
    _covariates(rep, result, runs)
    structure_section(rep, result, runs)
    _variance(rep, result, runs)
    _counts(rep, result, runs)
    _ripley(rep, result, runs)
    _checks(rep, result, runs)


def selection_report(selection: SelectionResult, title: str = "Model check: forward selection") -> Report:
    """An HTML report of forward selection (``--auto``): the path as a table and a ladder plot (error and
    goodness of fit at every step), then every section of :func:`check_report` for the final model (before:
    the starting model)."""
    rep = Report(title)
    rep.heading("Forward selection")
    rep.text("Path: " + " → ".join(s.label for s in selection.steps) + f". Stopped: {selection.stopped}.")
    rows = []
    for s in selection.steps:
        rows.append([s.label, *[_num(s.error[k]) for k in ("pixel", "variance", "growth")],
                     *[_num(s.gof[k]) for k in CHANNELS], ", ".join(s.flagged) or "—",
                     "; ".join(a.reason for a in s.rejected) or ""])
    rep.table(["step", "error.pixel", "error.variance", "error.growth", *[f"gof.{k} (p)" for k in CHANNELS],
               "flagged", "tried, not kept"], rows)
    for a in selection.rejected:
        rep.text(f"Tried and not kept: {a.reason}", note=True)
    _ladder(rep, selection)
    rep.heading(f"Final model: {' + '.join(selection.result.effects)}")
    _check_sections(rep, selection.result)
    return rep


def _ladder(rep: Report, selection: SelectionResult) -> None:
    """Error (log scale) and goodness-of-fit p-values (log scale) at every step of the path."""
    steps = selection.steps
    x = np.arange(len(steps))
    labels = [s.label for s in steps]
    fig, axes = new_figure(4.0 + 1.2 * len(steps), 3.4, ncols=2)
    ax = axes[0]
    for key, colour, label in (("pixel", "C0", "pixel (1 = noise floor)"), ("variance", "C1", "variance (RMS ln)"),
                               ("growth", "C2", "growth (deviance/df)")):
        y = np.array([np.nan if s.error[key] is None else s.error[key] for s in steps], dtype=float)
        if np.any(np.isfinite(y) & (y > 0)):
            ax.plot(x, np.where(y > 0, y, np.nan), "o-", color=colour, label=label)
    ax.axhline(1.0, color="k", lw=0.6, ls=":")
    ax.set_yscale("log")
    ax.set_xticks(x, labels, rotation=20, fontsize=8)
    _label(ax, "step", "held-out error", "error at each step")
    ax.legend(fontsize=7)
    ax = axes[1]
    floor = 1e-16
    for k, key in enumerate(CHANNELS):
        y = np.array([np.nan if s.gof[key] is None else max(s.gof[key], floor) for s in steps], dtype=float)
        ax.plot(x, y, "o-", color=f"C{k}", label=key)
    ax.axhline(0.01, color="k", lw=0.6, ls=":")
    ax.set_yscale("log")
    ax.set_ylim(floor / 3, 2.0)
    ax.set_xticks(x, labels, rotation=20, fontsize=8)
    _label(ax, "step", "goodness-of-fit p", "goodness of fit at each step")
    ax.legend(fontsize=7)
    rep.figure(fig, "ladder", "The forward-selection path: each step adds the top flagged candidate and refits. "
               "Left: held-out error per channel (log scale; dotted: 1 = the pixel channel's noise floor). Right: "
               "goodness-of-fit p-values (log scale, floored at 1e-16; dotted: 0.01).")


def _summary(rep: Report, result: CheckResult, runs: list[tuple[str, CheckResult]]) -> None:
    """Size of the data, the model and the warnings."""
    data = result.data
    rep.text(f"{data['frames']} frames of {data['size'][0]}×{data['size'][1]} pixels (full scale "
             f"{data['full_scale']:g} DN), {data['conditions']} conditions ({data['repeated_conditions']} with repeated "
             f"frames), {len(data['epochs'])} epochs, {data['light_levels']} light levels; "
             f"{data['classes']['partial']} partially stuck and {data['classes']['stuck']} stuck pixels at the last epoch.")
    rep.text("Model: " + " + ".join(result.effects)
             + (f" (before: {' + '.join(result.baseline.effects)})" if result.baseline is not None else ""))
    for w in result.warnings:
        rep.text("Warning: " + w, note=True)


def _numbers(rep: Report, result: CheckResult, runs: list[tuple[str, CheckResult]]) -> None:
    """Error and goodness of fit, before and after; the fitted parameters; the ranked candidates."""
    rep.heading("Error and goodness of fit")
    header = ["", *[name for name, _ in runs]]
    rows = []
    for key, label in (("pixel", "error.pixel (held-out; 1 = noise floor)"),
                       ("variance", "error.variance (RMS ln obs/pred)"),
                       ("growth", "error.growth (deviance/df)")):
        rows.append([label, *[_num(r.error[key]) for _, r in runs]])
    for cls in CLASSES:
        rows.append([f"  class {cls}", *[_num(r.error["classes"][cls]) for _, r in runs]])
    for key in CHANNELS:
        rows.append([f"gof.{key} (p)", *[_num(r.gof[key]) for _, r in runs]])
    rep.table(header, rows)
    rep.heading("Fitted parameters")
    rep.table(["effect", "parameter", "value", "standard error", "unit"],
              [[p.effect, p.name, p.value if p.identifiable and p.converged and not p.bound else p.summary(),
                "—" if p.se is None or p.bound else p.se, p.unit] for p in result.params]
              + [[p.effect, f"{p.name} (pattern, {p.blocks} blocks)", p.rms, "rms", p.hyper or ""]
                 for p in result.patterns]
              + [[p.effect, f"{p.name} (size in the frames, split halves)", p.size, p.size_se, ""]
                 for p in result.patterns if p.size is not None])
    q = getattr(result, "quantiser", None)
    if q and q.get("compared"):
        # the converter the variance channel shows, and how clearly (its χ² under each converter compared)
        rep.table(["converter", "uniform dither before rounding (DN)", "variance χ² under each converter"],
                  [["rounding, dithered" if q["dither"] else "rounding, no dither", q["dither"],
                    "; ".join(f"{k}: {v:.5g}" for k, v in q["variance_chi2"].items())]])
    rep.heading("Candidates")
    for name, r in runs:
        rep.table(["rank", "effect", "predicted ΔBIC", "ΔBIC as far as both halves show it", "p (Holm)", "flagged",
                   "evidence"],
                  [[i + 1, c.effect, c.delta_bic, "" if c.delta_bic_confirmed is None else c.delta_bic_confirmed, c.p,
                    "yes" if c.flagged else "", c.evidence]
                   for i, c in enumerate(r.candidates)], caption=name)
    if result.candidates or (result.baseline and result.baseline.candidates):
        fig, axes = new_figure(5.0 * len(runs), 3.2, ncols=len(runs))
        axes = np.atleast_1d(axes)
        for ax, (name, r) in zip(axes, runs):
            cands = r.candidates
            vals = [_symlog(c.delta_bic) for c in cands]
            colours = ["C3" if c.flagged else "C7" for c in cands]
            ax.barh(range(len(cands)), vals, color=colours)
            ax.set_yticks(range(len(cands)), [c.effect for c in cands], fontsize=8)
            ax.invert_yaxis()
            ax.axvline(_symlog(FLAG_DBIC), color="k", lw=0.8, ls=":")
            ax.set_xlabel("predicted ΔBIC (sign · log10(1 + |ΔBIC|))")
            ax.set_title(name)
        rep.figure(fig, "candidates", "Candidates ranked by predicted ΔBIC; red: flagged (ΔBIC > 10 — for a fixed "
                   "pattern also as far as both halves of the repeats show it — and Holm p < 0.01); dotted: ΔBIC = 10.")


def _residual_maps(rep: Report, result: CheckResult, runs: list[tuple[str, CheckResult]]) -> None:
    """Per-pixel maps: held-out RMS residual, mean residual, per-pixel consistency."""
    rep.heading("Where the model fails: pixels")
    fig, axes = new_figure(4.2 * len(runs), 10.5, ncols=len(runs), nrows=3)
    axes = np.asarray(axes).reshape(3, len(runs))
    lim_r = max(float(np.nanpercentile(np.abs(r.plots.residual_map), 99.5)) for _, r in runs) or 1.0
    for j, (name, r) in enumerate(runs):
        im = axes[0, j].imshow(r.plots.rms_map, cmap="magma", vmin=0, vmax=3, interpolation="nearest")
        axes[0, j].set_title(f"{name}: held-out RMS residual / noise floor", fontsize=9)
        fig.colorbar(im, ax=axes[0, j], shrink=0.8)
        im = axes[1, j].imshow(r.plots.residual_map, cmap="RdBu_r", vmin=-lim_r, vmax=lim_r, interpolation="nearest")
        axes[1, j].set_title(f"{name}: mean held-out residual (DN)", fontsize=9)
        fig.colorbar(im, ax=axes[1, j], shrink=0.8)
        im = axes[2, j].imshow(r.plots.consistency_map, cmap="RdBu_r", vmin=-5, vmax=5, interpolation="nearest")
        axes[2, j].set_title(f"{name}: per-pixel consistency z", fontsize=9)
        fig.colorbar(im, ax=axes[2, j], shrink=0.8)
        for ax in axes[:, j]:
            ax.set_xticks([])
            ax.set_yticks([])
    rep.figure(fig, "residual_maps", "Top: each pixel's held-out residual relative to its noise floor (RMS over "
               "conditions; 1 = at the floor): misfitting pixels light up. Middle: the held-out residual averaged "
               "over conditions. Bottom: the in-sample residual's component that is the same in every condition, "
               "standardised (a fixed pattern the model lacks shows as structure: stripes, speckle, rings).")


def _covariates(rep: Report, result: CheckResult, runs: list[tuple[str, CheckResult]]) -> None:
    """Held-out residuals against every covariate, per pixel class."""
    covs = list(result.plots.covariates)
    fig, axes = new_figure(3.0 * len(covs), 3.2, ncols=len(covs))
    axes = np.atleast_1d(axes)
    styles = {"before": dict(ls="--", alpha=0.6), "after": dict(ls="-"), "model": dict(ls="-")}
    for ax, cname in zip(axes, covs):
        for name, r in runs:
            entry = r.plots.covariates.get(cname, {})
            for k, klass in enumerate(("normal", "partial")):
                if klass not in entry:
                    continue
                e = entry[klass]
                ax.errorbar(e["x"], e["mean"], yerr=1.96 * e["se"], color=f"C{k}", marker="o", ms=3, capsize=2,
                            label=f"{klass} ({name})", **styles[name])
        ax.axhline(0, color="k", lw=0.6)
        ax.set_xlabel(cname, fontsize=8)
        ax.set_ylabel("held-out residual (DN)", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0].legend(fontsize=6)
    rep.figure(fig, "covariates", "Held-out residuals against every covariate (mean ± 95 % per bin), per pixel "
               "class: a missing effect shows as a trend with the covariates it depends on.")


def structure_section(rep: Report, result: CheckResult, runs: list[tuple[str, CheckResult]] | None = None) -> None:
    """Residual structure no fitted effect explains: the named structure, every test in a table, the row,
    column and radial profiles with their null band, and the per-condition trends."""
    runs = runs or [("model", result)]
    runs = [(name, r) for name, r in runs if r.structure is not None and r.structure.tests]
    if not runs:
        return
    rep.heading("Where the model fails: structure nobody's catalogue covers")
    for name, r in runs:
        st = r.structure
        rep.text(f"{name}: " + (f"unexplained structure — {st.named.summary()}." if st.named is not None else
                                "no structure named (every Holm-adjusted p ≥ 0.001).") + "".join(f" {n}." for n in st.notes))
        rep.table(["test", "statistic", "df", "p", "Holm p", "size", "unit", "pattern rms (DN)", "share"],
                  [[t.label, t.statistic, t.df, t.p, t.p_holm, t.size, t.unit, _num(t.pattern_rms), _num(t.share)]
                   for t in st.tests], caption=f"{name}: structure tests (what each can see: see below)")
    sees = {t.kind: t.sees for _, r in runs for t in r.structure.tests}
    rep.text(" ".join(f"{k}: {v}." for k, v in sees.items()), note=True)
    structure_profiles(rep, runs)
    structure_trends(rep, runs)


def structure_profiles(rep: Report, runs: list[tuple[str, CheckResult]]) -> None:
    """Column, row and radial profiles of the residual with their ±2σ null band, one row of panels per run."""
    kinds = [("column", "column (px)"), ("row", "row (px)"), ("radial", "distance from the frame centre (px)")]
    fig, axes = new_figure(4.0 * len(kinds), 3.0 * len(runs), ncols=len(kinds), nrows=len(runs))
    axes = np.asarray(axes).reshape(len(runs), len(kinds))
    for i, (name, r) in enumerate(runs):
        profiles = (r.structure.plots or {}).get("profiles", {})
        for j, (kind, xlabel) in enumerate(kinds):
            ax = axes[i, j]
            pl = profiles.get(kind)
            if pl is None:
                ax.set_axis_off()
                continue
            band = 2 * pl["null_sd"]
            ax.fill_between(pl["x"], -band, band, color="0.8", step="mid", label="±2σ of noise")
            ax.plot(pl["x"], pl["profile"], color="C3", lw=0.8, drawstyle="steps-mid", label="mean residual")
            ax.axhline(0, color="k", lw=0.5)
            t = next((t for t in r.structure.tests if t.kind == kind), None)
            title = f"{name}: {kind}" + ("" if t is None else f" (Holm p = {t.p_holm:.2g})")
            _label(ax, xlabel, "mean residual (DN)", title)
    axes[0, 0].legend(fontsize=6)
    rep.figure(fig, "structure_profiles", "The residual (both halves, normal pixels, mean over conditions) averaged "
               "per column, per row and per 1-pixel ring of distance from the frame centre, with the ±2σ band pure "
               "noise would fill. Smooth profiles are removed by the scene estimate and cannot show here.")


def structure_trends(rep: Report, runs: list[tuple[str, CheckResult]]) -> None:
    """Per-condition mean residual and held-out error² against each covariate, with the fitted line."""
    keys = sorted({k for _, r in runs for k in (r.structure.plots or {}).get("trends", {})})
    if not keys:
        return
    ncols = min(len(keys), 5)
    nrows = math.ceil(len(keys) / ncols)
    fig, axes = new_figure(3.0 * ncols, 2.8 * nrows, ncols=ncols, nrows=nrows)
    axes = np.atleast_1d(axes).ravel()
    for ax, key in zip(axes, keys):
        for k, (name, r) in enumerate(runs):
            tr = r.structure.plots["trends"].get(key)
            if tr is None:
                continue
            x = np.asarray(tr["x"])
            ax.plot(x, tr["y"], "o", ms=3, color=f"C{k}", label=name)
            xs = np.array([x.min(), x.max()])
            ax.plot(xs, tr["intercept"] + tr["slope"] * xs, color=f"C{k}", lw=0.8)
        kind, cov = key.split(": ", 1)
        _label(ax, cov, "mean residual (DN)" if kind == "trend" else "held-out error²", kind)
        ax.tick_params(labelsize=7)
    for ax in axes[len(keys):]:
        ax.set_axis_off()
    axes[0].legend(fontsize=6)
    rep.figure(fig, "structure_trends", "Per repeated condition: the mean residual of normal pixels (trend) and "
               "their held-out error² (misfit trend) against each covariate, with the least-squares line.")


def _variance(rep: Report, result: CheckResult, runs: list[tuple[str, CheckResult]]) -> None:
    """Observed against predicted temporal variance."""
    fig, axes = new_figure(4.2 * len(runs), 3.2, ncols=len(runs))
    axes = np.atleast_1d(axes)
    for ax, (name, r) in zip(axes, runs):
        v = r.plots.variance
        if len(v["level"]):
            ratio = np.log(v["observed"] / v["predicted"])
            ax.errorbar(v["level"], ratio, yerr=1.96 * np.sqrt(2 / v["df"]), fmt="o", ms=3, capsize=2)
        ax.axhline(0, color="k", lw=0.6)
        _label(ax, "mean signal (DN)", "ln(observed / predicted variance)", name)
    rep.figure(fig, "variance", "Temporal variance from repeated frames against the model's prediction, per "
               "condition and signal level.")


def _counts(rep: Report, result: CheckResult, runs: list[tuple[str, CheckResult]]) -> None:
    """Defect counts against time with the model's band."""
    rep.heading("Where the model fails: defects")
    fig, axes = new_figure(4.2 * len(runs), 3.4, ncols=len(runs))
    axes = np.atleast_1d(axes)
    for ax, (name, r) in zip(axes, runs):
        c = r.plots.counts
        t = np.asarray(c["times"])
        for kind, colour, label in ((PARTIAL, "C0", "partially stuck"), (STUCK, "C3", "stuck")):
            if "band" in c:
                lo, hi = c["band"][kind]
                ax.fill_between(t, lo, hi, color=colour, alpha=0.2)
            ax.plot(t, c["expected"][kind], color=colour, lw=1)
            ax.plot(t, c["observed"][kind], "o", color=colour, ms=4, label=label)
        _label(ax, "capture time (year)", "defects detected (cumulative)", name)
        ax.legend(fontsize=7)
    rep.figure(fig, "counts", "Defects detected by each epoch (points) against the fitted arrival model (line) "
               "and its 95 % Monte-Carlo band.")


def _ripley(rep: Report, result: CheckResult, runs: list[tuple[str, CheckResult]]) -> None:
    """Ripley's L of the defect sites with the fitted model's envelope."""
    if result.plots.ripley.get("radii") is not None:
        fig, axes = new_figure(4.2 * len(runs), 3.4, ncols=len(runs))
        axes = np.atleast_1d(axes)
        for ax, (name, r) in zip(axes, runs):
            rp = r.plots.ripley
            if rp.get("radii") is None:
                continue
            rr = np.asarray(rp["radii"])
            if "lo" in rp:
                ax.fill_between(rr, rp["lo"] - rr, rp["hi"] - rr, color="C7", alpha=0.3, label="95 % envelope")
                ax.plot(rr, rp["mean"] - rr, color="C7", lw=1, label="fitted model (mean)")
            ax.plot(rr, rp["observed"] - rr, "o-", color="C0", ms=3, label="observed")
            ax.axhline(0, color="k", lw=0.6)
            _label(ax, "r (pixels)", "L(r) − r", name)
            ax.legend(fontsize=7)
        rep.figure(fig, "ripley", "Ripley's L of the defect sites at the last epoch (translation edge correction) "
                   "against simulations of the fitted arrival model: above the envelope means clustering.")


def _checks(rep: Report, result: CheckResult, runs: list[tuple[str, CheckResult]]) -> None:
    """The table of checks of each run."""
    rep.heading("Checks")
    for name, r in runs:
        rep.table(["statistic", "measured", "predicted", "z"],
                  [[c.statistic, c.measured, c.predicted, "—" if c.z is None else c.z] for c in r.checks],
                  caption=name)


def _num(v: Any) -> Any:
    return "—" if v is None else v


def tiles_report(tiled: TiledCheck, selection: SelectionResult | None = None,
                 title: str = "Model check in tiles") -> Report:
    """An HTML report of a whole frame checked in tiles (:func:`~forensics.check.tiles.check_tiles`): with
    ``selection`` (``--auto`` on the central tile) its path first, then the combined parameters with their
    heterogeneity tests, a map of every parameter's value per tile in standard errors from the combined value,
    and a map of the held-out error per tile."""
    rep = Report(title)
    if selection is not None:
        rep.heading("Forward selection on the central tile")
        rep.text("Path: " + " → ".join(s.label for s in selection.steps) + f". Stopped: {selection.stopped}.")
        _ladder(rep, selection)
    h, w = tiled.shape
    rep.heading("Whole frame in tiles")
    rep.text(f"{w}×{h} pixels in {len(tiled.tiles)} tiles of about {tiled.size}×{tiled.size}, each checked on its "
             f"own; model {' + '.join(tiled.effects)}.  Global parameters combined by their information; 'p same' "
             "tests whether every tile has the same value (Cochran's Q), 'spread' is the tiles' standard deviation "
             "beyond their own errors.")
    rep.table(["parameter", "value", "SE", "unit", "tiles", "spread", "p same"],
              [[p.estimate.label, _num(p.estimate.value), _num(p.estimate.se), p.estimate.unit, p.tiles,
                _num(p.spread), _num(p.p_same)] for p in tiled.params])
    if tiled.patterns:
        rep.table(["pattern (size as the frames show it)", "value", "SE", "tiles", "spread", "p same"],
                  [[f"{p.effect}.{p.name}", _num(p.size), _num(p.size_se), p.tiles, _num(p.spread), _num(p.p_same)]
                   for p in tiled.patterns])
    rep.table(["channel", "error (pooled)", "gof p (Fisher)"],
              [[k, _num(tiled.error.get(k)), _num(tiled.gof.get(k))] for k in tiled.gof])
    rep.table(["candidate", "ΔBIC (summed)", "p (Holm)", "flagged", "flagged alone in tiles"],
              [[c.effect, _num(c.delta_bic), _num(c.p), "yes" if c.flagged else "", f"{c.flagged_tiles} of "
                f"{c.tested_tiles}"] for c in tiled.candidates])
    _tile_maps(rep, tiled)
    for warning in tiled.warnings:
        rep.text(warning, note=True)
    return rep


def _tile_grid_values(tiled: TiledCheck, value) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(row edges, column edges, values per tile) for ``pcolormesh``; NaN where ``value(tile)`` is None."""
    rows = sorted({t.tile.core[0] for t in tiled.tiles})
    cols = sorted({t.tile.core[1] for t in tiled.tiles})
    grid = np.full((len(rows), len(cols)), np.nan)
    for t in tiled.tiles:
        v = value(t)
        if v is not None:
            grid[rows.index(t.tile.core[0]), cols.index(t.tile.core[1])] = v
    return np.array([*rows, tiled.shape[0]]), np.array([*cols, tiled.shape[1]]), grid


def _tile_maps(rep: Report, tiled: TiledCheck) -> None:
    """Per tile: each combined parameter's (tile − combined)/SE of the tile, and the held-out pixel error."""
    params = [p for p in tiled.params if p.tiles >= 2]
    panels = len(params) + 1
    ncols = min(panels, 3)
    nrows = math.ceil(panels / ncols)
    fig, axes = new_figure(4.2 * ncols, 3.6 * nrows, ncols=ncols, nrows=nrows)
    axes = np.asarray(axes).ravel()
    for ax, p in zip(axes, params):
        label, centre = p.estimate.label, p.estimate.value

        def z(t, label=label, centre=centre):
            own = next((q for q in t.params if q.label == label and q.se and q.converged and not q.bound), None)
            if own is None or t.excluded:
                return None
            return (own.value - centre) / (own.se * math.sqrt(tile_dispersion(t)))
        ye, xe, grid = _tile_grid_values(tiled, z)
        im = ax.pcolormesh(xe, ye, grid, cmap="RdBu_r", vmin=-4, vmax=4)
        ax.set_ylim(ye[-1], ye[0])
        same = "—" if p.p_same is None else "< 1e-300" if p.p_same < 1e-300 else f"{p.p_same:.2g}"
        ax.set_title(f"{label}\n(tile − combined) / (SE·√φ); p same {same}", fontsize=8)
        fig.colorbar(im, ax=ax, shrink=0.8)
    ax = axes[len(params)]

    def error(t):
        vals = [v for v in t.classes.values() if v is not None]
        return None if t.excluded or not vals else max(vals)
    ye, xe, grid = _tile_grid_values(tiled, error)
    im = ax.pcolormesh(xe, ye, grid, cmap="magma", vmin=0, vmax=max(3.0, float(np.nanmax(grid)) if np.isfinite(grid).any() else 3.0))
    ax.set_ylim(ye[-1], ye[0])
    ax.set_title("held-out pixel error per tile (1 = noise floor)", fontsize=8)
    fig.colorbar(im, ax=ax, shrink=0.8)
    for extra in axes[panels:]:
        extra.set_visible(False)
    rep.figure(fig, "tile_maps", "Each tile's own estimate of every global parameter, in its own standard errors "
               "(scaled by its misfit φ, as the test) from the combined value (blue below, red above; a smooth gradient or a hot corner is a spatial "
               "effect the model lacks), and each tile's held-out pixel error (the worst class).")
