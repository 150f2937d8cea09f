"""Figures and a page for iris segmentations: overlays of the boundaries found, hit rates against marks.

:func:`overlay_figure` draws one eye with the segmentation's pupil and limbus (ellipses when it fitted them),
its eyelid margins and, dashed, the hand-checked circles when given; :func:`segmentation_report` makes a page
with the hit rates of a run and the overlays of the images that missed a mark or failed a check — on any
user's images, since it only needs the images, their segmentations and optionally marks.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from forensics.impact.segment.common import Segmentation
from forensics.impact.segment.evaluate import BoundaryMark, HitRates, circle_error, is_hit
from forensics.report.html import Report, new_figure


@dataclass(frozen=True)
class SegmentedImage:
    """One image for the page: its name, pixels, segmentation and (optionally) its mark."""

    name: str
    image: np.ndarray
    segmentation: Segmentation
    mark: BoundaryMark | None = None


def _draw_boundary(ax, circle, ellipse, colour: str, style: str = "-") -> None:
    from matplotlib.patches import Circle as CirclePatch
    from matplotlib.patches import Ellipse as EllipsePatch

    if ellipse is not None:
        x, y, a, b, phi = ellipse
        # Matplotlib's angle is counter-clockwise in data coordinates; with the image's y axis pointing down
        # that is clockwise on screen, the opposite of ours.
        ax.add_patch(EllipsePatch((x, y), 2 * a, 2 * b, angle=-np.degrees(phi), fill=False, color=colour,
                                  linestyle=style, linewidth=1.0))
    else:
        ax.add_patch(CirclePatch(circle[:2], circle[2], fill=False, color=colour, linestyle=style, linewidth=1.0))
    ax.plot([circle[0]], [circle[1]], marker="+", color=colour, markersize=6)


def overlay_figure(item: SegmentedImage, width: float = 4.0):
    """The eye with its boundaries: pupil red, limbus green, eyelids yellow, the mark's circles dashed cyan."""
    img = np.asarray(item.image, dtype=float)
    h, w = img.shape[:2]
    fig, ax = new_figure(width, width * h / w)
    ax.imshow(img, cmap="gray", interpolation="nearest")
    seg = item.segmentation
    _draw_boundary(ax, seg.pupil, seg.pupil_ellipse, "red")
    _draw_boundary(ax, seg.iris, seg.iris_ellipse, "lime")
    xs = np.linspace(0, w - 1, 200)
    for lid in (seg.upper_lid, seg.lower_lid):
        if lid is not None:
            x0, y0, a = lid
            ax.plot(xs, y0 + a * (xs - x0) ** 2, color="yellow", linewidth=0.8)
    if item.mark is not None:
        _draw_boundary(ax, item.mark.pupil, None, "cyan", "--")
        _draw_boundary(ax, item.mark.iris, None, "cyan", "--")
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_axis_off()
    verdict = "ok" if seg.ok else f"FAILED: {seg.reason}"
    ax.set_title(f"{item.name} ({seg.method or 'given'}): {verdict}", fontsize=7, wrap=True)
    return fig


def _error(found, truth) -> str:
    centre, radius = circle_error(found, truth)
    return f"{centre:.1f} px, {100 * radius:.0f} %"


def _rate(rates: HitRates, boundary: str, clear_only: bool = False) -> str:
    hits, n = rates.rate(boundary, clear_only)
    return f"{hits}/{n} = {100 * hits / n:.1f} %" if n else "–"


def segmentation_report(items: Iterable[SegmentedImage], rates: HitRates | None = None, method: str = "",
                        max_overlays: int = 36, title: str = "Iris segmentation") -> Report:
    """A page with the hit rates (when ``rates`` is given) and overlays of the problem images.

    Problem images are those that missed a mark (when marks are given) or failed a check; at most
    ``max_overlays`` are drawn, in the order given.  ``items`` is consumed once; only the problem images are
    kept (as figures).
    """
    rep = Report(title + (f" ({method})" if method else ""))
    if rates is not None:
        rep.heading("Hit rate against the marks")
        rep.text(f"A boundary is hit when the centre found lies within {rates.centre_tol:g} px of the mark's and "
                 f"the radius within {100 * rates.radius_tol:g} % of it.")
        rep.table(["boundary", "hits"], [["pupil", _rate(rates, "pupil")], ["limbus", _rate(rates, "limbus")],
                                         ["limbus (clearly visible)", _rate(rates, "limbus", True)],
                                         ["both", _rate(rates, "both")]])
        flagged, misses = rates.flagged()
        rep.text(f"{flagged} of the {misses} images with a missed boundary were flagged as failed by the "
                 "segmentation itself.")
    problems = []
    drawn = 0
    for item in items:
        seg, mark = item.segmentation, item.mark
        missed, errors = False, ["", ""]
        if mark is not None:
            missed = not (is_hit(seg.pupil, mark.pupil) and is_hit(seg.iris, mark.iris))
            errors = [_error(seg.pupil, mark.pupil), _error(seg.iris, mark.iris)]
        if seg.ok and not missed:
            continue
        problems.append([item.name, "missed" if missed else "", *errors, "ok" if seg.ok else "failed", seg.reason])
        if drawn < max_overlays:
            if drawn == 0:
                rep.heading("Images that missed a mark or failed a check")
            rep.figure(overlay_figure(item), f"overlay_{drawn:03d}",
                       "red: pupil found, green: limbus found, yellow: eyelids, dashed cyan: the marks")
            drawn += 1
    rep.heading("Problem images")
    if problems:
        rep.table(["image", "mark", "pupil error", "limbus error", "verdict", "reason"], problems)
        if len(problems) > drawn:
            rep.text(f"{len(problems) - drawn} more problem images are listed but not drawn.")
    else:
        rep.text("None: every image passed its checks" + (" and hit its marks." if rates is not None else "."))
    return rep
