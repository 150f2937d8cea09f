"""Demo section: does sensor ageing hurt iris recognition?  The paper's experiment on a small synthetic set."""
from __future__ import annotations

from pathlib import Path

from forensics._shared.parallel import Executor
from forensics._shared.progress import Progress
from forensics._shared.rng import RngLike
from forensics.impact.experiment import parse_sensors, run_impact
from forensics.impact.irises import simulate_irises
from forensics.impact.matchers import load_matchers
from forensics.io.dataset import open_dataset
from forensics.report.html import Report
from forensics.report.impact import impact_report

from . import DemoSection

TITLE = "Does sensor ageing hurt recognition? (the paper's section 5, in small)"
CLASSES, SAMPLES = 24, 3
SENSORS = "A,H*100"
AGES = [0.0, 48.0, 96.0]
MATCHER = "masek"


def run(workdir: Path, rng: RngLike, progress: Progress, executor: Executor | None = None) -> DemoSection:
    """Age a synthetic iris set with sensors A and H × 100 and measure Masek's EER against age."""
    simulate_irises(workdir / "irises", CLASSES, SAMPLES, rng, progress=progress)
    source = open_dataset(workdir / "irises")
    sensors = parse_sensors(SENSORS, source.shape()[:2], 8)
    result = run_impact(source, sensors, AGES, load_matchers([MATCHER]), rng, protocols=["same-age", "enrol-0"],
                        n_boot=500, progress=progress, executor=executor)
    rep = Report(TITLE)
    rep.text(f"{CLASSES} synthetic eyes × {SAMPLES} near-infrared images (320×240, 8-bit) are aged by two virtual "
             "sensors: A (the paper's Irisguard H100) and H × 100 (a hundred times the rates of H, the paper's most "
             "aggressive sensor: far beyond any real one).  Masek's 1-D Log-Gabor iris code scores every pair at each "
             "age. Run the full experiment with `forensics impact` (all sensors, 13 ages, both matchers).")
    rep.extend(impact_report(result, title="Impact"), prefix="impact_")
    summary = []
    data = {"eer": {}, "trend": {}}
    for sensor in result.sensors:
        t = result.trend(sensor, MATCHER, "same-age")
        first = result.unit(sensor, AGES[0], MATCHER, "same-age").eer.estimate
        last = result.unit(sensor, AGES[-1], MATCHER, "same-age").eer.estimate
        summary.append(f"impact: {MATCHER}, sensor {sensor}: EER {100 * first:.2f} % → {100 * last:.2f} % over "
                       f"{AGES[-1]:g} years; {t.describe()}")
        data["eer"][sensor] = [u.eer.to_dict() for u in result.trajectory(sensor, MATCHER, "same-age")]
        data["trend"][sensor] = t.to_dict()
    return DemoSection(TITLE, rep, summary, data)
