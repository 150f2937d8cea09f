"""Demo section: a cooled CCD's dark-frame series (FITS) — dark rates, their temperature law, hot pixels.

With the shared data present (``../shared/data/sbig-stl1001e-2017``, beside the checkout, or the folder
``FORENSICS_SHARED_DATA`` names) the section runs on the 52 real frames of an SBIG STL-1001E and sets its figures
against the independent ones of issue 28; without it, on a small synthetic series written with astropy
(:mod:`forensics.fixtures.darkseries`) whose truth it is compared with.  The real frames are never copied.
"""
from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from forensics._shared.parallel import Executor
from forensics._shared.progress import Progress
from forensics._shared.rng import RngLike
from forensics.defects.darkdetect import DarkDetectionResult, DarkSettings, detect_dark_dataset
from forensics.io.dataset import open_dataset
from forensics.report.darkseries import dark_report
from forensics.report.html import Report

from . import DemoSection

TITLE = "A cooled CCD's dark frames (FITS): dark rate, its temperature law, hot pixels"
REAL_SERIES = "sbig-stl1001e-2017"
#: The hot-pixel threshold of the example: 1 ADU/s at −10 °C (a few times the bulk's 0.17 ADU/s at −10 °C).
THRESHOLD_ADU_PER_S = 1.0
T_REF_C = -10.0


@dataclass(frozen=True)
class Reference:
    """An independent figure of one ``kind`` (``rate``, ``bias_all``, ``read_noise``, ``gain``, ``hot_pixels``), for
    the group at ``set_point`` (None: any group), known to within ``[lo, hi]`` (its rounding, or the range it was
    given as)."""

    kind: str
    set_point: float | None
    value: float
    lo: float
    hi: float
    source: str


#: Issue 28's independent figures for the 2017 series (simple per-pixel regressions, no temperature correction),
#: each with the interval its stated precision implies.
REFERENCES_2017 = (
    Reference("rate", -10.0, 0.17, 0.165, 0.175, "issue 28 (two digits)"),
    Reference("rate", -5.0, 0.35, 0.345, 0.355, "issue 28 (two digits)"),
    Reference("bias_all", None, 992.0, 991.5, 992.5, "issue 28 (≈ 992, all biases)"),
    Reference("read_noise", None, 6.8, 6.3, 7.3, "issue 28 (range 6.3–7.3)"),
    Reference("gain", None, 1.9, 1.85, 1.95, "issue 28 (a flat pair, two digits)"),
)


def shared_data() -> Path:
    """Where the team's real data are: ``$FORENSICS_SHARED_DATA``, else ``shared/data`` beside the checkout."""
    env = os.environ.get("FORENSICS_SHARED_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2].parent / "shared" / "data"


def measured_figures(result: DarkDetectionResult) -> list[dict[str, Any]]:
    """The fitted figures an astronomer quotes, each with its interval: every group's median dark rate (at its
    effective temperature) and bias, the bias over all bias frames, every group's read noise (its interval: the range
    of the group's and each bias frame's estimate), the hot-pixel count, and the conversion gains (flat pairs, the
    dark signal's shot noise)."""
    fit = result.series
    assert fit is not None
    rows = []
    for g in fit.groups:
        lo, hi = g.median_rate_ci()
        rows.append({"kind": "rate", "set_point": g.set_temperature_c,
                     "quantity": f"median dark rate at {g.temperature_c:+.2f} °C, {g.label} (ADU/s)",
                     "value": g.median_rate, "ci": [lo, hi]})
        if g.n_bias:
            half = 1.96 * g.bias_level_se
            rows.append({"kind": "bias", "set_point": g.set_temperature_c, "quantity": f"bias, {g.label} (ADU)",
                         "value": g.bias_level, "ci": [g.bias_level - half, g.bias_level + half]})
        # its sampling error over a megapixel is a few thousandths of an ADU; what does vary is the estimate's
        # definition (each frame against the pixels' offsets, or every pixel's temporal variance, which also holds
        # the frames' offset jitter): the interval is the range of these estimates, not a confidence interval
        spread = [g.read_noise, *g.read_noise_frames]
        rows.append({"kind": "read_noise", "set_point": g.set_temperature_c,
                     "quantity": f"read noise, {g.label} (ADU)", "value": g.read_noise,
                     "ci": [min(spread), max(spread)]})
    biases = [g for g in fit.groups if g.n_bias]
    if biases:  # every bias frame at once, as a single figure for the camera is usually quoted
        n = np.array([g.n_bias for g in biases], float)
        level = float(np.sum(n * [g.bias_level for g in biases]) / n.sum())
        half = 1.96 * float(np.sqrt(np.sum((n * [g.bias_level_se for g in biases]) ** 2)) / n.sum())
        rows.append({"kind": "bias_all", "set_point": None, "quantity": "bias, all bias frames (ADU)",
                     "value": level, "ci": [level - half, level + half]})
    if result.t_ref is not None:
        rows.append({"kind": "hot_pixels", "set_point": None,
                     "quantity": f"hot pixels above {result.threshold_rate:.3g} ADU/s at {result.t_ref:+.1f} °C "
                                 "(Garwood 95 %)", "value": float(result.count()), "ci": list(result.count_ci)})
    for key, gain in fit.gain.items():
        if isinstance(gain, dict) and "gain_e_per_adu" in gain:
            rows.append({"kind": "gain", "set_point": None,
                         "quantity": f"conversion gain, {key.replace('_', ' ')} (e⁻/ADU)",
                         "value": gain["gain_e_per_adu"], "ci": list(gain["ci"])})
    return rows


def compare(measured: Sequence[dict[str, Any]], references: Sequence[Reference]) -> list[dict[str, Any]]:
    """Each reference against every measured figure of its kind (and set point, when it names one): they agree when
    the measured interval overlaps the reference's."""
    out = []
    for ref in references:
        for row in measured:
            if row["kind"] != ref.kind or (ref.set_point is not None and row["set_point"] != ref.set_point):
                continue
            lo, hi = row["ci"]
            out.append({"kind": ref.kind, "quantity": row["quantity"], "measured": row["value"], "ci": [lo, hi],
                        "reference": ref.value, "reference_interval": [ref.lo, ref.hi], "source": ref.source,
                        "agree": bool(lo <= ref.hi and hi >= ref.lo)})
    return out


def truth_references(truth: Any, result: DarkDetectionResult) -> list[Reference]:
    """A synthetic series' true figures in the form of :data:`REFERENCES_2017` (exact: the interval is the value)."""
    d = truth.design
    refs = []
    for g in result.series.groups:  # type: ignore[union-attr]
        rate = float(np.median(truth.rate_at(g.temperature_c)))
        refs.append(Reference("rate", g.set_temperature_c, rate, rate, rate,
                              "truth at the group's effective temperature"))
    # the biases hold the charge of the read-out too: the true bias level is the bias map plus that dark signal
    levels = [float(np.median(truth.bias_map + truth.rate_at(sp) * d.readout_s)) for sp in d.setpoints]
    refs += [Reference("bias_all", None, float(np.mean(levels)), min(levels), max(levels),
                       "truth (bias map + read-out charge, over the set points)"),
             Reference("read_noise", None, d.read_noise, d.read_noise, d.read_noise, "truth"),
             Reference("gain", None, d.gain, d.gain, d.gain, "truth")]
    if result.t_ref is not None:
        hot = float((truth.rate_at(result.t_ref) > result.threshold_rate).sum())
        refs.append(Reference("hot_pixels", None, hot, hot, hot, "truth (pixels whose true rate is above it)"))
    return refs


def run(workdir: Path, rng: RngLike, progress: Progress, executor: Executor | None = None) -> DemoSection:
    """The real 2017 series when the shared data are here, else a synthetic one; detect, compare, report."""
    folder = shared_data() / REAL_SERIES
    real = folder.is_dir()
    truth = None
    if not real:
        from forensics.fixtures.darkseries import DarkSeriesDesign, make_dark_series

        folder = workdir / "series"
        truth = make_dark_series(folder, rng, DarkSeriesDesign(n_flats=4))
    settings = DarkSettings(threshold=THRESHOLD_ADU_PER_S, t_ref=T_REF_C)
    result = detect_dark_dataset(open_dataset(folder), settings, progress=progress, executor=executor)
    measured = measured_figures(result)
    refs = list(REFERENCES_2017) if real else truth_references(truth, result)
    table = compare(measured, refs)
    rep = Report(TITLE)
    if real:
        rep.text(f"The real frames of an SBIG STL-1001E (KAF-1001E CCD) taken on 2017-09-08, read from {folder} "
                 "(FITS with their headers, no manifest): biases and darks of 10–300 s at −10 and −5 °C, one frame "
                 "per exposure, and ten flat fields for the gain. Figures against issue 28's independent ones.")
    else:
        rep.text(f"The real series ({REAL_SERIES}) is not on this machine (looked in {shared_data()}); this "
                 "section runs instead on a small synthetic FITS series (forensics.fixtures.darkseries: a 96×64 CCD "
                 "with a lognormal bulk, a hot tail doubling more slowly, cosmic rays, thermistor noise) and compares "
                 "its figures with the truth it was made from.", note=True)
    rep.heading("Fitted figures against " + ("the independent ones" if real else "the truth"))
    rep.table(["quantity", "measured", "95 % (read noise: range of its estimates)", "reference", "its interval",
               "source", "agree"],
              [[r["quantity"], r["measured"], f"[{r['ci'][0]:.4g}, {r['ci'][1]:.4g}]", r["reference"],
                f"[{r['reference_interval'][0]:.4g}, {r['reference_interval'][1]:.4g}]", r["source"],
                "yes" if r["agree"] else "no"] for r in table])
    rep.extend(dark_report(result, title="Dark-frame series", source=REAL_SERIES if real else "synthetic series"),
               prefix="")  # the demo page prefixes the section's name
    lo, hi = result.count_ci
    groups = result.series.groups  # type: ignore[union-attr]
    rates = ", ".join(f"{g.median_rate:.3g} ADU/s at {g.temperature_c:+.1f} °C" for g in groups)
    agree = sum(r["agree"] for r in table)
    summary = [f"ccd ({'real 2017 STL-1001E' if real else 'synthetic FITS; real data absent'}): median dark rate "
               f"{rates}; {result.count()} hot pixels above {THRESHOLD_ADU_PER_S:g} ADU/s at {T_REF_C:+g} °C "
               f"[{lo:.0f}, {hi:.0f}]; {agree}/{len(table)} figures agree with the "
               f"{'independent ones' if real else 'truth'}"]
    data = {"real": real, "folder": str(folder), "hot_pixels": result.count(), "hot_pixels_ci": [lo, hi],
            "threshold_adu_per_s": THRESHOLD_ADU_PER_S, "t_ref_c": T_REF_C, "figures": _finite(table)}
    return DemoSection(TITLE, rep, summary, data)


def _finite(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """JSON-safe rows (no NaN tokens)."""
    def clean(v: Any) -> Any:
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, list):
            return [clean(x) for x in v]
        return v
    return [{k: clean(v) for k, v in row.items()} for row in rows]
