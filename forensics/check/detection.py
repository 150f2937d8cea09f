"""Stuck and partially stuck pixels at every epoch, from the per-condition statistics.

The toolkit's defect detection (:func:`forensics.defects.detection.detect`) works on one stack of ordinary
images: d̂ = mean − q×q median, thresholded at centre + σ·scale of a robust normal fit.  The checker sees
something else — per epoch, several conditions at known, different light levels, each with its own stack
statistics — and needs two things that detector cannot give: an offset that does not absorb a per-pixel
gain (the intercept of the pixel's residual regressed on scene level across the epoch's conditions), and
one threshold for every epoch of the count channel (so that the detection probability does not change with
time).  What is common is shared: the robust normal fit (:func:`~forensics.defects.detection.robust_normal`),
the catalogue's *once defective, always defective* records (:class:`~forensics.sensor.catalogue.DefectCatalogue`)
and the onset look-back (:func:`forensics.defects.onsets.look_back`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from forensics.check.classes import QUANT_VAR
from forensics.check.measurements import Measurements
from forensics.check.scene import scene_estimate
from forensics.defects.detection import robust_normal
from forensics.defects.onsets import look_back
from forensics.sensor.catalogue import PARTIAL, STUCK, DefectCatalogue

#: Partially stuck: offset d̂ above this many robust σ of d̂ over the sensor.
DETECT_Z = 6.0


@dataclass
class Detection:
    """Defects found at every epoch.

    Attributes
    ----------
    catalogue
        One record per site and kind, onset = the epoch it was first detected (or looked back to),
        amplitude = its offset d̂ (partially stuck) or constant value (stuck).
    threshold
        Offset threshold τ (DN) for partially stuck pixels (the largest over epochs).
    dhat
        Per-epoch offset maps d̂ (NaN outside the interior).
    """

    catalogue: DefectCatalogue
    threshold: float
    dhat: list[np.ndarray]


@dataclass(frozen=True)
class EpochOffsets:
    """One epoch's offsets d̂, constant (stuck) pixels and own threshold τ."""

    dhat: np.ndarray
    constant: np.ndarray
    tau: float


def epoch_offsets(meas: Measurements, gids: list[int], noise: float,
                  reference: np.ndarray | None = None) -> EpochOffsets:
    """Offsets and stuck candidates of one epoch from the conditions ``gids``.

    Stuck: the output does not follow the light — the same value in every frame (eq. 11 of the paper) or,
    with temporal noise after the stuck value, a slope of output against scene level below one half and a
    range of its mean output under half the light's — although the light at that pixel changes by more than
    10 noise σ across the epoch's conditions.
    Offset d̂: the intercept of the pixel's residual from the scene estimate (or from ``reference``)
    regressed on scene level across the conditions, read at the lowest level (the mean residual where the
    level does not vary), so that a per-pixel gain ends in the slope, not in d̂.
    """
    wts = np.array([meas.groups[g].n for g in gids], float)[:, None, None]
    lev = meas.scene_all[gids]
    output = meas.mean_all[gids]
    res = output - (lev if reference is None else reference[gids])
    wsum = wts.sum(0)
    lbar = (wts * lev).sum(0) / wsum
    rbar = (wts * res).sum(0) / wsum
    sxx = (wts * (lev - lbar) ** 2).sum(0)
    sxy = (wts * (lev - lbar) * (res - rbar)).sum(0)
    spread = lev.max(0) - lev.min(0)
    varies = spread > 10.0 * noise
    slope = np.where(varies & (sxx > 0), sxy / np.where(sxx > 0, sxx, 1.0), 0.0)
    dhat = rbar + slope * (lev.min(0) - lbar)
    if all(meas.groups[g].scenes and g in meas.repeated for g in gids):
        # photographs: a scene's edge can stand out like an offset in one photograph, a defect's offset is in
        # every one — so an offset counts only as far as both halves (different photographs) show it
        for g in gids:
            r = meas.repeated.index(g)
            dhat = np.minimum(dhat, np.minimum(*(m - scene_estimate(m) for m in (meas.mean_a[r], meas.mean_b[r]))))
    # not following the light is not enough: a hot pixel in raw darks beside flats that the capture software had
    # dark-subtracted (the 2017 STL-1001E series) reads 1,158 ADU in biases, 63,867 in a 300 s dark and the
    # flats' level in the flats — a negative slope, but nothing like a constant; a stuck pixel's output range
    # stays below half the light's, as its slope does
    flat = (np.where(sxx > 0, slope, 0.0) < -0.5) & (output.max(0) - output.min(0) < 0.5 * spread)
    constant = ((meas.lo[gids].min(0) == meas.hi[gids].max(0)) | flat) & varies
    inside = dhat[meas.interior]
    # the spread of d̂ over the sensor can never be below what the temporal noise alone gives it (its standard
    # error as an intercept); on quantised data read against a close reference most d̂ share a few values and
    # their MAD collapses to 0 (8-bit dark frames at black level 0: 14 828 "defects" of 16 384 pixels).
    # d̂ = Σ_g c_g · mean_g per pixel, each condition's mean with its own temporal variance (a dark frame
    # clipped at 0 far less than a flat)
    c = wts / wsum + np.where(varies & (sxx > 0), (lev.min(0) - lbar) / np.where(sxx > 0, sxx, 1.0), 0.0) * wts * (lev - lbar)
    var_g = np.array([float(np.mean(meas.var_all[g][meas.interior])) for g in gids])[:, None, None]
    se = np.sqrt(np.sum(c * c * var_g / wts, axis=0))
    spread_d = max(robust_normal(inside)[1], float(np.median(se[meas.interior]))) if inside.size else 0.0
    return EpochOffsets(dhat, constant, max(DETECT_Z * spread_d, 1e-6))


def detect_defects(meas: Measurements, groups_by_epoch: list[list[int]], common_threshold: bool,
                   look_back_z: float | None = None, reference: np.ndarray | None = None) -> Detection:
    """Detect stuck and partially stuck pixels per epoch (once defective, always defective).

    Per epoch, :func:`epoch_offsets`; partially stuck where d̂ exceeds the epoch's threshold (with
    ``common_threshold``, the largest over epochs).  With ``look_back_z`` (a z value), a partially stuck
    pixel first detected at epoch e is also taken to be present at the epochs just before e where its d̂
    exceeds ``look_back_z`` robust σ and agrees with its amplitude within as much (its onset is estimated,
    rather than set at the first epoch sensitive enough to see it); used for pixel classes, not for counts.
    ``reference`` (one image per condition) replaces the scene estimate as what a defect-free pixel reads.
    """
    interior = meas.interior
    noise = math.sqrt(max(float(np.median(meas.var_all[meas.repeated][:, interior])), QUANT_VAR))
    per_epoch = [epoch_offsets(meas, gids, noise, reference) if gids else None for gids in groups_by_epoch]
    taus = [p.tau for p in per_epoch if p is not None]
    common = max(taus) if taus else 0.0
    first_partial = np.full(meas.shape, -1)
    first_stuck = np.full(meas.shape, -1)
    amp_partial = np.zeros(meas.shape)
    amp_stuck = np.zeros(meas.shape)
    maps = []
    for e, item in enumerate(per_epoch):
        if item is None:
            maps.append(np.full(meas.shape, np.nan))
            continue
        tau = common if common_threshold else item.tau
        stuck = item.constant & interior
        partial = (item.dhat > tau) & interior & ~stuck
        new_p = partial & (first_partial < 0) & (first_stuck < 0)
        first_partial[new_p] = e
        amp_partial[new_p] = item.dhat[new_p]
        new_s = stuck & (first_stuck < 0)
        first_stuck[new_s] = e
        amp_stuck[new_s] = meas.lo[groups_by_epoch[e]].min(0)[new_s]
        maps.append(np.where(interior, item.dhat, np.nan))
    if look_back_z is not None:
        first_partial = _partial_onsets(per_epoch, first_partial, amp_partial, look_back_z)
    rows = []
    for kind, first, amp in ((PARTIAL, first_partial, amp_partial), (STUCK, first_stuck, amp_stuck)):
        yy, xx = np.nonzero(first >= 0)
        rows.append(DefectCatalogue(xx.astype(np.int64), yy.astype(np.int64), np.full(len(xx), kind, np.int8),
                                    amp[yy, xx].astype(float), meas.epoch_times[first[yy, xx]].astype(float),
                                    np.full(len(xx), "detected", dtype=object)))
    return Detection(DefectCatalogue.concatenate(rows), common, maps)


def _partial_onsets(per_epoch: list[EpochOffsets | None], first: np.ndarray, amplitude: np.ndarray,
                    z: float) -> np.ndarray:
    """Onsets of the partially stuck pixels by the look-back: a site shows at an epoch where its d̂ exceeds
    ``z`` σ of that epoch and lies within ``z`` σ of its detected amplitude (consecutive epochs only)."""
    ys, xs = np.nonzero(first >= 0)
    if not len(ys):
        return first
    amp = amplitude[ys, xs]
    present = np.zeros((len(per_epoch), len(ys)), bool)
    for e, item in enumerate(per_epoch):
        if item is not None:
            sd = item.tau / DETECT_Z
            d = item.dhat[ys, xs]
            present[e] = (d > z * sd) & (np.abs(d - amp) < z * sd)
    observed = np.array([item is not None for item in per_epoch])
    out = first.copy()
    out[ys, xs] = look_back(first[ys, xs], present, contiguous=True, observed=observed)
    return out
