"""Demo section: a simulated device ages; its defects accumulate as the Poisson model says."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import stats

from forensics.io.dataset import open_dataset
from forensics.sensor.model import PARTIAL, STUCK
from forensics.sensor.presets import preset
from forensics._shared.progress import Progress
from forensics.report.html import Report, new_figure
from forensics.sensor.simulate import age_dataset, make_scenes, parse_years, read_catalogue
from . import DemoSection

TITLE = "Sensor ageing (the paper's AGEDIMAGESEQUENCE)"
SENSOR = "H"
SIZE = (480, 640)


def run(workdir: Path, seed: int, progress: Progress) -> DemoSection:
    scenes = make_scenes(workdir / "scenes", 12, SIZE, seed, progress=progress)
    ages = parse_years("0:96:8")
    model = preset(SENSOR, SIZE, bit_depth=8)
    result = age_dataset(scenes, workdir / "aged", model, ages, seed, start_year=2000.0, sensor_name=SENSOR,
                         progress=progress)
    catalogue = read_catalogue(workdir / "aged" / "defects.csv")
    rep = Report(TITLE)
    lam_ps, lam_s = model.effects[0].rate_partial, model.effects[0].rate_stuck
    rep.text(f"Virtual sensor {SENSOR} of the paper's table 4 (λ_ps = {lam_ps:.4g}, λ_s = {lam_s:.4g} defects per "
             f"megapixel per year) ages {len(scenes)} scene images of {SIZE[1]}×{SIZE[0]} pixels over 96 years in "
             "8-year steps. One device, one defect history: every image at a given age carries the same defects, "
             "and a defect once present never leaves.")

    fig, ax = new_figure()
    ages_arr = np.asarray(ages)
    grid = np.linspace(0, ages_arr.max(), 200)
    mp = model.megapixels
    for kind, rate, colour, label in ((PARTIAL, lam_ps, "C0", "partially stuck"), (STUCK, lam_s, "C3", "stuck")):
        counts = result.counts["partial" if kind == PARTIAL else "stuck"]
        mean = rate * mp * grid
        lo, hi = stats.poisson.ppf(0.025, mean), stats.poisson.ppf(0.975, mean)
        ax.fill_between(grid, lo, hi, color=colour, alpha=0.2, label=f"{label}: Poisson 95 % band")
        ax.plot(grid, mean, color=colour, lw=1)
        ax.plot(ages_arr, counts, "o", color=colour, label=f"{label}: simulated")
    ax.set_xlabel("virtual age (years)")
    ax.set_ylabel("defective pixels")
    ax.legend(fontsize=8)
    rep.figure(fig, "counts", "Defect count against virtual age, with the expected Poisson 95 % band "
               "(λ·MP·t; stuck pixels that land on partially stuck ones override them).")

    fig, ax = new_figure(6.4, 5.0)
    final = catalogue.effective(2000.0 + ages_arr.max())
    for kind, marker, label in ((PARTIAL, "o", "partially stuck"), (STUCK, "s", "stuck")):
        sel = final.kind == kind
        sc = ax.scatter(final.x[sel], final.y[sel], c=final.onset[sel] - 2000.0, cmap="viridis", marker=marker,
                        s=14, vmin=0, vmax=ages_arr.max(), label=label)
    ax.set_xlim(0, SIZE[1])
    ax.set_ylim(SIZE[0], 0)
    ax.set_aspect("equal")
    ax.legend(fontsize=8, loc="upper right")
    fig.colorbar(sc, ax=ax, label="onset (years)")
    rep.figure(fig, "defect_map", "Defect map at 96 years, coloured by onset: uniform, independent sites.")

    young = open_dataset(workdir / "aged" / "year_000")[0].load()
    old = open_dataset(workdir / "aged" / "year_096")[0].load()
    stuck = final.select(final.kind == STUCK)
    cx, cy = (int(stuck.x[0]), int(stuck.y[0])) if len(stuck) else (SIZE[1] // 2, SIZE[0] // 2)
    x0, y0 = np.clip(cx - 20, 0, SIZE[1] - 40), np.clip(cy - 20, 0, SIZE[0] - 40)
    fig, axes = new_figure(8, 4, ncols=2)
    for ax, img, label in ((axes[0], young, "age 0"), (axes[1], old, "age 96 years")):
        ax.imshow(img[y0:y0 + 40, x0:x0 + 40], cmap="gray", vmin=0, vmax=255, interpolation="nearest")
        ax.set_title(label)
        ax.axis("off")
    rep.figure(fig, "before_after", "The same 40×40 crop of the same scene before and after ageing.")

    summary = [f"ageing: sensor {SENSOR}, {len(scenes)} images × {len(ages)} ages; at 96 years "
               f"{result.counts['partial'][-1]} partially stuck and {result.counts['stuck'][-1]} stuck pixels "
               f"(expected {lam_ps * mp * 96:.1f} and {lam_s * mp * 96:.1f})"]
    return DemoSection(TITLE, rep, summary, {"ages": ages, **result.counts})
