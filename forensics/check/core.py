"""Model against measurement: fit the sensor model, show where it fails, name the missing effect.

Overview
--------
:func:`check` takes a dataset (images + ``manifest.csv``) and a model (the
base model — ``growth``, ``offset``, ``stuck``, ``read_noise`` and saturation
at the bit depth — plus any added effects), and returns a :class:`CheckResult`:
the fitted parameters, the held-out error, goodness-of-fit p-values, a table
of checks, and the candidate effects ranked by how much adding each would
improve the fit.

The measurements are reduced to four *channels* of statistics; every effect
acts on one or more of them according to its :class:`~forensics.sensor.model.Stage`,
so nothing here depends on an effect's name:

``pixel``
    For every condition (epoch, exposure, ISO, temperature, subject) with
    repeated frames, the repeats are split into two halves (even and odd
    frames).  The mean of each half is compared, pixel by pixel, with the
    model's prediction: the scene of each frame is estimated from the frame
    itself (a leave-one-out local quadratic fit over 7 × 7 neighbours, with the
    detected defects and outliers filled in — the paper's local median, made
    unbiased for smooth vignetting and with a known noise), mapped to incident
    light by inverting the typical pixel's chain, and sent through every
    non-noise effect's ``apply`` with the pixel's own fitted state.  The model
    is fitted on the first half and scored on the second.
``variance``
    Temporal variance from the repeats, pooled over normal pixels in bins of
    signal level per condition, against the variance the ``NOISE`` effects
    predict (plus the quantisation variance 1/12 DN²).
``growth``
    Defects detected at every epoch (on the conditions common to all epochs,
    so the detection threshold is the same), cumulative counts against time,
    against the ``ARRIVAL`` effects' expected counts.
``spatial``
    Ripley's L of the defect sites at the last epoch against Monte-Carlo
    simulations of the fitted arrival model.

The noise floor is always measured from repeated frames, never from a model's
residual: per pixel and condition the sample variance of the repeats, and
for weighting a smooth per-condition function of level fitted to those
variances.  Because the scene is itself estimated from a noisy frame, the
floor of a predicted pixel mean includes the estimate's known noise,
``σ²·Σw²`` for the filter weights ``w`` (0.081 for 7 × 7).

Pixel classes
-------------
Stuck and partially stuck pixels are detected per epoch (stuck: the output
does not follow the light; partially stuck: the pixel's offset d̂ — the
intercept of its residual against scene level — above 6 robust σ), once
defective always defective, with onsets estimated by looking back.  The
classes normal / partial / stuck give the error per class.  When the fitted
model has fixed patterns on normal pixels (a PRNU map, column offsets), the
detection is repeated against the model's prediction and the model refitted,
so that a pattern the model explains no longer hides small defects.  Known
defects are filled in before the scene is estimated; the prediction replaces
the fill by what the model says a normal pixel there would read.  Defect
counts for the growth and placement channels use only the conditions measured
at every epoch with one threshold, so that the detection probability does not
change with time.

Diagnosis
---------
For each candidate not in the model, its *signature* — the derivative of the
channel statistics as its parameters leave their null values, computed by
finite differences through the effect's own ``apply`` / ``variance`` /
``expected_arrivals`` — is tested against the fitted model's residuals:

* pixel, global parameters: Gaussian score (Lagrange-multiplier) test,
  LM = g'H⁻¹g on the standardised residuals, after projecting out the model's
  own per-pixel parameters pixel by pixel;
* pixel, fixed patterns (one value per pixel or block): likelihood ratio for
  the variance of a random effect per block (the pattern's spread), which has
  one parameter however many blocks there are;
* variance: score test on the log binned variances;
* growth: Poisson score test of the candidate's expected-count direction (for
  a power-law arrival rate, the grouped Laplace/Crow trend test), with a
  quasi-Poisson dispersion estimated under the alternative;
* spatial: projection of the observed Ripley L on the direction the candidate
  moves it (simulated), calibrated by the null simulations.

Each gives a predicted ΔBIC ≈ LM − q·ln n (q: the candidate's parameter count,
n: the channel's sample size) and a p-value.  Candidates are ranked by
predicted ΔBIC (p-values underflow) and flagged only when ΔBIC > 10 and the
Holm-adjusted p < 0.01.
"""
from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import ndimage, optimize, stats

import forensics.stats.spatial as sp
from forensics.io.dataset import Dataset, open_dataset, split_epochs
from forensics.defects.detection import robust_normal
from forensics._shared.arrays import grey_mean, infer_full_scale
from forensics._shared.errors import InputError, UsageError
from forensics.sensor.model import (
    EFFECTS,
    PARTIAL,
    STUCK,
    DefectCatalogue,
    Device,
    Effect,
    SensorModel,
    Stage,
    make_effect,
)
from forensics._shared.progress import Progress, no_progress
from forensics.stats.counts import poisson_deviance

if TYPE_CHECKING:
    from forensics.report.html import Report

CLASSES = ("normal", "partial", "stuck")
NORMAL, PART, STK = 0, 1, 2
CHANNELS = ("pixel", "variance", "growth", "spatial")
QUANT_VAR = 1.0 / 12.0
#: Flagging rule: predicted ΔBIC above this and Holm-adjusted p below ``FLAG_P``.
FLAG_DBIC = 10.0
FLAG_P = 0.01
DETECT_Z = 6.0
SCENE_SIZE = 7


# =========================================================================== scene estimation
def loo_quadratic_kernel(size: int = SCENE_SIZE) -> np.ndarray:
    """Weights of a least-squares quadratic surface fitted to a ``size × size`` window *without* its centre,
    evaluated at the centre: exact for any quadratic scene, independent of the centre pixel's noise."""
    h = size // 2
    yy, xx = np.mgrid[-h:h + 1, -h:h + 1].astype(float)
    keep = ~((yy == 0) & (xx == 0))
    x, y = xx[keep], yy[keep]
    design = np.column_stack([np.ones_like(x), x, y, x * x, y * y, x * y])
    weights = np.linalg.solve(design.T @ design, design.T)[0]
    kernel = np.zeros((size, size))
    kernel[keep] = weights
    return kernel


KERNEL = loo_quadratic_kernel()
KERNEL_VAR = float(np.sum(KERNEL**2))


def scene_estimate(image: np.ndarray, exclude: np.ndarray | None = None, kernel: np.ndarray = KERNEL,
                   passes: int = 4, return_fill: bool = False) -> Any:
    """The light each pixel would show if it were typical, estimated from its neighbours.

    The leave-one-out quadratic ``kernel`` is applied to the image in which the
    ``exclude`` mask (known defects) and outliers (more than 6 robust σ from
    their estimate) are replaced by the mean of their good 5 × 5 neighbours; a
    few passes settle the outlier set.  Unlike a local median, the estimate is
    unbiased for any quadratic scene (vignetting), and its noise is known:
    σ²·Σw² (0.081 σ² for 7 × 7).  With ``return_fill`` also the image as filtered (replacements included).
    """
    img = np.asarray(image, np.float64)
    base = np.zeros(img.shape, bool) if exclude is None else np.asarray(exclude, bool)
    bad = base
    est = img
    for it in range(passes):
        if bad.any():
            good = (~bad).astype(np.float64)
            num = ndimage.uniform_filter(img * good, size=5, mode="reflect")
            den = ndimage.uniform_filter(good, size=5, mode="reflect")
            wide = den < 1e-6
            if wide.any():
                num = np.where(wide, ndimage.uniform_filter(img * good, size=15, mode="reflect"), num)
                den = np.where(wide, ndimage.uniform_filter(good, size=15, mode="reflect"), den)
            filled = np.where(bad, num / np.maximum(den, 1e-12), img)
        else:
            filled = img
        est = ndimage.correlate(filled, kernel, mode="reflect")
        resid = img - est
        keep = resid[~bad]
        mad = robust_normal(keep)[1] if keep.size else 0.0
        new_bad = base | (np.abs(resid) > 6.0 * max(mad, 1e-9))
        if np.array_equal(new_bad, bad):
            break
        bad = new_bad
    if return_fill:
        return est, filled
    return est


# =========================================================================== measurements
@dataclass
class Group:
    """Frames sharing one condition at one epoch."""

    index: int
    epoch: int
    time: float
    exposure_s: float | None
    iso: float | None
    temperature_c: float | None
    subject: str | None
    frames: list[int]

    @property
    def n(self) -> int:
        return len(self.frames)

    @property
    def condition(self) -> tuple[Any, ...]:
        return (self.exposure_s, self.iso, self.temperature_c, self.subject)

    def label(self) -> str:
        parts = [f"epoch {self.epoch}"]
        if self.subject:
            parts.append(str(self.subject))
        if self.exposure_s is not None:
            parts.append(f"{self.exposure_s:g} s")
        if self.iso is not None:
            parts.append(f"ISO {self.iso:g}")
        if self.temperature_c is not None:
            parts.append(f"{self.temperature_c:g} °C")
        return ", ".join(parts)


@dataclass
class Measurements:
    """Per-condition statistics of a dataset, ready for checking.

    Arrays indexed ``[g]`` run over :attr:`groups` (every condition); those
    indexed by the pixel channel run over :attr:`repeated` (conditions with at
    least two frames), in that order.
    """

    root: Path
    shape: tuple[int, int]
    full_scale: float
    border: int
    epoch_times: np.ndarray
    has_time: bool
    groups: list[Group]
    mean_all: np.ndarray
    var_all: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    repeated: list[int]
    mean_a: np.ndarray
    mean_b: np.ndarray
    n_a: np.ndarray
    n_b: np.ndarray
    n_frames: int
    scene_all: np.ndarray = field(default=None)  # type: ignore[assignment]
    notes: list[str] = field(default_factory=list)

    @property
    def interior(self) -> np.ndarray:
        h, w = self.shape
        m = np.zeros(self.shape, bool)
        b = self.border
        m[b:h - b, b:w - b] = True
        return m

    @property
    def window(self) -> sp.Window:
        h, w = self.shape
        b = self.border
        return (float(b), float(b), float(w - b), float(h - b))

    def field_values(self, name: str) -> list[Any]:
        """Distinct values of a condition field over all frames (None excluded)."""
        attr = {"exposure_s": "exposure_s", "iso": "iso", "temperature_c": "temperature_c"}.get(name)
        if attr is None:
            return []
        return sorted({getattr(g, attr) for g in self.groups if getattr(g, attr) is not None})


def load_measurements(data: Dataset | str | Path, border: int | None = None, epoch_gap: float = 0.25,
                      max_size: int = 512, progress: Progress = no_progress) -> Measurements:
    """Read every frame once and reduce the dataset to per-condition statistics.

    Parameters
    ----------
    data
        A dataset or its folder.
    border
        Pixels ignored at each edge (default: half the scene window, 3).
    epoch_gap
        Capture-time gap (years) that starts a new epoch.
    max_size
        Larger frames are cropped to their central ``max_size × max_size`` pixels.

    Raises
    ------
    InputError
        No condition has two or more frames (the noise floor cannot be measured).
    """
    ds = data if isinstance(data, Dataset) else open_dataset(data)
    shape = ds.shape()
    notes = []
    h, w = shape[0], shape[1]
    crop = (slice(max(0, (h - max_size) // 2), max(0, (h - max_size) // 2) + min(h, max_size)),
            slice(max(0, (w - max_size) // 2), max(0, (w - max_size) // 2) + min(w, max_size)))
    if h > max_size or w > max_size:
        notes.append(f"frames of {w}×{h} cropped to their central {min(w, max_size)}×{min(h, max_size)} pixels")
    if len(shape) == 3:
        notes.append("colour frames averaged to grey")
    try:
        times = ds.captured_times()
        has_time = True
    except InputError:
        times = np.zeros(len(ds))
        has_time = False
        notes.append("no 'captured' field: one epoch, defect arrival and placement not tested")
    epoch, epoch_times = split_epochs(times, epoch_gap)
    keys: dict[tuple[Any, ...], list[int]] = {}
    for i, f in enumerate(ds.frames):
        keys.setdefault((int(epoch[i]), f.exposure_s, f.iso, f.temperature_c, f.subject), []).append(i)
    groups = [Group(j, k[0], float(epoch_times[k[0]]), k[1], k[2], k[3], k[4], idx)
              for j, (k, idx) in enumerate(sorted(keys.items(), key=lambda kv: (kv[0][0], kv[1][0])))]
    shp = (crop[0].stop - crop[0].start, crop[1].stop - crop[1].start)
    G = len(groups)
    mean_all = np.zeros((G, *shp))
    var_all = np.zeros((G, *shp))
    lo = np.zeros((G, *shp))
    hi = np.zeros((G, *shp))
    repeated = [g.index for g in groups if g.n >= 2]
    if not repeated:
        raise InputError(f"{ds.root}: no condition has two or more frames; the noise floor is measured from repeated "
                         "frames of one condition (same exposure_s, iso, temperature_c, subject and epoch): "
                         "take at least 2 frames per condition")
    R = len(repeated)
    mean_a = np.zeros((R, *shp))
    mean_b = np.zeros((R, *shp))
    n_a = np.zeros(R, int)
    n_b = np.zeros(R, int)
    rpos = {g: r for r, g in enumerate(repeated)}
    dtype = None
    maximum = 0.0
    for g in progress(groups, total=G, desc="frames"):
        stack = []
        for i in g.frames:
            img = ds.frames[i].load()
            dtype = img.dtype if dtype is None else dtype
            stack.append(grey_mean(img[crop], np.float64))
        arr = np.stack(stack)
        maximum = max(maximum, float(arr.max()))
        mean_all[g.index] = arr.mean(0)
        var_all[g.index] = arr.var(0, ddof=1) if len(arr) > 1 else 0.0
        lo[g.index] = arr.min(0)
        hi[g.index] = arr.max(0)
        if g.index in rpos:
            r = rpos[g.index]
            mean_a[r] = arr[0::2].mean(0)
            mean_b[r] = arr[1::2].mean(0)
            n_a[r], n_b[r] = len(arr[0::2]), len(arr[1::2])
    full_scale = infer_full_scale(np.dtype(dtype), maximum)
    border = SCENE_SIZE // 2 if border is None else int(border)
    meas = Measurements(ds.root, shp, full_scale, border, epoch_times, has_time, groups, mean_all, var_all, lo, hi,
                        repeated, mean_a, mean_b, n_a, n_b, len(ds), notes=notes)
    meas.scene_all = np.stack([scene_estimate(m) for m in mean_all])
    return meas


# =========================================================================== defect detection
@dataclass
class Detection:
    """Defects found at every epoch.

    Attributes
    ----------
    catalogue
        One record per site and kind, onset = the epoch it was first detected, amplitude = its offset d̂
        (partially stuck) or constant value (stuck).
    threshold
        Offset threshold τ (DN) for partially stuck pixels (the largest over epochs).
    dhat
        Per-epoch offset maps d̂ (NaN outside the interior).
    """

    catalogue: DefectCatalogue
    threshold: float
    dhat: list[np.ndarray]


def detect_defects(meas: Measurements, groups_by_epoch: list[list[int]], common_threshold: bool,
                   look_back: float | None = None, reference: np.ndarray | None = None) -> Detection:
    """Detect stuck and partially stuck pixels per epoch (once defective, always defective).

    Stuck: the output does not follow the light — the same value in every frame (eq. 11 of the paper) or, with
    temporal noise after the stuck value, a slope of output against scene level below one half — although the
    light at that pixel changes by more than 10 noise σ across the epoch's conditions.  Partially stuck: the offset d̂ — the intercept of the pixel's residual
    from the scene estimate regressed on scene level across the epoch's conditions, read at the lowest level
    (the mean residual where the level does not vary) — above ``DETECT_Z`` robust σ of d̂ over the sensor
    (a per-pixel gain then ends in the slope, not in d̂).

    With ``look_back`` (a z value), a partially stuck pixel first detected at epoch e is also taken to be
    present at the epochs just before e where its d̂ exceeds ``look_back`` robust σ and agrees with its
    amplitude within as much (its onset is estimated,
    rather than set at the first epoch sensitive enough to see it); used for pixel classes, not for counts.
    ``reference`` (one image per condition) replaces the scene estimate as what a defect-free pixel reads.
    """
    interior = meas.interior
    per_epoch = []
    noise = math.sqrt(max(float(np.median(meas.var_all[meas.repeated][:, interior])), QUANT_VAR))
    for gids in groups_by_epoch:
        if not gids:
            per_epoch.append(None)
            continue
        wts = np.array([meas.groups[g].n for g in gids], float)[:, None, None]
        lev = meas.scene_all[gids]
        res = meas.mean_all[gids] - (lev if reference is None else reference[gids])
        wsum = wts.sum(0)
        lbar = (wts * lev).sum(0) / wsum
        rbar = (wts * res).sum(0) / wsum
        sxx = (wts * (lev - lbar) ** 2).sum(0)
        sxy = (wts * (lev - lbar) * (res - rbar)).sum(0)
        spread = lev.max(0) - lev.min(0)
        varies = spread > 10.0 * noise
        slope = np.where(varies & (sxx > 0), sxy / np.where(sxx > 0, sxx, 1.0), 0.0)
        dhat = rbar + slope * (lev.min(0) - lbar)
        flat = np.where(sxx > 0, slope, 0.0) < -0.5
        constant = ((meas.lo[gids].min(0) == meas.hi[gids].max(0)) | flat) & varies
        inside = dhat[interior]
        tau = DETECT_Z * robust_normal(inside)[1] if inside.size else 0.0
        per_epoch.append((dhat, constant, max(tau, 1e-6)))
    taus = [p[2] for p in per_epoch if p is not None]
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
        dhat, constant, tau = item
        tau = common if common_threshold else tau
        stuck = constant & interior
        partial = (dhat > tau) & interior & ~stuck
        new_p = partial & (first_partial < 0) & (first_stuck < 0)
        first_partial[new_p] = e
        amp_partial[new_p] = dhat[new_p]
        if look_back is not None and new_p.any():
            back = new_p.copy()
            for e2 in range(e - 1, -1, -1):
                prev = per_epoch[e2]
                if prev is None:
                    continue
                sd = prev[2] / DETECT_Z
                back &= (prev[0] > look_back * sd) & (np.abs(prev[0] - amp_partial) < look_back * sd)
                if not back.any():
                    break
                first_partial[back] = e2
        new_s = stuck & (first_stuck < 0)
        first_stuck[new_s] = e
        amp_stuck[new_s] = meas.lo[groups_by_epoch[e]].min(0)[new_s]
        maps.append(np.where(interior, dhat, np.nan))
    rows = []
    for kind, first, amp in ((PARTIAL, first_partial, amp_partial), (STUCK, first_stuck, amp_stuck)):
        yy, xx = np.nonzero(first >= 0)
        rows.append(DefectCatalogue(xx.astype(np.int64), yy.astype(np.int64), np.full(len(xx), kind, np.int8),
                                    amp[yy, xx].astype(float), meas.epoch_times[first[yy, xx]].astype(float),
                                    np.full(len(xx), "detected", dtype=object)))
    return Detection(DefectCatalogue.concatenate(rows), common, maps)


def _kernel_scatter(mask: np.ndarray, kernel: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(source, destination, weight) triples such that correlating an image that is zero outside ``mask`` with
    ``kernel`` is ``bincount(destination, weight · image.ravel()[source])`` (reflecting at the edges)."""
    h, w = mask.shape
    ys, xs = np.nonzero(mask)
    k = kernel.shape[0] // 2
    src, dst, wts = [], [], []
    for dy in range(-k, k + 1):
        for dx in range(-k, k + 1):
            wt = kernel[k + dy, k + dx]
            if wt == 0:
                continue
            # out[p] = Σ_q K[q − p + k] · img[q]  ⇒  the source at (ys, xs) feeds p = (ys − dy, xs − dx)
            py, px = ys - dy, xs - dx
            ok = (py >= 0) & (py < h) & (px >= 0) & (px < w)
            src.append(ys[ok] * w + xs[ok])
            dst.append(py[ok] * w + px[ok])
            wts.append(np.full(int(ok.sum()), wt))
    if not src:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    return np.concatenate(src), np.concatenate(dst), np.concatenate(wts)


def class_maps(catalogue: DefectCatalogue, shape: tuple[int, int], times: Sequence[float]) -> np.ndarray:
    """Pixel class (NORMAL / PART / STK) at each time, from a catalogue (stuck overrides)."""
    out = np.zeros((len(times), *shape), np.int8)
    for i, t in enumerate(times):
        eff = catalogue.effective(t)
        out[i][eff.y[eff.kind == PARTIAL], eff.x[eff.kind == PARTIAL]] = PART
        out[i][eff.y[eff.kind == STUCK], eff.x[eff.kind == STUCK]] = STK
    return out


# =========================================================================== per-pixel projection
class PixelProjector:
    """Projection, pixel by pixel, off the span of per-pixel nuisance directions (weighted).

    ``columns`` are arrays ``(R, H, W)`` already multiplied by √weight; for each pixel the projection acts on the
    vector over conditions.
    """

    def __init__(self, columns: list[np.ndarray]):
        self.cols = columns
        k = len(columns)
        if k == 0:
            self.inv = None
            return
        gram = np.empty((*columns[0].shape[1:], k, k))
        for i in range(k):
            for j in range(i, k):
                gram[..., i, j] = gram[..., j, i] = np.einsum("r...,r...->...", columns[i], columns[j])
        diag = np.einsum("...ii->...i", gram)
        scale = np.where(diag > 0, diag, 1.0)
        norm = np.sqrt(scale[..., :, None] * scale[..., None, :])
        g = gram / norm
        for i in range(k):
            g[..., i, i] = np.where(diag[..., i] > 0, g[..., i, i] + 1e-10, 1.0)
        self.inv = np.linalg.inv(g) / norm

    def project(self, x: np.ndarray) -> np.ndarray:
        if self.inv is None:
            return x
        k = len(self.cols)
        b = np.stack([np.einsum("r...,r...->...", c, x) for c in self.cols], axis=-1)
        coef = np.einsum("...ij,...j->...i", self.inv, b)
        out = x.copy()
        for j in range(k):
            out -= coef[..., j][None] * self.cols[j]
        return out

    def leverage(self) -> np.ndarray | None:
        if self.inv is None:
            return None
        k = len(self.cols)
        h = np.zeros(self.cols[0].shape)
        for i in range(k):
            for j in range(k):
                h += self.cols[i] * self.cols[j] * self.inv[..., i, j][None]
        return h


# =========================================================================== results
@dataclass
class ParamEstimate:
    effect: str
    name: str
    value: float
    se: float | None
    unit: str = ""

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class PatternEstimate:
    effect: str
    name: str
    blocks: int
    rms: float
    maximum: float
    hyper: str | None = None
    hyper_value: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class CheckRow:
    statistic: str
    measured: float
    predicted: float
    z: float | None

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class Signature:
    """How one parameter of an effect moves one channel's statistics away from its null value.

    ``x`` is the derivative of the channel's statistics: pixel — ``(R, H, W)`` over repeated conditions;
    variance — one value per bin; growth — one value per count increment; spatial — the change of the
    standardised Ripley L per radius.  ``blocks`` (pixel channel) makes it a fixed pattern with one value per
    block, tested as a random effect.
    """

    channel: str
    name: str
    x: np.ndarray
    blocks: np.ndarray | None = None
    pixel_local: bool = False


@dataclass
class ChannelTest:
    """One channel's test of a candidate: LM (or likelihood-ratio) statistic, degrees of freedom, sample size."""

    channel: str
    lm: float
    df: int
    n: int
    detail: str
    boundary: bool = False  #: variance component tested at zero: the null distribution is ½χ²₀ + ½χ²₁
    absorbed: bool = False  #: the model's own parameters absorb (almost) all of the signature

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class Candidate:
    """One candidate effect's evidence."""

    effect: str
    delta_bic: float
    p: float
    flagged: bool
    lm: float
    df: int
    p_raw: float
    q: int
    tests: list[ChannelTest]
    evidence: str
    absorbed: bool = False

    def to_dict(self) -> dict[str, Any]:
        return {"effect": self.effect, "delta_bic": self.delta_bic, "p": self.p, "flagged": self.flagged,
                "lm": self.lm, "df": self.df, "p_raw": self.p_raw, "q": self.q, "evidence": self.evidence,
                "tests": [t.to_dict() for t in self.tests]}


@dataclass
class PlotData:
    """Arrays kept for the report (not serialised)."""

    residual_map: np.ndarray
    rms_map: np.ndarray
    consistency_map: np.ndarray
    class_map: np.ndarray
    covariates: dict[str, dict[str, Any]]
    counts: dict[str, Any]
    ripley: dict[str, Any]
    variance: dict[str, Any]


@dataclass
class CheckResult:
    """Everything :func:`check` found.  ``to_dict()`` gives the documented JSON."""

    effects: list[str]
    params: list[ParamEstimate]
    patterns: list[PatternEstimate]
    error: dict[str, Any]
    gof: dict[str, float | None]
    checks: list[CheckRow]
    candidates: list[Candidate]
    warnings: list[str]
    data: dict[str, Any]
    plots: PlotData | None = None
    baseline: "CheckResult | None" = None

    @property
    def flagged(self) -> list[str]:
        return [c.effect for c in self.candidates if c.flagged]

    def to_dict(self) -> dict[str, Any]:
        out = {"effects": self.effects, "error": self.error, "gof": self.gof,
               "candidates": [c.to_dict() for c in self.candidates],
               "params": [p.to_dict() for p in self.params], "patterns": [p.to_dict() for p in self.patterns],
               "checks": [c.to_dict() for c in self.checks], "warnings": self.warnings, "data": self.data}
        if self.baseline is not None:
            out["before"] = {"effects": self.baseline.effects, "error": self.baseline.error,
                             "gof": self.baseline.gof, "flagged": self.baseline.flagged}
        return out


# =========================================================================== the evidence
def _is_pixel(effect: Effect) -> bool:
    return effect.stage not in (Stage.ARRIVAL, Stage.NOISE)


class Evidence:
    """The measurements, the detected defects and the model being fitted, with the helpers effects use.

    Effects' :meth:`~forensics.sensor.model.Effect.fit` receives this object; the public helpers are
    :meth:`amplitude_max`, :meth:`detect_fraction`, :meth:`arrival_rate`, :meth:`site_intensity`,
    :meth:`cluster_excess`, :attr:`shape`, :attr:`sites`, :attr:`window`, plus :meth:`signature` (the
    generic signature) and :meth:`predict`.
    """

    def __init__(self, meas: Measurements, seed: int = 0, n_sim: int = 199):
        self.meas = meas
        self.seed = seed
        self.n_sim = n_sim
        self.shape = meas.shape
        self.window = meas.window
        #: bit depth of the fitted model: effects that scale with full scale (a response curve) must see the data's
        self.bit_depth = int(np.clip(round(math.log2(meas.full_scale + 1)), 1, 16))
        interior = meas.interior
        times = meas.epoch_times
        self.times = times
        # --- detection: classes from every frame of an epoch; counts from the conditions every epoch has
        by_epoch_all = [[g.index for g in meas.groups if g.epoch == e] for e in range(len(times))]
        self.classes_detection = detect_defects(meas, by_epoch_all, common_threshold=False, look_back=3.0)
        conditions = [{g.condition for g in meas.groups if g.epoch == e} for e in range(len(times))]
        common = set.intersection(*conditions) if conditions else set()
        if not common:
            common = set().union(*conditions)
            if len(times) > 1:
                meas.notes.append("no condition is measured at every epoch: defect counts use every frame "
                                  "(detection sensitivity may differ between epochs)")
        self.reference_conditions = sorted(common, key=str)
        by_epoch_ref = [[g.index for g in meas.groups if g.epoch == e and g.condition in common]
                        for e in range(len(times))]
        self.count_detection = detect_defects(meas, by_epoch_ref, common_threshold=True)
        self.threshold = {PARTIAL: self.count_detection.threshold, STUCK: -np.inf}
        cat = self.count_detection.catalogue
        self.count_catalogue = cat
        self.counts = {k: np.array([np.sum((cat.kind == k) & (cat.onset <= t)) for t in times]) for k in (PARTIAL, STUCK)}
        last = cat.at(times[-1]) if len(cat) else cat
        sites = np.unique(np.column_stack([last.y, last.x]), axis=0) if len(last) else np.zeros((0, 2), int)
        self.sites = sites  # (n, 2): row, column
        first = cat.at(times[0]) if len(cat) else cat
        self.first_sites = np.unique(np.column_stack([first.y, first.x]), axis=0) if len(first) else np.zeros((0, 2), int)
        self.area_fraction = float(interior.sum() / interior.size)
        self.interior_mp = interior.sum() / 1e6
        # --- pixel channel data
        self.rep = meas.repeated
        self.rgroups = [meas.groups[g] for g in self.rep]
        fs = meas.full_scale
        self.censored = np.stack([(meas.lo[g] <= 0) | (meas.hi[g] >= fs) for g in self.rep])
        self.usable = interior[None] & ~self.censored
        self.by_epoch_all = by_epoch_all
        self.initial_catalogue = self.classes_detection.catalogue
        self.catalogue: DefectCatalogue | None = None
        self.set_classes(self.initial_catalogue)

    def set_classes(self, catalogue: DefectCatalogue) -> None:
        """Pixel classes from a catalogue of detected defects, and everything that depends on them: the scene
        estimates (defects masked), the noise floor (normal pixels) and the variance bins."""
        if self.catalogue is catalogue:
            return
        meas = self.meas
        rgroups = self.rgroups
        self.catalogue = catalogue
        epoch_classes = class_maps(catalogue, meas.shape, self.times)
        self.classes = np.stack([epoch_classes[g.epoch] for g in rgroups])
        mask_by_epoch = [c != NORMAL for c in epoch_classes]
        # scene estimates per half; the known defects are filled in, and the fill values kept so that the
        # prediction can replace them by what the model says a typical pixel there would read
        self.defect_mask = np.stack([mask_by_epoch[g.epoch] for g in rgroups])
        sa = [scene_estimate(meas.mean_a[r], self.defect_mask[r], return_fill=True) for r in range(len(rgroups))]
        sb = [scene_estimate(meas.mean_b[r], self.defect_mask[r], return_fill=True) for r in range(len(rgroups))]
        self.scene_a = np.stack([x[0] for x in sa])
        self.scene_b = np.stack([x[0] for x in sb])
        self.fill_a = np.stack([np.where(self.defect_mask[r], sa[r][1], 0.0) for r in range(len(rgroups))])
        self.fill_b = np.stack([np.where(self.defect_mask[r], sb[r][1], 0.0) for r in range(len(rgroups))])
        self._refill_ops = {}
        for e, m in enumerate(epoch_classes):
            self._refill_ops[e] = _kernel_scatter(m != NORMAL, KERNEL)
        self._noise_floor()
        self._variance_bins()

    def redetect(self, device: Device) -> DefectCatalogue:
        """Detect the pixel classes again against the model's prediction for defect-free pixels, so that fixed
        patterns the model now explains (a per-pixel gain, column offsets) no longer raise the threshold."""
        meas = self.meas
        intact = Device(model=device.model, times=device.times, catalogue=DefectCatalogue.empty(), state=device.state)
        typical = device.typical()
        ref = np.empty_like(meas.mean_all)
        for g in meas.groups:
            ctx = intact.context(g.time, g.exposure_s, g.iso, g.temperature_c)
            tctx = typical.context(g.time, g.exposure_s, g.iso, g.temperature_c)
            ref[g.index] = intact.mean_signal(self.light(typical, tctx, meas.scene_all[g.index]), ctx)
        return detect_defects(meas, self.by_epoch_all, common_threshold=False, look_back=3.0, reference=ref).catalogue

    def light(self, typical: Device, tctx: Any, scene: np.ndarray) -> np.ndarray:
        """Incident light whose typical-pixel output is ``scene`` (inverse of the typical chain, tabulated on a
        grid and cached per parameter values and condition)."""
        table = self._table(typical, tctx)
        return scene if table is None else np.interp(scene, table[0], table[1])

    def _table(self, typical: Device, tctx: Any) -> tuple[np.ndarray, np.ndarray] | None:
        """The typical chain tabulated as (output, light), sorted; None where it is the identity."""
        key = (tuple((e.key, tuple(sorted(e.params().items()))) for e in typical.model.effects
                     if e.stage not in (Stage.ARRIVAL, Stage.NOISE)),
               tctx.time, tctx.exposure_s, tctx.iso, tctx.temperature_c)
        cache = self.__dict__.setdefault("_chain_cache", {})
        if key not in cache:
            if len(cache) > 4096:
                cache.clear()
            fs = self.meas.full_scale
            h, w = self.shape
            grid = np.linspace(-0.25 * fs, 2.0 * fs, h * w).reshape(h, w)
            chain = typical.mean_signal(grid, tctx)
            if np.max(np.abs(chain - grid)) < 1e-9 * fs:
                cache[key] = None
            else:
                flat_c, flat_g = chain.ravel(), grid.ravel()
                if np.any(np.diff(flat_c) <= 0):
                    order = np.argsort(flat_c, kind="stable")
                    flat_c, flat_g = flat_c[order], flat_g[order]
                cache[key] = (flat_c, flat_g)
        return cache[key]

    # ------------------------------------------------------------------ noise floor
    def _noise_floor(self) -> None:
        """σ²(level) = a_g + b·level per condition from the repeats of normal pixels; measured, never modelled."""
        meas = self.meas
        var = meas.var_all[self.rep]
        level = meas.mean_all[self.rep]
        normal = self.usable & (self.classes == NORMAL)
        a = np.zeros(len(self.rep))
        num = den = 0.0
        for r in range(len(self.rep)):
            m = normal[r]
            lv, vv = level[r][m], var[r][m]
            if lv.size < 10:
                continue
            lc = lv - lv.mean()
            num += float(np.sum(lc * (vv - vv.mean())))
            den += float(np.sum(lc * lc))
        b = num / den if den > 0 else 0.0
        for r in range(len(self.rep)):
            m = normal[r]
            a[r] = float(np.mean(var[r][m] - b * level[r][m])) if m.any() else float(np.median(var[r]))
        self.floor_a, self.floor_b = a, b
        smooth = np.maximum(a[:, None, None] + b * level, QUANT_VAR)
        stuck = self.classes == STK
        constant = np.all(var == 0, axis=0)[None] & stuck  # noiseless stuck pixels: only quantisation remains
        self.floor = np.where(constant, QUANT_VAR, smooth)  # per-frame temporal variance at each (condition, pixel)
        self.raw_floor = np.maximum(var, QUANT_VAR * constant)
        na = meas.n_a[:, None, None].astype(float)
        scene_term = np.where(stuck, 0.0, KERNEL_VAR)
        self.var_a = self.floor * (1.0 + scene_term) / na
        self.weight = np.where(self.usable, 1.0 / self.var_a, 0.0)

    # ------------------------------------------------------------------ variance bins
    def _variance_bins(self, n_bins: int = 3) -> None:
        meas = self.meas
        rows = []
        for r, g in enumerate(self.rgroups):
            m = self.usable[r] & (self.classes[r] == NORMAL)
            if m.sum() < 30:
                continue
            lev = meas.mean_all[g.index][m]
            v = meas.var_all[g.index][m]
            edges = np.quantile(lev, np.linspace(0, 1, n_bins + 1))
            which = np.clip(np.searchsorted(edges, lev, side="right") - 1, 0, n_bins - 1)
            for k in range(n_bins):
                s = which == k
                if s.sum() < 10:
                    continue
                rows.append((r, float(lev[s].mean()), float(v[s].mean()), int(s.sum() * (g.n - 1))))
        self.vbin_group = np.array([x[0] for x in rows], int)
        self.vbin_level = np.array([x[1] for x in rows])
        self.vbin_obs = np.maximum(np.array([x[2] for x in rows]), 1e-12)
        self.vbin_df = np.array([x[3] for x in rows], float)

    # ------------------------------------------------------------------ helpers for effects
    def amplitude_max(self, kind: int, default: float) -> float:
        """Largest detected amplitude of ``kind``, unbiased as (n + 1)/n · max (``default`` when none)."""
        cat = self.count_catalogue
        amp = cat.amplitude[cat.kind == kind]
        if kind == STUCK:
            return float(self.meas.full_scale)
        if amp.size == 0:
            return float(default)
        return float(amp.max() * (amp.size + 1) / amp.size)

    def detect_fraction(self, kind: int, amplitude: float) -> float:
        """Fraction of uniform amplitudes in [0, amplitude] above the detection threshold."""
        tau = self.threshold.get(kind, -np.inf)
        if not np.isfinite(tau) or tau <= 0:
            return 1.0
        return max(0.0, 1.0 - tau / amplitude) if amplitude > 0 else 0.0

    def arrival_rate(self, kind: int) -> float:
        """Detected arrivals of ``kind`` per megapixel per year between the first and last epoch (interior)."""
        t = self.times
        if len(t) < 2 or t[-1] <= t[0]:
            return 0.0
        c = self.counts[kind]
        return float((c[-1] - c[0]) / (t[-1] - t[0]) / self.interior_mp)

    def site_intensity(self) -> float:
        """Defective sites per pixel at the last epoch (interior)."""
        return len(self.sites) / sp.window_area(self.window)

    def cluster_excess(self) -> tuple[float, float]:
        """Thomas-cluster excess of Ripley's K at the last epoch: (A, σ) by minimum contrast."""
        if len(self.sites) < 10:
            return 0.0, 1.0
        radii = np.array([1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 12.0])
        k = sp.ripley_k(self.sites[:, 1], self.sites[:, 0], self.window, radii)
        return sp.fit_thomas_excess(radii, k)

    # ------------------------------------------------------------------ forward model (pixel channel)
    def predict(self, device: Device, half: str = "a", clip: bool = True) -> np.ndarray:
        """Predicted mean output ``(R, H, W)`` of every repeated condition for the half's scene estimates.

        The scene estimate of each pixel is mapped to incident light through the inverse of the typical
        pixel's chain and sent through the device's chain.  Known defects entered the scene estimate through
        fill values; here they are replaced by the defect's reading minus its modelled deviation from a
        typical pixel (what a typical pixel there would have read, noise and fixed patterns included), so
        that the neighbours' prediction does not depend on how the gap was filled.  (The deviation is the
        defect's: the pixel's fixed patterns, which a normal pixel there would show too, stay in.)
        """
        scenes = self.scene_a if half == "a" else self.scene_b
        fills = self.fill_a if half == "a" else self.fill_b
        means = self.meas.mean_a if half == "a" else self.meas.mean_b
        typical = device.typical()
        intact = Device(model=device.model, times=device.times, catalogue=DefectCatalogue.empty(), state=device.state)
        out = np.empty(scenes.shape)
        h, w = self.shape
        fs = self.meas.full_scale
        cache = self.__dict__.setdefault("_light_cache", {})
        for r, g in enumerate(self.rgroups):
            ctx = device.context(g.time, g.exposure_s, g.iso, g.temperature_c)
            tctx = typical.context(g.time, g.exposure_s, g.iso, g.temperature_c)
            table = self._table(typical, tctx)
            if table is None:
                light = scenes[r]
            else:  # the light of the fixed scene estimate depends only on the global parameters: cache it
                key = (id(table[0]), half, r)
                if key not in cache:
                    if len(cache) > 6 * len(self.rgroups):
                        cache.clear()
                    cache[key] = (table[0], np.interp(scenes[r], table[0], table[1]))
                light = cache[key][1]
            mu = device.mean_signal(light, ctx)
            mask = self.defect_mask[r]
            if mask.any():
                ictx = intact.context(g.time, g.exposure_s, g.iso, g.temperature_c)
                deviation = mu - intact.mean_signal(light, ictx)
                src, dst, wts = self._refill_ops[g.epoch]
                refill = (means[r] - deviation - fills[r]).ravel()[src]
                correction = np.bincount(dst, wts * refill, minlength=h * w)
                touched = np.flatnonzero(correction)
                light = light.copy().ravel()
                scene = scenes[r].ravel()[touched] + correction[touched]
                light[touched] = scene if table is None else np.interp(scene, table[0], table[1])
                mu = device.mean_signal(light.reshape(h, w), ctx)
            out[r] = mu
        if clip:
            np.clip(out, 0.0, fs, out=out)
        return out

    # ------------------------------------------------------------------ arrival model
    def arrival_device(self, effects: list[Effect]) -> Device:
        model = SensorModel(shape=self.shape, bit_depth=self.bit_depth, effects=[dataclasses.replace(e) for e in effects],
                            t0=float(self.times[0]))
        return Device(model=model, times=tuple(float(t) for t in self.times))

    def expected_counts(self, effects: list[Effect]) -> dict[int, np.ndarray]:
        """Expected cumulative detected records per kind at every epoch (interior), from the arrival effects."""
        dev = self.arrival_device(effects)
        out = {PARTIAL: np.zeros(len(self.times)), STUCK: np.zeros(len(self.times))}
        for e in dev.model.effects:
            got = e.expected_arrivals(dev, self.times, self.threshold)
            for k in out:
                out[k] = out[k] + np.asarray(got.get(k, 0.0), float) * self.area_fraction
        return out

    def increments(self, expected: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Observed and expected count increments between consecutive epochs, kinds concatenated."""
        obs, exp = [], []
        for k in (PARTIAL, STUCK):
            obs.append(np.diff(self.counts[k]))
            exp.append(np.diff(expected[k]))
        return np.concatenate(obs).astype(float), np.concatenate(exp)

    def simulate_arrivals(self, effects: list[Effect], rng: np.random.Generator) -> tuple[dict[int, np.ndarray], np.ndarray]:
        """One Monte-Carlo draw of the fitted arrival model: counts per kind at each epoch and the sites at the last."""
        model = SensorModel(shape=self.shape, bit_depth=self.bit_depth, effects=[dataclasses.replace(e) for e in effects],
                            t0=float(self.times[0]))
        dev = model.realize(rng, self.times)
        cat = dev.catalogue
        interior = self.meas.interior
        if len(cat):
            keep = interior[cat.y, cat.x] & ((cat.kind == STUCK) | (cat.amplitude > self.threshold[PARTIAL]))
            cat = cat.select(keep)
        counts = {k: np.array([np.sum((cat.kind == k) & (cat.onset <= t)) for t in self.times]) + self.counts[k][0]
                  for k in (PARTIAL, STUCK)}
        last = cat.at(self.times[-1])
        pts = np.column_stack([last.y, last.x]) if len(last) else np.zeros((0, 2), int)
        if len(self.first_sites):
            pts = np.concatenate([pts, self.first_sites])
        pts = np.unique(pts, axis=0) if len(pts) else pts
        return counts, pts

    # ------------------------------------------------------------------ generic signature
    def signature(self, effect: Effect) -> list[Signature]:
        """Generic signature of ``effect`` (not in the model) at its null values, by finite differences."""
        fitted = self.fitted
        if effect.stage == Stage.ARRIVAL:
            return self._arrival_signature(effect, fitted)
        if effect.stage == Stage.NOISE:
            return self._variance_signature(effect, fitted)
        return self._pixel_signature(effect, fitted)

    def _pixel_signature(self, effect: Effect, fitted: "FittedModel") -> list[Signature]:
        probe_effect = effect.nulled()
        model = fitted.device.model.with_effects(probe_effect)
        dev = fitted.device.copy(model)
        probe_effect.realize(dev, np.random.default_rng(self.seed))
        for pat in probe_effect.patterns(dev):
            pat.values[...] = 0.0
        base = self.predict(dev, clip=False)
        sigs = []
        for pat in probe_effect.patterns(dev):
            used = np.unique(pat.blocks[pat.blocks >= 0])
            if used.size == 0:
                continue
            delta = 1e-2
            pat.values[used] += delta
            x = (self.predict(dev, clip=False) - base) / delta * (pat.blocks >= 0)[None]
            pat.values[used] -= delta
            sigs.append(Signature("pixel", f"{effect.key}.{pat.name}", x, pat.blocks, pat.pixel_local))
        names = list(dict.fromkeys([*probe_effect.null_values(), *probe_effect.free_params()]))
        for name in names:
            value = getattr(probe_effect, name)
            delta = 1e-3 * (1.0 + abs(value))
            lo, hi = probe_effect.bounds(name)
            if value + delta > hi:
                delta = -delta
            setattr(probe_effect, name, value + delta)
            x = (self.predict(dev, clip=False) - base) / delta
            setattr(probe_effect, name, value)
            sigs.append(Signature("pixel", f"{effect.key}.{name}", x))
        return sigs

    def _variance_signature(self, effect: Effect, fitted: "FittedModel") -> list[Signature]:
        probe_effect = effect.nulled()
        noise = [*fitted.noise_effects(), probe_effect]
        base = self.predicted_variance(noise, fitted.device)
        sigs = []
        for name in dict.fromkeys([*probe_effect.null_values(), *probe_effect.free_params()]):
            value = getattr(probe_effect, name)
            delta = 1e-3 * (1.0 + abs(value))
            setattr(probe_effect, name, value + delta)
            x = (np.log(self.predicted_variance(noise, fitted.device)) - np.log(base)) / delta
            setattr(probe_effect, name, value)
            sigs.append(Signature("variance", f"{effect.key}.{name}", x))
        return sigs

    def _arrival_signature(self, effect: Effect, fitted: "FittedModel") -> list[Signature]:
        sigs = []
        if len(self.times) < 3:
            return sigs
        strong = effect.probe(self)
        probe_effect = dataclasses.replace(strong, **effect.null_values())
        arrivals = fitted.arrival_effects()
        base = self.increments(self.expected_counts([*arrivals, probe_effect]))[1]
        for name in dict.fromkeys([*probe_effect.null_values(), *probe_effect.free_params()]):
            value = getattr(probe_effect, name)
            delta = 1e-3 * (1.0 + abs(getattr(strong, name)))
            setattr(probe_effect, name, value + delta)
            x = (self.increments(self.expected_counts([*arrivals, probe_effect]))[1] - base) / delta
            setattr(probe_effect, name, value)
            sigs.append(Signature("growth", f"{effect.key}.{name}", x))
        if len(self.sites) >= 10 and fitted.spatial_null is not None:
            rng = np.random.default_rng([self.seed, 7])
            ls = []
            for _ in range(self.n_sim):
                _, pts = self.simulate_arrivals([*arrivals, strong], rng)
                ls.append(self.ripley_l(pts))
            ls = np.array(ls)
            m0, s0 = fitted.spatial_null["mean"], fitted.spatial_null["sd"]
            direction = (np.nanmean(ls, 0) - m0) / s0
            noise = np.sqrt(1.0 / self.n_sim + 1.0 / self.n_sim)
            if np.nanmax(np.abs(direction)) > 4.0 * noise:
                sigs.append(Signature("spatial", f"{effect.key}.placement", np.nan_to_num(direction)))
        return sigs

    # ------------------------------------------------------------------ shared statistics
    def ripley_l(self, pts: np.ndarray) -> np.ndarray:
        if len(pts) < 2:
            return np.full(len(sp.DEFAULT_RADII), np.nan)
        return sp.ripley_l(pts[:, 1], pts[:, 0], self.window, sp.DEFAULT_RADII)

    def predicted_variance(self, noise_effects: list[Effect], device: Device) -> np.ndarray:
        """Predicted temporal variance of each variance bin."""
        out = np.full(len(self.vbin_level), QUANT_VAR)
        for r in np.unique(self.vbin_group):
            g = self.rgroups[r]
            sel = self.vbin_group == r
            ctx = device.context(g.time, g.exposure_s, g.iso, g.temperature_c)
            for e in noise_effects:
                out[sel] += np.asarray(e.variance(self.vbin_level[sel], ctx), float)
        return np.maximum(out, 1e-12)


# =========================================================================== fitting
@dataclass
class FittedModel:
    """A model fitted to the evidence: the device (fitted defects and patterns) and the fit's by-products."""

    device: Device
    effects: list[Effect]
    mu_a: np.ndarray
    mu_b: np.ndarray
    nuisance: list[np.ndarray]
    projector: PixelProjector
    params: list[ParamEstimate]
    patterns: list[PatternEstimate]
    expected: dict[int, np.ndarray]
    arrival_free: list[tuple[Effect, str]]
    growth_jac: np.ndarray | None
    variance_pred: np.ndarray
    variance_jac: np.ndarray | None
    spatial_null: dict[str, Any] | None
    sims: dict[str, Any] = field(default_factory=dict)

    def arrival_effects(self) -> list[Effect]:
        return [e for e in self.effects if e.stage == Stage.ARRIVAL]

    def noise_effects(self) -> list[Effect]:
        return [e for e in self.effects if e.stage == Stage.NOISE]


def _unit(effect: Effect, name: str) -> str:
    for f in dataclasses.fields(effect):
        if f.name == name:
            return f.metadata.get("unit", "")
    return ""


def _set_param(effect: Effect, name: str, value: float) -> None:
    lo, hi = effect.bounds(name)
    setattr(effect, name, float(np.clip(value, lo, hi)))


def fit_model(ev: Evidence, effects: list[Effect], max_cycles: int = 12) -> FittedModel:
    """Fit ``effects`` to the evidence: arrival effects on the counts, pixel effects on the first half of the
    repeats, noise effects on the binned variances.

    Pixel classes come from defect detection; when the model has fixed patterns on normal pixels, detection is
    repeated against the fitted model's prediction for defect-free pixels and the model refitted once.
    """
    ev.set_classes(ev.initial_catalogue)
    fitted = _fit_once(ev, effects, max_cycles)
    device = fitted.device
    covers_normal = any(bool(np.any((p.blocks >= 0) & (ev.classes[-1] == NORMAL)))
                        for e in device.model.effects if _is_pixel(e) and e.null_values() for p in e.patterns(device))
    if covers_normal:
        catalogue = ev.redetect(device)
        if not _same_catalogue(catalogue, ev.catalogue):
            ev.set_classes(catalogue)
            fitted = _fit_once(ev, fitted.effects, max_cycles)
    return fitted


def _same_catalogue(a: DefectCatalogue, b: DefectCatalogue | None) -> bool:
    if b is None or len(a) != len(b):
        return False
    ka = sorted(zip(a.y.tolist(), a.x.tolist(), a.kind.tolist(), a.onset.tolist()))
    kb = sorted(zip(b.y.tolist(), b.x.tolist(), b.kind.tolist(), b.onset.tolist()))
    return ka == kb


def _fit_once(ev: Evidence, effects: list[Effect], max_cycles: int) -> FittedModel:
    model = SensorModel(shape=ev.shape, bit_depth=ev.bit_depth, effects=list(effects), t0=float(ev.times[0]))
    effects = model.effects
    ev.fitted = None  # type: ignore[attr-defined]
    params: list[ParamEstimate] = []
    # ---------------------------------------------------------------- arrivals
    arrivals = [e for e in effects if e.stage == Stage.ARRIVAL]
    expected, arrival_free, growth_jac = _fit_arrivals(ev, arrivals, params)
    # ---------------------------------------------------------------- pixel channel
    device = Device(model=model, times=tuple(float(t) for t in ev.times),
                    catalogue=ev.catalogue.select(np.arange(len(ev.catalogue))))
    rng = np.random.default_rng(ev.seed)
    for e in effects:
        if e.stage != Stage.ARRIVAL:
            e.realize(device, rng)
    for e in effects:
        if _is_pixel(e) and e.null_values():
            for pat in e.patterns(device):
                pat.values[...] = 0.0
    pixel_effects = [e for e in effects if _is_pixel(e)]
    ev.device = device  # type: ignore[attr-defined]  # for bespoke fits
    for e in pixel_effects:
        e.fit(ev)
    mu_a, nuisance, local_se = _fit_pixels(ev, device, pixel_effects, params, max_cycles)
    projector = PixelProjector([c * np.sqrt(ev.weight) for c in nuisance])
    patterns = _pattern_summaries(device, pixel_effects, local_se)
    mu_b = ev.predict(device, "b")
    # ---------------------------------------------------------------- variance
    noise = [e for e in effects if e.stage == Stage.NOISE]
    for e in noise:
        e.fit(ev)
    vpred, vjac = _fit_variance(ev, noise, device, params)
    fitted = FittedModel(device, effects, mu_a, mu_b, nuisance, projector, params, patterns, expected, arrival_free,
                         growth_jac, vpred, vjac, None)
    ev.fitted = fitted  # type: ignore[attr-defined]
    _simulate_null(ev, fitted)
    return fitted


def _fit_arrivals(ev: Evidence, arrivals: list[Effect], params: list[ParamEstimate]):
    if not arrivals:
        return {PARTIAL: np.zeros(len(ev.times)), STUCK: np.zeros(len(ev.times))}, [], None
    free = [(e, n) for e in arrivals for n in e.free_params()]
    for _ in range(3):
        for e in arrivals:
            e.fit(ev)
        if not free or len(ev.times) < 2:
            break
        obs, _ = ev.increments(ev.expected_counts(arrivals))
        # starting values: scale rates so the total matches the observed count
        total_obs = obs.sum()

        def unpack(theta: np.ndarray) -> None:
            for (e, n), t in zip(free, theta):
                lo, hi = e.bounds(n)
                setattr(e, n, float(np.exp(t)) if lo >= 0 and np.isinf(hi) else float(np.clip(t, lo, hi)))

        def pack() -> np.ndarray:
            out = []
            for e, n in free:
                lo, hi = e.bounds(n)
                v = getattr(e, n)
                out.append(np.log(max(v, 1e-9)) if lo >= 0 and np.isinf(hi) else v)
            return np.array(out, float)

        exp_total = ev.increments(ev.expected_counts(arrivals))[1].sum()
        if exp_total > 0 and total_obs > 0:
            for e, n in free:
                lo, hi = e.bounds(n)
                if lo >= 0 and np.isinf(hi) and e.null_values().get(n) is None:
                    setattr(e, n, getattr(e, n) * total_obs / exp_total)

        def nll(theta: np.ndarray) -> float:
            unpack(theta)
            o, m = ev.increments(ev.expected_counts(arrivals))
            m = np.maximum(m, 1e-12)
            return float(np.sum(m - o * np.log(m)))

        bounds = []
        for e, n in free:
            lo, hi = e.bounds(n)
            # positive parameters are optimised on a log scale, kept within e^-25 … e^25
            bounds.append((-25.0, 25.0) if lo >= 0 and np.isinf(hi) else (lo if np.isfinite(lo) else None,
                                                                            hi if np.isfinite(hi) else None))
        best = None
        starts = [pack()]
        for x0 in starts:
            res = optimize.minimize(nll, x0, method="L-BFGS-B", bounds=bounds)
            if best is None or res.fun < best.fun:
                best = res
        unpack(best.x)
    expected = ev.expected_counts(arrivals)
    jac = None
    if free:
        base = ev.increments(expected)[1]
        cols = []
        for e, n in free:
            v = getattr(e, n)
            d = 1e-4 * (1 + abs(v))
            setattr(e, n, v + d)
            cols.append((ev.increments(ev.expected_counts(arrivals))[1] - base) / d)
            setattr(e, n, v)
        jac = np.array(cols)
        m = np.maximum(base, 1e-9)
        info = (jac / m) @ jac.T
        cov = np.linalg.pinv(info)
        for i, (e, n) in enumerate(free):
            params.append(ParamEstimate(e.key, n, float(getattr(e, n)), float(np.sqrt(max(cov[i, i], 0))), _unit(e, n)))
    for e in arrivals:
        for n in e.self_fitted:
            params.append(ParamEstimate(e.key, n, float(getattr(e, n)), None, _unit(e, n)))
    return expected, free, jac


def _pattern_derivative(ev: Evidence, device: Device, pat, base: np.ndarray) -> np.ndarray:
    """∂μ/∂value of each pixel's own block, all blocks perturbed at once (zero outside the blocks: a block's
    influence on other pixels, e.g. through their scene estimate, is not a parameter of theirs)."""
    used = np.unique(pat.blocks[pat.blocks >= 0])
    if used.size == 0:
        return np.zeros_like(base)
    delta = 1e-3 * (1.0 + float(np.max(np.abs(pat.values[used]))))
    pat.values[used] += delta
    x = (ev.predict(device, clip=False) - base) / delta
    pat.values[used] -= delta
    return x * (pat.blocks >= 0)[None]


def _solve_local(ev: Evidence, X: list[np.ndarray], r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel weighted least squares of ``r`` on the columns ``X``: (coefficients (k,H,W), their variances)."""
    w = ev.weight
    k = len(X)
    A = np.empty((*ev.shape, k, k))
    b = np.empty((*ev.shape, k))
    for i in range(k):
        b[..., i] = np.einsum("r...,r...->...", X[i] * w, r)
        for j in range(i, k):
            A[..., i, j] = A[..., j, i] = np.einsum("r...,r...->...", X[i] * w, X[j])
    diag = np.einsum("...ii->...i", A).copy()
    dead = diag <= 1e-12 * (diag.max() if diag.size else 1.0)
    for i in range(k):
        A[..., i, i] = np.where(dead[..., i], 1.0, A[..., i, i] * (1 + 1e-10))
        b[..., i] = np.where(dead[..., i], 0.0, b[..., i])
        for j in range(k):
            if i != j:
                A[..., i, j] = np.where(dead[..., i] | dead[..., j], 0.0, A[..., i, j])
    inv = np.linalg.inv(A)
    coef = np.einsum("...ij,...j->...i", inv, b)
    var = np.einsum("...ii->...i", inv).copy()
    var[dead] = np.nan
    return np.moveaxis(coef, -1, 0), np.moveaxis(var, -1, 0)


def _fit_pixels(ev: Evidence, device: Device, effects: list[Effect], params: list[ParamEstimate],
                max_cycles: int):
    meas = ev.meas
    y = meas.mean_a
    w = ev.weight
    pats = [(e, p) for e in effects for p in e.patterns(device)]
    local = [(e, p) for e, p in pats if p.pixel_local]
    other = [(e, p) for e, p in pats if not p.pixel_local]
    glob = [(e, n) for e in effects for n in e.free_params()]
    chi_prev = np.inf
    X_local: list[np.ndarray] = []
    local_var = None
    fs = ev.meas.full_scale
    for cycle in range(max_cycles):
        raw = ev.predict(device, clip=False)  # derivatives ignore the clipping (clipped values are censored)
        mu = np.clip(raw, 0.0, fs)
        # -- pixel-local patterns, jointly per pixel
        X_local = [_pattern_derivative(ev, device, p, raw) for _, p in local]
        if local:
            coef, local_var = _solve_local(ev, X_local, y - mu)
            for (e, p), c in zip(local, coef):
                m = p.blocks >= 0
                p.values[p.blocks[m]] += c[m]
            mu = ev.predict(device)
        # -- other patterns, block by block
        for e, p in other:
            raw = ev.predict(device, clip=False)
            x = _pattern_derivative(ev, device, p, raw)
            m = (p.blocks >= 0)[None] & (w > 0)
            blk = np.broadcast_to(p.blocks[None], x.shape)[m]
            num = np.bincount(blk, (x * w * (y - mu))[m], minlength=len(p.values))
            den = np.bincount(blk, (x * x * w)[m], minlength=len(p.values))
            p.values[...] += np.where(den > 0, num / np.where(den > 0, den, 1), 0.0)
            mu = ev.predict(device)
        # -- global parameters: profiled Gauss–Newton with step halving
        if glob:
            r = y - mu
            raw = ev.predict(device, clip=False)
            proj = PixelProjector([c * np.sqrt(w) for c in X_local])
            J = []
            for e, n in glob:
                v = getattr(e, n)
                d = 1e-3 * (1 + abs(v))
                lo, hi = e.bounds(n)
                if v + d > hi:
                    d = -d
                setattr(e, n, v + d)
                J.append(proj.project((ev.predict(device, clip=False) - raw) / d * np.sqrt(w)))
                setattr(e, n, v)
            zr = proj.project(r * np.sqrt(w))
            H = np.array([[np.sum(a * b) for b in J] for a in J])
            g = np.array([np.sum(a * zr) for a in J])
            step = np.linalg.lstsq(H + 1e-9 * np.diag(np.diag(H) + 1e-30), g, rcond=None)[0]
            old = [getattr(e, n) for e, n in glob]
            old_vals = [p.values.copy() for _, p in pats]
            chi_old = float(np.sum(w * r * r))
            for _ in range(8):
                for (e, n), v, s in zip(glob, old, step):
                    _set_param(e, n, v + s)
                mu_new = ev.predict(device)
                if local:
                    coef, _ = _solve_local(ev, X_local, y - mu_new)
                    for (e, p), c in zip(local, coef):
                        m = p.blocks >= 0
                        p.values[p.blocks[m]] += c[m]
                    mu_new = ev.predict(device)
                chi_new = float(np.sum(w * (y - mu_new) ** 2))
                if chi_new <= chi_old:
                    break
                for (_, p), v in zip(pats, old_vals):
                    p.values[...] = v
                step = step / 2
            else:
                for (e, n), v in zip(glob, old):
                    setattr(e, n, v)
            ev._glob_info = (glob, H)  # for standard errors
        mu = ev.predict(device)
        chi = float(np.sum(w * (y - mu) ** 2))
        if np.isfinite(chi_prev) and abs(chi_prev - chi) <= 1e-6 * max(chi, 1.0) and cycle >= 1:
            break
        chi_prev = chi
    raw = ev.predict(device, clip=False)
    mu = np.clip(raw, 0.0, fs)
    if local:
        X_local = [_pattern_derivative(ev, device, p, raw) for _, p in local]
        _, local_var = _solve_local(ev, X_local, y - mu)
    if glob:
        gl, H = ev._glob_info
        cov = np.linalg.pinv(H)
        for i, (e, n) in enumerate(gl):
            params.append(ParamEstimate(e.key, n, float(getattr(e, n)), float(np.sqrt(max(cov[i, i], 0.0))),
                                        _unit(e, n)))
    ev._local_patterns = local
    return mu, X_local, (local, local_var)


def _pattern_summaries(device: Device, effects: list[Effect], local_se) -> list[PatternEstimate]:
    local, local_var = local_se
    var_by_id = {}
    if local_var is not None:
        for (e, p), v in zip(local, local_var):
            var_by_id[p.name, e.key] = (p.blocks, v)
    out = []
    for e in effects:
        for p in e.patterns(device):
            used = np.unique(p.blocks[p.blocks >= 0])
            if used.size == 0:
                out.append(PatternEstimate(e.key, p.name, 0, 0.0, 0.0, p.hyper, None))
                continue
            vals = p.values[used].astype(float)
            ms = float(np.mean(vals**2))
            item = var_by_id.get((p.name, e.key))
            noise = 0.0
            if item is not None:
                m = item[0] >= 0
                noise = float(np.nanmean(item[1][m])) if m.any() else 0.0
            rms = math.sqrt(max(ms - noise, 0.0))
            hyper_value = None
            if p.hyper:
                hyper_value = {"rms": rms, "max": float(vals.max()), "mean": float(vals.mean())}[p.summary]
                setattr(e, p.hyper, hyper_value)
            out.append(PatternEstimate(e.key, p.name, int(used.size), rms, float(np.max(np.abs(vals))), p.hyper,
                                       hyper_value))
    return out


def _fit_variance(ev: Evidence, noise: list[Effect], device: Device, params: list[ParamEstimate]):
    free = [(e, n) for e in noise for n in e.free_params()]
    y = np.log(ev.vbin_obs)
    w = ev.vbin_df / 2.0
    jac = None
    if free and len(y):
        for _ in range(30):
            pred = np.log(ev.predicted_variance(noise, device))
            r = y - pred
            cols = []
            for e, n in free:
                v = getattr(e, n)
                d = 1e-4 * (1 + abs(v))
                setattr(e, n, v + d)
                cols.append((np.log(ev.predicted_variance(noise, device)) - pred) / d)
                setattr(e, n, v)
            J = np.array(cols)
            H = (J * w) @ J.T
            g = (J * w) @ r
            step = np.linalg.lstsq(H, g, rcond=None)[0]
            old = [getattr(e, n) for e, n in free]
            chi_old = float(np.sum(w * r * r))
            for _ in range(20):
                for (e, n), v, s in zip(free, old, step):
                    _set_param(e, n, v + s)
                chi_new = float(np.sum(w * (y - np.log(ev.predicted_variance(noise, device))) ** 2))
                if chi_new <= chi_old:
                    break
                step = step / 2
            else:
                for (e, n), v in zip(free, old):
                    setattr(e, n, v)
            if np.all(np.abs(step) <= 1e-7 * (1 + np.abs(old))):
                break
        pred = np.log(ev.predicted_variance(noise, device))
        cols = []
        for e, n in free:
            v = getattr(e, n)
            d = 1e-4 * (1 + abs(v))
            setattr(e, n, v + d)
            cols.append((np.log(ev.predicted_variance(noise, device)) - pred) / d)
            setattr(e, n, v)
        jac = np.array(cols)
        cov = np.linalg.pinv((jac * w) @ jac.T)
        for i, (e, n) in enumerate(free):
            params.append(ParamEstimate(e.key, n, float(getattr(e, n)), float(np.sqrt(max(cov[i, i], 0.0))),
                                        _unit(e, n)))
    return ev.predicted_variance(noise, device), jac


def _simulate_null(ev: Evidence, fitted: FittedModel) -> None:
    """Monte-Carlo draws of the fitted arrival model: count distribution and Ripley-L envelope."""
    arrivals = fitted.arrival_effects()
    if not arrivals or len(ev.times) < 2:
        return
    rng = np.random.default_rng([ev.seed, 1])
    counts = {PARTIAL: [], STUCK: []}
    ls = []
    devs = []
    pearson = []
    obs, exp = ev.increments(fitted.expected)
    exp = np.maximum(exp, 1e-9)
    for _ in range(ev.n_sim):
        c, pts = ev.simulate_arrivals(arrivals, rng)
        for k in counts:
            counts[k].append(c[k])
        ls.append(ev.ripley_l(pts))
        o = np.concatenate([np.diff(c[PARTIAL]), np.diff(c[STUCK])]).astype(float)
        devs.append(poisson_deviance(o, exp))
        pearson.append(float(np.sum((o - exp) ** 2 / exp)))
    fitted.sims = {"counts": {k: np.array(v) for k, v in counts.items()}, "deviance": np.array(devs),
                   "pearson": np.array(pearson)}
    ls = np.array(ls)
    if len(ev.sites) >= 10 and np.isfinite(ls).all():
        m0 = ls.mean(0)
        s0 = np.maximum(ls.std(0, ddof=1), 1e-9)
        fitted.spatial_null = {"sims": ls, "mean": m0, "sd": s0}


# =========================================================================== scoring
def _class_errors(ev: Evidence, fitted: FittedModel) -> dict[str, float | None]:
    """Held-out error per class: √(Σ residual² / Σ noise floor) on the second half of the repeats."""
    meas = ev.meas
    r = meas.mean_b - fitted.mu_b
    nb = meas.n_b[:, None, None].astype(float)
    scene_term = np.where(ev.classes == STK, 0.0, KERNEL_VAR)
    floor = ev.raw_floor * (1.0 + scene_term) / nb
    out: dict[str, float | None] = {}
    r2 = r * r
    for k, name in enumerate(CLASSES):
        m = ev.usable & (ev.classes == k)
        if not m.any():
            out[name] = None
            continue
        num = float(r2[m].sum())
        quant = float(np.sum(m.sum(axis=(1, 2)) * QUANT_VAR / meas.n_b))
        den = max(float(floor[m].sum()), quant)
        out[name] = math.sqrt(num / den)
    return out


def _pixel_gof(ev: Evidence, fitted: FittedModel, checks: list[CheckRow]) -> tuple[float, np.ndarray]:
    """Goodness of fit of the pixel channel: binned residual means and per-pixel consistency (in-sample)."""
    meas = ev.meas
    sw = np.sqrt(ev.weight)
    z = fitted.projector.project((meas.mean_a - fitted.mu_a) * sw)
    lev = fitted.projector.leverage()
    keep = ev.usable & (ev.classes != STK)
    var1 = np.where(keep, 1.0 - (lev if lev is not None else 0.0), 0.0)
    # (a) mean residual of the defect classes per condition (normal pixels' smooth misfit is absorbed by the
    # scene estimate by construction; their pixel-to-pixel misfit is test (b))
    chi = 0.0
    nb = 0
    for r in range(len(ev.rep)):
        for k in (PART,):
            m = keep[r] & (ev.classes[r] == k)
            if m.sum() < 3:
                continue
            v = float(var1[r][m].sum())
            if v <= 0.5:
                continue
            chi += float(z[r][m].sum()) ** 2 / v
            nb += 1
    p_a = float(stats.chi2.sf(chi, nb)) if nb else 1.0
    if nb:
        checks.append(CheckRow("pixel: mean residual of partially stuck pixels per condition, χ²/df", chi / nb, 1.0,
                               (chi - nb) / math.sqrt(2 * nb)))
    # (b) per-pixel consistency: component along the constant, against the within-pixel scatter
    ones = fitted.projector.project(np.where(keep, sw, 0.0))
    norm = np.sqrt(np.sum(ones**2, axis=0))
    zk = np.where(keep, z, 0.0)
    u = np.where(norm > 0, np.sum(ones * zk, axis=0) / np.where(norm > 0, norm, 1), 0.0)
    npix_obs = keep.sum(axis=0)
    k_local = np.zeros(ev.shape)
    for c in fitted.nuisance:
        k_local += (np.abs(c).sum(axis=0) > 0)
    df_within = np.maximum(npix_obs - k_local - 1, 0)
    ss_within = np.sum(zk**2, axis=0) - u**2
    use = (norm > 0) & (df_within > 0)
    n_pix = int(use.sum())
    consistency = np.where(use, u, np.nan)
    if n_pix > 10:
        between = float(np.mean(u[use] ** 2))
        within = float(ss_within[use].sum() / df_within[use].sum())
        ratio = between / max(within, 1e-12)
        dfw = float(df_within[use].sum())
        p_b = float(stats.f.sf(ratio, n_pix, dfw))
        checks.append(CheckRow("pixel: per-pixel consistency (between / within)", ratio, 1.0,
                               (ratio - 1) / math.sqrt(2 / n_pix + 2 / dfw)))
    else:
        p_b = 1.0
    return min(1.0, 2 * min(p_a, p_b)), consistency


def _covariate_checks(ev: Evidence, fitted: FittedModel, checks: list[CheckRow]) -> dict[str, dict[str, Any]]:
    """Held-out residuals against every covariate: binned means per class, and a weighted slope test."""
    meas = ev.meas
    r = meas.mean_b - fitted.mu_b
    nb = meas.n_b[:, None, None].astype(float)
    var_b = ev.floor * (1.0 + np.where(ev.classes == STK, 0.0, KERNEL_VAR)) / nb
    z = r / np.sqrt(var_b)
    covs = {
        "scene level (DN)": ev.scene_a,  # the other half's estimate: binning on its own would bias the residual
        "exposure_s": np.array([g.exposure_s if g.exposure_s is not None else np.nan for g in ev.rgroups]),
        "iso": np.array([g.iso if g.iso is not None else np.nan for g in ev.rgroups]),
        "temperature_c": np.array([g.temperature_c if g.temperature_c is not None else np.nan for g in ev.rgroups]),
        "epoch (year)": np.array([g.time for g in ev.rgroups]),
    }
    out: dict[str, dict[str, Any]] = {}
    for cname, cov in covs.items():
        c = cov if cov.ndim == 3 else np.broadcast_to(cov[:, None, None], z.shape)
        entry: dict[str, Any] = {}
        for k, klass in enumerate(CLASSES[:2]):
            m = ev.usable & (ev.classes == k) & np.isfinite(c)
            if m.sum() < 10:
                continue
            cv, zv, rv = c[m], z[m], r[m]
            if np.ptp(cv) <= 0:
                continue
            uniq = np.unique(cv)
            if uniq.size > 12:
                edges = np.quantile(cv, np.linspace(0, 1, 9))
                idx = np.clip(np.searchsorted(edges, cv, side="right") - 1, 0, 7)
                centres = np.array([cv[idx == i].mean() if np.any(idx == i) else np.nan for i in range(8)])
            else:
                idx = np.searchsorted(uniq, cv)
                centres = uniq
            nbin = len(centres)
            mean_r = np.array([rv[idx == i].mean() if np.any(idx == i) else np.nan for i in range(nbin)])
            se_r = np.array([rv[idx == i].std() / math.sqrt(max(np.sum(idx == i), 1)) if np.any(idx == i) else np.nan
                             for i in range(nbin)])
            entry[klass] = {"x": centres, "mean": mean_r, "se": se_r}
            cc = (cv - cv.mean()) / cv.std()
            slope_z = float(np.sum(cc * zv) / math.sqrt(np.sum(cc * cc)))
            slope = float(np.sum((cv - cv.mean()) * rv) / np.sum((cv - cv.mean()) ** 2))
            checks.append(CheckRow(f"pixel: {klass} residual slope vs {cname}", slope, 0.0, slope_z))
        out[cname] = entry
    return out


def _variance_gof(ev: Evidence, fitted: FittedModel, checks: list[CheckRow]) -> tuple[float | None, float | None]:
    if not len(ev.vbin_obs):
        return None, None
    e = np.log(ev.vbin_obs) - np.log(fitted.variance_pred)
    w = ev.vbin_df / 2.0
    q = 0 if fitted.variance_jac is None else fitted.variance_jac.shape[0]
    chi = float(np.sum(w * e * e))
    df = max(len(e) - q, 1)
    checks.append(CheckRow("variance: mean ln(observed/predicted)", float(np.average(e, weights=w)), 0.0,
                           float(np.sum(w * e) / math.sqrt(np.sum(w)))))
    lv = ev.vbin_level
    if np.ptp(lv) > 0:
        c = (lv - np.average(lv, weights=w))
        slope_z = float(np.sum(w * c * e) / math.sqrt(np.sum(w * c * c)))
        checks.append(CheckRow("variance: slope of ln(observed/predicted) vs level (per 1000 DN)",
                               float(np.sum(w * c * e) / np.sum(w * c * c) * 1000), 0.0, slope_z))
    checks.append(CheckRow("variance: χ²/df of ln variance", chi / df, 1.0, (chi - df) / math.sqrt(2 * df)))
    return float(np.sqrt(np.mean(e * e))), float(stats.chi2.sf(chi, df))


def _growth_gof(ev: Evidence, fitted: FittedModel, checks: list[CheckRow]) -> tuple[float | None, float | None]:
    if len(ev.times) < 3 or not fitted.arrival_effects():
        return None, None
    obs, exp = ev.increments(fitted.expected)
    used = (exp > 1e-9) | (obs > 0)
    n_free = len(fitted.arrival_free)
    df = max(int(used.sum()) - n_free, 1)
    dev = poisson_deviance(obs[used], exp[used])
    sims = fitted.sims.get("deviance")
    scale = float(np.mean(sims)) / df if sims is not None and len(sims) else 1.0
    scale = max(scale, 1e-6)
    p = float(stats.chi2.sf(dev / scale, df))
    pearson = float(np.sum((obs[used] - exp[used]) ** 2 / np.maximum(exp[used], 1e-9)))
    pred_disp = float(np.mean(fitted.sims["pearson"])) / df if sims is not None else 1.0
    checks.append(CheckRow("growth: Poisson deviance / df", dev / df, scale, (dev / scale - df) / math.sqrt(2 * df)))
    checks.append(CheckRow("growth: dispersion index (Pearson χ²/df)", pearson / df, pred_disp,
                           (pearson / pred_disp - df) / math.sqrt(2 * df) if pred_disp > 0 else None))
    # grouped Laplace trend test on partially stuck arrivals
    t = ev.times
    d = np.diff(ev.counts[PARTIAL]).astype(float)
    n = d.sum()
    if n > 0 and t[-1] > t[0]:
        mid = (t[1:] + t[:-1]) / 2
        pw = np.diff(t) / (t[-1] - t[0])
        mbar = float(np.sum(pw * mid))
        vm = float(np.sum(pw * (mid - mbar) ** 2) + np.sum(pw * np.diff(t) ** 2) / 12)
        u = float((np.sum(d * mid) - n * mbar) / math.sqrt(n * vm))
        checks.append(CheckRow("growth: Laplace trend z (partially stuck arrivals)", u, 0.0, u))
    return dev / df, p


def _spatial_gof(ev: Evidence, fitted: FittedModel, checks: list[CheckRow]) -> tuple[float | None, dict[str, Any]]:
    info: dict[str, Any] = {}
    if len(ev.sites) < 10:
        return None, info
    l_obs = ev.ripley_l(ev.sites)
    ce = sp.clark_evans(ev.sites[:, 1], ev.sites[:, 0], ev.window)
    info.update({"radii": sp.DEFAULT_RADII, "observed": l_obs})
    null = fitted.spatial_null
    if null is None:
        checks.append(CheckRow("spatial: Clark–Evans ratio (Donnelly)", ce.ratio, 1.0, ce.z))
        return None, info
    m0, s0, sims = null["mean"], null["sd"], null["sims"]
    dev_obs = float(np.max(np.abs(l_obs - m0) / s0))
    dev_sim = np.max(np.abs(sims - m0) / s0, axis=1)
    p = float((1 + np.sum(dev_sim >= dev_obs)) / (1 + len(dev_sim)))
    info.update({"mean": m0, "lo": np.quantile(sims, 0.025, axis=0), "hi": np.quantile(sims, 0.975, axis=0),
                 "min": sims.min(0), "max": sims.max(0)})
    checks.append(CheckRow("spatial: Clark–Evans ratio (Donnelly)", ce.ratio, 1.0, ce.z))
    j = int(np.argmax(np.abs(l_obs - m0) / s0))
    checks.append(CheckRow(f"spatial: Ripley L at r = {sp.DEFAULT_RADII[j]:g} px (largest deviation)",
                           float(l_obs[j]), float(m0[j]), float((l_obs[j] - m0[j]) / s0[j])))
    return p, info


# =========================================================================== diagnosis
def _random_effect_lr(zb: np.ndarray, ab: np.ndarray) -> tuple[float, float]:
    """Likelihood ratio for a per-block random effect: z_b ~ N(0, 1 + t·a_b), t ≥ 0. Returns (LR, t̂)."""
    keep = ab > 1e-12
    zb, ab = zb[keep], ab[keep]
    if zb.size == 0:
        return 0.0, 0.0
    score = 0.5 * float(np.sum(ab * (zb**2 - 1)))
    if score <= 0:
        return 0.0, 0.0

    def negll(u: float) -> float:
        t = math.exp(u)
        s = 1 + t * ab
        return float(np.sum(0.5 * np.log(s) - 0.5 * zb**2 * t * ab / s))

    lo = math.log(1e-8 / ab.max())
    hi = math.log(1e8 / ab.min())
    res = optimize.minimize_scalar(negll, bounds=(lo, hi), method="bounded", options={"xatol": 1e-6})
    return max(0.0, -2.0 * res.fun), math.exp(res.x)


def _test_pixel(ev: Evidence, fitted: FittedModel, sigs: list[Signature], z: np.ndarray, n_obs: int) -> list[ChannelTest]:
    tests = []
    sw = np.sqrt(ev.weight)
    keep = ev.usable & (ev.classes != STK)
    glob_cols = []
    glob_names = []
    for s in sigs:
        raw = np.where(keep, s.x * sw, 0.0)
        raw_norm = float(np.sum(raw**2))
        if raw_norm <= 0 or float(np.max(np.abs(raw))) < 1e-4:  # no signature (up to rounding) in these data
            continue
        xp = fitted.projector.project(raw) if s.pixel_local or s.blocks is None else raw
        xp = np.where(keep, xp, 0.0)
        if s.blocks is not None:
            blk = np.broadcast_to(s.blocks[None], xp.shape)
            m = (blk >= 0) & keep
            nblk = int(s.blocks.max()) + 1
            zb_num = np.bincount(blk[m], (xp * z)[m], minlength=nblk)
            ab = np.bincount(blk[m], (xp * xp)[m], minlength=nblk)
            used = ab > 1e-12 * max(ab.max(), 1e-300)
            zb = np.where(used, zb_num / np.sqrt(np.where(used, ab, 1)), 0.0)
            lr, t = _random_effect_lr(zb[used], ab[used])
            frac = float(np.sum(ab)) / raw_norm
            tests.append(ChannelTest("pixel", lr, 1, n_obs,
                                     f"{s.name}: random-effect LR {lr:.4g} over {int(used.sum())} blocks "
                                     f"(typical size {math.sqrt(t):.3g}; {frac:.0%} of the signature survives the "
                                     "model's own parameters)", boundary=True, absorbed=frac < 0.05))
        else:
            frac = float(np.sum(xp**2)) / raw_norm
            if frac < 1e-6:
                tests.append(ChannelTest("pixel", 0.0, 0, n_obs, f"{s.name}: absorbed by the model's parameters",
                                         absorbed=True))
                continue
            glob_cols.append(xp)
            glob_names.append((s.name, frac))
    if glob_cols:
        H = np.array([[np.sum(a * b) for b in glob_cols] for a in glob_cols])
        g = np.array([np.sum(a * z) for a in glob_cols])
        lm = float(g @ np.linalg.pinv(H) @ g)
        names = ", ".join(n for n, _ in glob_names)
        frac = min(f for _, f in glob_names)
        tests.append(ChannelTest("pixel", lm, len(glob_cols), n_obs,
                                 f"{names}: score LM {lm:.4g} on {n_obs} pixel means ({frac:.0%} of the signature "
                                 "survives the model's own parameters)", absorbed=frac < 0.05))
    return tests


def _test_variance(ev: Evidence, fitted: FittedModel, sigs: list[Signature]) -> list[ChannelTest]:
    if not sigs or not len(ev.vbin_obs):
        return []
    e = np.log(ev.vbin_obs) - np.log(fitted.variance_pred)
    w = ev.vbin_df / 2.0
    X = np.array([s.x for s in sigs])
    if fitted.variance_jac is not None:
        J = fitted.variance_jac
        coef = np.linalg.lstsq((J * w) @ J.T, (J * w) @ X.T, rcond=None)[0]
        X = X - coef.T @ J
    H = (X * w) @ X.T
    g = (X * w) @ e
    lm = float(g @ np.linalg.pinv(H) @ g)
    return [ChannelTest("variance", lm, len(sigs), len(e),
                        f"{', '.join(s.name for s in sigs)}: score LM {lm:.4g} on {len(e)} binned variances")]


def _test_growth(ev: Evidence, fitted: FittedModel, sigs: list[Signature]) -> list[ChannelTest]:
    out = []
    if len(ev.times) < 3:
        return out
    obs, mu = ev.increments(fitted.expected)
    mu = np.maximum(mu, 1e-9)
    M = fitted.growth_jac
    for s in sigs:
        x = s.x.copy()
        if M is not None and len(M):
            coef = np.linalg.lstsq((M / mu) @ M.T, (M / mu) @ x, rcond=None)[0]
            x = x - coef @ M
        info = float(np.sum(x * x / mu))
        raw = float(np.sum(s.x * s.x / mu))
        if raw <= 0 or info <= 1e-9 * raw:
            continue
        u = float(np.sum(x * (obs - mu) / mu))
        mu_alt = np.maximum(mu + x * (u / info), 1e-9)  # one Fisher-scoring step towards the alternative
        pearson_alt = float(np.sum((obs - mu_alt) ** 2 / mu_alt))
        df_alt = max(len(obs) - (0 if M is None else M.shape[0]) - 1, 1)
        # quasi-Poisson dispersion, applied only when the counts are clearly over-dispersed (pre-test at 1 %)
        phi = pearson_alt / df_alt if pearson_alt > stats.chi2.ppf(0.99, df_alt) else 1.0
        lm = u * u / info / phi
        out.append(ChannelTest("growth", lm, 1, int(max(obs.sum(), 1)),
                               f"{s.name}: Poisson score z {u / math.sqrt(info * phi):+.3g} on {len(obs)} count "
                               f"increments (dispersion {phi:.2g})"))
    return out


def _test_spatial(ev: Evidence, fitted: FittedModel, sigs: list[Signature]) -> list[ChannelTest]:
    out = []
    null = fitted.spatial_null
    if null is None:
        return out
    l_obs = ev.ripley_l(ev.sites)
    u_obs = (l_obs - null["mean"]) / null["sd"]
    u_sim = (null["sims"] - null["mean"]) / null["sd"]
    for s in sigs:
        d = s.x / max(float(np.linalg.norm(s.x)), 1e-12)
        t_obs = float(d @ u_obs)
        t_sim = u_sim @ d
        zval = (t_obs - float(t_sim.mean())) / max(float(t_sim.std(ddof=1)), 1e-9)
        lm = zval * zval if zval > 0 else 0.0
        out.append(ChannelTest("spatial", lm, 1, len(ev.sites),
                               f"{s.name}: Ripley L moves the way this effect predicts, z {zval:+.3g} against "
                               f"{len(t_sim)} simulations of the fitted model"))
    return out


def diagnose(ev: Evidence, fitted: FittedModel, candidates: list[str]) -> tuple[list[Candidate], list[str]]:
    """Rank the candidates by predicted ΔBIC and flag the strongly supported ones."""
    meas = ev.meas
    sw = np.sqrt(ev.weight)
    keep = ev.usable & (ev.classes != STK)
    z = np.where(keep, fitted.projector.project((meas.mean_a - fitted.mu_a) * sw), 0.0)
    n_obs = int(keep.sum())
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
            sigs = effect.signature(ev)
        except InputError as exc:
            notes.append(f"{name} not tested: {exc}")
            continue
        tests = []
        tests += _test_pixel(ev, fitted, [s for s in sigs if s.channel == "pixel"], z, n_obs)
        tests += _test_variance(ev, fitted, [s for s in sigs if s.channel == "variance"])
        tests += _test_growth(ev, fitted, [s for s in sigs if s.channel == "growth"])
        tests += _test_spatial(ev, fitted, [s for s in sigs if s.channel == "spatial"])
        lm = float(sum(t.lm for t in tests))
        df = int(sum(t.df for t in tests))
        q = effect.n_params()
        if tests and df > 0:
            main = max(tests, key=lambda t: t.lm)
            dbic = lm - q * math.log(max(main.n, 2))
            p_raw = float(stats.chi2.sf(lm, df))
            if len(tests) == 1 and tests[0].boundary:
                p_raw *= 0.5
        else:
            main = None
            dbic, p_raw = -q * math.log(max(n_obs, 2)), 1.0
        absorbed = bool(tests) and all(t.absorbed and t.channel == "pixel" for t in tests)
        evidence = "; ".join(t.detail for t in sorted(tests, key=lambda t: -t.lm)) or "no signature in these data"
        where = _where(ev, sigs)
        if where:
            evidence = f"{where}; {evidence}"
        results.append(Candidate(name, float(dbic), p_raw, False, lm, df, p_raw, q, tests, evidence, absorbed))
    # Holm adjustment
    order = sorted(range(len(results)), key=lambda i: results[i].p_raw)
    m = len(results)
    running = 0.0
    for rank, i in enumerate(order):
        adj = min(1.0, (m - rank) * results[i].p_raw)
        running = max(running, adj)
        results[i].p = running
        results[i].flagged = results[i].delta_bic > FLAG_DBIC and results[i].p < FLAG_P
    results.sort(key=lambda c: -c.delta_bic)
    return results, notes


def _where(ev: Evidence, sigs: list[Signature]) -> str:
    """Which pixel classes a pixel signature acts on."""
    mass = np.zeros(3)
    for s in sigs:
        if s.channel != "pixel":
            continue
        x2 = np.where(ev.usable, s.x**2 * ev.weight, 0.0)
        for k in range(3):
            mass[k] += float(np.sum(x2[ev.classes == k]))
    if mass.sum() <= 0:
        return ""
    share = mass / mass.sum()
    names = [f"{CLASSES[k]} {share[k]:.0%}" for k in range(3) if share[k] >= 0.01]
    return "acts on " + ", ".join(names) + " pixels"


# =========================================================================== warnings
def _design_warnings(ev: Evidence, candidates: list[Candidate], effects: list[Effect]) -> list[str]:
    meas = ev.meas
    out = []
    levels = _light_levels(ev)
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
    reps = [g.n for g in meas.groups]
    if min(reps) < 2:
        out.append(f"{sum(1 for r in reps if r < 2)} condition(s) have a single frame: they serve defect detection only; "
                   "take 2 frames per condition for the noise floor")
    if meas.has_time and len(ev.times) < 5:
        out.append(f"only {len(ev.times)} epochs: defect arrival and placement need at least 5 epochs of a few frames each")
    # near-ties between flagged candidates
    flagged = [c for c in candidates if c.flagged]
    for i, a in enumerate(flagged):
        for b in flagged[i + 1:]:
            if abs(a.delta_bic - b.delta_bic) < FLAG_DBIC and {t.channel for t in a.tests} & {t.channel for t in b.tests}:
                out.append(f"the data cannot separate {a.effect} from {b.effect} (predicted ΔBIC "
                           f"{a.delta_bic:.3g} vs {b.delta_bic:.3g}): {_frames_to_add(ev, a.effect, b.effect)}")
    for c in candidates:
        if not c.tests:
            stage = EFFECTS[c.effect].stage.name.lower() if c.effect in EFFECTS else "?"
            out.append(f"{c.effect} cannot be tested with these data: its signature is zero here (it acts at the "
                       f"{stage} stage; e.g. on defective pixels, which these data may lack)")
        if c.absorbed:
            model_names = ", ".join(e.key for e in effects if _is_pixel(e))
            out.append(f"{c.effect} cannot be detected with these data: its signature is absorbed by the fitted "
                       f"parameters of {model_names}; {_frames_to_add(ev, c.effect, None)}")
    return out


def _fmt_values(values: list[Any]) -> str:
    return ", ".join(f"{v:g}" for v in values) if values else "none"


def _light_levels(ev: Evidence) -> int:
    """Number of distinct light levels over the repeated conditions (medians more than 10 noise σ apart)."""
    meds = np.sort([float(np.median(ev.scene_a[r][ev.meas.interior])) for r in range(len(ev.rep))])
    noise = math.sqrt(max(float(np.median(ev.floor)), QUANT_VAR))
    if meds.size == 0:
        return 0
    return int(1 + np.sum(np.diff(meds) > 10 * noise))


def _frames_to_add(ev: Evidence, a: str, b: str | None) -> str:
    fa = set(EFFECTS[a].fields) if a in EFFECTS else set()
    fb = set(EFFECTS[b].fields) if b in EFFECTS else set()
    fields = sorted((fa ^ fb) if b else fa) or sorted(fa | fb)
    fields = [f for f in fields if f != "captured"]
    parts = []
    for f in fields:
        vals = ev.meas.field_values(f)
        parts.append(f"frames at another {f} (the data have {_fmt_values(vals)}), other conditions unchanged")
    if not parts:
        parts.append(f"flat fields at more light levels (the data have {_light_levels(ev)})")
    return "add " + "; ".join(parts)


# =========================================================================== entry point
def base_model() -> list[Effect]:
    """The base model: every registered effect whose role is ``base``, at its defaults."""
    return [cls() for cls in EFFECTS.values() if cls.role == "base"]


def candidate_names(model_effects: list[Effect]) -> list[str]:
    have = {e.key for e in model_effects}
    return [n for n, c in EFFECTS.items() if c.role == "candidate" and n not in have]


def run_check(ev: Evidence, effects: list[Effect]) -> CheckResult:
    """Fit ``effects`` to prepared evidence, score, and diagnose."""
    fitted = fit_model(ev, effects)
    checks: list[CheckRow] = []
    classes = _class_errors(ev, fitted)
    vals = [v for v in classes.values() if v is not None]
    gof_pixel, consistency = _pixel_gof(ev, fitted, checks)
    covariates = _covariate_checks(ev, fitted, checks)
    err_var, gof_var = _variance_gof(ev, fitted, checks)
    err_growth, gof_growth = _growth_gof(ev, fitted, checks)
    gof_spatial, ripley = _spatial_gof(ev, fitted, checks)
    for name, value in classes.items():
        if value is not None:
            n = int(np.sum(ev.usable & (ev.classes == CLASSES.index(name))))
            checks.insert(0, CheckRow(f"pixel: held-out error² ({name}, {n} pixel means)", value**2, 1.0,
                                      (value**2 - 1) / math.sqrt(2 / max(n, 1))))
    candidates, notes = diagnose(ev, fitted, candidate_names(fitted.effects))
    warn = list(ev.meas.notes) + notes + _design_warnings(ev, candidates, fitted.effects)
    meas = ev.meas
    r = meas.mean_b - fitted.mu_b
    nb = meas.n_b[:, None, None].astype(float)
    zb = r / np.sqrt(ev.floor * (1.0 + np.where(ev.classes == STK, 0.0, KERNEL_VAR)) / nb)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        residual_map = np.nanmean(np.where(ev.usable, r, np.nan), axis=0)
        rms_map = np.sqrt(np.nanmean(np.where(ev.usable, zb * zb, np.nan), axis=0))
    counts_plot = {"times": ev.times, "observed": {k: ev.counts[k] for k in (PARTIAL, STUCK)},
                   "expected": {k: fitted.expected[k] + ev.counts[k][0] for k in (PARTIAL, STUCK)}}
    if fitted.sims:
        counts_plot["band"] = {k: (np.quantile(v, 0.025, axis=0), np.quantile(v, 0.975, axis=0))
                               for k, v in fitted.sims["counts"].items()}
    variance_plot = {"level": ev.vbin_level, "observed": ev.vbin_obs, "predicted": fitted.variance_pred,
                     "df": ev.vbin_df}
    plots = PlotData(residual_map, rms_map, consistency, ev.classes[-1], covariates, counts_plot, ripley,
                     variance_plot)
    data = {"folder": str(meas.root), "frames": meas.n_frames, "conditions": len(meas.groups),
            "repeated_conditions": len(ev.rep), "epochs": [float(t) for t in ev.times],
            "size": [meas.shape[1], meas.shape[0]], "full_scale": meas.full_scale, "border": meas.border,
            "light_levels": _light_levels(ev),
            "defects": {"partial": int(ev.counts[PARTIAL][-1]), "stuck": int(ev.counts[STUCK][-1]),
                        "threshold_dn": float(ev.threshold[PARTIAL])},
            "classes": {name: int(np.sum(ev.classes[-1][meas.interior] == k)) for k, name in enumerate(CLASSES)}}
    return CheckResult(
        effects=[e.key for e in fitted.effects],
        params=fitted.params,
        patterns=fitted.patterns,
        error={"pixel": max(vals) if vals else None, "classes": classes, "variance": err_var, "growth": err_growth},
        gof={"pixel": gof_pixel, "variance": gof_var, "growth": gof_growth, "spatial": gof_spatial},
        checks=checks,
        candidates=candidates,
        warnings=warn,
        data=data,
        plots=plots,
    )


def resolve_effects(add: Sequence[str | Effect]) -> list[Effect]:
    """Effects from names, ``module:Class``, ``file.py:Class`` or instances."""
    out = []
    for spec in add:
        out.append(spec if isinstance(spec, Effect) else make_effect(spec))
    return out


def check(data: Dataset | str | Path | Measurements, add: Sequence[str | Effect] = (), seed: int = 0,
          baseline: bool = True, n_sim: int = 199, progress: Progress = no_progress) -> CheckResult:
    """Fit the base model plus ``add`` to a dataset, score it and diagnose what is missing.

    Parameters
    ----------
    data
        Dataset (or its folder, or prepared :class:`Measurements`).
    add
        Effects to add to the base model: registry names, ``module:Class``, ``file.py:Class`` or instances.
    seed
        Seed of the Monte-Carlo simulations (arrival counts, placement).
    baseline
        With ``add``, also check the base model alone and keep it as :attr:`CheckResult.baseline`
        (for before/after comparisons).
    n_sim
        Monte-Carlo simulations of the fitted arrival model.

    Returns
    -------
    CheckResult
    """
    extra = resolve_effects(add)
    base = base_model()
    names = [e.key for e in base]
    for e in extra:
        if e.key in names:
            raise UsageError(f"the effect '{e.key}' is already in the model")
        names.append(e.key)
    meas = data if isinstance(data, Measurements) else load_measurements(data, progress=progress)
    ev = Evidence(meas, seed=seed, n_sim=n_sim)
    result = run_check(ev, [*base, *extra])
    if extra and baseline:
        result.baseline = run_check(ev, base_model())
    return result


# =========================================================================== report
def _symlog(v: float) -> float:
    return math.copysign(math.log10(1 + abs(v)), v)


def check_report(result: CheckResult, title: str = "Model check") -> "Report":
    """An HTML report of a check: tables, residual maps, residuals against every covariate, defect counts
    against time with the model's band, Ripley's L with its envelope; with a baseline, before and after side by
    side."""
    from forensics.report.html import Report, new_figure

    rep = Report(title)
    runs = [("before", result.baseline), ("after", result)] if result.baseline is not None else [("model", result)]
    data = result.data
    rep.text(f"{data['frames']} frames of {data['size'][0]}×{data['size'][1]} pixels (full scale "
             f"{data['full_scale']:g} DN), {data['conditions']} conditions ({data['repeated_conditions']} with repeated "
             f"frames), {len(data['epochs'])} epochs, {data['light_levels']} light levels; "
             f"{data['classes']['partial']} partially stuck and {data['classes']['stuck']} stuck pixels at the last epoch.")
    rep.text("Model: " + " + ".join(result.effects)
             + (f" (before: {' + '.join(result.baseline.effects)})" if result.baseline is not None else ""))
    for w in result.warnings:
        rep.text("Warning: " + w, note=True)
    # ---------------------------------------------------------------- numbers
    rep.heading("Error and goodness of fit")
    header = ["", *[name for name, _ in runs]]
    rows = []
    for key, label in (("pixel", "error.pixel (held-out; 1 = noise floor)"),
                       ("variance", "error.variance (RMS ln obs/pred)"),
                       ("growth", "error.growth (deviance/df)")):
        rows.append([label, *[_num(r.error[key]) for _, r in runs]])
    for cls in CLASSES:
        rows.append([f"  class {cls}", *[_num(r.error["classes"][cls]) for _, r in runs]])
    for key in CHANNELS:
        rows.append([f"gof.{key} (p)", *[_num(r.gof[key]) for _, r in runs]])
    rep.table(header, rows)
    rep.heading("Fitted parameters")
    rep.table(["effect", "parameter", "value", "standard error", "unit"],
              [[p.effect, p.name, p.value, "—" if p.se is None else p.se, p.unit] for p in result.params]
              + [[p.effect, f"{p.name} (pattern, {p.blocks} blocks)", p.rms, "rms", p.hyper or ""]
                 for p in result.patterns])
    rep.heading("Candidates")
    for name, r in runs:
        rep.table(["rank", "effect", "predicted ΔBIC", "p (Holm)", "flagged", "evidence"],
                  [[i + 1, c.effect, c.delta_bic, c.p, "yes" if c.flagged else "", c.evidence]
                   for i, c in enumerate(r.candidates)], caption=name)
    if result.candidates or (result.baseline and result.baseline.candidates):
        fig, axes = new_figure(5.0 * len(runs), 3.2, ncols=len(runs))
        axes = np.atleast_1d(axes)
        for ax, (name, r) in zip(axes, runs):
            cands = r.candidates
            vals = [_symlog(c.delta_bic) for c in cands]
            colours = ["C3" if c.flagged else "C7" for c in cands]
            ax.barh(range(len(cands)), vals, color=colours)
            ax.set_yticks(range(len(cands)), [c.effect for c in cands], fontsize=8)
            ax.invert_yaxis()
            ax.axvline(_symlog(FLAG_DBIC), color="k", lw=0.8, ls=":")
            ax.set_xlabel("predicted ΔBIC (sign · log10(1 + |ΔBIC|))")
            ax.set_title(name)
        rep.figure(fig, "candidates", "Candidates ranked by predicted ΔBIC; red: flagged (ΔBIC > 10 and Holm "
                   "p < 0.01); dotted: ΔBIC = 10.")
    # ---------------------------------------------------------------- residual maps
    rep.heading("Where the model fails: pixels")
    fig, axes = new_figure(4.2 * len(runs), 10.5, ncols=len(runs), nrows=3)
    axes = np.asarray(axes).reshape(3, len(runs))
    lim_r = max(float(np.nanpercentile(np.abs(r.plots.residual_map), 99.5)) for _, r in runs) or 1.0
    for j, (name, r) in enumerate(runs):
        im = axes[0, j].imshow(r.plots.rms_map, cmap="magma", vmin=0, vmax=3, interpolation="nearest")
        axes[0, j].set_title(f"{name}: held-out RMS residual / noise floor", fontsize=9)
        fig.colorbar(im, ax=axes[0, j], shrink=0.8)
        im = axes[1, j].imshow(r.plots.residual_map, cmap="RdBu_r", vmin=-lim_r, vmax=lim_r, interpolation="nearest")
        axes[1, j].set_title(f"{name}: mean held-out residual (DN)", fontsize=9)
        fig.colorbar(im, ax=axes[1, j], shrink=0.8)
        im = axes[2, j].imshow(r.plots.consistency_map, cmap="RdBu_r", vmin=-5, vmax=5, interpolation="nearest")
        axes[2, j].set_title(f"{name}: per-pixel consistency z", fontsize=9)
        fig.colorbar(im, ax=axes[2, j], shrink=0.8)
        for ax in axes[:, j]:
            ax.set_xticks([])
            ax.set_yticks([])
    rep.figure(fig, "residual_maps", "Top: each pixel's held-out residual relative to its noise floor (RMS over "
               "conditions; 1 = at the floor): misfitting pixels light up. Middle: the held-out residual averaged "
               "over conditions. Bottom: the in-sample residual's component that is the same in every condition, "
               "standardised (a fixed pattern the model lacks shows as structure: stripes, speckle, rings).")
    # ---------------------------------------------------------------- covariates
    covs = list(result.plots.covariates)
    fig, axes = new_figure(3.0 * len(covs), 3.2, ncols=len(covs))
    axes = np.atleast_1d(axes)
    styles = {"before": dict(ls="--", alpha=0.6), "after": dict(ls="-"), "model": dict(ls="-")}
    for ax, cname in zip(axes, covs):
        for name, r in runs:
            entry = r.plots.covariates.get(cname, {})
            for k, klass in enumerate(("normal", "partial")):
                if klass not in entry:
                    continue
                e = entry[klass]
                ax.errorbar(e["x"], e["mean"], yerr=1.96 * e["se"], color=f"C{k}", marker="o", ms=3, capsize=2,
                            label=f"{klass} ({name})", **styles[name])
        ax.axhline(0, color="k", lw=0.6)
        ax.set_xlabel(cname, fontsize=8)
        ax.set_ylabel("held-out residual (DN)", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0].legend(fontsize=6)
    rep.figure(fig, "covariates", "Held-out residuals against every covariate (mean ± 95 % per bin), per pixel "
               "class: a missing effect shows as a trend with the covariates it depends on.")
    # ---------------------------------------------------------------- variance
    fig, axes = new_figure(4.2 * len(runs), 3.2, ncols=len(runs))
    axes = np.atleast_1d(axes)
    for ax, (name, r) in zip(axes, runs):
        v = r.plots.variance
        if len(v["level"]):
            ratio = np.log(v["observed"] / v["predicted"])
            ax.errorbar(v["level"], ratio, yerr=1.96 * np.sqrt(2 / v["df"]), fmt="o", ms=3, capsize=2)
        ax.axhline(0, color="k", lw=0.6)
        ax.set_xlabel("mean signal (DN)")
        ax.set_ylabel("ln(observed / predicted variance)")
        ax.set_title(name, fontsize=9)
    rep.figure(fig, "variance", "Temporal variance from repeated frames against the model's prediction, per "
               "condition and signal level.")
    # ---------------------------------------------------------------- counts
    rep.heading("Where the model fails: defects")
    fig, axes = new_figure(4.2 * len(runs), 3.4, ncols=len(runs))
    axes = np.atleast_1d(axes)
    for ax, (name, r) in zip(axes, runs):
        c = r.plots.counts
        t = np.asarray(c["times"])
        for kind, colour, label in ((PARTIAL, "C0", "partially stuck"), (STUCK, "C3", "stuck")):
            if "band" in c:
                lo, hi = c["band"][kind]
                ax.fill_between(t, lo, hi, color=colour, alpha=0.2)
            ax.plot(t, c["expected"][kind], color=colour, lw=1)
            ax.plot(t, c["observed"][kind], "o", color=colour, ms=4, label=label)
        ax.set_xlabel("capture time (year)")
        ax.set_ylabel("defects detected (cumulative)")
        ax.set_title(name, fontsize=9)
        ax.legend(fontsize=7)
    rep.figure(fig, "counts", "Defects detected by each epoch (points) against the fitted arrival model (line) "
               "and its 95 % Monte-Carlo band.")
    if result.plots.ripley.get("radii") is not None:
        fig, axes = new_figure(4.2 * len(runs), 3.4, ncols=len(runs))
        axes = np.atleast_1d(axes)
        for ax, (name, r) in zip(axes, runs):
            rp = r.plots.ripley
            if rp.get("radii") is None:
                continue
            rr = np.asarray(rp["radii"])
            if "lo" in rp:
                ax.fill_between(rr, rp["lo"] - rr, rp["hi"] - rr, color="C7", alpha=0.3, label="95 % envelope")
                ax.plot(rr, rp["mean"] - rr, color="C7", lw=1, label="fitted model (mean)")
            ax.plot(rr, rp["observed"] - rr, "o-", color="C0", ms=3, label="observed")
            ax.axhline(0, color="k", lw=0.6)
            ax.set_xlabel("r (pixels)")
            ax.set_ylabel("L(r) − r")
            ax.set_title(name, fontsize=9)
            ax.legend(fontsize=7)
        rep.figure(fig, "ripley", "Ripley's L of the defect sites at the last epoch (translation edge correction) "
                   "against simulations of the fitted arrival model: above the envelope means clustering.")
    # ---------------------------------------------------------------- checks
    rep.heading("Checks")
    for name, r in runs:
        rep.table(["statistic", "measured", "predicted", "z"],
                  [[c.statistic, c.measured, c.predicted, "—" if c.z is None else c.z] for c in r.checks],
                  caption=name)
    return rep


def _num(v: Any) -> Any:
    return "—" if v is None else v
