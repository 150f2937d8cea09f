"""Dark conditions of a single frame in the pixel channel: their noise, their cosmic-ray hits, their misfits.

A dark series is usually one frame per exposure and temperature: without a second frame no noise floor can be
measured for such a condition, but the model predicts its every pixel from the chain alone (no light, no scene
estimate), so the pixel channel fits it all the same (:attr:`~forensics.check.measurements.Measurements.single`)
— never scores it: the held-out error stays that of the repeats' second halves.

* **Noise.** A single frame's weight is the inverse of the variance the repeats' **pooled dark variance law**
  predicts at its level (:func:`dark_variance_law`: σ² = a + b·level over the repeated dark conditions —
  read noise plus the dark charge's shot noise), read at the level of the pixel's own line through the dark
  conditions (below), a level free of the frame's own noise.
* **Cosmic rays** (:func:`cosmic_hits`).  Within a temperature cluster of dark conditions every pixel follows a
  line in exposure, y = a + r·x (x the exposure carried to the cluster's mean temperature with a nominal
  doubling of :data:`NOMINAL_T_DOUBLE` °C: the measured temperature wanders by a few tenths of a degree); a
  hit is a single frame's sample whose weighted least-squares residual exceeds :data:`K_HIT` standard deviations
  of its exact variance (leverage included) *above* the line — charge is only ever added —, one sample per pixel
  and round (a hit pulls the whole line), the hit's neighbours of the same frame from :data:`K_GROW` (a track
  spreads its charge: :func:`forensics.defects.darkrounds.mark_hits`, the dark-series detection's rule).  A
  pixel that is hot in every condition follows its own line and is no outlier: only a one-frame excess is.
  Hits are excluded from the fit (weight 0), counted and reported.
* **Misfits** (:func:`single_frame_warnings`): a dark condition whose mean residual over its normal pixels is
  far from the others' (an offset that jumped, a sensor off its set point) is named.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from forensics.stats.tails import chi2_isf

from forensics.check.classes import NORMAL, QUANT_VAR, dark_groups
from forensics.check.measurements import Group, Measurements

if TYPE_CHECKING:
    from forensics.check.evidence import Evidence
    from forensics.check.fit import FittedModel

#: A single frame's sample this many standard deviations above its pixel's line is a cosmic-ray hit
#: (the dark-series detection's threshold: ≈ 3·10⁻⁷ false marks per sample).
K_HIT = 5.0
#: A hit's 8 neighbours are hits too from this many standard deviations, when their worst sample is in its frame.
K_GROW = 3.0
#: Rounds of the hit search (a pixel hit twice loses one sample per round).
ROUNDS = 3
#: Dark conditions whose temperatures lie within this many °C of each other form one cluster (one set point).
CLUSTER_GAP_C = 2.0
#: Doubling temperature used only to carry exposures across the few tenths of a degree within a cluster.
NOMINAL_T_DOUBLE = 7.0
#: A dark condition whose mean residual lies this many robust standard deviations from the others' is named.
K_MISFIT = 5.0


@dataclass(frozen=True)
class DarkLaw:
    """The pooled dark variance law σ²(level) = a + b·level (DN², DN) of the repeated dark conditions."""

    a: float
    b: float
    conditions: int  #: repeated dark conditions it was fitted on

    def __call__(self, level: np.ndarray) -> np.ndarray:
        return np.maximum(self.a + self.b * np.asarray(level, float), QUANT_VAR)


@dataclass(frozen=True)
class SingleFrames:
    """What the pixel channel needs of its single-frame rows (arrays ``(S, H, W)`` over
    :attr:`~forensics.check.measurements.Measurements.single`, in that order)."""

    law: DarkLaw | None
    hits: np.ndarray  #: cosmic-ray samples, excluded from the fit
    level: np.ndarray  #: the level the noise law is read at: the pixel's line through its cluster's conditions
    floor: np.ndarray  #: per-frame variance the law predicts there

    @property
    def n_hits(self) -> int:
        return int(self.hits.sum())

    def hits_per_frame(self, meas: Measurements) -> dict[str, int]:
        """Cosmic-ray samples per single condition's label."""
        return {meas.groups[g].label(): int(self.hits[k].sum()) for k, g in enumerate(meas.single)}


#: A pixel's temporal variance whose χ² tail probability, at the variance its level predicts, is below this is
#: an outlier (a cosmic-ray hit in one frame; a telegraph pixel): the mean left out of a χ² sample is ≈ 10⁻⁵ relative.
OUTLIER_P = 1e-6


def robust_variance_line(level: np.ndarray, v: np.ndarray, df: np.ndarray | int,
                         iterations: int = 4) -> tuple[float, float, np.ndarray]:
    """σ² = a + b·level fitted to sample variances ``v`` (``df`` degrees of freedom each) at the pixels' own
    means ``level``, without their outliers: ``(a, b, outlier)``.

    Outliers are variances beyond the χ² tail of probability :data:`OUTLIER_P` about the line (a cosmic-ray hit
    in one frame of a repeated condition, a telegraph pixel).  The line starts from the median variance (a few
    hits cannot move it, whatever their size) and is refitted (least squares weighted by the χ² variance of
    each value, 2σ⁴/df) on the values within the tail, from scratch each time, so that warm pixels — whose shot
    noise grows with their level — are judged against the line at their own level, not the bulk's.
    """
    df_arr = np.maximum(np.broadcast_to(np.asarray(df, float), v.shape), 1.0)
    cut = chi2_isf(OUTLIER_P, df_arr) / df_arr
    median = float(np.median(v)) if v.size else 0.0
    a, b = median, 0.0
    keep = np.ones(v.shape, bool)
    for _ in range(iterations):
        expected = np.maximum(a + b * level, QUANT_VAR)
        keep = v <= expected * cut
        if keep.sum() < 3:
            break
        w = df_arr[keep] / expected[keep] ** 2
        x, y = level[keep], v[keep]
        xm = float(np.average(x, weights=w))
        sxx = float(np.sum(w * (x - xm) ** 2))
        b = max(float(np.sum(w * (x - xm) * (y - np.average(y, weights=w)))) / sxx, 0.0) if sxx > 0 else 0.0
        a = float(np.average(y, weights=w)) - b * xm  # a variance never falls with the level: b ≥ 0
    return a, b, ~keep


def dark_variance_law(meas: Measurements, readable: np.ndarray) -> DarkLaw | None:
    """σ² = a + b·level fitted over the interior, readable pixels of the repeated dark conditions
    (``readable``: ``(R, H, W)`` over :attr:`~Measurements.fitted`), their frame-to-frame level changes removed
    and their outliers left out (:func:`robust_variance_line`).  A dark frame's normal pixels span a few DN, its
    hot pixels thousands: the slope (shot noise per DN of dark charge) comes from the hot pixels, the intercept
    from the bulk.  None without a repeated dark condition.
    """
    from forensics.check.pixels import level_changes

    levels, variances, dfs = [], [], []
    for r, g in enumerate(meas.repeated):
        group = meas.groups[g]
        if not dark_groups([group])[0]:
            continue
        m = readable[r] & meas.interior & (meas.var_all[g] > 0)
        levels.append(meas.mean_all[g][m])
        variances.append(meas.var_all[g][m] - level_changes(meas, group))
        dfs.append(np.full(int(m.sum()), group.n - 1.0))
    if not levels:
        return None
    lev, var = np.concatenate(levels), np.concatenate(variances)
    if lev.size < 10:
        return DarkLaw(float(np.median(var)) if var.size else QUANT_VAR, 0.0, len(levels))
    a, b, _ = robust_variance_line(lev, var, np.concatenate(dfs))
    return DarkLaw(a, b, len(levels))


def temperature_clusters(groups: list[Group]) -> list[list[int]]:
    """Positions in ``groups`` grouped by temperature: sorted temperatures split where they jump by more than
    :data:`CLUSTER_GAP_C` (one cluster per set point); groups without a temperature form one cluster."""
    known = sorted((g.temperature_c, i) for i, g in enumerate(groups) if g.temperature_c is not None)
    out: list[list[int]] = []
    last = None
    for t, i in known:
        if last is None or t - last > CLUSTER_GAP_C:
            out.append([])
        out[-1].append(i)
        last = t
    unknown = [i for i, g in enumerate(groups) if g.temperature_c is None]
    return out + ([unknown] if unknown else [])


def _line_fit(y: np.ndarray, x: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel, the weighted least-squares line through ``(x_c, y_c)`` with weights ``w`` (all ``(C, H, W)``;
    ``x`` may be ``(C, 1, 1)``): the fitted values and each sample's leverage (NaN where a pixel has fewer
    than three weighted samples or no spread of ``x``)."""
    xb = np.broadcast_to(x, y.shape)
    sw = w.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        xm = (w * xb).sum(axis=0) / sw
        ym = (w * y).sum(axis=0) / sw
        sxx = (w * (xb - xm) ** 2).sum(axis=0)
        slope = (w * (xb - xm) * (y - ym)).sum(axis=0) / sxx
        fit = ym + slope * (xb - xm)
        lev = w * (1.0 / sw + (xb - xm) ** 2 / sxx)
    bad = ((w > 0).sum(axis=0) < 3) | ~(sxx > 0)
    fit = np.where(bad, np.nan, fit)
    return fit, lev, bad


def cosmic_hits(meas: Measurements, readable: np.ndarray, law: DarkLaw) -> tuple[np.ndarray, np.ndarray]:
    """Cosmic-ray samples of the single frames, and the level each single frame's pixel is expected at (its
    line's fitted value): ``(S, H, W)`` each, over :attr:`~Measurements.single` (see the module's notes).

    ``readable`` ``(R, H, W)`` over :attr:`~Measurements.fitted`: samples that touched a bound take no part.
    """
    from forensics.defects.darkrounds import mark_hits

    fitted = meas.fitted
    n_rep = len(meas.repeated)
    S = len(meas.single)
    shape = meas.shape
    hits = np.zeros((S, *shape), bool)
    level = np.stack([meas.mean_all[g] for g in meas.single]) if S else np.zeros((0, *shape))
    rows = [r for r, g in enumerate(fitted) if dark_groups([meas.groups[g]])[0]]
    groups = [meas.groups[fitted[r]] for r in rows]
    for cluster in temperature_clusters(groups):
        crow = [rows[i] for i in cluster]
        singles = [k for k, r in enumerate(crow) if r >= n_rep]
        if not singles:
            continue
        cg = [meas.groups[fitted[r]] for r in crow]
        temps = np.array([g.temperature_c if g.temperature_c is not None else 0.0 for g in cg])
        t = np.array([g.exposure_s or 0.0 for g in cg])
        t_mean = float(np.average(temps, weights=np.maximum(t, 1e-9))) if t.any() else float(temps.mean())
        x = (t * 2.0 ** ((temps - t_mean) / NOMINAL_T_DOUBLE))[:, None, None]
        if np.ptp(x) <= 0:
            continue
        y = np.stack([meas.mean_all[fitted[r]] for r in crow])
        n = np.array([float(g.n) for g in cg])[:, None, None]
        ok = np.stack([readable[r] for r in crow])
        single_mask = np.zeros(len(crow), bool)
        single_mask[singles] = True
        cut = np.zeros(y.shape, bool)
        # the first round's weights read the law at each sample's own level (a hit then weighs little), later
        # rounds at the line's
        var = law(y)
        for _ in range(ROUNDS):
            w = np.where(ok & ~cut, n / var, 0.0)
            fit, lev, bad = _line_fit(y, x, w)
            var = law(np.where(np.isfinite(fit), fit, y))
            with np.errstate(invalid="ignore", divide="ignore"):
                z = (y - fit) / np.sqrt(var / n * np.clip(1.0 - lev, 1e-6, None))
            z = np.where(single_mask[:, None, None] & ok & ~cut & ~bad[None] & np.isfinite(z), z, -np.inf)
            where = np.argmax(z, axis=0)
            zmax = np.take_along_axis(z, where[None], 0)[0]
            idx, frame, _ = mark_hits(zmax.ravel(), where.ravel(), zmax.ravel(), shape, K_HIT, K_GROW)
            if not idx.size:
                break
            cut.reshape(len(crow), -1)[frame, idx] = True
        w = np.where(ok & ~cut, n / var, 0.0)
        fit, _, _ = _line_fit(y, x, w)
        for k in singles:
            s = crow[k] - n_rep
            hits[s] = cut[k]
            level[s] = np.where(np.isfinite(fit[k]), fit[k], level[s])
    return hits, level


def single_frames(meas: Measurements, readable: np.ndarray) -> SingleFrames | None:
    """The single-frame rows' noise law, cosmic-ray hits and floor (None without single dark conditions)."""
    if not meas.single:
        return None
    law = dark_variance_law(meas, readable)
    S = len(meas.single)
    if law is None:  # no repeated dark condition: nothing measures the dark noise, the frames are not fitted
        empty = np.zeros((S, *meas.shape))
        return SingleFrames(None, np.zeros((S, *meas.shape), bool), empty, empty)
    hits, level = cosmic_hits(meas, readable, law)
    return SingleFrames(law, hits, level, law(level))


def without_hits(meas: Measurements, sf: SingleFrames | None) -> Measurements:
    """``meas`` with every cosmic-ray sample of the single frames replaced by its pixel's line (mean, lowest and
    highest readout), for defect detection: a one-frame excess is no defect (a hit in a short exposure read as a
    pixel whose output falls with the light, "stuck").  ``meas`` itself when there are no hits."""
    if sf is None or sf.law is None or not sf.hits.any():
        return meas
    mean_all, lo, hi = meas.mean_all.copy(), meas.lo.copy(), meas.hi.copy()
    for k, g in enumerate(meas.single):
        hit = sf.hits[k]
        for arr in (mean_all, lo, hi):
            arr[g][hit] = sf.level[k][hit]
    return dataclasses.replace(meas, mean_all=mean_all, lo=lo, hi=hi)


def singles_note(meas: Measurements, sf: SingleFrames | None) -> list[str]:
    """What the check did with the single frames, in words (for the notes)."""
    if sf is None:
        return []
    S = len(meas.single)
    if sf.law is None:
        return [f"{S} dark condition(s) have a single frame and no dark condition is repeated: no noise law for "
                "them, so they serve defect detection only; take 2 frames of one dark condition"]
    per = sf.hits_per_frame(meas)
    frames_hit = sum(1 for v in per.values() if v)
    return [f"{S} dark condition(s) of a single frame fitted by the pixel channel (not scored: the held-out error is "
            f"the repeats'), weighted by the repeats' pooled dark variance law σ² = {sf.law.a:.4g} + {sf.law.b:.4g}·level "
            f"DN²; cosmic-ray hits: {sf.n_hits} sample(s) in {frames_hit} of the {S} frames excluded (a one-frame "
            f"excess over the pixel's line in exposure beyond {K_HIT:g}σ, neighbours from {K_GROW:g}σ)"]


def condition_residuals(ev: Evidence, fitted: FittedModel) -> list[tuple[Group, float, float]]:
    """Per dark condition the pixel channel fits: (condition, mean residual of its fitted normal pixels in DN,
    that mean's standard error from the pixels' noise)."""
    px = fitted.pixels
    meas = ev.meas
    out = []
    for r, g in enumerate(ev.rgroups):
        if not dark_groups([g])[0]:
            continue
        m = (px.weight[r] > 0) & (px.classes[r] == NORMAL) & meas.interior
        if m.sum() < 10:
            continue
        res = (meas.mean_a[r] - fitted.mu_a[r])[m]
        out.append((g, float(res.mean()), float(np.sqrt(np.mean(1.0 / px.weight[r][m]) / m.sum()))))
    return out


def single_frame_warnings(ev: Evidence, fitted: FittedModel) -> list[str]:
    """Dark conditions that do not follow the model: the mean residual of their normal pixels lies more than
    :data:`K_MISFIT` robust standard deviations (of all dark conditions' mean residuals, and at least the
    pixels' own standard error) from the median (an offset that jumped, a frame whose sensor was off its set
    point, a law that does not hold)."""
    rows = condition_residuals(ev, fitted)
    if len(rows) < 4:
        return []
    means = np.array([m for _, m, _ in rows])
    centre = float(np.median(means))
    spread = 1.4826 * float(np.median(np.abs(means - centre)))
    out = []
    for g, m, se in rows:
        scale = max(spread, se)
        if scale > 0 and abs(m - centre) > K_MISFIT * scale:
            out.append(f"condition '{g.label()}' does not follow the model: its normal pixels' mean residual is "
                       f"{m - centre:+.3g} DN from the dark conditions' median ({abs(m - centre) / scale:.1f} robust "
                       f"standard deviations of {scale:.3g} DN; an offset that jumped, or a sensor off its set "
                       "point?)")
    return out


def summary(meas: Measurements, sf: SingleFrames | None) -> dict[str, Any]:
    """The single frames' part of the check's data summary (JSON-ready)."""
    if sf is None:
        return {"conditions": 0}
    law = None if sf.law is None else {"a_dn2": sf.law.a, "b_dn": sf.law.b, "conditions": sf.law.conditions}
    return {"conditions": len(meas.single), "fitted": sf.law is not None, "noise_law": law,
            "cosmic_ray_samples": sf.n_hits, "cosmic_ray_samples_per_frame": sf.hits_per_frame(meas)}

