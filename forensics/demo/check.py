"""Demo section: a simulated device with a hidden effect; the model check names it; adding it, the error falls."""
from __future__ import annotations

from pathlib import Path

from forensics._shared.parallel import Executor
from forensics._shared.progress import Progress
from forensics._shared.rng import RngLike
from forensics.check import Evidence, base_model, load_measurements, run_check
from forensics.report.check import check_report
from forensics.report.html import Report
from forensics.sensor.model import make_effect
from . import DemoSection

TITLE = "Model against measurement: find the missing effect, add it, watch the error fall"
HIDDEN = "dark_current"


def run(workdir: Path, rng: RngLike, progress: Progress, executor: Executor | None = None) -> DemoSection:
    from forensics.fixtures.hidden import HIDDEN as STRENGTHS
    from forensics.fixtures.hidden import make_hidden

    data = make_hidden(HIDDEN, workdir / "lab", rng=rng, progress=progress)
    meas = load_measurements(data.out, progress=progress)
    evidence = Evidence(meas, rng=rng)
    before = run_check(evidence, base_model())
    named = before.flagged[0] if before.flagged else None
    rep = Report(TITLE)
    params = ", ".join(f"{k} = {v:g}" for k, v in STRENGTHS[HIDDEN].items())
    rep.text(f"A simulated sensor has the base model's defects (Poisson arrivals of partially stuck and stuck "
             f"pixels, read noise) and one effect the base model lacks: {HIDDEN} ({params}). It is measured as a lab "
             f"would: {data.n_frames} frames — dark frames and vignetted flat fields at 3 exposure times, 2 ISO "
             f"values, 2 temperatures, 2 frames per condition, and a reference condition at each of 10 yearly "
             f"epochs. The check fits the base model on one half of the repeated frames, scores it on the other, "
             f"and ranks the candidate effects by predicted ΔBIC without fitting them.")
    summary = [f"model check: hidden {HIDDEN}; base model error.pixel {before.error['pixel']:.3g} "
               f"(1.0 = noise floor)"]
    out = {"hidden": HIDDEN, "named": named, "before": before.error, "flagged_before": before.flagged}
    if named is None:
        rep.text("The base check flagged nothing, so there is nothing to add.", note=True)
        rep.extend(check_report(before, title="Base model"), prefix="base_")
        summary.append("model check: nothing flagged")
        return DemoSection(TITLE, rep, summary, out)
    top = before.candidates[0]
    after = run_check(evidence, [*base_model(), make_effect(named)])
    after.baseline = before
    rep.text(f"The check names {named} (predicted ΔBIC {top.delta_bic:.3g}, Holm-adjusted p {top.p:.2g}): "
             f"{top.evidence}.")
    rep.text(f"Adding {named} and refitting: error.pixel {before.error['pixel']:.3g} → {after.error['pixel']:.3g}; "
             f"flagged before: {', '.join(before.flagged)}; flagged after: {', '.join(after.flagged) or 'nothing'}; "
             "gof p after: " + ", ".join(f"{k} {v:.2g}" for k, v in after.gof.items() if v is not None) + ".")
    rep.extend(check_report(after, title="Before and after"), prefix="check_")
    summary.append(f"model check: named {named} (ΔBIC {top.delta_bic:.3g}); adding it, error.pixel "
                   f"{before.error['pixel']:.3g} → {after.error['pixel']:.3g}, flagged after: "
                   f"{', '.join(after.flagged) or 'nothing'}")
    out.update({"after": after.error, "flagged_after": after.flagged, "gof_after": after.gof})
    tiled = _whole_frame_in_tiles(workdir, rng, progress, executor, rep)
    summary.append(tiled[0])
    out["tiles"] = tiled[1]
    return DemoSection(TITLE, rep, summary, out)


#: The demo's tiled dark series: a cooled CCD whose output amplifier glows, tripling the dark rate at one corner.
GLOW = 2.0


def _whole_frame_in_tiles(workdir: Path, rng: RngLike, progress: Progress, executor: Executor | None,
                          rep: Report) -> tuple[str, dict]:
    """A whole frame checked tile by tile (:func:`~forensics.check.tiles.check_tiles`): a synthetic cooled-CCD
    dark series with amplifier glow, which one region cannot show and the tiles' disagreement on the dark rate
    does.  Returns the summary line and the figures, and adds the section to ``rep``."""
    from forensics.check.tiles import check_tiles
    from forensics.fixtures.darkseries import DarkSeriesDesign, make_dark_series
    from forensics.report.check import tiles_report

    design = DarkSeriesDesign(shape=(96, 128), temperature_wander=0.0, offset_jitter=0.0, readout_s=0.0,
                              column_pattern=0.0, doubling_hot=5.0, hot_fraction=0.01, hot_min=3.0, hot_max=10.0,
                              n_repeat_dark=6, cosmic_rate=1e-5, glow=GLOW)
    folder = workdir / "glow"
    make_dark_series(folder, rng, design)
    tiled = check_tiles(folder, add=["shot_noise", "dark_current"], size=48, rng=rng, progress=progress,
                        executor=executor)
    rate = next(p for p in tiled.params if p.estimate.label == "dark_current.rate")
    rep.text(f"The whole frame, tile by tile: a simulated cooled CCD's dark series (biases and darks at two set "
             f"points, {design.shape[1]}×{design.shape[0]} px) whose output amplifier glows, multiplying the dark "
             f"rate by up to {1 + GLOW:g} near one corner. Each of {len(tiled.tiles)} tiles is checked on its own "
             f"and the tiles are combined; the dark rate's heterogeneity test says the tiles disagree (p same "
             f"{rate.p_same:.2g}, spread {rate.spread:.2g} DN/s), which no single region can show — the map below "
             "shows where.")
    rep.extend(tiles_report(tiled, title="Whole frame in tiles"), prefix="tiles_")
    line = (f"model check in tiles: amplifier glow found as a dark rate that differs between {len(tiled.tiles)} tiles "
            f"(p same {rate.p_same:.2g}); read noise p same "
            + next(f"{p.p_same:.2g}" for p in tiled.params if p.estimate.label == "read_noise.sigma"))
    return line, {"rate_p_same": rate.p_same, "rate_spread": rate.spread,
                  "p_same": {p.estimate.label: p.p_same for p in tiled.params}}
