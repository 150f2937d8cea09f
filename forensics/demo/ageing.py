"""Demo section: a simulated device ages; its defects accumulate as the Poisson model says."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import stats

from forensics._shared.parallel import Executor
from forensics._shared.progress import Progress
from forensics._shared.rng import RngLike
from forensics.io.dataset import open_dataset
from forensics.report.ageing import ageing_demo_report
from forensics.sensor.catalogue import STUCK
from forensics.sensor.presets import preset
from forensics.sensor.simulate import age_dataset, make_scenes, parse_years, read_catalogue

from . import DemoSection

TITLE = "Sensor ageing (the paper's AGEDIMAGESEQUENCE)"
SENSOR = "H"
SIZE = (480, 640)
START = 2000.0
CROP = 40


def poisson_bands(rates: dict[str, float], megapixels: float, max_age: float, n: int = 200) -> dict[str, tuple]:
    """Expected count ``λ·MP·t`` and its central Poisson 95 % band per kind: ``{kind: (grid, mean, lo, hi)}``."""
    grid = np.linspace(0, max_age, n)
    out = {}
    for kind, rate in rates.items():
        mean = rate * megapixels * grid
        out[kind] = (grid, mean, stats.poisson.ppf(0.025, mean), stats.poisson.ppf(0.975, mean))
    return out


def run(workdir: Path, rng: RngLike, progress: Progress, executor: Executor | None = None) -> DemoSection:
    """Age 12 scenes with sensor H over 96 years and compare the counts with the Poisson model.

    ``rng`` (Generator or int seed) draws the scenes, then the device and the frames' noise.
    """
    scenes = make_scenes(workdir / "scenes", 12, SIZE, rng, progress=progress)
    ages = parse_years("0:96:8")
    model = preset(SENSOR, SIZE, bit_depth=8)
    result = age_dataset(scenes, workdir / "aged", model, ages, rng, start_year=START, sensor_name=SENSOR,
                         progress=progress, executor=executor)
    catalogue = read_catalogue(workdir / "aged" / "defects.csv")
    lam_ps, lam_s = model.effects[0].rate_partial, model.effects[0].rate_stuck
    mp = model.megapixels
    max_age = float(max(ages))
    bands = poisson_bands({"partial": lam_ps, "stuck": lam_s}, mp, max_age)
    final = catalogue.effective(START + max_age)

    young = open_dataset(workdir / "aged" / "year_000")[0].load()
    old = open_dataset(workdir / "aged" / "year_096")[0].load()
    stuck = final.select(final.kind == STUCK)
    cx, cy = (int(stuck.x[0]), int(stuck.y[0])) if len(stuck) else (SIZE[1] // 2, SIZE[0] // 2)
    x0, y0 = np.clip(cx - CROP // 2, 0, SIZE[1] - CROP), np.clip(cy - CROP // 2, 0, SIZE[0] - CROP)
    crops = [(img[y0:y0 + CROP, x0:x0 + CROP], label) for img, label in ((young, "age 0"), (old, "age 96 years"))]
    rep = ageing_demo_report(TITLE, sensor=SENSOR, rates=(lam_ps, lam_s), n_images=len(scenes), result=result,
                             bands=bands, defects=final, shape=SIZE, t0=START, crops=crops)

    summary = [f"ageing: sensor {SENSOR}, {len(scenes)} images × {len(ages)} ages; at 96 years "
               f"{result.counts['partial'][-1]} partially stuck and {result.counts['stuck'][-1]} stuck pixels "
               f"(expected {lam_ps * mp * 96:.1f} and {lam_s * mp * 96:.1f})"]
    return DemoSection(TITLE, rep, summary, {"ages": ages, **result.counts})
