"""Design warnings: what the data cannot show, and which frames to add."""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from forensics.check.classes import QUANT_VAR, dark_groups
from forensics.check.diagnosis import FLAG_DBIC
from forensics.check.evidence import Evidence
from forensics.check.measurements import Measurements
from forensics.check.params import is_pixel
from forensics.check.pixels import PixelData
from forensics.check.result import Candidate
from forensics.sensor.model import EFFECTS, Effect, Stage


def design_warnings(ev: Evidence, px: PixelData, candidates: list[Candidate], effects: list[Effect]) -> list[str]:
    """What the data lack to test or separate the candidates, and what frames to add."""
    meas = ev.meas
    out = []
    levels = light_levels(ev, px)
    mins = {"exposure_s": 3, "iso": 2, "temperature_c": 2}
    have = {name: meas.field_values(name) for name in mins}
    for name, need in mins.items():
        if len(have[name]) < need:
            users = [n for n, c in EFFECTS.items() if c.role == "candidate" and name in c.fields]
            out.append(f"the data have {len(have[name])} value(s) of {name} ({_fmt_values(have[name])}); "
                       f"at least {need} are needed to test {', '.join(users) or 'effects that need it'}: "
                       f"add frames at another {name}")
    if levels < 3:
        users = [n for n, c in EFFECTS.items() if c.role == "candidate" and c.stage in (Stage.GAIN, Stage.RESPONSE)]
        out.append(f"the data have {levels} distinct light level(s); with fewer than 3 a per-pixel response and a "
                   f"response curve cannot be told apart ({', '.join(users)}): add flat fields at a third light level")
    fitted_singles = set(meas.single) if ev.singles is not None and ev.singles.law is not None else set()
    unfitted = sum(1 for g in meas.groups if g.n < 2 and g.index not in fitted_singles)
    if unfitted:
        out.append(f"{unfitted} condition(s) have a single frame{' and are not dark frames' if fitted_singles else ''}: "
                   "they serve defect detection only; take 2 frames per condition for the noise floor")
    if meas.has_time and len(ev.times) < 5:
        out.append(f"only {len(ev.times)} epochs: defect arrival and placement need at least 5 epochs of a few frames each")
    # near-ties between flagged candidates
    flagged = [c for c in candidates if c.flagged]
    for i, a in enumerate(flagged):
        for b in flagged[i + 1:]:
            if abs(a.delta_bic - b.delta_bic) < FLAG_DBIC and {t.channel for t in a.tests} & {t.channel for t in b.tests}:
                out.append(f"the data cannot separate {a.effect} from {b.effect} (predicted ΔBIC "
                           f"{a.delta_bic:.3g} vs {b.delta_bic:.3g}): {_frames_to_add(ev, px, a.effect, b.effect)}")
    out += data_limits(ev.meas)
    for c in candidates:
        if not c.tests:
            stage = EFFECTS[c.effect].stage.name.lower() if c.effect in EFFECTS else "?"
            out.append(f"{c.effect} cannot be tested with these data: its signature is zero here (it acts at the "
                       f"{stage} stage; e.g. on defective pixels, which these data may lack)")
        channels = {t.channel for t in c.tests} if c.absorbed else set()
        if "pixel" in channels:
            model_names = ", ".join(e.key for e in effects if is_pixel(e))
            out.append(f"{c.effect} cannot be detected with these data: its signature is absorbed by the fitted "
                       f"parameters of {model_names}; {_frames_to_add(ev, px, c.effect, None)}")
        if "variance" in channels:
            noise_names = ", ".join(e.key for e in effects if e.stage == Stage.NOISE)
            out.append(f"{c.effect} cannot be detected with these data: it moves the frames' temporal variance only "
                       f"as the fitted parameters of {noise_names} do")
    return out


#: Lag-1 spatial correlation of the temporal noise above which it is no longer a raw sensor's (≈ 0).
CORRELATED_NOISE = 0.2


def data_limits(meas: Measurements) -> list[str]:
    """What the frames themselves limit: in-camera processing (JPEG, demosaicing: spatially correlated noise)
    and frame-to-frame level changes."""
    out = []
    traits = meas.traits
    if traits is None:
        return out
    rho = traits.lag1
    correlated = rho is not None and rho > CORRELATED_NOISE
    if traits.jpeg or correlated:
        why = " and ".join(w for w in ("the frames are JPEG-compressed" if traits.jpeg else "",
                                        f"the temporal noise is spatially correlated (lag-1 ρ = {rho:.2f})"
                                        if correlated else "") if w)
        out.append(f"{why}: the camera processed the sensor's output (demosaicing, compression), so σ_k is the "
                   "effective in-camera value, not the sensor's raw PRNU (and likewise for every fixed pattern); "
                   "the pixel channel's noise floor is measured on the residuals, so its tests stay calibrated")
    drifts = [(meas.drift(r), meas.groups[g]) for r, g in enumerate(meas.repeated)]
    moved = [(d, g) for d, g in drifts
             if d.material(float(np.median(meas.var_all[g.index][meas.interior])))]
    if moved:
        sd = math.sqrt(max(d.var for d, _ in moved))
        noise = max(float(np.median(meas.var_all[g.index][meas.interior])) for _, g in moved)
        out.append(f"frame-to-frame level changes removed; they are not pixel noise: in {len(moved)} of "
                   f"{len(drifts)} condition(s) the frame means spread by up to {sd:.2g} DN rms, more than "
                   f"the noise allows (F test p < 0.001; {sd**2 / max(noise, 1e-12):.0%} of a pixel's temporal "
                   "variance); the noise floor and the binned variances are measured without them")
    return out


def _fmt_values(values: list[Any]) -> str:
    return ", ".join(f"{v:g}" for v in values) if values else "none"


def light_levels(ev: Evidence, px: PixelData) -> int:
    """Number of distinct light levels over the repeated conditions (medians more than 10 noise σ apart)."""
    meds = np.sort([float(np.median(px.scene_a[r][ev.meas.interior])) for r in range(len(ev.rep))])
    noise = math.sqrt(max(float(np.median(px.floor)), QUANT_VAR))
    if meds.size == 0:
        return 0
    return int(1 + np.sum(np.diff(meds) > 10 * noise))


def unscored_fields(ev: Evidence, fields: list[str]) -> dict[str, list[Any]]:
    """The ``fields`` that vary over the dark conditions only through their single frames (each with the dark
    conditions' values): the repeated (scored) dark conditions hold fewer than two values of it, the dark
    conditions together two or more.

    Why it matters: a single frame is fitted but never scored (it has no second half to predict,
    :mod:`~forensics.check.singles`), so an effect that shows only across the single darks — a dark series whose one
    repeated condition is its biases — cannot be tested however many exposures the series has.  Scoring the single
    frames' own residuals was tried: a frame's level jitters from readout to readout, and once that is taken out
    a synthetic series without read-out charge still read its thermistor's quantisation (a hot pixel's 18,000 DN
    moved by 0.35 % per 0.025 °C) as read-out charge and a response curve (benchmarks/RESULTS_check.md,
    twenty-fourth session)."""
    is_dark = dark_groups(ev.rgroups)
    n_rep = len(ev.meas.repeated)
    out = {}
    for f in fields:
        scored = {getattr(g, f) for g, d in zip(ev.rgroups[:n_rep], is_dark[:n_rep]) if d} - {None}
        every = {getattr(g, f) for g, d in zip(ev.rgroups, is_dark) if d} - {None}
        if len(scored) < 2 <= len(every):
            out[f] = sorted(every)
    return out


def _frames_to_add(ev: Evidence, px: PixelData, a: str, b: str | None) -> str:
    if b is None and a in EFFECTS and ev.singles is not None and ev.singles.law is not None:
        fields = unscored_fields(ev, [f for f in ("exposure_s", "temperature_c") if f in EFFECTS[a].fields])
        if fields:
            values = " and ".join(f"{f} ({_fmt_values(v)})" for f, v in fields.items())
            return (f"the dark frames vary {values} only in single frames, which are "
                    "fitted but not scored: take two or more frames of one dark exposure (a repeated dark "
                    "condition, e.g. ten of 60 s) at each temperature")
    fa = set(EFFECTS[a].fields) if a in EFFECTS else set()
    fb = set(EFFECTS[b].fields) if b in EFFECTS else set()
    fields = sorted((fa ^ fb) if b else fa) or sorted(fa | fb)
    fields = [f for f in fields if f != "captured"]
    parts = []
    for f in fields:
        vals = ev.meas.field_values(f)
        parts.append(f"frames at another {f} (the data have {_fmt_values(vals)}), other conditions unchanged")
    if not parts:
        parts.append(f"flat fields at more light levels (the data have {light_levels(ev, px)})")
    return "add " + "; ".join(parts)
