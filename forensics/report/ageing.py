"""Figures and the demo page of sensor ageing: defect counts against age, the defect map, before/after crops.

Drawing and page layout only: the counts come from :class:`~forensics.sensor.simulate.AgeingResult`, the
expected Poisson bands are computed by the caller (:func:`forensics.demo.ageing.poisson_bands`), the
defects from a :class:`~forensics.sensor.catalogue.DefectCatalogue`.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from forensics.report.html import Report, new_figure
from forensics.sensor.catalogue import PARTIAL, STUCK, DefectCatalogue
from forensics.sensor.simulate import AgeingResult

__all__ = ["counts_figure", "onset_map_figure", "crops_figure", "ageing_demo_report"]

_KINDS = (("partial", "C0", "partially stuck"), ("stuck", "C3", "stuck"))


def counts_figure(result: AgeingResult, bands: Mapping[str, Any]):
    """Defect counts per kind against virtual age, over the expected Poisson 95 % band of each kind.

    ``bands[kind]`` (kind 'partial' or 'stuck') is ``(grid, mean, lo, hi)`` over ages in years.
    """
    fig, ax = new_figure()
    for kind, colour, label in _KINDS:
        grid, mean, lo, hi = bands[kind]
        ax.fill_between(grid, lo, hi, color=colour, alpha=0.2, label=f"{label}: Poisson 95 % band")
        ax.plot(grid, mean, color=colour, lw=1)
        ax.plot(np.asarray(result.ages), result.counts[kind], "o", color=colour, label=f"{label}: simulated")
    ax.set_xlabel("virtual age (years)")
    ax.set_ylabel("defective pixels")
    ax.legend(fontsize=8)
    return fig


def onset_map_figure(defects: DefectCatalogue, shape: tuple[int, int], t0: float, max_age: float):
    """Where the defects are, coloured by onset (years after ``t0``)."""
    fig, ax = new_figure(6.4, 5.0)
    sc = None
    for kind, marker, label in ((PARTIAL, "o", "partially stuck"), (STUCK, "s", "stuck")):
        sel = defects.kind == kind
        sc = ax.scatter(defects.x[sel], defects.y[sel], c=defects.onset[sel] - t0, cmap="viridis", marker=marker,
                        s=14, vmin=0, vmax=max_age, label=label)
    ax.set_xlim(0, shape[1])
    ax.set_ylim(shape[0], 0)
    ax.set_aspect("equal")
    ax.legend(fontsize=8, loc="upper right")
    fig.colorbar(sc, ax=ax, label="onset (years)")
    return fig


def crops_figure(crops: Sequence[tuple[np.ndarray, str]], vmax: float = 255):
    """Image crops side by side, each with its title (grey, nearest-neighbour)."""
    fig, axes = new_figure(4 * len(crops), 4, ncols=len(crops))
    for ax, (img, label) in zip(np.atleast_1d(axes), crops):
        ax.imshow(img, cmap="gray", vmin=0, vmax=vmax, interpolation="nearest")
        ax.set_title(label)
        ax.axis("off")
    return fig


def ageing_demo_report(title: str, *, sensor: str, rates: tuple[float, float], n_images: int, result: AgeingResult,
                       bands: Mapping[str, Any], defects: DefectCatalogue, shape: tuple[int, int], t0: float,
                       crops: Sequence[tuple[np.ndarray, str]]) -> Report:
    """The demo's ageing section: what was simulated, the counts against the Poisson band, the map, the crops.

    ``rates`` are the sensor's (λ_ps, λ_s) in defects per megapixel per year; ``defects`` the device's
    defects at the last age.
    """
    lam_ps, lam_s = rates
    max_age = float(max(result.ages))
    rep = Report(title)
    rep.text(f"Virtual sensor {sensor} of the paper's table 4 (λ_ps = {lam_ps:.4g}, λ_s = {lam_s:.4g} defects per "
             f"megapixel per year) ages {n_images} scene images of {shape[1]}×{shape[0]} pixels over "
             f"{max_age:g} years in 8-year steps. One device, one defect history: every image at a given age carries "
             "the same defects, and a defect once present never leaves.")
    rep.figure(counts_figure(result, bands), "counts", "Defect count against virtual age, with the expected Poisson "
               "95 % band (λ·MP·t; stuck pixels that land on partially stuck ones override them).")
    rep.figure(onset_map_figure(defects, shape, t0, max_age), "defect_map",
               f"Defect map at {max_age:g} years, coloured by onset: uniform, independent sites.")
    rep.figure(crops_figure(crops), "before_after", "The same 40×40 crop of the same scene before and after ageing.")
    return rep
