"""Figures and the report of a dark-frame series: what an astronomer looks at to judge a cooled sensor.

* dark signal against exposure, per temperature group (each frame's median dark signal above the pixels'
  offsets, and the line of the median rate);
* dark rate against temperature (the groups' median rates with their intervals, and the fitted law of the bulk
  and of each class of hot pixels), and the doubling temperature against the rate;
* the accumulated histogram of dark rates (pixels above each rate, per group, carried to the reference
  temperature, with the threshold): where the groups' curves agree, the law carries the hot tail right;
* the hot-pixel map and the map of dark rates;
* the frames table (how each frame was used, its residual and noise against the model, what is wrong with it).

Drawing only: every number comes from :class:`~forensics.defects.darkdetect.DarkDetectionResult`.
"""
from __future__ import annotations

import numpy as np

from forensics.defects.darkdetect import DarkDetectionResult
from forensics.report.html import Report, new_figure
from forensics.sensor.catalogue import PARTIAL, STUCK

__all__ = ["dark_level_figure", "rate_temperature_figure", "rate_histogram_figure", "hot_map_figure",
           "rate_map_figure", "dark_report"]


def dark_level_figure(result: DarkDetectionResult):
    """Each frame's median dark signal (ADU above the offsets) against its exposure, and the median-rate lines."""
    fit = result.series
    fig, ax = new_figure(6.4, 4.0)
    for index, g in enumerate(fit.groups):
        colour = f"C{index}"
        frames = [f for f in fit.frames if f.group == index and f.dark_level is not None]
        t = np.array([f.exposure_s for f in frames])
        level = np.array([f.dark_level for f in frames])
        bad = np.array([bool(f.problems) for f in frames], bool)
        ax.plot(t[~bad], level[~bad], "o", color=colour, ms=4, label=f"{g.label}: frames")
        if bad.any():
            ax.plot(t[bad], level[bad], "x", color="C3", ms=7, label="frames named as off the model")
        grid = np.linspace(0, max(t.max(), 1.0), 50)
        ax.plot(grid, g.median_rate * grid, color=colour, lw=1,
                label=f"median rate {g.median_rate:.3g} ADU/s at {g.temperature_c:+.2f} °C")
    ax.set_xlabel("exposure (s)")
    ax.set_ylabel("median dark signal above the offset (ADU)")
    ax.legend(fontsize=7)
    return fig


def rate_temperature_figure(result: DarkDetectionResult):
    """Median rates against temperature with the fitted law, and T_d against rate class."""
    fit, law = result.series, result.law
    fig, (ax, ax2) = new_figure(9.6, 4.0, ncols=2)
    temps = np.array([g.temperature_c for g in fit.groups if g.temperature_c is not None])
    for g in fit.groups:
        if g.temperature_c is None:
            continue
        lo, hi = g.median_rate_ci()
        ax.errorbar([g.temperature_c], [g.median_rate], yerr=[[g.median_rate - lo], [hi - g.median_rate]],
                    xerr=[[1.96 * g.temperature_se], [1.96 * g.temperature_se]], fmt="o", color="k", capsize=3)
    if law is not None and temps.size:
        span = np.linspace(temps.min() - 2, temps.max() + 2, 40)
        for point, colour, label in [(law.bulk, "k", "bulk (median pixel)")] + [
                (c, f"C{i}", f"pixels near {c.rate:.3g} ADU/s") for i, c in enumerate(law.classes)]:
            ax.plot(span, point.rate * np.exp2(point.beta * (span - law.t_class)), color=colour, lw=1,
                    label=f"{label}: T_d {point.doubling:.2f} °C")
        rates = [law.bulk.rate] + [c.rate for c in law.classes]
        doubling = [law.bulk] + law.classes
        cis = [p.doubling_ci() for p in doubling]
        mid = np.array([p.doubling for p in doubling])
        lo = mid - np.array([c[0] for c in cis])
        hi = np.array([(c[1] if c[1] is not None else mid[i] * 3) for i, c in enumerate(cis)]) - mid
        ax2.errorbar(rates, mid, yerr=[lo, hi], fmt="o", capsize=3)
        ax2.set_xscale("log")
        ax2.set_xlabel(f"dark rate at {law.t_class:+.2f} °C (ADU/s)")
        ax2.set_ylabel("doubling temperature T_d (°C), 95 %")
        ax2.set_title("the law by rate class", fontsize=9)
    ax.set_yscale("log")
    ax.set_xlabel("sensor temperature, measured (°C)")
    ax.set_ylabel("dark rate (ADU/s)")
    ax.legend(fontsize=6)
    return fig


def rate_histogram_figure(result: DarkDetectionResult):
    """The accumulated histogram of dark rates per group (carried to t_ref): pixels above each rate."""
    fig, ax = new_figure(6.4, 4.0)
    for index, hist in enumerate(result.group_hist):
        x = np.asarray(hist["rate_adu_per_s"])
        n = np.asarray(hist["pixels_above"], float)
        ax.step(x, 100.0 * np.maximum(n, 0.5) / hist["pixels"], where="post", color=f"C{index}",
                label=f"{hist['group']} ({hist['above_threshold']} above the threshold)")
    ax.axvline(result.threshold_rate, color="C3", lw=1.2, ls="--",
               label=f"threshold {result.threshold_rate:.3g} ADU/s")
    ax.set_xscale("log")
    ax.set_yscale("log")
    t_ref = "" if result.t_ref is None else f" at {result.t_ref:+.1f} °C"
    ax.set_xlabel(f"dark rate{t_ref} (ADU/s)")
    ax.set_ylabel("pixels with a higher rate (%)")
    ax.legend(fontsize=7)
    return fig


def hot_map_figure(result: DarkDetectionResult):
    """Where the hot and stuck pixels are, coloured by rate."""
    h, w = result.shape
    fig, ax = new_figure(6.4, 6.4 * h / w + 0.6)
    hot = result.kind == PARTIAL
    points = ax.scatter(result.x[hot], result.y[hot], c=np.log10(np.maximum(result.amplitude[hot], 1e-3)), s=3,
                        cmap="inferno_r", label=f"hot ({int(hot.sum())})")
    stuck = result.kind == STUCK
    if stuck.any():
        ax.scatter(result.x[stuck], result.y[stuck], marker="s", s=12, facecolors="none", edgecolors="C0",
                   label=f"stuck ({int(stuck.sum())})")
    fig.colorbar(points, ax=ax, label="log₁₀ rate (ADU/s)", shrink=0.8)
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_title(f"hot pixels: rate > {result.threshold_rate:.3g} ADU/s", fontsize=9)
    ax.legend(fontsize=7, loc="upper right")
    return fig


def rate_map_figure(result: DarkDetectionResult):
    """The map of dark rates at t_ref (log scale): gradients, amplifier glow, columns, hot pixels."""
    h, w = result.shape
    fig, ax = new_figure(6.4, 6.4 * h / w + 0.6)
    rates = np.asarray(result.d_hat, np.float64)
    floor = max(float(np.percentile(rates, 1)), 1e-4)
    logs = np.log10(np.maximum(rates, floor))
    image = ax.imshow(logs, cmap="magma", vmin=float(np.log10(floor)), vmax=float(np.percentile(logs, 99.9)),
                      interpolation="nearest")
    fig.colorbar(image, ax=ax, label="log₁₀ dark rate (ADU/s)", shrink=0.8)
    ax.set_title("dark rate per pixel (log scale, 1–99.9 % range)", fontsize=9)
    return fig


def dark_report(result: DarkDetectionResult, title: str = "Dark-frame series", source: str = "") -> Report:
    """The HTML report of a dark-series detection: groups, gain, law, figures, frames."""
    fit = result.series
    rep = Report(title)
    rep.text(f"{source + ': ' if source else ''}{fit.n_frames} bias and dark frames of {fit.shape[1]}×{fit.shape[0]} "
             f"in {len(fit.groups)} temperature group(s); hot pixels: dark rate above {result.threshold_rate:.4g} "
             f"ADU/s" + ("" if result.t_ref is None else f" at {result.t_ref:+.2f} °C") + ".")
    for w in result.warnings:
        rep.text(w, note=True)
    rep.heading("Temperature groups")
    rows = []
    for g in fit.groups:
        lo, hi = g.median_rate_ci()
        spread = [g.read_noise, *g.read_noise_frames]
        rows.append([g.label, g.temperature_c, g.temperature_se, len(g.frames), g.n_bias, g.bias_level,
                     g.bias_level_se, g.read_noise, f"[{min(spread):.4g}, {max(spread):.4g}]", g.offset_jitter,
                     g.median_rate, f"[{lo:.4g}, {hi:.4g}]", g.outliers, int(g.misfit.sum())])
    rep.table(["group", "T (°C)", "± (°C)", "frames", "biases", "bias (ADU)", "± (ADU)", "read noise (ADU)",
               "its range (group, each bias)", "offset jitter (ADU)", "median rate (ADU/s)", "95 %",
               "cosmic-ray samples", "misfit pixels"], rows,
              caption="± is one standard error; the read noise's range spans the group's estimate (every pixel's "
                      "temporal variance over the biases) and each bias frame's against the pixels' offsets")
    gains = [[k.replace("_", " "), v["gain_e_per_adu"], f"[{v['ci'][0]:.4g}, {v['ci'][1]:.4g}]", v.get("mean_signal_adu")]
             for k, v in fit.gain.items() if isinstance(v, dict)]
    if fit.gain.get("header_e_per_adu"):
        gains.append(["header EGAIN (the maker's)", fit.gain["header_e_per_adu"], "", ""])
    rep.table(["conversion gain", "e⁻/ADU", "95 %", "signal (ADU)"], gains,
              caption=f"the noise model used {fit.gain_used:.4g} e⁻/ADU ({fit.gain_source})")
    rep.figure(dark_level_figure(result), "dark_level",
               "Dark signal against exposure: each frame's median signal above the pixels' fitted offsets, and the "
               "median rate's line. Frames named as off the model are crossed.")
    if result.law is not None:
        rep.heading("Temperature law")
        rep.text(f"{result.law_source}. Rates are carried between temperatures with the doubling temperature of "
                 "pixels like them (hot pixels double more slowly than the bulk).")
        rep.table(["pixels", "rate (ADU/s)", "count", "T_d (°C)", "95 %", "pixel spread of 1/T_d (1/°C)"],
                  [["bulk (median)", result.law.bulk.rate, result.law.bulk.n, result.law.bulk.doubling,
                    _ci(result.law.bulk), ""]]
                  + [[f"class [{c.lo:.3g}, {c.hi:.3g})", c.rate, c.n, c.doubling, _ci(c),
                      "" if c.spread is None else c.spread] for c in result.law.classes])
        rep.figure(rate_temperature_figure(result), "rate_temperature",
                   "Dark rate against the measured temperature (medians with 95 % intervals) with the fitted law, "
                   "and the doubling temperature of each rate class.")
    rep.heading("Hot pixels")
    lo, hi = result.count_ci
    text = (f"{result.count(PARTIAL)} hot pixels (Poisson 95 % [{lo:.0f}, {hi:.0f}]) and {result.count(STUCK)} "
            f"stuck over {result.megapixels:.4g} MP.")
    if result.count_law_range:
        text += f" With the law at the ends of its interval: {result.count_law_range[0]}–{result.count_law_range[1]}."
    rep.text(text)
    rep.figure(rate_histogram_figure(result), "rate_histogram",
               "Accumulated histogram of dark rates, each group carried to the reference temperature: the share of "
               "pixels above each rate. Where the curves agree, the law carries the hot tail right.")
    rep.figure(hot_map_figure(result), "hot_map", "Hot-pixel map.")
    rep.figure(rate_map_figure(result), "rate_map", "Map of the dark rate per pixel.")
    rep.heading("Frames")
    rep.table(["file", "type", "t (s)", "T (°C)", "group", "dark level (ADU)", "residual (ADU)", "noise / model",
               "cosmic-ray samples", "saturated", "notes"],
              [[f.name, f.frame_type, f.exposure_s, f.temperature_c, "" if f.group is None else f.group,
                f.dark_level, f.common_residual, f.noise_ratio, f.outliers, f.saturated,
                f.reason or "; ".join(f.problems)] for f in fit.frames])
    return rep


def _ci(point) -> str:
    lo, hi = point.doubling_ci()
    return f"[{lo:.3g}, {'∞' if hi is None else f'{hi:.3g}'}]"
