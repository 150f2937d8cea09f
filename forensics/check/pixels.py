"""What the pixel and variance channels need once the pixel classes are known.

Given a catalogue of detected defects, :func:`pixel_data` derives everything that depends on the pixel
classes: the scene estimates of both halves with the known defects filled in (and the fill values, so that
the prediction can replace them), the noise floor measured from the repeats of normal pixels, the
weights of the pixel channel and the variance bins.  The result is immutable; a new catalogue (after
re-detection) gives a new :class:`PixelData`.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from forensics.check.classes import NORMAL, QUANT_VAR, STK, class_maps
from forensics.check.measurements import Group, Measurements
from forensics.check.scene import KERNEL, KERNEL_VAR, kernel_scatter, scene_estimate_and_fill
from forensics.sensor.catalogue import DefectCatalogue


@dataclass(frozen=True)
class NoiseFloor:
    """σ²(level) = a_g + b·level per repeated condition, measured from the repeats of normal pixels."""

    a: np.ndarray
    b: float
    floor: np.ndarray  #: per-frame temporal variance at each (condition, pixel)
    raw: np.ndarray  #: the sample variance itself (quantisation variance for noiseless stuck pixels)


@dataclass(frozen=True)
class VarianceBins:
    """Temporal variance of normal pixels pooled in bins of signal level per repeated condition."""

    group: np.ndarray
    level: np.ndarray
    observed: np.ndarray
    df: np.ndarray
    #: per bin near a bound, its pixels' scene levels at evenly spaced quantiles (NaN for the other bins)
    spread: np.ndarray | None = None
    #: the data's full scale (readouts lie in [0, full_scale]); None: no bounds
    full_scale: float | None = None


@dataclass(frozen=True)
class PixelData:
    """Pixel classes and what depends on them (arrays over repeated conditions ``(R, H, W)``)."""

    catalogue: DefectCatalogue
    classes: np.ndarray
    defect_mask: np.ndarray
    scene_a: np.ndarray
    scene_b: np.ndarray
    fill_a: np.ndarray
    fill_b: np.ndarray
    refill_ops: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]
    noise: NoiseFloor
    var_a: np.ndarray
    weight: np.ndarray
    bins: VarianceBins
    #: incident light of the scene estimates per chain table (filled by the prediction; depends on the scenes)
    light_cache: dict[Any, Any] = field(default_factory=dict, compare=False, repr=False)

    @property
    def floor(self) -> np.ndarray:
        return self.noise.floor

    @property
    def raw_floor(self) -> np.ndarray:
        return self.noise.raw


def pixel_data(meas: Measurements, rgroups: Sequence[Group], times: np.ndarray, usable: np.ndarray,
               catalogue: DefectCatalogue) -> PixelData:
    """Pixel classes from a catalogue of detected defects, the scene estimates (defects masked), the noise
    floor (normal pixels) and the variance bins."""
    epoch_classes = class_maps(catalogue, meas.shape, times)
    classes = np.stack([epoch_classes[g.epoch] for g in rgroups])
    # scene estimates per half; the known defects are filled in, and the fill values kept so that the
    # prediction can replace them by what the model says a typical pixel there would read
    mask_by_epoch = [c != NORMAL for c in epoch_classes]
    defect_mask = np.stack([mask_by_epoch[g.epoch] for g in rgroups])
    sa = [scene_estimate_and_fill(meas.mean_a[r], defect_mask[r]) for r in range(len(rgroups))]
    sb = [scene_estimate_and_fill(meas.mean_b[r], defect_mask[r]) for r in range(len(rgroups))]
    fill_a = np.stack([np.where(defect_mask[r], sa[r][1], 0.0) for r in range(len(rgroups))])
    fill_b = np.stack([np.where(defect_mask[r], sb[r][1], 0.0) for r in range(len(rgroups))])
    refill_ops = {e: kernel_scatter(m != NORMAL, KERNEL) for e, m in enumerate(epoch_classes)}
    rep = [g.index for g in rgroups]
    noise = noise_floor(meas, rep, usable, classes)
    na = meas.n_a[:, None, None].astype(float)
    var_a = noise.floor * (1.0 + np.where(classes == STK, 0.0, KERNEL_VAR)) / na
    weight = np.where(usable, 1.0 / var_a, 0.0)
    scene = 0.5 * (np.stack([x[0] for x in sa]) + np.stack([x[0] for x in sb]))
    bins = variance_bins(meas, rgroups, usable, classes, scene=scene)
    return PixelData(catalogue, classes, defect_mask, np.stack([x[0] for x in sa]), np.stack([x[0] for x in sb]),
                     fill_a, fill_b, refill_ops, noise, var_a, weight, bins)


def noise_floor(meas: Measurements, rep: list[int], usable: np.ndarray, classes: np.ndarray) -> NoiseFloor:
    """σ²(level) = a_g + b·level per condition from the repeats of normal pixels; measured, never modelled."""
    var = meas.var_all[rep]
    level = meas.mean_all[rep]
    normal = usable & (classes == NORMAL)
    a = np.zeros(len(rep))
    num = den = 0.0
    for r in range(len(rep)):
        m = normal[r]
        lv, vv = level[r][m], var[r][m]
        if lv.size < 10:
            continue
        lc = lv - lv.mean()
        num += float(np.sum(lc * (vv - vv.mean())))
        den += float(np.sum(lc * lc))
    b = num / den if den > 0 else 0.0
    for r in range(len(rep)):
        m = normal[r]
        a[r] = float(np.mean(var[r][m] - b * level[r][m])) if m.any() else float(np.median(var[r]))
    smooth = np.maximum(a[:, None, None] + b * level, QUANT_VAR)
    constant = np.all(var == 0, axis=0)[None] & (classes == STK)  # noiseless stuck pixels: only quantisation remains
    return NoiseFloor(a, b, np.where(constant, QUANT_VAR, smooth), np.maximum(var, QUANT_VAR * constant))


def variance_bins(meas: Measurements, rgroups: Sequence[Group], usable: np.ndarray, classes: np.ndarray,
                  n_bins: int = 3, scene: np.ndarray | None = None, n_spread: int = 16,
                  near_fraction: float = 0.01) -> VarianceBins:
    """Mean level and variance of normal pixels in ``n_bins`` quantile bins of level per repeated condition.

    A condition in which more than ``near_fraction`` of the normal pixels touched 0 or the full scale in some
    frame (those are not usable) is near a bound: there a pixel's own mean and its temporal variance are
    correlated (the readout's noise is skewed by the bound), so binning on the pixel's own mean would select on
    its variance.  Such a condition is pooled into one bin, whose ``spread`` holds its pixels' scene levels
    (from the neighbours, not the pixel itself) at ``n_spread`` quantiles for the prediction near the bound.
    """
    rows = []
    spread = []
    qs = (np.arange(n_spread) + 0.5) / n_spread
    for r, g in enumerate(rgroups):
        m = usable[r] & (classes[r] == NORMAL)
        if m.sum() < 30:
            continue
        lev = meas.mean_all[g.index][m]
        v = meas.var_all[g.index][m]
        normal = meas.interior & (classes[r] == NORMAL)
        near = scene is not None and float(np.mean(~usable[r][normal])) > near_fraction
        if near:
            # the readout near a bound is far from normal (mostly one or two levels): the bin's weight is the
            # df of a χ² with the spread of its pixels' variances, not the normal theory's
            df = float(m.sum() * (g.n - 1))
            sv = float(v.var(ddof=1))
            if sv > 0:
                df = min(df, 2.0 * float(v.mean()) ** 2 * v.size / sv)
            rows.append((r, float(lev.mean()), float(v.mean()), df))
            # the scene estimate's outlier rejection leans low where most readouts sit on a bound: centre it on
            # the mean readout of all normal pixels (a plain average of the clipped readout, unbiased)
            shift = float(meas.mean_all[g.index][normal].mean() - scene[r][normal].mean())
            spread.append(np.quantile(scene[r][m], qs) + shift)
            continue
        edges = np.quantile(lev, np.linspace(0, 1, n_bins + 1))
        which = np.clip(np.searchsorted(edges, lev, side="right") - 1, 0, n_bins - 1)
        for k in range(n_bins):
            s = which == k
            if s.sum() < 10:
                continue
            rows.append((r, float(lev[s].mean()), float(v[s].mean()), int(s.sum() * (g.n - 1))))
            spread.append(np.full(n_spread, np.nan))
    return VarianceBins(np.array([x[0] for x in rows], int), np.array([x[1] for x in rows]),
                        np.maximum(np.array([x[2] for x in rows]), 1e-12), np.array([x[3] for x in rows], float),
                        np.array(spread).reshape(len(rows), n_spread), float(meas.full_scale))
