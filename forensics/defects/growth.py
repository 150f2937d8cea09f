"""Defect growth rates from image sets of one device taken at different dates.

Three families of estimates are computed side by side:

* **The paper's** (section 3.2, eq. 16–20), exactly as written:
  γ = n_match/n₁ (16), λ_ps = γ·(n₂ − n₁)/((T₂ − T₁)·w·h) (17), λ_s likewise from
  the stuck counts (18), a_ps = max(D_{s_k}) (19), a_s := 255 (20); w·h is the
  frame size in megapixels so that rates are per megapixel per year.
* **Capture–recapture**: the two epochs' detections as two captures of a
  population that only gains members (once defective, always defective).
  Chapman's bias-corrected estimator N̂ = (n₁+1)(n₂+1)/(m+1) − 1 estimates the
  defects present at the second epoch, missed ones included, with
  var = (n₁+1)(n₂+1)(n₁−m)(n₂−m)/((m+1)²(m+2)).
* **Poisson counts with exact intervals**: the defects that first appear after
  the first epoch form a Poisson count with mean λ·A·(T_last − T_first) (A =
  analysed megapixels), so the rate has an exact Garwood interval.  A site
  first detected at epoch i is checked at earlier epochs with a lower
  threshold (z > 3 by default) before it counts as new, which keeps defects
  near the threshold from "appearing" twice.  From three epochs on, a
  Poisson regression of the per-interval new counts on time (log link,
  exposure offset) gives a likelihood-ratio test of constant rate, i.e. of
  linear growth of the cumulative count.

Rates are in defects per megapixel per year of the *analysed* region, always
reported with the detection threshold used.
"""
from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import stats

from forensics.defects.detection import DEFAULT_Q, DEFAULT_SIGMA, DetectionResult, MaskSpec, detect_datasets
from forensics.defects.onsets import Z_RECHECK, first_epochs, presence_matrix
from forensics.defects.onsets import z_at as _z_at  # noqa: F401  (dating reads it from here)
from forensics._shared.errors import InputError
from forensics.stats.counts import LEVEL, TrendTest, garwood, trend_test
from forensics.sensor.catalogue import KIND_CODES, KIND_NAMES, PARTIAL, STUCK
from forensics._shared.progress import Progress, no_progress

if TYPE_CHECKING:
    from forensics._shared.parallel import Executor

MODEL_FORMAT = "forensics-growth-model/1"


# =========================================================================== the paper's estimates

def paper_gamma(n1: int, n_match: int) -> float:
    """Eq. 16: γ = n_match / n₁."""
    return n_match / n1 if n1 else float("nan")


def paper_rate(n1: int, n2: int, n_match: int, t1: float, t2: float, width: int, height: int) -> float:
    """Eq. 17 (and 18 with stuck counts): λ = γ·(n₂ − n₁)/((T₂ − T₁)·(w·h)), w·h in megapixels.

    >>> round(paper_rate(27, 28, 5, 2009.0, 2013.0, 640, 480), 5)   # the paper's H100 figures
    0.1507
    """
    return paper_gamma(n1, n_match) * (n2 - n1) / ((t2 - t1) * (width * height / 1e6))


@dataclass
class PaperEstimate:
    """Eq. 16–20 on the first and last epoch."""

    n1: int
    n2: int
    n_match: int
    n_s1: int
    n_s2: int
    t1: float
    t2: float
    width: int
    height: int
    gamma: float
    lambda_ps: float
    lambda_s: float
    a_ps: float
    a_s: float

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def paper_estimate(first: DetectionResult, last: DetectionResult, t1: float, t2: float) -> PaperEstimate:
    """The paper's estimates from the detections at T₁ and T₂ (sites matched exactly)."""
    p1, p2 = first.sites(PARTIAL), last.sites(PARTIAL)
    n1, n2, m = len(p1), len(p2), len(p1 & p2)
    s1, s2 = first.count(STUCK), last.count(STUCK)
    h, w = last.shape
    gamma = paper_gamma(n1, m)
    lam_ps = paper_rate(n1, n2, m, t1, t2, w, h)
    lam_s = gamma * (s2 - s1) / ((t2 - t1) * (w * h / 1e6)) if n1 else float("nan")
    amps = last.amplitude[last.kind == PARTIAL]
    return PaperEstimate(n1, n2, m, s1, s2, t1, t2, w, h, gamma, lam_ps, lam_s,
                         float(amps.max()) if len(amps) else float("nan"), 255.0)


# =========================================================================== capture–recapture
@dataclass
class ChapmanEstimate:
    """Chapman's capture–recapture estimate of the defects present at the later epoch."""

    n1: int
    n2: int
    m: int
    n_hat: float
    variance: float
    ci: tuple[float, float]
    lincoln_petersen: float
    efficiency: float
    level: float = LEVEL

    def to_dict(self) -> dict[str, Any]:
        return {"n1": self.n1, "n2": self.n2, "m": self.m, "n_hat": self.n_hat, "variance": self.variance,
                "se": math.sqrt(self.variance), "ci": list(self.ci), "lincoln_petersen": self.lincoln_petersen,
                "detection_efficiency": self.efficiency, "level": self.level}


def chapman(n1: int, n2: int, m: int, level: float = LEVEL) -> ChapmanEstimate:
    """Chapman's N̂ = (n₁+1)(n₂+1)/(m+1) − 1 and var = (n₁+1)(n₂+1)(n₁−m)(n₂−m)/((m+1)²(m+2)).

    The interval is the normal one, N̂ ± z·√var, floored at the number of distinct
    defects seen (n₁ + n₂ − m).
    """
    if not 0 <= m <= min(n1, n2):
        raise ValueError(f"matches m = {m} must lie in [0, min(n1, n2)]")
    n_hat = (n1 + 1) * (n2 + 1) / (m + 1) - 1
    var = (n1 + 1) * (n2 + 1) * (n1 - m) * (n2 - m) / ((m + 1) ** 2 * (m + 2))
    z = stats.norm.ppf(0.5 + level / 2)
    seen = n1 + n2 - m
    ci = (max(seen, n_hat - z * math.sqrt(var)), n_hat + z * math.sqrt(var))
    lp = n1 * n2 / m if m else float("inf")
    return ChapmanEstimate(n1, n2, m, n_hat, var, ci, lp, n2 / n_hat if n_hat > 0 else float("nan"), level)


# =========================================================================== Poisson rates and regression
@dataclass
class RateEstimate:
    """A rate in defects per megapixel per year: count / exposure with an exact interval."""

    kind: str
    count: int
    exposure: float
    rate: float
    ci: tuple[float, float]
    level: float = LEVEL
    method: str = "Garwood exact Poisson interval on the defects new after the first epoch"

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "count": self.count, "exposure_mp_years": self.exposure, "rate": self.rate,
                "ci": list(self.ci), "level": self.level, "units": "defects/MP/year", "method": self.method}


def poisson_rate(count: int, exposure: float, kind: str = "partial", level: float = LEVEL) -> RateEstimate:
    """Rate = count / exposure (MP·years) with the Garwood interval scaled by the exposure."""
    if exposure <= 0:
        raise InputError("the epochs span no time: give image sets captured at different dates")
    lo, hi = garwood(int(count), level)
    return RateEstimate(kind, int(count), float(exposure), count / exposure, (lo / exposure, hi / exposure), level)


# =========================================================================== epochs and catalogue
@dataclass
class Epoch:
    """One image set of the device: its capture date (decimal year) and what was detected."""

    date: float
    detection: DetectionResult
    label: str = ""
    device: str | None = None


@dataclass
class CatalogueEntry:
    """A defect seen in the reference sets: site, kind, amplitude and the interval its onset lies in."""

    x: int
    y: int
    kind: int
    amplitude: float
    first_epoch: int
    onset_lo: float | None
    onset_hi: float
    seen: int
    possible: int

    def to_dict(self) -> dict[str, Any]:
        return {"x": self.x, "y": self.y, "kind": KIND_NAMES[self.kind], "amplitude": self.amplitude,
                "first_epoch": self.first_epoch, "onset_lo": self.onset_lo, "onset_hi": self.onset_hi,
                "seen": self.seen, "possible": self.possible}

    @classmethod
    def from_dict(cls, obj: dict[str, Any]) -> "CatalogueEntry":
        return cls(int(obj["x"]), int(obj["y"]), KIND_CODES[obj["kind"]], float(obj["amplitude"]),
                   int(obj["first_epoch"]), None if obj.get("onset_lo") is None else float(obj["onset_lo"]),
                   float(obj["onset_hi"]), int(obj.get("seen", 1)), int(obj.get("possible", 1)))


def build_catalogue(epochs: Sequence[Epoch], z_recheck: float = Z_RECHECK) -> list[CatalogueEntry]:
    """The defect catalogue with onset intervals (t_{e−1}, t_e] for a defect first present at epoch e.

    *Once defective, always defective*: a site is kept only if it still shows
    at the last epoch and in at least half of the epochs from its first on;
    the others were false alarms (or defects lost under the threshold).
    """
    dates = [ep.date for ep in epochs]
    by_site: dict[tuple[int, int], CatalogueEntry] = {}
    amplitudes = [ep.detection.amplitudes() for ep in epochs]
    for kind in (STUCK, PARTIAL):
        firsts = first_epochs(epochs, kind, z_recheck)
        sites = list(firsts)
        shows = presence_matrix(epochs, sites, kind, z_recheck)
        for col, site in enumerate(sites):
            e = firsts[site]
            later = shows[e:, col]
            if not later[-1] or later.sum() < 0.5 * len(later):
                continue
            if site in by_site:
                continue  # stuck overrides partially stuck
            seen = sum(site in ep.detection.sites(kind) for ep in epochs[e:])
            amps = [amplitudes[i][site] for i, ep in enumerate(epochs) if site in ep.detection.sites(kind)]
            by_site[site] = CatalogueEntry(site[0], site[1], kind, float(np.median(amps)), e + 1,
                                           None if e == 0 else dates[e - 1], dates[e], seen, len(epochs) - e)
    return sorted(by_site.values(), key=lambda c: (c.first_epoch, c.y, c.x))


# =========================================================================== growth result
@dataclass
class KindGrowth:
    """Per-kind counts and estimates."""

    kind: str
    counts: list[int]
    new: list[int]
    rate: RateEstimate
    trend: TrendTest | None
    chapman: ChapmanEstimate | None

    def to_dict(self) -> dict[str, Any]:
        return {"counts": self.counts, "new_per_interval": self.new, "rate": self.rate.to_dict(),
                "trend": self.trend.to_dict() if self.trend else None,
                "chapman": self.chapman.to_dict() if self.chapman else None}


@dataclass
class GrowthResult:
    """Everything estimated from ≥ 2 epochs of one device."""

    dates: list[float]
    labels: list[str]
    shape: tuple[int, int]
    area_mp: float
    threshold: dict[str, Any]
    partial: KindGrowth
    stuck: KindGrowth
    paper: PaperEstimate
    catalogue: list[CatalogueEntry]
    device: str | None = None
    detection_settings: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    near_last: list[tuple[int, int]] = field(default_factory=list)

    @property
    def span(self) -> float:
        return self.dates[-1] - self.dates[0]

    def to_dict(self) -> dict[str, Any]:
        return {
            "device": self.device, "epochs": [{"label": lab, "date": d, "partial": p, "stuck": s}
                                              for lab, d, p, s in zip(self.labels, self.dates, self.partial.counts,
                                                                      self.stuck.counts)],
            "shape": list(self.shape), "area_mp": self.area_mp, "threshold": self.threshold,
            "rate_partial": self.partial.rate.rate, "rate_partial_ci": list(self.partial.rate.ci),
            "rate_stuck": self.stuck.rate.rate, "rate_stuck_ci": list(self.stuck.rate.ci),
            "rate_units": "defects/MP/year", "level": self.partial.rate.level,
            "partial": self.partial.to_dict(), "stuck": self.stuck.to_dict(), "paper": self.paper.to_dict(),
            "catalogue_size": len(self.catalogue), "warnings": self.warnings,
        }

    def model(self) -> "GrowthModel":
        """The part needed later for dating, as a :class:`GrowthModel`."""
        return GrowthModel(device=self.device, shape=self.shape, area_mp=self.area_mp, dates=list(self.dates),
                           labels=list(self.labels), counts={"partial": self.partial.counts, "stuck": self.stuck.counts},
                           new={"partial": self.partial.new, "stuck": self.stuck.new},
                           rates={"partial": self.partial.rate.to_dict(), "stuck": self.stuck.rate.to_dict()},
                           threshold=self.threshold, detection=self.detection_settings, catalogue=self.catalogue,
                           near_last=list(self.near_last))


def estimate_growth(epochs: Sequence[Epoch], level: float = LEVEL, z_recheck: float = Z_RECHECK) -> GrowthResult:
    """Growth estimates from ≥ 2 epochs of one device (detections made with one setting).

    Raises
    ------
    InputError
        Fewer than two epochs, epochs of different sizes or analysed regions,
        epochs of different devices, or two epochs at the same date.
    """
    if len(epochs) < 2:
        raise InputError("growth needs at least two image sets taken at different dates")
    epochs = sorted(epochs, key=lambda e: e.date)
    check_epochs(epochs)
    dates = [e.date for e in epochs]
    area = epochs[0].detection.megapixels
    kinds = {}
    for kind in (PARTIAL, STUCK):
        firsts = first_epochs(epochs, kind, z_recheck)
        if len(epochs) >= 3:  # a site that no longer shows at the last epoch was no defect
            sites = list(firsts)
            keep = presence_matrix(epochs, sites, kind, z_recheck)[-1] if sites else []
            firsts = {s: e for s, e, k in zip(sites, firsts.values(), keep) if k}
        new = [sum(1 for e in firsts.values() if e == i) for i in range(1, len(epochs))]
        counts = [ep.detection.count(kind) for ep in epochs]
        rate = poisson_rate(sum(new), area * (dates[-1] - dates[0]), KIND_NAMES[kind], level)
        trend = trend_test(new, dates, area, level) if len(epochs) >= 3 else None
        a, b = epochs[0].detection.sites(kind), epochs[-1].detection.sites(kind)
        cr = chapman(len(a), len(b), len(a & b), level) if (a or b) else None
        kinds[kind] = KindGrowth(KIND_NAMES[kind], counts, new, rate, trend, cr)
    det = epochs[-1].detection
    threshold = det.threshold_dict()
    threshold["tau_per_epoch"] = [ep.detection.tau for ep in epochs]
    threshold["z_recheck"] = z_recheck
    warnings = [w for ep in epochs for w in ep.detection.warnings]
    settings = {"q": det.q, "sigma": det.sigma, "tau": det.tau_given, "mask": det.mask_spec.to_dict(),
                "stuck_tolerance": det.stuck_tolerance}
    catalogue = build_catalogue(epochs, z_recheck)
    return GrowthResult(dates, [e.label for e in epochs], det.shape, area, threshold, kinds[PARTIAL], kinds[STUCK],
                        paper_estimate(epochs[0].detection, epochs[-1].detection, dates[0], dates[-1]),
                        catalogue, epochs[0].device, settings, warnings,
                        near_sites(epochs[-1].detection, {(c.x, c.y) for c in catalogue}, z_recheck))


def near_sites(detection: DetectionResult, exclude: set[tuple[int, int]], z_recheck: float = Z_RECHECK,
               limit: int = 200_000) -> list[tuple[int, int]]:
    """Sites with z > z_recheck at an epoch that are not in ``exclude`` (the largest ``limit`` by z).

    Kept in the growth model so that a later query does not count a defect
    that was just under the threshold at the last reference epoch as new.
    """
    if detection.d_hat is None:
        return []
    from forensics.defects.detection import _lattices

    z = np.full(detection.shape, -np.inf, np.float32)
    for fit, (_, (sy, sx)) in zip(detection.fits, _lattices(detection.shape, detection.cfa)):
        z[sy, sx] = (detection.d_hat[sy, sx] - fit.center) / fit.scale
    if detection.mask is not None:
        z[~detection.mask] = -np.inf
    ys, xs = np.nonzero(z > z_recheck)
    if len(ys) > limit:
        keep = np.argsort(-z[ys, xs])[:limit]
        ys, xs = ys[keep], xs[keep]
    return [(int(x), int(y)) for x, y in zip(xs, ys) if (int(x), int(y)) not in exclude]


def check_epochs(epochs: Sequence[Epoch]) -> None:
    """Refuse epochs that cannot be compared: other sizes, other analysed regions, other devices, equal dates."""
    ref = epochs[0]
    for ep in epochs[1:]:
        if ep.detection.shape != ref.detection.shape:
            raise InputError(f"{ep.label or 'an epoch'}: images are {ep.detection.shape[1]}×{ep.detection.shape[0]} "
                             f"but {ref.label or 'the first epoch'} has {ref.detection.shape[1]}×"
                             f"{ref.detection.shape[0]}; every epoch must come from the same sensor at the same size")
        if ep.detection.n_analysed != ref.detection.n_analysed:
            raise InputError(f"{ep.label or 'an epoch'}: the analysed region ({ep.detection.n_analysed} pixels) "
                             f"differs from {ref.label or 'the first epoch'}'s ({ref.detection.n_analysed}); "
                             "use one mask for every epoch")
        if ep.device and ref.device and ep.device != ref.device:
            raise InputError(f"{ep.label or 'an epoch'} is from device '{ep.device}' but {ref.label or 'the first'} "
                             f"is from '{ref.device}'; growth needs one device")
    dates = sorted(ep.date for ep in epochs)
    if any(b - a <= 0 for a, b in zip(dates, dates[1:])):
        raise InputError("two epochs have the same capture date; each set must be taken at its own date")


def dataset_device(ds: Any) -> str | None:
    """The one device a dataset comes from (manifest 'device', else EXIF make/model/serial), or None if unknown.

    Raises
    ------
    InputError
        If the set mixes devices.
    """
    names = {f.device for f in ds.frames if f.device}
    if not names:
        info = ds.frames[0].info()
        parts = [p for p in (info.make, info.model, info.serial) if p]
        others = set()
        for frame in ds.frames[1:]:
            i2 = frame.info()
            others.add(tuple(p for p in (i2.make, i2.model, i2.serial) if p))
        if others and others != {tuple(parts)}:
            raise InputError(f"{ds.root}: the images come from several cameras (EXIF make/model/serial differ); "
                             "an epoch must be one device")
        return " ".join(parts) or None
    if len(names) > 1:
        raise InputError(f"{ds.root}: the manifest names several devices ({', '.join(sorted(names))}); "
                         "an epoch must be one device")
    return names.pop()


def epochs_from_datasets(datasets: Sequence[Any], q: int = DEFAULT_Q, sigma: float | None = DEFAULT_SIGMA,
                         tau: float | None = None, mask: MaskSpec | None = None, stuck_tolerance: float = 0.0,
                         progress: Progress = no_progress, executor: Executor | None = None) -> list[Epoch]:
    """Detect defects in each dataset (one epoch each), dated by the median of their 'captured' field.

    The frames of all epochs are read on ``executor`` as one list of (epoch, chunk) work items
    (:func:`~forensics.defects.detection.detect_datasets`): the detections are identical on every backend.
    """
    infos = []
    for ds in datasets:
        date = ds.epoch()  # InputError naming 'captured' when missing
        shape = ds.shape()
        infos.append((ds, date, shape, dataset_device(ds)))
    first = infos[0]
    for ds, _, shape, device in infos[1:]:
        if shape != first[2]:
            raise InputError(f"{ds.root}: images are {shape[1]}×{shape[0]} but {first[0].root} has "
                             f"{first[2][1]}×{first[2][0]}; every epoch must come from the same sensor at the same size")
        if device and first[3] and device != first[3]:
            raise InputError(f"{ds.root} is from device '{device}' but {first[0].root} is from '{first[3]}'; "
                             "growth needs sets from one device")
    detections = detect_datasets([ds for ds, *_ in infos], q=q, sigma=sigma, tau=tau, mask=mask,
                                 stuck_tolerance=stuck_tolerance, progress=progress, executor=executor)
    return [Epoch(date, det, str(ds.root), device) for (ds, date, _, device), det in zip(infos, detections)]


# =========================================================================== the saved model
@dataclass
class GrowthModel:
    """What dating needs from the reference epochs: rates, counts, dates, detection settings and the catalogue.

    ``near_last`` lists the sites just under the threshold (z > 3) at the last
    epoch, so a later query does not count them as new defects.
    """

    device: str | None
    shape: tuple[int, int]
    area_mp: float
    dates: list[float]
    labels: list[str]
    counts: dict[str, list[int]]
    new: dict[str, list[int]]
    rates: dict[str, dict[str, Any]]
    threshold: dict[str, Any]
    detection: dict[str, Any]
    catalogue: list[CatalogueEntry]
    near_last: list[tuple[int, int]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {"format": MODEL_FORMAT, "device": self.device, "shape": list(self.shape), "area_mp": self.area_mp,
                "dates": self.dates, "labels": self.labels, "counts": self.counts, "new": self.new,
                "rates": self.rates, "threshold": self.threshold, "detection": self.detection,
                "catalogue": [c.to_dict() for c in self.catalogue],
                "near_last": [list(site) for site in self.near_last]}

    @classmethod
    def from_dict(cls, obj: dict[str, Any]) -> "GrowthModel":
        return cls(obj.get("device"), tuple(obj["shape"]), float(obj["area_mp"]), [float(d) for d in obj["dates"]],
                   list(obj.get("labels", [""] * len(obj["dates"]))), obj["counts"], obj["new"], obj["rates"],
                   obj.get("threshold", {}), obj.get("detection", {}),
                   [CatalogueEntry.from_dict(c) for c in obj.get("catalogue", [])],
                   [(int(x), int(y)) for x, y in obj.get("near_last", [])])

    def save(self, path: str | os.PathLike, force: bool = False) -> Path:
        """Write the model as JSON (atomically)."""
        from forensics._shared.atomic import write_json

        return write_json(path, self.to_dict(), force=force)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "GrowthModel":
        """Read a model written by :meth:`save`.

        Raises
        ------
        InputError
            If the file cannot be read, is not JSON, or any field is missing, of the wrong type or out of
            range (dates not strictly increasing, a defect outside the frame …): the message names the field.
        """
        path = Path(path)
        try:
            obj = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
            raise InputError(f"{path}: cannot read the growth model ({exc})") from exc
        found = f"format {obj.get('format')!r}" if isinstance(obj, dict) else f"a JSON {type(obj).__name__}"
        if not isinstance(obj, dict) or obj.get("format") != MODEL_FORMAT:
            raise InputError(f"{path}: not a growth model written by 'forensics defects growth -o' ({found})")
        try:
            check_model_fields(obj)
            return cls.from_dict(obj)
        except (KeyError, TypeError, ValueError) as exc:
            what = f"'{exc.args[0]}' is missing" if isinstance(exc, KeyError) else exc
            raise InputError(f"{path}: malformed growth model: {what}; write it again with "
                             "'forensics defects growth -o'") from exc

    def mask_spec(self) -> MaskSpec:
        return MaskSpec.from_dict(self.detection.get("mask", {}))


def _finite(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{name} is {value!r}, not a finite number")
    return float(value)


def _whole(value: Any, name: str, low: int, high: float = math.inf) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        bound = f"from {low} to {high}" if math.isfinite(high) else f"≥ {low}"
        raise ValueError(f"{name} is {value!r}, not a whole number {bound}")
    return value


def _list(value: Any, name: str, length: int | None = None) -> list[Any]:
    if not isinstance(value, list) or (length is not None and len(value) != length):
        raise ValueError(f"{name} is not a list" + (f" of {length} values" if length is not None else ""))
    return value


def check_model_fields(obj: dict[str, Any]) -> None:
    """Check every field of a saved :class:`GrowthModel` that dating relies on.

    Raises
    ------
    ValueError, KeyError
        Naming the first field that is missing, of the wrong type or out of range.
    """
    h, w = (_whole(v, "shape", 1) for v in _list(obj["shape"], "shape", 2))
    if _finite(obj["area_mp"], "area_mp") <= 0:
        raise ValueError(f"area_mp is {obj['area_mp']!r}, not positive")
    dates = [_finite(d, "a date") for d in _list(obj["dates"], "dates")]
    if len(dates) < 2 or any(b <= a for a, b in zip(dates, dates[1:])):
        raise ValueError(f"dates {dates} are not two or more epochs in increasing order")
    _list(obj.get("labels", [""] * len(dates)), "labels", len(dates))
    for key, length in (("counts", len(dates)), ("new", len(dates) - 1)):
        if not isinstance(obj[key], dict):
            raise ValueError(f"{key} is not an object")
        for kind in ("partial", "stuck"):
            for v in _list(obj[key][kind], f"{key}.{kind}", length):
                _whole(v, f"a value of {key}.{kind}", 0)
    for key in ("rates", "threshold", "detection"):
        if not isinstance(obj.get(key, {}), dict):
            raise ValueError(f"{key} is not an object")
    detection = obj.get("detection", {})
    if "q" in detection and (_whole(detection["q"], "detection.q", 1) % 2 == 0):
        raise ValueError(f"detection.q is {detection['q']}, not odd")
    for key in ("sigma", "tau"):
        if detection.get(key) is not None and _finite(detection[key], f"detection.{key}") <= 0:
            raise ValueError(f"detection.{key} is {detection[key]!r}, not positive")
    if _finite(detection.get("stuck_tolerance", 0.0), "detection.stuck_tolerance") < 0:
        raise ValueError("detection.stuck_tolerance is negative")
    if not isinstance(detection.get("mask", {}), dict):
        raise ValueError("detection.mask is not an object")
    for i, c in enumerate(_list(obj.get("catalogue", []), "catalogue")):
        name = f"catalogue[{i}]"
        if not isinstance(c, dict):
            raise ValueError(f"{name} is not an object")
        _whole(c["x"], f"{name}.x", 0, w - 1)
        _whole(c["y"], f"{name}.y", 0, h - 1)
        if c["kind"] not in KIND_CODES:
            raise ValueError(f"{name}.kind is {c['kind']!r}, not one of {', '.join(map(repr, KIND_CODES))}")
        _finite(c["amplitude"], f"{name}.amplitude")
        _whole(c["first_epoch"], f"{name}.first_epoch", 1, len(dates))
        hi = _finite(c["onset_hi"], f"{name}.onset_hi")
        if c.get("onset_lo") is not None and _finite(c["onset_lo"], f"{name}.onset_lo") > hi:
            raise ValueError(f"{name}: onset_lo {c['onset_lo']} is after onset_hi {hi}")
    for i, site in enumerate(_list(obj.get("near_last", []), "near_last")):
        x, y = _list(site, f"near_last[{i}]", 2)
        _whole(x, f"near_last[{i}] x", 0, w - 1)
        _whole(y, f"near_last[{i}] y", 0, h - 1)
