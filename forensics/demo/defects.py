"""Demo section: defects detected from ordinary images, their growth rate against the truth, a dated set."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from forensics.io.dataset import open_dataset
from forensics.defects.dating import date_dataset, set_dating_figure
from forensics.defects.detection import MaskSpec, defect_map_figure, histogram_figure
from forensics.defects.growth import epochs_from_datasets, estimate_growth, counts_figure
from forensics.sensor.model import PARTIAL
from forensics.sensor.presets import preset
from forensics._shared.progress import Progress
from forensics.report.html import Report, new_figure
from forensics.sensor.simulate import age_dataset, make_scenes, read_catalogue
from . import DemoSection

TITLE = "Sensor defects: detection, growth rate and dating"
SENSOR = "G"
SIZE = (240, 320)
IMAGES = 20
RATE_SCALE = 25.0
REFERENCE_AGES = (2.0, 6.0, 10.0)
QUERY_AGE = 14.0
START = 2000.0


def run(workdir: Path, seed: int, progress: Progress) -> DemoSection:
    scenes = make_scenes(workdir / "scenes", IMAGES, SIZE, seed, bit_depth=16, progress=progress)
    model = preset(SENSOR, SIZE, bit_depth=16, rate_scale=RATE_SCALE)
    ages = list(REFERENCE_AGES) + [QUERY_AGE]
    age_dataset(scenes, workdir / "aged", model, ages, seed, start_year=START, sensor_name=SENSOR, progress=progress)
    truth = read_catalogue(workdir / "aged" / "defects.csv")
    sets = [open_dataset(workdir / "aged" / f"year_{int(a):03d}") for a in ages]
    mask = MaskSpec("centre", 0.3)
    epochs = epochs_from_datasets(sets[:-1], mask=mask, progress=progress)
    growth = estimate_growth(epochs)
    gmodel = growth.model()
    dated = date_dataset(gmodel, sets[-1], progress=progress)

    # truth: the rate of partially stuck defects above the threshold used, λ·(1 − (τ − centre)/a_ps)
    g = model.effect("growth")
    det = epochs[-1].detection
    thr = det.tau - det.fits[0].center
    true_rate = g.rate_partial * max(0.0, 1 - thr / g.amp_partial)
    region = det.mask
    true_counts = []
    for a in REFERENCE_AGES:
        eff = truth.effective(START + a)
        inside = region[eff.y, eff.x] & (eff.kind == PARTIAL) & (eff.amplitude > thr)
        true_counts.append(int(inside.sum()))
    found = det.sites()
    eff = truth.effective(START + REFERENCE_AGES[-1])
    inside = region[eff.y, eff.x]
    strong = inside & (eff.amplitude >= det.tau - det.fits[0].center + 3 * det.fits[0].scale)
    recall = float(np.mean([s in found for s in zip(eff.x[strong].tolist(), eff.y[strong].tolist())])) if strong.any() else float("nan")
    true_sites = set(zip(eff.x.tolist(), eff.y.tolist()))
    precision = len(found & true_sites) / max(len(found), 1)

    rep = Report(TITLE)
    rep.text(f"A simulated device (the paper's sensor {SENSOR}, rates ×{RATE_SCALE:g} so that a {SIZE[1]}×{SIZE[0]} "
             f"frame collects defects, 16-bit) images the same {IMAGES} ordinary scenes at ages "
             f"{', '.join(f'{a:g}' for a in REFERENCE_AGES)} years (reference epochs) and {QUERY_AGE:g} years (the "
             "query). Nothing but the images and their capture dates is given to the estimators.")
    rep.heading("Detection at two epochs")
    for ep in (epochs[0], epochs[-1]):
        d = ep.detection
        rep.text(f"{ep.date:.0f}: {d.count()} defects, τ = {d.tau:.4g} DN = median + 5·1.4826·MAD of d̂ over "
                 f"{d.megapixels:.3g} MP (centre 30 % left out).")
    rep.figure(histogram_figure(det), "histogram", "Accumulated histogram of d̂ at the last reference epoch: "
               "pixels above each threshold; the dashed line is the normal model fitted to the bulk.")
    rep.figure(defect_map_figure(det), "map", f"Defects detected at {epochs[-1].date:.0f}.")
    rep.text(f"Against the truth at {epochs[-1].date:.0f}: recall {recall:.2f} for defects 3σ above τ, "
             f"precision {precision:.2f}.")
    rep.heading("Growth rate")
    r = growth.partial.rate
    rep.text(f"Partially stuck: {r.rate:.3g} defects/MP/year, exact 95 % interval [{r.ci[0]:.3g}, {r.ci[1]:.3g}] "
             f"(threshold {det.sigma:g}σ); true rate above that threshold {true_rate:.3g} "
             f"(λ = {g.rate_partial:.3g} for all amplitudes). The paper's eq. 17 on the first and last epoch gives "
             f"{growth.paper.lambda_ps:.3g} (γ = {growth.paper.gamma:.2f}).")
    fig = counts_figure(growth)
    rep.figure(fig, "growth", "Defects first seen by each epoch with Garwood intervals and the fitted rate.")
    fig, ax = new_figure(6.4, 3.2)
    ax.plot([START + a for a in REFERENCE_AGES], true_counts, "s--", color="0.4", label="true (above τ)")
    cum = np.cumsum([growth.partial.counts[0]] + growth.partial.new)
    ax.plot(growth.dates, cum, "o-", label="estimated (first appearances)")
    ax.set_xlabel("year")
    ax.set_ylabel("partially stuck defects")
    ax.legend(fontsize=8)
    rep.figure(fig, "truth", "Estimated and true counts of defects above the threshold.")
    rep.heading("Dating a query set")
    lo, hi = dated.interval
    rep.text(f"The query set was taken in {START + QUERY_AGE:g}; estimated {dated.estimate:.2f}, 95 % interval "
             f"[{lo if lo is None else round(lo, 2)}, {hi if hi is None else round(hi, 2)}] ({dated.method}).")
    rep.figure(set_dating_figure(gmodel, dated), "dating", "Reference counts and the query's date with its interval.")
    summary = [f"defects: {det.count()} found at {epochs[-1].date:.0f} (recall {recall:.2f}, precision "
               f"{precision:.2f}); rate {r.rate:.3g} [{r.ci[0]:.3g}, {r.ci[1]:.3g}] /MP/yr vs true {true_rate:.3g}; "
               f"query set of {START + QUERY_AGE:g} dated {dated.estimate:.1f} "
               f"[{'…' if lo is None else f'{lo:.1f}'}, {'…' if hi is None else f'{hi:.1f}'}]"]
    data = {"rate_partial": r.rate, "rate_partial_ci": list(r.ci), "true_rate": true_rate, "recall": recall,
            "precision": precision, "query_true": START + QUERY_AGE, "query_estimate": dated.estimate,
            "query_interval": [lo, hi]}
    return DemoSection(TITLE, rep, summary, data)
