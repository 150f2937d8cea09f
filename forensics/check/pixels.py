"""What the pixel and variance channels need once the pixel classes are known.

Given a catalogue of detected defects, :func:`pixel_data` derives everything that depends on the pixel
classes: the scene estimates of both halves with the known defects filled in (and the fill values, so that
the prediction can replace them), the noise floor measured from the repeats of normal pixels, the
weights of the pixel channel and the variance bins.  The result is immutable; a new catalogue (after
re-detection) gives a new :class:`PixelData`.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.fft
from scipy import ndimage, special

from forensics.check.classes import NORMAL, PART, QUANT_VAR, STK, class_maps, dark_groups
from forensics.check.measurements import Group, Measurements
from forensics.check.scene import (
    KERNEL,
    KERNEL_VAR,
    kernel_scatter,
    loo_quadratic_kernel,
    scene_estimate_and_fill,
)
from forensics.check.singles import SingleFrames, robust_variance_line
from forensics.sensor.catalogue import DefectCatalogue


@dataclass(frozen=True)
class NoiseFloor:
    """The pixel channel's noise floor per repeated condition, measured from the repeats of normal pixels.

    Where a pixel's prediction uses the scene estimate (every pixel but stuck ones, in frames with light), the
    floor is fitted to the temporal variance of each frame's residual from its own scene estimate,
    v(level) = a_g + b_g·level — the noise a residual actually has, whatever the temporal noise's spatial
    correlation and whether or not the frames' level drifts — and stored divided by the scene-noise factor
    1 + Σw² the pixel channel multiplies it by: ``floor · (1 + Σw²) / n`` is then the measured variance of a
    residual of a mean of ``n`` frames.  Elsewhere (stuck pixels, dark frames) the prediction does not use the
    neighbours, and the floor is the pixel's own temporal variance law, a_grey + b_grey·level.
    """

    a: np.ndarray  #: per condition, the residual law's intercept (DN²)
    b: np.ndarray  #: per condition, the residual law's slope (DN)
    floor: np.ndarray  #: per-frame temporal variance at each (condition, pixel), as described above
    raw: np.ndarray  #: the same from each pixel's own sample variance (quantisation variance for noiseless stuck pixels)
    a_grey: np.ndarray | None = None  #: the pixel's own variance law: intercept per condition
    b_grey: np.ndarray | None = None  #: and slope
    #: the scored half's floor and raw floor where they differ from the fitted half's (photographs: each half
    #: has its own scenes' texture); None: the same as ``floor`` / ``raw``
    floor_b: np.ndarray | None = None
    raw_b: np.ndarray | None = None


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
    #: (R, H, W) the bin each pixel's variance went into (−1: none), to average per-pixel quantities per bin
    labels: np.ndarray | None = None
    #: the spread holds latent means (the fitted model's, :func:`with_latent_spread`), not mean readouts
    spread_latent: bool = False
    #: per bin away from the bounds, the means of cos(2πk·level) over its pixels' latent levels (NaN for the other
    #: bins; :func:`phase_moments`), for the exact rounding variance at low noise
    #: (:func:`~forensics.check.prediction.phase_averaged`)
    phase: np.ndarray | None = None

    def bin_means(self, r: int, values: np.ndarray | float) -> np.ndarray:
        """Per bin of repeated condition ``r`` (in the order of ``group == r``), the mean of ``values`` — a
        number, or an ``(H, W)`` array averaged over the bin's pixels."""
        idx = np.flatnonzero(self.group == r)
        if np.ndim(values) == 0 or self.labels is None:
            mean = float(np.mean(values)) if np.ndim(values) else float(values)
            return np.full(idx.size, mean)
        lab = self.labels[r]
        m = lab >= 0
        total = np.bincount(lab[m], np.broadcast_to(values, lab.shape)[m], minlength=len(self.group))
        count = np.bincount(lab[m], minlength=len(self.group))
        return total[idx] / np.maximum(count[idx], 1)


def log_variance(observed: np.ndarray, df: np.ndarray) -> np.ndarray:
    """ln of binned variances less the bias of the log of a sample variance: a bin's variance pools its pixels'
    ``df`` degrees of freedom, σ²·χ²_ν/ν with ν = ``df``, and E[ln s²] = ln σ² + ψ(ν/2) − ln(ν/2) (Bartlett & Kendall
    1946, whose variance of ln s², ≈ 2/ν, already weighs the bins: ``df / 2``).

    Why: fitted in logs without it, every bin's variance reads low by ≈ 1/ν, a scale the noise law's parameters
    take up (on EMVA 1288 series of 48 × 64 pixels, ν ≈ 400–4,000 per bin: −0.08 % on average, −0.26 % in the
    smallest bins; ``benchmarks/grid_emva_standard.py``).

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> s2 = rng.chisquare(10, 200_000) / 10          # sample variances of σ² = 1 with ν = 10
    >>> round(float(np.mean(np.log(s2))), 2), round(float(np.mean(log_variance(s2, np.full(s2.size, 10.0)))), 2)
    (-0.1, 0.0)
    """
    nu = np.asarray(df, float)
    return np.log(observed) - (special.digamma(nu / 2.0) - np.log(nu / 2.0))


#: Harmonics of the level's fractional part kept in :attr:`VarianceBins.phase`: the rounding variance's k-th harmonic
#: falls as exp(−2π²k²σ²), below 10⁻⁵ of the variance at k = 15 for σ ≥ 0.1 DN (a nearly noiseless readout, whose
#: variance is a step in the level, is not followed closely).
HARMONICS = 15


#: A variance bin above this (DN²) gets no phase harmonics: its noise is above ≈ 1.3 DN under either converter,
#: where the rounding's swing (≈ exp(−2π²σ²) < 10⁻¹⁴) is nothing a bin resolves — and on whole frames of a
#: photon-transfer series most bins are such, whose pixels need not be visited.
PHASE_VARIANCE_MAX = 2.0


def phase_moments(labels: np.ndarray, levels: np.ndarray, n_bins: int, skip: np.ndarray) -> np.ndarray:
    """Per bin, the mean of cos(2πk·level) over its pixels (``labels`` ≥ 0, as :attr:`VarianceBins.labels`) for
    k = 0 … :data:`HARMONICS`; NaN rows for the bins to ``skip`` (near a bound, or too noisy to need them) and
    those without pixels.

    Why these: the readout's variance at low noise is an even periodic function of the level (period 1 DN), so its
    mean over a bin's pixels is Σ a_k·mean cos(2πk·level) — exact for pixels at one level as for pixels spread over
    many (:func:`~forensics.check.prediction.phase_averaged`).  (A histogram of the fractional parts was tried
    first: pixels at one level sit up to half a part from its middle, and at σ = 0.32 DN without a dither, where the
    variance swings by ±36 %, 32 parts missed it by 3.6 %.)

    Examples
    --------
    >>> import numpy as np
    >>> labels = np.array([[[0, 0, 1, 1]]])
    >>> m = phase_moments(labels, np.array([[[2.0, 7.0, 3.25, 3.75]]]), 2, np.array([False, False]))
    >>> [round(float(v), 6) for v in m[0, :3]], [round(float(v), 6) + 0.0 for v in m[1, :3]]
    ([1.0, 1.0, 1.0], [1.0, 0.0, -1.0])
    """
    wanted = ~np.asarray(skip, bool)
    out = np.full((n_bins, HARMONICS + 1), np.nan)
    if not wanted.any():
        return out
    m = labels >= 0
    lab = labels[m].astype(np.int64)
    keep = wanted[lab]
    lab, v = lab[keep], levels[m][keep]
    c1 = np.cos(2.0 * np.pi * (v - np.floor(v)))
    count = np.bincount(lab, minlength=n_bins)[:n_bins].astype(float)
    # cos kθ by the Chebyshev recurrence cos (k+1)θ = 2 cos θ cos kθ − cos (k−1)θ: one cosine per pixel, not sixteen
    prev, cur = np.ones_like(c1), c1
    out[:, 0] = 1.0
    for k in range(1, HARMONICS + 1):
        out[:, k] = np.bincount(lab, cur, minlength=n_bins)[:n_bins] / np.maximum(count, 1.0)
        prev, cur = cur, 2.0 * c1 * cur - prev
    out[(count == 0) | ~wanted] = np.nan
    return out


def with_latent_spread(bins: VarianceBins, latent: np.ndarray) -> VarianceBins:
    """``bins`` whose near-bound bins' spread is the fitted model's latent mean of their pixels (``latent``,
    ``(R, H, W)``, unclipped) at the same quantiles, instead of the pixels' scene levels.

    Why: near a bound the readout's variance depends steeply on a pixel's own latent level, and the bin holds only
    pixels that never touched the bound — selected towards high levels.  The scene level (the neighbours' mean)
    carries neither a pixel's own offset (its DSNU, its dark rate) nor that selection, only the neighbours'
    noise; once the pixel fit has the pixels' own patterns, their latent means carry both.  (8-bit dark frames at
    0 DN with a DSNU: the variance channel flagged shot noise, input noise and a nonlinearity the camera does not
    have.)"""
    if bins.spread is None or bins.labels is None:
        return bins
    near = np.flatnonzero(np.all(np.isfinite(bins.spread), axis=1))
    if bins.phase is not None:  # the other bins' fractional parts: the pixels' own latent levels, offsets included
        near_rows = np.zeros(len(bins.level), bool)
        near_rows[near] = True
        bins = dataclasses.replace(bins, phase=phase_moments(bins.labels, latent, len(bins.level),
                                                             near_rows | (bins.observed > PHASE_VARIANCE_MAX)))
    if near.size == 0:
        return bins
    spread = bins.spread.copy()
    qs = (np.arange(spread.shape[1]) + 0.5) / spread.shape[1]
    for b in near:
        r = bins.group[b]
        values = latent[r][bins.labels[r] == b]
        if values.size:
            spread[b] = np.quantile(values, qs)
    return dataclasses.replace(bins, spread=spread, spread_latent=True)


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
    #: the weights the pixel-local patterns are solved with: :attr:`weight`, and in dark frames also the frame's
    #: border (outside the scene estimate's reach, so not scored, but predicted from the chain alone: its patterns
    #: are measured there, and the neighbours' scene estimates contain them)
    #: (the same array as :attr:`weight` when there is no such border)
    pattern_weight: np.ndarray
    #: per condition, the pixels whose reading did not enter the scene estimates (outliers the estimate filled,
    #: beyond the known defects): their patterns are not in the neighbours' scene estimate
    scene_excluded: np.ndarray
    #: incident light of the scene estimates per chain table (filled by the prediction; depends on the scenes)
    light_cache: dict[Any, Any] = field(default_factory=dict, compare=False, repr=False)
    #: arrays derived from the pixel data alone, computed on first use (e.g. :func:`wide_residuals`)
    derived: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)

    @property
    def floor(self) -> np.ndarray:
        return self.noise.floor

    @property
    def raw_floor(self) -> np.ndarray:
        return self.noise.raw

    @property
    def floor_b(self) -> np.ndarray:
        """The floor of the scored (second) half's means."""
        return self.noise.floor if self.noise.floor_b is None else self.noise.floor_b

    @property
    def raw_floor_b(self) -> np.ndarray:
        return self.noise.raw if self.noise.raw_b is None else self.noise.raw_b


def pixel_data(meas: Measurements, rgroups: Sequence[Group], times: np.ndarray, usable: np.ndarray,
               catalogue: DefectCatalogue, readable: np.ndarray | None = None, fit_usable: np.ndarray | None = None,
               singles: SingleFrames | None = None) -> PixelData:
    """Pixel classes from a catalogue of detected defects, the scene estimates (defects masked), the noise
    floor (normal pixels) and the variance bins.  ``usable`` (R, H, W): the pixel means scored (and from which
    the floor is measured); ``fit_usable``: those fitted (default ``usable``; the single dark frames' rows
    too, their cosmic-ray hits left out); ``readable``: the pixels whose means are not censored, border
    included (for the patterns' weights in dark frames; default ``fit_usable``).  ``singles``: the single
    frames' floor, from the repeats' dark variance law (:mod:`forensics.check.singles`)."""
    fit_usable = usable if fit_usable is None else fit_usable
    epoch_classes = class_maps(catalogue, meas.shape, times)
    classes = np.stack([epoch_classes[g.epoch] for g in rgroups])
    # scene estimates per half; the known defects are filled in, and the fill values kept so that the
    # prediction can replace them by what the model says a typical pixel there would read
    mask_by_epoch = [c != NORMAL for c in epoch_classes]
    defect_mask = np.stack([mask_by_epoch[g.epoch] for g in rgroups])
    # photographs: no search for outliers beyond the known defects — in a textured scene the outliers are its
    # edges, and filling them would make the estimate a non-linear function of the scenes, whose noise the
    # per-frame residuals (linear) no longer measure
    passes = [1 if g.scenes else 4 for g in rgroups]
    sa = [scene_estimate_and_fill(meas.mean_a[r], defect_mask[r], passes=passes[r]) for r in range(len(rgroups))]
    sb = [scene_estimate_and_fill(meas.mean_b[r], defect_mask[r], passes=passes[r]) for r in range(len(rgroups))]
    fill_a = np.stack([np.where(defect_mask[r], sa[r][1], 0.0) for r in range(len(rgroups))])
    fill_b = np.stack([np.where(defect_mask[r], sb[r][1], 0.0) for r in range(len(rgroups))])
    refill_ops = {e: kernel_scatter(m != NORMAL, KERNEL) for e, m in enumerate(epoch_classes)}
    rep = [g.index for g in rgroups]
    scene = 0.5 * (np.stack([x[0] for x in sa]) + np.stack([x[0] for x in sb]))
    noise = noise_floor(meas, rep, usable, classes, rgroups, typical_levels(meas, rep, rgroups, usable, classes,
                                                                            scene))
    noise = with_single_floor(noise, len(meas.repeated), singles)
    na = meas.n_a[:, None, None].astype(float)
    var_a = noise.floor * (1.0 + np.where(uses_scene(classes, rgroups), KERNEL_VAR, 0.0)) / na
    weight = np.where(fit_usable, 1.0 / var_a, 0.0)
    border_dark = dark_groups(rgroups)[:, None, None] & ~meas.interior[None] & (fit_usable if readable is None
                                                                                else readable)
    pattern_weight = np.where(fit_usable | border_dark, 1.0 / var_a, 0.0) if border_dark.any() else weight
    excluded = np.stack([((sa[r][1] != meas.mean_a[r]) | (sb[r][1] != meas.mean_b[r])) & ~defect_mask[r]
                         for r in range(len(rgroups))])
    bins = variance_bins(meas, rgroups, usable, classes, scene=scene)
    return PixelData(catalogue, classes, defect_mask, np.stack([x[0] for x in sa]), np.stack([x[0] for x in sb]),
                     fill_a, fill_b, refill_ops, noise, var_a, weight, bins, pattern_weight, excluded)


def with_single_floor(noise: NoiseFloor, n_rep: int, singles: SingleFrames | None) -> NoiseFloor:
    """``noise`` with the single frames' rows (after the ``n_rep`` repeated ones) taken from the repeats' dark
    variance law: a single frame has no temporal variance of its own to measure a floor from."""
    if singles is None or singles.law is None or noise.floor.shape[0] <= n_rep:
        return noise
    def replaced(x: np.ndarray | None) -> np.ndarray | None:
        if x is None:
            return None
        out = x.copy()
        out[n_rep:] = singles.floor
        return out

    return dataclasses.replace(noise, floor=replaced(noise.floor), raw=replaced(noise.raw),
                               floor_b=replaced(noise.floor_b), raw_b=replaced(noise.raw_b))


#: A pool of conditions with fewer pixels than this in the mask takes the slope pooled over all conditions.
POOL_PIXELS = 1000


def variance_law(level: np.ndarray, var: np.ndarray, mask: np.ndarray,
                 pools: Sequence[Any] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """σ²(level) = a_g + b_g·level fitted to ``var`` over ``mask``: an intercept per condition g and a slope
    per pool of conditions (``pools``: a label per condition; None: one pool).

    A pool with fewer than :data:`POOL_PIXELS` pixels takes the slope pooled over all conditions (a condition
    with fewer than 10 pixels has no say in a slope); a condition with none takes the median of its ``var``
    as intercept.
    """
    n = len(level)
    labels = [0] * n if pools is None else list(pools)
    a = np.zeros(n)
    sums: dict[Any, list[float]] = {}
    for r in range(n):
        m = mask[r]
        lv, vv = level[r][m], var[r][m]
        if lv.size < 10:
            continue
        lc = lv - lv.mean()
        acc = sums.setdefault(labels[r], [0.0, 0.0, 0.0])
        acc[0] += float(np.sum(lc * (vv - vv.mean())))
        acc[1] += float(np.sum(lc * lc))
        acc[2] += lv.size
    num, den = sum(v[0] for v in sums.values()), sum(v[1] for v in sums.values())
    common = num / den if den > 0 else 0.0
    slope = {k: v[0] / v[1] if v[2] >= POOL_PIXELS and v[1] > 0 else common for k, v in sums.items()}
    b = np.array([slope.get(labels[r], common) for r in range(n)])
    for r in range(n):
        m = mask[r]
        a[r] = float(np.mean(var[r][m] - b[r] * level[r][m])) if m.any() else float(np.median(var[r]))
    return a, b


def typical_levels(meas: Measurements, rep: list[int], rgroups: Sequence[Group], usable: np.ndarray,
                   classes: np.ndarray, scene: np.ndarray) -> np.ndarray:
    """Per (condition, pixel), a level free of the pixel's own noise: the neighbours' scene estimate, and in a
    dark frame the mean of its usable normal pixels (there the levels spread by offsets without shot noise)."""
    out = np.array(scene, float, copy=True)
    for r, d in enumerate(dark_groups(rgroups)):
        if d:
            m = usable[r] & (classes[r] == NORMAL)
            out[r] = float(meas.mean_all[rep[r]][m].mean()) if m.any() else float(np.median(meas.mean_all[rep[r]]))
    return out


def uses_scene(classes: np.ndarray, rgroups: Sequence[Group]) -> np.ndarray:
    """Per (condition, pixel): whether the prediction uses the scene estimate (not for stuck pixels, whose
    reading is their own, nor in frames known to be dark, whose light is zero)."""
    return (classes != STK) & ~dark_groups(rgroups)[:, None, None]


#: A condition in which more than this share of the interior's normal pixels touched 0 or full scale in some
#: frame is near a bound: the normal pixels left there are a truncated sample.
NEAR_BOUND_SHARE = 0.01
#: A condition with light in which more than this share of the normal pixels touched a bound has no variance bin
#: (:func:`variance_bins`): its scene estimate, an average of clipped readouts, is off the latent level by
#: σ·(φ(a) − a·p) for a share p of readouts beyond a bound a σ away — 0.02 σ at p = 5 % (10 % of the pixels of two
#: frames: a truncated variance off by ≈ 0.6 %), 0.4 σ at p = 50 % (30 % seen at K = 2 DN/e⁻).
LIGHT_BOUND_SHARE = 0.10


def near_bound_conditions(meas: Measurements, usable: np.ndarray, classes: np.ndarray,
                          share: float = NEAR_BOUND_SHARE) -> np.ndarray:
    """Per repeated condition: whether more than ``share`` of its interior normal pixels are not usable (their
    readout touched 0 or full scale)."""
    bad, normal = bound_counts(meas, usable, classes)
    return bad > share * normal


def bound_counts(meas: Measurements, usable: np.ndarray, classes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per repeated condition: how many interior normal pixels are not usable, and how many there are (at least 1)."""
    normal = meas.interior[None] & (classes == NORMAL)
    return (normal & ~usable).sum(axis=(1, 2)), np.maximum(normal.sum(axis=(1, 2)), 1)


def _pooled_law(level: np.ndarray, var: np.ndarray, mask: np.ndarray, pools: Sequence[Any],
                df: Sequence[float]) -> dict[Any, tuple[float, float]]:
    """Per pool of conditions, one law var = a + b·level fitted over ``mask`` of all its conditions (``df``: the
    degrees of freedom of each condition's variances; b = 0 with fewer than 10 pixels; pools without pixels
    are left out).

    The pixels are partially stuck ones, whose levels span from just above the bound to thousands of DN (a hot
    pixel's charge carries its own shot noise), and each variance is of a few frames: the law is weighted by
    each variance's own precision and its outliers left out (:func:`~forensics.check.singles.robust_variance_line`,
    the dark law's fit).  Ordinary least squares let the brightest, noisiest variances decide and left the law
    negative at the dim end (camera convention, ISO 200 darks: a = −1,015 DN², so six hot pixels at 260 DN were
    weighted as if they had the rounding noise only).
    """
    out = {}
    labels = np.asarray(pools, dtype=object)
    dfs = np.broadcast_to(np.asarray(df, float)[:, None, None], mask.shape)
    for pool in dict.fromkeys(pools):
        sel = np.array([p == pool for p in labels])
        m = mask & sel[:, None, None]
        lv, vv = level[m], var[m]
        if not lv.size:
            continue
        out[pool] = robust_variance_line(lv, vv, dfs[m])[:2] if lv.size >= 10 else (float(vv.mean()), 0.0)
    return out


def noise_floor(meas: Measurements, rep: list[int], usable: np.ndarray, classes: np.ndarray,
                rgroups: Sequence[Group] | None = None, typical_level: np.ndarray | None = None) -> NoiseFloor:
    """The pixel channel's noise floor from the repeats of normal pixels; measured, never modelled
    (see :class:`NoiseFloor`).  ``typical_level`` (R, H, W): where to read the laws for normal pixels — a
    level free of the pixel's own noise (default: the pixel's own mean).

    Stuck pixels and dark frames keep the law of the pixels' own temporal variance; a stuck pixel that never
    changed (no noise downstream of it) has the quantisation variance only.
    """
    rgroups = [meas.groups[g] for g in rep] if rgroups is None else rgroups
    level = meas.mean_all[rep]
    var = meas.var_all[rep]
    normal = usable & (classes == NORMAL)
    # Slopes of the variance laws are pooled over the conditions of one analog gain (ISO): the slope is the
    # conversion gain, which the ISO setting multiplies; across light levels it is well determined.
    gain_pools = [g.iso for g in rgroups]
    # Where a normal pixel's law is read: not at its own mean, whose noise its residual shares — a weight
    # falling with the pixel's own noisy level biases the weighted fit by −b/2 DN (b the law's slope; ~0.5 DN
    # on the dark frames of the emva1288 series) — but at a level free of it (``typical_level``).
    at = level if typical_level is None else np.where(classes == NORMAL, typical_level, level)
    # the pixel's own variance: stuck pixels and dark frames (predictions that do not use the neighbours)
    a_grey, b_grey = variance_law(level, var, normal, gain_pools)
    own = np.maximum(a_grey[:, None, None] + b_grey[:, None, None] * at, QUANT_VAR)
    constant = np.all(var == 0, axis=0)[None] & (classes == STK)  # noiseless stuck pixels: only quantisation remains
    own = np.where(constant, QUANT_VAR, own)
    own_raw = np.maximum(var, QUANT_VAR * constant)
    # the residual's variance where the prediction uses the scene estimate: what the pixel channel's residuals
    # have, with the noise's spatial correlation and without the frames' level changes
    scene = uses_scene(classes, rgroups)
    resid = meas.var_resid[rep] if meas.var_resid is not None else var * (1.0 + KERNEL_VAR)
    a, b = variance_law(level, resid, normal & scene, gain_pools)
    factor = 1.0 + KERNEL_VAR
    smooth = np.maximum(a[:, None, None] + b[:, None, None] * at, QUANT_VAR * factor) / factor
    floor = np.where(scene, smooth, own)
    raw = np.where(scene, np.maximum(resid, QUANT_VAR * factor) / factor, own_raw)
    # near a bound the normal pixels left are a truncated sample (an 8-bit dark frame at black level 0: the few
    # that read above 0 in every frame vary by 0.12 DN², a partially stuck pixel 9 DN up by 0.57): there the
    # partially stuck pixels read their law from their own kind — one law per analog gain over all such
    # conditions, measured on their temporal variances
    near = near_bound_conditions(meas, usable, classes)
    if near.any():
        lifted = usable & (classes == PART) & near[:, None, None]
        laws = _pooled_law(level, var, lifted, gain_pools, [g.n - 1 for g in rgroups])
        for r in np.flatnonzero(near):
            if gain_pools[r] in laws:
                a_p, b_p = laws[gain_pools[r]]
                m = classes[r] == PART
                floor[r][m] = np.maximum(a_p + b_p * level[r][m], QUANT_VAR)
    if meas.half_ms is None:
        return NoiseFloor(a, b, floor, raw, a_grey, b_grey)
    # photographs: each half's own residual mean square (its scenes' texture and the noise), per pixel — a level
    # law cannot describe texture, which lives at edges — smoothed over 3 × 3 pixels for weights and z-scores
    photo = np.array([g.scenes for g in rgroups])[:, None, None] & scene
    halves = []
    for h in (0, 1):
        ms = np.maximum(meas.half_ms[:, h].astype(np.float64), QUANT_VAR * factor) / factor
        local = np.stack([ndimage.uniform_filter(x, 3, mode="nearest") for x in ms])
        halves.append((np.where(photo, local, floor), np.where(photo, ms, raw)))
    return NoiseFloor(a, b, halves[0][0], halves[0][1], a_grey, b_grey, halves[1][0], halves[1][1])


def level_changes(meas: Measurements, g: Group) -> float:
    """The variance the frames' level changes add to every pixel of condition ``g`` (DN²), when they are
    significant and material (:meth:`~forensics.check.measurements.LevelDrift.material`); else 0.  They move
    whole frames, not pixels: they are not pixel noise."""
    if g.index not in meas.repeated:
        return 0.0
    r = meas.repeated.index(g.index)
    drift = meas.drift(r)
    return drift.var if drift.material(float(np.median(meas.var_all[g.index][meas.interior]))) else 0.0


def variance_bins(meas: Measurements, rgroups: Sequence[Group], usable: np.ndarray, classes: np.ndarray,
                  n_bins: int = 3, scene: np.ndarray | None = None, n_spread: int = 16,
                  near_fraction: float = NEAR_BOUND_SHARE) -> VarianceBins:
    """Mean level and variance of normal pixels in ``n_bins`` quantile bins of level per repeated condition
    (quantiles of ``scene``, the neighbours' estimate, where given).

    The frames' level changes, where material, are removed from the variances (:func:`level_changes`).
    A condition in which more than ``near_fraction`` of the normal pixels touched 0 or the full scale in some
    frame (those are not usable) is near a bound: there a pixel's own mean and its temporal variance are
    correlated (the readout's noise is skewed by the bound), so binning on the pixel's own mean would select on
    its variance.  Such a condition is pooled into one bin, whose ``spread`` holds its pixels' scene levels (from
    the neighbours, not the pixel itself) at ``n_spread`` quantiles for the prediction near the bound — except a
    condition with light in which more than :data:`LIGHT_BOUND_SHARE` of them did, which has no bin (its latent
    level is not known there: the scene estimate averages clipped readouts).
    """
    rows = []
    spread = []
    qs = (np.arange(n_spread) + 0.5) / n_spread
    labels = np.full(usable.shape, -1, np.int16 if n_bins * len(rgroups) < 2**15 else np.int32)
    bad, normal = bound_counts(meas, usable, classes)
    near_rows, clipped_rows = bad > near_fraction * normal, bad > LIGHT_BOUND_SHARE * normal
    dark = dark_groups(rgroups)
    for r, g in enumerate(rgroups):
        m = usable[r] & (classes[r] == NORMAL)
        if m.sum() < 30 or g.scenes:  # photographs: a pixel's spread over scenes is not its temporal variance
            continue
        lev = meas.mean_all[g.index][m]
        v = meas.var_all[g.index][m] - level_changes(meas, g)
        near = scene is not None and bool(near_rows[r])
        if near and not dark[r] and clipped_rows[r]:
            # a frame with light far into a bound has no bin: its pixels' latent level comes from the neighbours'
            # scene estimate, an average of readouts the bound clipped (58 % of them at 4095 DN: 37 DN below the
            # latent level), and the truncated variance it predicts is steep in that level.  On EMVA 1288 series at
            # K = 2 DN/e⁻ such a bin read 30 % below its prediction (z −4) and pulled K down by 0.5 standard
            # errors; EMVA 1288 itself leaves saturated points out of the photon transfer
            # (benchmarks/grid_emva_standard.py)
            continue
        if near:
            # the readout near a bound is far from normal (mostly one or two levels): the bin's weight is the
            # df of a χ² with the spread of its pixels' variances, not the normal theory's
            df = float(m.sum() * (g.n - 1))
            sv = float(v.var(ddof=1))
            if sv > 0:
                df = min(df, 2.0 * float(v.mean()) ** 2 * v.size / sv)
            labels[r][m] = len(rows)
            rows.append((r, float(lev.mean()), float(v.mean()), df))
            # the scene estimate's outlier rejection leans low where most readouts sit on a bound: centre it on
            # the mean readout of all normal pixels (a plain average of the clipped readout, unbiased)
            normal = meas.interior & (classes[r] == NORMAL)
            shift = float(meas.mean_all[g.index][normal].mean() - scene[r][normal].mean())
            spread.append(np.quantile(scene[r][m], qs) + shift)
            continue
        # bins chosen by a level free of the pixel's own noise (its neighbours' scene estimate): on quantised
        # data a mean of two readouts that is a half-integer implies an odd difference, so quantiles of the own
        # mean select on the variance (8-bit, σ 0.7 DN: ±9 % between bins); each bin still reports the mean
        # of its pixels' own means (unbiased for their latent level, on which the noise laws depend)
        key = lev if scene is None else scene[r][m]
        outlier = robust_variance_line(lev, v, g.n - 1)[2] if dark[r] else np.zeros(lev.shape, bool)
        edges = np.quantile(key, np.linspace(0, 1, n_bins + 1))
        which = np.clip(np.searchsorted(edges, key, side="right") - 1, 0, n_bins - 1)
        sites = np.flatnonzero(m.ravel())  # lev's pixels, in the order of the boolean index
        for k in range(n_bins):
            s = which == k
            if s.sum() < 10:
                continue
            s &= ~outlier  # a cosmic-ray hit in one frame of a repeated dark condition is not the pixel's noise
            labels[r].reshape(-1)[sites[s]] = len(rows)
            rows.append((r, float(lev[s].mean()), float(v[s].mean()), int(s.sum() * (g.n - 1))))
            spread.append(np.full(n_spread, np.nan))
    spread = np.array(spread).reshape(len(rows), n_spread)
    # until a fit gives the pixels' latent levels, their fractional parts are the neighbours' (exact without a
    # DSNU, where every pixel of a frame shares one level — the case in which they matter most)
    observed = np.maximum(np.array([x[2] for x in rows]), 1e-12)
    phase = None if scene is None else phase_moments(labels, scene, len(rows), np.all(np.isfinite(spread), axis=1)
                                                     | (observed > PHASE_VARIANCE_MAX))
    return VarianceBins(np.array([x[0] for x in rows], int), np.array([x[1] for x in rows]), observed,
                        np.array([x[3] for x in rows], float), spread, float(meas.clip_level), labels, phase=phase)


#: Side of the scene estimate that measures a pattern's size: wide enough to leave almost all of a pattern
#: that varies from pixel to pixel (its own share of a white pattern is Σw² ≈ 0.4 %), still exact for a
#: quadratic scene (vignetting).
WIDE_SCENE = 31
#: Side of the tiles the interval of a pattern's size resamples (far larger than the noise's correlation length).
SIZE_TILE = 16
#: a condition in which more than this share of the interior's means touched 0 or full scale is left out of the
#: split-half size (:func:`pattern_size`)
SIZE_CENSORED_SHARE = 0.01
#: Tile-bootstrap replicates for that interval.
N_BOOT = 400


def wide_scene(images: np.ndarray, size: int = WIDE_SCENE) -> np.ndarray:
    """The leave-one-out quadratic scene estimate of ``size × size`` of each image of a stack ``(R, H, W)``,
    reflecting at the edges (as :func:`~forensics.check.scene.scene_estimate`'s kernel), by FFT: the cost does
    not grow with the window."""
    kernel = loo_quadratic_kernel(size)  # symmetric: correlation and convolution agree
    e = size // 2
    padded = np.pad(images, ((0, 0), (e, e), (e, e)), mode="symmetric")  # ndimage's "reflect"
    return _fft_convolve_valid(padded, kernel)


def _fft_convolve_valid(stack: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """``scipy.signal.fftconvolve(stack, kernel[None], mode="valid", axes=(1, 2))``, step for step (the same
    transform sizes and crops: the same bits), without importing ``scipy.signal`` — it imports ``scipy.stats``,
    0.3–0.4 s of every model check for this one call."""
    full = [stack.shape[a] + kernel.shape[a - 1] - 1 for a in (1, 2)]
    fshape = [scipy.fft.next_fast_len(n, True) for n in full]
    spectrum = scipy.fft.rfftn(stack, fshape, axes=(1, 2)) * scipy.fft.rfftn(kernel[None], fshape, axes=(1, 2))
    out = scipy.fft.irfftn(spectrum, fshape, axes=(1, 2))[:, :full[0], :full[1]]
    valid = [stack.shape[a] - kernel.shape[a - 1] + 1 for a in (1, 2)]
    start = [(f - v) // 2 for f, v in zip(full, valid)]
    return out[:, start[0]:start[0] + valid[0], start[1]:start[1] + valid[1]]


def uncensored_conditions(meas: Measurements, n: int) -> np.ndarray:
    """Of the pixel channel's first ``n`` conditions (:attr:`~Measurements.fitted`), those in which at most
    :data:`SIZE_CENSORED_SHARE` of the interior's means touched 0 or full scale (the single frames, which have no
    halves, never)."""
    out = np.zeros(n, bool)
    for r, g in enumerate(meas.repeated[:n]):
        out[r] = float(np.mean(meas.censored(g)[meas.interior])) <= SIZE_CENSORED_SHARE
    return out


def wide_residuals(meas: Measurements, px: PixelData) -> tuple[np.ndarray, np.ndarray]:
    """Both halves' residuals from the wide scene estimate, known defects filled in first (computed once per
    pixel data: they depend on nothing a fit changes)."""
    if "wide" not in px.derived:
        px.derived["wide"] = tuple(
            mean - wide_scene(np.where(px.defect_mask, fill, mean))
            for mean, fill in ((meas.mean_a, px.fill_a), (meas.mean_b, px.fill_b)))
    return px.derived["wide"]


def _profiled_projections(x: np.ndarray, others: Sequence[np.ndarray], weight: np.ndarray, ok: np.ndarray,
                          res_a: np.ndarray, res_b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel, (u_a, u_b, a) of :func:`pattern_size`: with no ``others`` u = Σ_r x·w·residual and a = Σ_r x²·w;
    with others, u = a·β where β is ``x``'s coefficient in the pixel's weighted least-squares regression of the
    residual on every pattern (a pseudo-inverse where a pattern does not act on the pixel)."""
    xw = np.where(ok, x * weight, 0.0)
    a = np.sum(np.where(ok, x * xw, 0.0), axis=0)
    if not others:
        return np.sum(xw * res_a, axis=0), np.sum(xw * res_b, axis=0), a
    cols = [x, *others]
    k = len(cols)
    wok = np.where(ok, weight, 0.0)
    gram = np.empty((*a.shape, k, k))
    for i in range(k):
        for j in range(i, k):
            gram[..., i, j] = gram[..., j, i] = np.sum(cols[i] * cols[j] * wok, axis=0)
    proj_a = np.stack([np.sum(c * wok * res_a, axis=0) for c in cols], axis=-1)
    proj_b = np.stack([np.sum(c * wok * res_b, axis=0) for c in cols], axis=-1)
    # scale to a unit diagonal before the pseudo-inverse (the patterns' units differ: DN, DN/s, relative gain)
    d = np.sqrt(np.clip(np.diagonal(gram, axis1=-2, axis2=-1), 0.0, None))
    d = np.where(d > 0, d, 1.0)
    inv = np.linalg.pinv(gram / (d[..., :, None] * d[..., None, :]), rcond=1e-9, hermitian=True)
    inv = inv / (d[..., :, None] * d[..., None, :])
    beta_a = np.einsum("...ij,...j->...i", inv, proj_a)[..., 0]
    beta_b = np.einsum("...ij,...j->...i", inv, proj_b)[..., 0]
    return a * beta_a, a * beta_b, a


@dataclass(frozen=True)
class PatternSize:
    """The size of a pixel-local pattern as the frames show it: its standard deviation and standard error."""

    sigma: float
    se: float
    tiles: int


def pattern_size(meas: Measurements, px: PixelData, x: np.ndarray, ok: np.ndarray,
                 rng: np.random.Generator, others: Sequence[np.ndarray] = ()) -> PatternSize | None:
    """The size of a pixel-local pattern whose effect on each pixel's mean is ``x`` per unit (``(R, H, W)``,
    e.g. the scene level for a relative gain), from the split-half cross-product of the residuals from a wide
    scene estimate (:data:`WIDE_SCENE`).

    The pixel channel's 7 × 7 scene estimate absorbs part of a spatially correlated pattern (demosaicing
    spreads each pixel's gain over its neighbours); the wide one leaves almost all of it.  The two halves'
    noises are independent, so the cross-product estimates the pattern's variance whatever the noise floor:
    σ² = Σ_p u_a·u_b / Σ_p a_p², with u = Σ_r x·w·residual and a = Σ_r x²·w per pixel (w: the pixel
    channel's weights), over the pixels at least half the wide window from the frame's edge.  The standard
    error is from a bootstrap over ``SIZE_TILE`` tiles (spatially correlated noise stays within a tile).  Known
    defects are filled in before the wide estimate (a defect would
    otherwise leak into hundreds of neighbours); only the pixels in ``ok`` count, and only the conditions that are
    not censored (:func:`uncensored_conditions`).  None when ``x`` has no weight there.

    ``others``: the effects per unit ``(R, H, W)`` of the other pixel-local patterns of the model.  The wide
    residual holds every fixed pattern, and one projected alone onto ``x`` carries the others' share along it (on
    an EMVA 1288 series a PRNU of 1.0 % came out 1.9 %, with the DSNU and the dark-rate non-uniformity acting
    on the same light frames).  With ``others`` each half's residual is regressed, pixel by pixel, on all the
    patterns at once (least squares, the pixel channel's weights) and the cross-product taken of ``x``'s
    coefficients, weighted by a² as before: with no others the same numbers.
    """
    res_a, res_b = wide_residuals(meas, px)
    # a condition whose means are censored at a bound (8-bit dark frames at a black level of 0 DN) shows only the
    # pixels that never touched it, and those lie above the wide estimate of all of them in both halves at once:
    # their cross-product holds that common shift, not the pattern (8-bit DSNU, σ_o 0.19 DN: 0.85 DN from the dark
    # frames, 0.195 from the flats, 0.37 from both)
    ok = ok & uncensored_conditions(meas, ok.shape[0])[:, None, None]
    ua, ub, a = _profiled_projections(x, others, px.weight, ok, res_a, res_b)
    # near the frame's edge the wide window reflects the scene, which is then no longer quadratic in it
    inner = np.zeros(meas.shape, bool)
    e = WIDE_SCENE // 2
    inner[e:meas.shape[0] - e, e:meas.shape[1] - e] = True
    used = (a > 0) & inner
    if not used.any():
        return None
    h, w = meas.shape
    yy, xx = np.mgrid[0:h, 0:w]
    tiles = ((yy // SIZE_TILE) * (-(-w // SIZE_TILE)) + xx // SIZE_TILE)[used]
    _, tix = np.unique(tiles, return_inverse=True)
    n_tiles = int(tix.max()) + 1
    s_g = np.bincount(tix, (ua * ub)[used], minlength=n_tiles)
    a_g = np.bincount(tix, (a * a)[used], minlength=n_tiles)
    var = float(s_g.sum()) / float(a_g.sum())
    sigma = math.sqrt(max(var, 0.0))
    if n_tiles < 2:
        return PatternSize(sigma, math.inf, n_tiles)
    picks = rng.integers(0, n_tiles, size=(N_BOOT, n_tiles))
    boot = s_g[picks].sum(axis=1) / a_g[picks].sum(axis=1)
    se_var = float(np.std(boot, ddof=1))
    # se of σ from that of σ² by the delta method, valid while σ² is clearly above 0; closer to 0, the σ that
    # one se of σ² allows
    se = se_var / (2.0 * sigma) if sigma**2 > 2.0 * se_var else math.sqrt(se_var)
    return PatternSize(sigma, se, n_tiles)
