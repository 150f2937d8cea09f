"""Figures and the page of the ageing-impact experiment (the reference paper's figures 5 and 6).

Drawing and layout only: every number comes from an :class:`~forensics.impact.experiment.ImpactResult`.
"""
from __future__ import annotations

import numpy as np

from forensics.impact.experiment import PROTOCOLS, ImpactResult
from forensics.report.html import Report, new_figure

__all__ = ["histograms_figure", "impact_report", "matchers_figure", "sensors_figure"]


def _errorbars(ax, result: ImpactResult, sensor: str, matcher: str, protocol: str, **style) -> None:
    units = result.trajectory(sensor, matcher, protocol)
    y = np.array([100 * u.eer.estimate for u in units])
    lo = np.array([100 * u.eer.ci[0] for u in units])
    hi = np.array([100 * u.eer.ci[1] for u in units])
    ax.errorbar(result.ages, y, yerr=[y - lo, hi - y], capsize=3, marker="o", ms=4, **style)


def matchers_figure(result: ImpactResult, sensor: str, protocol: str):
    """Figure-5 style: EER against age for every matcher, one sensor, with class-bootstrap intervals."""
    fig, ax = new_figure()
    for matcher in result.matchers:
        _errorbars(ax, result, sensor, matcher, protocol, label=matcher)
    ax.set_xlabel("virtual sensor age (years)")
    ax.set_ylabel("EER (%)")
    ax.set_title(f"sensor {sensor}, {protocol}")
    ax.legend(fontsize=8)
    return fig


def sensors_figure(result: ImpactResult, matcher: str, protocol: str):
    """Figure-6 style: EER against age for every sensor, one matcher, and the mean over sensors (dashed)."""
    fig, ax = new_figure()
    for sensor in result.sensors:
        y = [100 * u.eer.estimate for u in result.trajectory(sensor, matcher, protocol)]
        ax.plot(result.ages, y, marker="o", ms=4, lw=0.8, label=sensor)
    spread = [s for s in result.spreads if s.matcher == matcher and s.protocol == protocol]
    mean = [100 * s.mean for s in spread]
    ax.plot(result.ages, mean, "k--", lw=1.5, label="mean")
    ax.fill_between(result.ages, [100 * s.mean_ci[0] for s in spread], [100 * s.mean_ci[1] for s in spread],
                    color="k", alpha=0.12, label=f"mean, {100 * result.level:g} % interval")
    ax.set_xlabel("virtual sensor age (years)")
    ax.set_ylabel("EER (%)")
    ax.set_title(f"{matcher}, {protocol}")
    ax.legend(fontsize=7, ncol=2)
    return fig


def histograms_figure(result: ImpactResult, matcher: str, protocol: str):
    """Genuine and impostor score histograms at the first and the last age, one row per sensor."""
    rows = len(result.sensors)
    fig, axes = new_figure(8, 2.2 * rows, ncols=2, nrows=rows)
    axes = np.atleast_2d(axes)
    for r, sensor in enumerate(result.sensors):
        for c, age in enumerate((result.ages[0], result.ages[-1])):
            unit = result.unit(sensor, age, matcher, protocol)
            edges = np.asarray(unit.histogram["edges"])
            for key, colour in (("genuine", "C2"), ("impostor", "C3")):
                counts = np.asarray(unit.histogram[key], dtype=float)
                axes[r, c].stairs(counts / max(counts.sum(), 1) / np.diff(edges), edges, color=colour, label=key,
                                  fill=True, alpha=0.4)
            axes[r, c].set_title(f"{sensor}, year {age:g}: EER {100 * unit.eer.estimate:.2f} %", fontsize=9)
            axes[r, c].set_xlabel("score", fontsize=8)
    axes[0, 0].legend(fontsize=7)
    return fig


def impact_report(result: ImpactResult, title: str = "Does sensor ageing hurt recognition?") -> Report:
    """The whole page: set-up, trend table, figure 5 and 6 analogues, histograms."""
    rep = Report(title)
    rep.text(f"{result.n_images} images of {result.n_classes} classes from {result.source}: "
             f"{result.n_genuine:,} genuine and {result.n_impostor:,} impostor comparisons per age "
             f"({'a uniform sample of the' if result.impostors_sampled else 'all'} impostor pairs). Sensors "
             f"{', '.join(result.sensors)}; ages {', '.join(f'{a:g}' for a in result.ages)} years; matchers "
             f"{', '.join(result.matchers)}.")
    for protocol in result.protocols:
        rep.text(f"Protocol {protocol}: {PROTOCOLS[protocol]}.")
    rep.text(f"Intervals: {100 * result.level:g} % class bootstrap ({result.n_boot} resamples of the classes, the "
             "same resamples at every age and for every sensor, so trends and differences are paired). A trend is "
             "called significant only when its slope interval excludes zero.", note=True)
    rep.heading("Trend of the EER against age")
    rep.table(["sensor", "matcher", "protocol", "EER first (%)", "EER last (%)", "slope (points/decade)",
               "interval", "p", "verdict"],
              [[t.sensor, t.matcher, t.protocol,
                100 * result.unit(t.sensor, result.ages[0], t.matcher, t.protocol).eer.estimate,
                100 * result.unit(t.sensor, result.ages[-1], t.matcher, t.protocol).eer.estimate,
                1000 * t.slope, f"[{1000 * t.slope_ci[0]:+.3f}, {1000 * t.slope_ci[1]:+.3f}]", t.p_value,
                "significant" if t.significant else "no significant trend"] for t in result.trends])
    for protocol in result.protocols:
        rep.heading(f"Every matcher, protocol {protocol} (figure 5)")
        for k, sensor in enumerate(result.sensors):
            rep.figure(matchers_figure(result, sensor, protocol), f"matchers_{protocol}_{k}",
                       f"EER against age for sensor {sensor} with {100 * result.level:g} % intervals")
        rep.heading(f"Every sensor, protocol {protocol} (figure 6)")
        for k, matcher in enumerate(result.matchers):
            rep.figure(sensors_figure(result, matcher, protocol), f"sensors_{protocol}_{k}",
                       f"{matcher}: EER against age per sensor; dashed: mean over sensors with its paired interval")
    failures = [u for u in result.units if u.failed_images]
    rep.heading("Segmentation failures")
    if failures:
        rep.text("Images whose segmentation failed a check (implausible radii, pupil outside the iris, too little "
                 "usable iris, weak boundaries) are not scored as eyes: their comparisons count as non-matches at "
                 "every threshold (genuine pairs falsely rejected, impostor pairs correctly rejected).")
        rep.table(["sensor", "year", "matcher", "protocol", "failed images", "comparisons as non-matches", "images"],
                  [[u.sensor, f"{u.age:g}", u.matcher, u.protocol, len(u.failed_images), u.failed_pairs,
                    ", ".join(u.failed_images[:8]) + (" …" if len(u.failed_images) > 8 else "")]
                   for u in failures])
    else:
        rep.text("None: every image passed the segmentation's checks at every age.")
    rep.heading("Score distributions at the first and last age")
    for k, matcher in enumerate(result.matchers):
        protocol = result.protocols[0]
        rep.figure(histograms_figure(result, matcher, protocol), f"histograms_{k}",
                   f"{matcher}, {protocol}: genuine (green) and impostor (red) score densities")
    return rep
