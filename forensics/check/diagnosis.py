"""Diagnosis: rank the candidate effects by how much adding each would improve the fit, without fitting them.

For each candidate not in the model, its signature (:mod:`forensics.check.signatures`) is tested against
the fitted model's residuals in every channel (:mod:`forensics.check.scoretests`).  Each candidate gets a
predicted ΔBIC ≈ LM − q·ln n (q: its parameter count, n: the main channel's sample size) and a p-value;
candidates are ranked by predicted ΔBIC (p-values underflow) and flagged only when ΔBIC > ``FLAG_DBIC``
(also with each fixed pattern counted only as far as both halves of the frames show it) and the Holm-adjusted
p < ``FLAG_P`` (:func:`flag_rule`).
"""
from __future__ import annotations

import math

import numpy as np
from forensics.stats.tails import chi2_sf

from forensics._shared.errors import InputError
from forensics.check.classes import CLASSES, STK
from forensics.check.evidence import Evidence
from forensics.check.fit import FittedModel
from forensics.check.result import Candidate, ChannelTest
from forensics.check.scoretests import score_growth, score_pixel, score_spatial, score_variance
from forensics.check.signatures import Signature, SignatureContext
from forensics.check.pixels import PixelData
from forensics.sensor.model import Effect, make_effect
from forensics.stats.multiple import holm_adjusted

#: Flagging rule: predicted ΔBIC above this and Holm-adjusted p below ``FLAG_P``.
FLAG_DBIC = 10.0
FLAG_P = 0.01


def diagnose(ev: Evidence, fitted: FittedModel, candidates: list[str]) -> tuple[list[Candidate], list[str]]:
    """Rank the candidates by predicted ΔBIC and flag the strongly supported ones.

    Returns the candidates (best first) and notes on the candidates that could not be tested.
    """
    px = fitted.pixels
    meas = ev.meas
    keep = ev.usable & (px.classes != STK)
    z = np.where(keep, fitted.projector.project((meas.mean_a - fitted.mu_a) * np.sqrt(px.weight)), 0.0)
    n_obs = int(keep.sum())
    context = SignatureContext(ev, fitted)
    results = []
    notes = []
    have = {name: meas.field_values(name) for name in ("exposure_s", "iso", "temperature_c")}
    for name in candidates:
        effect = make_effect(name)
        missing = [f for f in effect.fields if (f == "captured" and (not meas.has_time or len(ev.times) < 3))
                   or (f in have and not have[f])]
        if missing:
            notes.append(f"{name} not tested: the data lack {', '.join(missing)}"
                         + (" (at least 3 epochs)" if "captured" in missing else ""))
            continue
        try:
            sigs = effect.signature(context)
        except InputError as exc:
            notes.append(f"{name} not tested: {exc}")
            continue
        tests = []
        tests += score_pixel(ev, fitted, [s for s in sigs if s.channel == "pixel"], z, n_obs)
        tests += score_variance(ev, fitted, [s for s in sigs if s.channel == "variance"])
        tests += score_growth(ev, fitted, [s for s in sigs if s.channel == "growth"])
        tests += score_spatial(ev, fitted, [s for s in sigs if s.channel == "spatial"])
        results.append(_candidate(effect, name, tests, n_obs, _where(ev.usable, px, sigs)))
    holm(results)
    results.sort(key=lambda c: -c.delta_bic)
    return results, notes


def _candidate(effect: Effect, name: str, tests: list[ChannelTest], n_obs: int, where: str) -> Candidate:
    """One candidate's evidence from its channel tests: predicted ΔBIC and raw p-value."""
    lm = float(sum(t.lm for t in tests))
    df = int(sum(t.df for t in tests))
    q = effect.n_params()
    confirmed = None
    if tests and df > 0:
        main = max(tests, key=lambda t: t.lm)
        penalty = q * math.log(max(main.n, 2))
        dbic = lm - penalty
        if any(t.confirmed is not None for t in tests):
            confirmed = sum(t.lm if t.confirmed is None else min(t.lm, t.confirmed) for t in tests) - penalty
        p_raw = float(chi2_sf(lm, df))
        if len(tests) == 1 and tests[0].boundary:
            p_raw *= 0.5
    else:
        dbic, p_raw = -q * math.log(max(n_obs, 2)), 1.0
    absorbed = bool(tests) and all(t.absorbed for t in tests)
    evidence = "; ".join(t.detail for t in sorted(tests, key=lambda t: -t.lm)) or "no signature in these data"
    if where:
        evidence = f"{where}; {evidence}"
    return Candidate(name, float(dbic), p_raw, False, lm, df, p_raw, q, tests, evidence, absorbed,
                     None if confirmed is None else float(confirmed))


def flag_rule(delta_bic: float, delta_bic_confirmed: float | None, p_adjusted: float) -> bool:
    """The flagging rule: predicted ΔBIC above :data:`FLAG_DBIC` — also when every fixed pattern counts only as far
    as both halves of the frames show it — and the Holm-adjusted p below :data:`FLAG_P`.

    The second condition is there because the first half's random-effect ratio also grows with anything that
    inflates that half's residual variance unevenly (noise the floor misses, a misfit of the other parameters);
    a pattern the model lacks is in both halves, and the split-half z² is that test's own χ²₁.

    Examples
    --------
    >>> flag_rule(30.0, None, 1e-6), flag_rule(30.0, -2.0, 1e-6), flag_rule(30.0, 12.0, 0.5)
    (True, False, False)
    """
    confirmed = delta_bic_confirmed is None or delta_bic_confirmed > FLAG_DBIC
    return bool(delta_bic > FLAG_DBIC and confirmed and p_adjusted < FLAG_P)


def holm(results: list[Candidate]) -> None:
    """Holm-adjusted p-values and the flags, set on ``results`` (the candidates being assembled)."""
    if not results:
        return
    for c, adj in zip(results, holm_adjusted([c.p_raw for c in results])):
        c.p = float(adj)
        c.flagged = flag_rule(c.delta_bic, c.delta_bic_confirmed, c.p)


def _where(usable: np.ndarray, px: PixelData, sigs: list[Signature]) -> str:
    """Which pixel classes a pixel signature acts on."""
    mass = np.zeros(3)
    for s in sigs:
        if s.channel != "pixel":
            continue
        x2 = np.where(usable, s.x**2 * px.weight, 0.0)
        for k in range(3):
            mass[k] += float(np.sum(x2[px.classes == k]))
    if mass.sum() <= 0:
        return ""
    share = mass / mass.sum()
    names = [f"{CLASSES[k]} {share[k]:.0%}" for k in range(3) if share[k] >= 0.01]
    return "acts on " + ", ".join(names) + " pixels"
