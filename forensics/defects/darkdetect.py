"""Hot pixels from a dark-frame series: dark rate above a threshold stated in ADU/s at a reference temperature.

A hot pixel is the tail of the per-pixel dark rate (:mod:`forensics.defects.darkseries`), not a separate
fiction: every pixel's fitted rate is carried to the reference temperature ``t_ref`` with the temperature law
of pixels like it (:mod:`forensics.defects.darklaw`) — fitted on the series itself when it spans two
temperatures, else given — and the pixels above the threshold are hot.  Series taken at different temperatures
or exposure times, or years apart, are then compared at one threshold in one unit.

The result is a :class:`~forensics.defects.detection.DetectionResult` (hot pixels are the paper's partially
stuck kind: y = i + d with d = rate × exposure; pixels that read one value in every frame are stuck), so defect
growth (γ, Chapman, Garwood rates) and dating (:mod:`forensics.defects.growth`, :mod:`forensics.defects.dating`)
use it unchanged: its d̂ map holds the normalised rates, and its z is (rate − median)/(1.4826·MAD) of them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import stats

from forensics._shared.errors import InputError, UsageError
from forensics._shared.progress import Progress, no_progress
from forensics.defects.darklaw import TemperatureLaw, can_fit, fit_temperature_law
from forensics.defects.darkseries import (
    DARK_TYPES,
    LIGHT_TYPES,
    K_GROW,
    K_OUTLIER,
    ROUNDS,
    DarkSeriesFit,
    SeriesFrame,
    fit_dark_series,
    plan_series,
)
from forensics.defects.detection import (
    ChannelFit,
    DetectionResult,
    MaskSpec,
    _constant_neighbours,
    accumulated_histogram,
    centre_mask,
    load_mask,
    robust_normal,
)
from forensics.io.dataset import binning, is_dark_subject
from forensics.sensor.catalogue import PARTIAL, STUCK
from forensics.stats.counts import LEVEL, garwood

if TYPE_CHECKING:
    from forensics._shared.parallel import Executor
    from forensics.defects.growth import GrowthModel

METHOD = "dark_series"
#: Without a threshold, hot pixels are this many robust σ above the median normalised rate (a warning says so).
DEFAULT_SIGMA = 5.0
#: A threshold closer to the median than this many typical per-pixel standard errors counts noise, not hot pixels.
NOISE_MARGIN = 5.0
#: Points of the accumulated histograms (log-spaced rates).
HIST_POINTS = 200


@dataclass(frozen=True)
class DarkSettings:
    """How hot pixels are called in a dark series (kept in a growth model so that dating repeats them).

    ``threshold`` in ADU/s at ``t_ref`` (°C); ``law`` carries rates between temperatures (None: fitted on the
    series when it spans two temperatures); ``gain`` the noise model's e⁻/ADU (None: flats, else EGAIN).
    """

    threshold: float | None = None
    t_ref: float | None = None
    law: TemperatureLaw | None = None
    gain: float | None = None
    sigma: float = DEFAULT_SIGMA
    mask: MaskSpec = field(default_factory=lambda: MaskSpec("all"))
    k: float = K_OUTLIER
    k_grow: float = K_GROW
    rounds: int = ROUNDS
    saturation: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"method": METHOD, "threshold_adu_per_s": self.threshold, "t_ref_c": self.t_ref,
                "law": self.law.to_dict() if self.law else None, "gain": self.gain, "sigma": self.sigma,
                "mask": self.mask.to_dict(), "k_outlier": self.k, "k_grow": self.k_grow, "rounds": self.rounds,
                "saturation": self.saturation}

    @classmethod
    def from_dict(cls, obj: dict[str, Any]) -> "DarkSettings":
        law = obj.get("law")
        return cls(obj.get("threshold_adu_per_s"), obj.get("t_ref_c"),
                   TemperatureLaw.from_dict(law) if law else None, obj.get("gain"), float(obj.get("sigma", DEFAULT_SIGMA)),
                   MaskSpec.from_dict(obj.get("mask", {"kind": "all"})), float(obj.get("k_outlier", K_OUTLIER)),
                   float(obj.get("k_grow", K_GROW)), int(obj.get("rounds", ROUNDS)), obj.get("saturation"))


@dataclass
class DarkDetectionResult(DetectionResult):
    """A :class:`DetectionResult` whose d̂ is the dark rate (ADU/s at ``t_ref``), with the series' fit and law."""

    t_ref: float | None = None
    threshold_rate: float = float("nan")
    law: TemperatureLaw | None = None
    law_source: str = ""
    series: DarkSeriesFit | None = field(default=None, repr=False)
    settings: DarkSettings | None = None
    count_ci: tuple[float, float] = (float("nan"), float("nan"))
    count_law_range: tuple[int, int] | None = None
    typical_rate_se: float = float("nan")
    group_hist: list[dict[str, Any]] = field(default_factory=list)
    at_set_points: list[dict[str, Any]] = field(default_factory=list)
    rate_se: np.ndarray | None = field(default=None, repr=False)
    group_rates: list[np.ndarray] = field(default_factory=list, repr=False)

    def threshold_dict(self) -> dict[str, Any]:
        return {"method": METHOD, "threshold_adu_per_s": self.threshold_rate, "t_ref_c": self.t_ref,
                "sigma": self.sigma, "tau": self.threshold_rate, "units": "ADU/s", "mask": self.mask_spec.describe(),
                "analysed_megapixels": self.megapixels, "law": self.law_source, "q": self.q,
                "stuck_tolerance": self.stuck_tolerance}

    def detection_settings(self) -> dict[str, Any]:
        base = self.settings or DarkSettings()
        return replace(base, threshold=self.threshold_rate, t_ref=self.t_ref, law=self.law).to_dict()

    def to_dict(self) -> dict[str, Any]:
        out = super().to_dict()
        out.update({"units": "ADU/s at t_ref", "t_ref_c": self.t_ref, "threshold_adu_per_s": self.threshold_rate,
                    "hot_pixels": self.count(PARTIAL), "hot_pixels_ci": list(self.count_ci),
                    "hot_pixels_over_law_interval": list(self.count_law_range) if self.count_law_range else None,
                    "typical_rate_se": self.typical_rate_se,
                    "law": self.law.to_dict() if self.law else None, "law_source": self.law_source,
                    "series": self.series.to_dict() if self.series else None,
                    "median_rates_at_set_points": self.at_set_points,
                    "group_histograms": self.group_hist})
        return out


# =========================================================================== detection
def detect_dark(fit: DarkSeriesFit, settings: DarkSettings = DarkSettings(), level: float = LEVEL
                ) -> DarkDetectionResult:
    """Hot (and stuck) pixels of a fitted dark series, at ``settings.threshold`` ADU/s at ``settings.t_ref``.

    Raises
    ------
    InputError
        Rates must be carried to another temperature but there is no law (a single-temperature series without
        ``settings.law``), or no pixel has a fitted rate.
    """
    law, source = _law_for(fit, settings)
    t_ref = settings.t_ref if settings.t_ref is not None else _default_t_ref(fit)
    warnings = list(fit.warnings)
    if settings.law is not None and (settings.law.file or settings.law.classes):
        # a law fitted elsewhere: its rate classes are rates of pixels of its binning (one --doubling has no
        # classes and holds whatever the binning)
        warnings += law.binning_warnings(fit.binning)
    carried, errors = [], []
    for g in fit.groups:
        if law is None or g.temperature_c is None or t_ref is None or g.temperature_c == t_ref:
            if t_ref is not None and g.temperature_c is not None and g.temperature_c != t_ref:
                raise InputError(f"{g.label}: its rates refer to {g.temperature_c:+.2f} °C; carrying them to "
                                 f"{t_ref:+.2f} °C needs a temperature law: give --law (a law saved from a series "
                                 "at two temperatures) or --doubling, or --t-ref equal to the series' temperature")
            factor = np.ones(g.rate.size)
        else:
            factor = law.factor(g.rate, g.temperature_c, t_ref)
        carried.append((g.rate * factor).astype(np.float32))
        errors.append((g.rate_se * factor).astype(np.float32))
    rate, se = _combine(carried, errors)
    shape = fit.shape
    region = _region(settings.mask, shape)  # the analysed area is the mask's, so that epochs compare
    values = rate.reshape(shape)[region & np.isfinite(rate).reshape(shape)]
    if values.size == 0:
        raise InputError("no pixel has a fitted dark rate; check the series' frames")
    center, scale = robust_normal(values)
    scale = scale if scale > 0 else float(np.std(values)) or 1e-9
    typical_se = float(np.nanmedian(se.reshape(shape)[region & np.isfinite(rate).reshape(shape)]))
    threshold = settings.threshold
    if threshold is None:
        threshold = center + settings.sigma * scale
        warnings.append(f"no --rate-threshold: hot pixels are {settings.sigma:g} robust σ above the median "
                        f"({threshold:.4g} ADU/s), a threshold of this series only; give --rate-threshold to compare "
                        "series")
    elif threshold - center < NOISE_MARGIN * typical_se:
        warnings.append(f"the threshold {threshold:.4g} ADU/s is within {NOISE_MARGIN:g} per-pixel standard errors "
                        f"({typical_se:.3g} ADU/s) of the median rate {center:.4g}: its count measures the noise as "
                        "much as the hot pixels")
    constant = np.logical_and.reduce([g.constant for g in fit.groups]).reshape(shape)
    stuck = constant & region
    if stuck.any():
        stuck &= _constant_neighbours(constant, stuck) <= 2
    rate_img = rate.reshape(shape)
    hot = (np.nan_to_num(rate_img, nan=-np.inf) > threshold) & region & ~stuck
    ys, xs = np.nonzero(hot | stuck)
    kind = np.where(stuck[ys, xs], STUCK, PARTIAL).astype(np.int8)
    amp = rate_img[ys, xs].astype(np.float64)
    n_hot = int(hot.sum())
    law_range = _law_range(fit, law, t_ref, carried, errors, threshold, region, shape) if law else None
    region_fitted = region & np.isfinite(rate_img)
    hist_x, hist_n, hist_e = accumulated_histogram(values, center, scale)
    result = DarkDetectionResult(
        shape=shape, n_images=fit.n_frames, q=0, sigma=settings.sigma if settings.threshold is None else None,
        tau_given=threshold, stuck_tolerance=0.0, mask_spec=settings.mask, n_analysed=int(region.sum()),
        fits=[ChannelFit("dark rate", center, scale, float(threshold), int(values.size))],
        x=xs.astype(np.int64), y=ys.astype(np.int64), kind=kind, amplitude=amp,
        z=(amp - center) / scale, channel=np.zeros(len(xs), np.int8), hist_thresholds=hist_x, hist_counts=hist_n,
        hist_expected=hist_e, cfa=None, warnings=warnings, d_hat=np.nan_to_num(rate_img, nan=center),
        mask=region, full_scale=None, t_ref=t_ref, threshold_rate=float(threshold), law=law, law_source=source,
        series=fit, settings=settings, count_ci=garwood(n_hot, level), count_law_range=law_range,
        typical_rate_se=typical_se, group_hist=_group_histograms(fit, carried, region_fitted, threshold),
        at_set_points=set_point_medians(fit, law, level),
        rate_se=se.reshape(shape), group_rates=carried)
    return result


def set_point_medians(fit: DarkSeriesFit, law: TemperatureLaw | None, level: float = LEVEL) -> list[dict[str, Any]]:
    """Each group's median rate carried from its effective temperature to its set point, with an interval that adds
    the effective temperature's uncertainty and the law's to the median's own."""
    if law is None:
        return []
    z = float(stats.norm.ppf(0.5 + level / 2))
    out = []
    for g in fit.groups:
        if g.set_temperature_c is None or g.temperature_c is None:
            continue
        factor = float(law.factor(g.median_rate, g.temperature_c, g.set_temperature_c))
        value = g.median_rate * factor
        beta = float(law.beta(g.median_rate))
        beta_se = law.bulk.beta_se  # the median pixel is the bulk's
        dt = g.set_temperature_c - g.temperature_c
        se = math.sqrt((g.median_rate_se * factor) ** 2 + (value * math.log(2) * beta * g.temperature_se) ** 2
                       + (value * math.log(2) * dt * beta_se) ** 2)
        out.append({"group": g.label, "set_temperature_c": g.set_temperature_c, "median_rate_adu_per_s": value,
                    "ci": [value - z * se, value + z * se], "from_temperature_c": g.temperature_c})
    return out


def _law_for(fit: DarkSeriesFit, settings: DarkSettings) -> tuple[TemperatureLaw | None, str]:
    if settings.law is not None:
        return settings.law, settings.law.source or "given"
    if can_fit(fit.groups):
        law = replace(fit_temperature_law(fit.groups), binning=fit.binning)
        return law, law.source
    return None, "none (the series has one temperature)"


def _default_t_ref(fit: DarkSeriesFit) -> float | None:
    """One group: its effective temperature (nothing to carry).  Several: the coldest group's set point (else its
    effective temperature), where such a camera is usually run."""
    known = [g for g in fit.groups if g.temperature_c is not None]
    if not known:
        return None
    if len(fit.groups) == 1:
        return known[0].temperature_c
    coldest = min(known, key=lambda g: g.temperature_c)  # type: ignore[arg-type, return-value]
    return coldest.set_temperature_c if coldest.set_temperature_c is not None else coldest.temperature_c


def _combine(rates: list[np.ndarray], errors: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Inverse-variance mean of the groups' carried rates per pixel (NaN where no group has one)."""
    if len(rates) == 1:
        return rates[0], errors[0]
    num = np.zeros(rates[0].size, np.float64)
    den = np.zeros(rates[0].size, np.float64)
    for r, e in zip(rates, errors):
        ok = np.isfinite(r) & np.isfinite(e) & (e > 0)
        w = np.where(ok, 1.0 / np.where(ok, e, 1.0) ** 2, 0.0)
        num += np.where(ok, r, 0.0) * w
        den += w
    with np.errstate(divide="ignore", invalid="ignore"):
        return (num / den).astype(np.float32), (1.0 / np.sqrt(den)).astype(np.float32)


def _region(spec: MaskSpec, shape: tuple[int, int]) -> np.ndarray:
    if spec.kind == "centre":
        return centre_mask(shape, spec.fraction)
    if spec.kind == "file":
        return load_mask(spec.path, shape)  # type: ignore[arg-type]
    if spec.kind == "auto":
        raise UsageError("--mask auto leaves out textured regions of photographs; a dark series has none: use all, "
                         "centre[:FRACTION] or a mask image")
    return np.ones(shape, bool)


def _law_range(fit: DarkSeriesFit, law: TemperatureLaw, t_ref: float | None, carried: list[np.ndarray],
               errors: list[np.ndarray], threshold: float, region: np.ndarray, shape: tuple[int, int]
               ) -> tuple[int, int] | None:
    """The hot-pixel count with every β of the law at the ends of its 95 % interval (both ways)."""
    if t_ref is None or all(g.temperature_c == t_ref for g in fit.groups):
        return None
    z = float(stats.norm.ppf(0.5 + LEVEL / 2))
    counts = []
    for shift in (-z, z):
        moved = [g.rate * law.factor(g.rate, g.temperature_c, t_ref, shift) if g.temperature_c is not None else r
                 for g, r in zip(fit.groups, carried)]
        errs = [g.rate_se * law.factor(g.rate, g.temperature_c, t_ref, shift) if g.temperature_c is not None else e
                for g, e in zip(fit.groups, errors)]
        rate, _ = _combine([m.astype(np.float32) for m in moved], [e.astype(np.float32) for e in errs])
        counts.append(int(((rate.reshape(shape) > threshold) & region).sum()))
    return min(counts), max(counts)


def _group_histograms(fit: DarkSeriesFit, carried: list[np.ndarray], region: np.ndarray,
                      threshold: float) -> list[dict[str, Any]]:
    """Each group's accumulated histogram of carried rates: pixels above x on a log grid of x."""
    flat_region = region.ravel()
    tops = [float(np.nanmax(r[flat_region])) for r in carried if np.isfinite(r[flat_region]).any()]
    meds = [float(np.nanmedian(r[flat_region])) for r in carried if np.isfinite(r[flat_region]).any()]
    if not tops:
        return []
    lo = max(min(meds) / 10, 1e-4)
    grid = np.geomspace(lo, max(max(tops), threshold * 2, lo * 10), HIST_POINTS)
    out = []
    for g, r in zip(fit.groups, carried):
        v = np.sort(r[flat_region & np.isfinite(r)])
        above = v.size - np.searchsorted(v, grid, side="right")
        out.append({"group": g.label, "temperature_c": g.temperature_c, "rate_adu_per_s": grid.tolist(),
                    "pixels_above": above.tolist(), "pixels": int(v.size),
                    "above_threshold": int(v.size - np.searchsorted(v, threshold, side="right"))})
    return out


# =========================================================================== comparing two series
@dataclass
class CountComparison:
    """Hot-pixel counts of two series of one sensor at one threshold: Poisson intervals and a paired test.

    The paired (McNemar) test looks only at the pixels hot in one series and not the other: far more sensitive
    than the intervals, since the pixels hot in both are the same population.
    """

    labels: tuple[str, str]
    counts: tuple[int, int]
    cis: tuple[tuple[float, float], tuple[float, float]]
    overlap: bool
    only_first: int
    only_second: int
    paired_p: float
    threshold: float
    t_ref: float | None

    def to_dict(self) -> dict[str, Any]:
        return {"labels": list(self.labels), "counts": list(self.counts), "cis": [list(c) for c in self.cis],
                "intervals_overlap": self.overlap, "only_first": self.only_first, "only_second": self.only_second,
                "paired_p": self.paired_p, "threshold_adu_per_s": self.threshold, "t_ref_c": self.t_ref}


def compare_counts(first: DarkDetectionResult, second: DarkDetectionResult, labels: tuple[str, str] = ("first", "second"),
                   pixels: np.ndarray | None = None, level: float = LEVEL) -> CountComparison:
    """Compare the hot pixels of two detections of one sensor at one threshold and reference temperature.

    ``pixels`` (a boolean image) restricts the count, e.g. to the pixels a law was not fitted on.

    Raises
    ------
    UsageError
        The detections use different thresholds, reference temperatures or frame sizes.
    """
    if first.shape != second.shape:
        raise UsageError("the two series have different frame sizes; compare series of one sensor")
    if first.threshold_rate != second.threshold_rate or first.t_ref != second.t_ref:
        raise UsageError("the two detections use different thresholds or reference temperatures; give both the same "
                         "--rate-threshold and --t-ref")
    keep = np.ones(first.shape, bool) if pixels is None else np.asarray(pixels, bool)
    a = _hot_image(first) & keep
    b = _hot_image(second) & keep
    na, nb = int(a.sum()), int(b.sum())
    ca, cb = garwood(na, level), garwood(nb, level)
    only_a, only_b = int((a & ~b).sum()), int((b & ~a).sum())
    p = float(stats.binomtest(only_a, only_a + only_b, 0.5).pvalue) if only_a + only_b else 1.0
    return CountComparison(labels, (na, nb), (ca, cb), ca[1] >= cb[0] and cb[1] >= ca[0], only_a, only_b, p,
                           first.threshold_rate, first.t_ref)


def _hot_image(det: DetectionResult) -> np.ndarray:
    img = np.zeros(det.shape, bool)
    sel = det.kind == PARTIAL
    img[det.y[sel], det.x[sel]] = True
    return img


# =========================================================================== datasets
def series_frames(ds: Any) -> list[SeriesFrame]:
    """The frames of a dataset as a series, with the conditions its manifest or FITS headers give
    (:mod:`forensics.io.dataset`: a manifest overrides the header).

    The frame type is the ``frame_type`` column (FITS: IMAGETYP), else the ``subject``: ``dark`` (no light) is a
    bias at exposure 0 and a dark otherwise.
    """
    out = []
    for frame in ds.frames:
        exposure = frame.exposure_s
        kind = str(frame.get("frame_type") or "").strip().lower()
        if not kind and frame.subject:
            kind = "dark" if is_dark_subject(frame.subject) else frame.subject.strip().lower()
        if kind == "dark" and exposure == 0:
            kind = "bias"
        out.append(SeriesFrame(str(frame.path), kind, exposure, frame.get("temperature_c"),
                               _number(frame.get("set_temperature_c")), frame.captured, binning(frame)))
    return out


def _number(text: Any) -> float | None:
    if text is None or str(text).strip() == "":
        return None
    try:
        value = float(text)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def is_dark_series(ds: Any) -> bool:
    """Whether a dataset is a dark series: every frame has a frame type (FITS IMAGETYP, a manifest ``frame_type``, or
    a ``subject`` of dark, bias, flat or light), and its biases and darks span two exposure times, one above 0.

    Photographs and mixed folders are not: their frames have no frame type."""
    try:
        frames = series_frames(ds)
    except InputError:
        return False
    if not frames or any(f.frame_type not in DARK_TYPES + LIGHT_TYPES for f in frames):
        return False
    exposures = {f.exposure_s for f in frames if f.frame_type in DARK_TYPES and f.exposure_s is not None}
    return len(exposures) >= 2 and any(e > 0 for e in exposures)


def detect_dark_dataset(ds: Any, settings: DarkSettings = DarkSettings(), progress: Progress = no_progress,
                        executor: Executor | None = None) -> DarkDetectionResult:
    """Fit a dataset's dark series (:func:`~forensics.defects.darkseries.fit_dark_series`) and call its hot pixels."""
    plan = plan_series(series_frames(ds))
    fit = fit_dark_series(plan, gain=settings.gain, saturation=settings.saturation, k=settings.k,
                          k_grow=settings.k_grow, rounds=settings.rounds, executor=executor, progress=progress)
    return detect_dark(fit, settings)


# =========================================================================== dating one dark frame
def frame_growth_model(model: "GrowthModel", exposure_s: float, temperature_c: float | None) -> "GrowthModel":
    """A dark-series growth model with its catalogue's amplitudes turned into the ADU one dark frame shows.

    A catalogued hot pixel of rate r (ADU/s at t_ref) adds r·2^(β(T − t_ref))·t ADU to a dark frame of exposure t
    at temperature T, so single-frame dating (:func:`forensics.defects.dating.date_image`) can test for it.

    Raises
    ------
    InputError
        The model is not a dark-series model, or the frame's temperature differs from t_ref without a law.
    """
    settings = model.detection
    if settings.get("method") != METHOD:
        raise InputError("the growth model was not made from dark series; a single dark frame can only be dated "
                         "against a dark-series model")
    dark = DarkSettings.from_dict(settings)
    if not exposure_s or exposure_s <= 0:
        raise InputError("the query frame has no exposure time > 0: a hot pixel shows only in a dark exposure")
    rates = np.array([c.amplitude for c in model.catalogue], np.float64)
    factor = np.ones_like(rates)
    if dark.t_ref is not None and temperature_c is not None and temperature_c != dark.t_ref:
        if dark.law is None:
            raise InputError(f"the frame was taken at {temperature_c:+.2f} °C and the model's rates refer to "
                             f"{dark.t_ref:+.2f} °C, with no temperature law in the model")
        factor = dark.law.factor(rates, dark.t_ref, temperature_c)
    catalogue = [replace(c, amplitude=float(r * f * exposure_s)) if c.kind == PARTIAL else c
                 for c, r, f in zip(model.catalogue, rates, factor)]
    return replace(model, catalogue=catalogue)


# =========================================================================== epochs for growth and dating
def dark_epochs(datasets: list[Any], settings: DarkSettings = DarkSettings(), progress: Progress = no_progress,
                executor: Executor | None = None) -> list[Any]:
    """One :class:`~forensics.defects.growth.Epoch` per dark series, every one called at one threshold and ``t_ref``.

    Without ``settings.law``, the law is fitted on the first series that spans two temperatures and carries every
    series (one law for all epochs, so that a change in the counts is a change of the sensor, not of the law).
    Each epoch is dated by the median capture time of its frames.

    Raises
    ------
    InputError
        A series without capture dates, series of different sizes or devices, or rates to carry without a law.
    """
    from forensics.defects.growth import Epoch, dataset_device

    fits, dates, devices = [], [], []
    for ds in datasets:
        frames = series_frames(ds)
        times = [f.captured for f in frames if f.captured is not None]
        if not times:
            raise InputError(f"{ds.root}: no capture dates (DATE-OBS or a manifest 'captured'): a series must be dated "
                             "to be an epoch")
        plan = plan_series(frames)
        fits.append(fit_dark_series(plan, gain=settings.gain, saturation=settings.saturation, k=settings.k,
                                    k_grow=settings.k_grow, rounds=settings.rounds, executor=executor,
                                    progress=progress))
        dates.append(float(np.median(times)))
        devices.append(dataset_device(ds))
    for ds, fit in zip(datasets[1:], fits[1:]):
        if fit.shape != fits[0].shape:
            raise InputError(f"{ds.root}: frames are {fit.shape[1]}×{fit.shape[0]} but {datasets[0].root}'s are "
                             f"{fits[0].shape[1]}×{fits[0].shape[0]}; every epoch must come from one sensor")
    law = settings.law
    if law is None:
        spanning = next((f for f in fits if can_fit(f.groups)), None)
        law = fit_temperature_law(spanning.groups) if spanning is not None else None
    t_ref = settings.t_ref if settings.t_ref is not None else _default_t_ref(fits[0])
    common = replace(settings, law=law, t_ref=t_ref)
    epochs = []
    for ds, fit, date, device in zip(datasets, fits, dates, devices):
        detection = detect_dark(fit, common)
        epochs.append(Epoch(date, detection, str(ds.root), device))
    return epochs
