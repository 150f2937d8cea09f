"""Demo section: defects detected from ordinary images, their growth rate against the truth, a dated set."""
from __future__ import annotations

from pathlib import Path

from forensics._shared.parallel import Executor
from forensics._shared.progress import Progress
from forensics._shared.rng import RngLike
from forensics.defects.dating import date_dataset
from forensics.defects.detection import MaskSpec
from forensics.defects.growth import epochs_from_datasets, estimate_growth
from forensics.io.dataset import open_dataset
from forensics.report.defects import defects_demo_report
from forensics.sensor.catalogue import PARTIAL
from forensics.sensor.presets import preset
from forensics.sensor.simulate import age_dataset, make_scenes, read_catalogue
from forensics.validate.truth import count_true, match_truth

from . import DemoSection

TITLE = "Sensor defects: detection, growth rate and dating"
SENSOR = "G"
SIZE = (240, 320)
IMAGES = 20
RATE_SCALE = 25.0
REFERENCE_AGES = (2.0, 6.0, 10.0)
QUERY_AGE = 14.0
START = 2000.0


def run(workdir: Path, rng: RngLike, progress: Progress, executor: Executor | None = None) -> DemoSection:
    """Simulate a device at three reference ages and a query age; detect, estimate growth, date the query.

    ``rng`` (Generator or int seed) draws the scenes, then the device and the frames' noise.
    """
    scenes = make_scenes(workdir / "scenes", IMAGES, SIZE, rng, bit_depth=16, progress=progress)
    model = preset(SENSOR, SIZE, bit_depth=16, rate_scale=RATE_SCALE)
    ages = list(REFERENCE_AGES) + [QUERY_AGE]
    age_dataset(scenes, workdir / "aged", model, ages, rng, start_year=START, sensor_name=SENSOR, progress=progress,
                executor=executor)
    truth = read_catalogue(workdir / "aged" / "defects.csv")
    sets = [open_dataset(workdir / "aged" / f"year_{int(a):03d}") for a in ages]
    mask = MaskSpec("centre", 0.3)
    epochs = epochs_from_datasets(sets[:-1], mask=mask, progress=progress, executor=executor)
    growth = estimate_growth(epochs)
    gmodel = growth.model()
    dated = date_dataset(gmodel, sets[-1], progress=progress, executor=executor)

    # truth: the rate of partially stuck defects above the threshold used, λ·(1 − (τ − centre)/a_ps)
    g = model.effect("growth")
    det = epochs[-1].detection
    thr = det.tau - det.fits[0].center
    true_rate = g.rate_partial * max(0.0, 1 - thr / g.amp_partial)
    true_counts = [count_true(truth, START + a, det.mask, PARTIAL, above=thr) for a in REFERENCE_AGES]
    matched = match_truth(det, truth, START + REFERENCE_AGES[-1])
    recall = matched.recall(matched.amplitude >= det.tau - det.fits[0].center + 3 * det.fits[0].scale)
    precision = matched.precision

    intro = (f"A simulated device (the paper's sensor {SENSOR}, rates ×{RATE_SCALE:g} so that a {SIZE[1]}×{SIZE[0]} "
             f"frame collects defects, 16-bit) images the same {IMAGES} ordinary scenes at ages "
             f"{', '.join(f'{a:g}' for a in REFERENCE_AGES)} years (reference epochs) and {QUERY_AGE:g} years (the "
             "query). Nothing but the images and their capture dates is given to the estimators.")
    rep = defects_demo_report(
        TITLE, intro, epochs=epochs, growth=growth, model=gmodel, dated=dated, query_true=START + QUERY_AGE,
        truth={"recall": recall, "precision": precision, "true_rate": true_rate, "rate_partial": g.rate_partial,
               "dates": [START + a for a in REFERENCE_AGES], "counts": true_counts})
    r = growth.partial.rate
    lo, hi = dated.interval
    summary = [f"defects: {det.count()} found at {epochs[-1].date:.0f} (recall {recall:.2f}, precision "
               f"{precision:.2f}); rate {r.rate:.3g} [{r.ci[0]:.3g}, {r.ci[1]:.3g}] /MP/yr vs true {true_rate:.3g}; "
               f"query set of {START + QUERY_AGE:g} dated {dated.estimate:.1f} "
               f"[{'…' if lo is None else f'{lo:.1f}'}, {'…' if hi is None else f'{hi:.1f}'}]"]
    data = {"rate_partial": r.rate, "rate_partial_ci": list(r.ci), "true_rate": true_rate, "recall": recall,
            "precision": precision, "query_true": START + QUERY_AGE, "query_estimate": dated.estimate,
            "query_interval": [lo, hi]}
    return DemoSection(TITLE, rep, summary, data)
