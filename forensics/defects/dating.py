"""When was this set, or this single image, taken?  Dating from the growth of sensor defects.

**A set of images** (same device as a growth model).  Its defects are detected
with the model's settings and compared with the model's catalogue:

* after the last reference epoch, the X defects new since then and the Y
  defects that appeared over the reference span S are independent Poisson
  counts with means λ·A·Δt and λ·A·S.  Conditionally on X + Y they are binomial
  with π = Δt/(Δt + S), so an exact binomial (mid-p) interval for π gives an
  interval for Δt = S·π/(1 − π) that carries both the query count's Poisson
  uncertainty and the rate's — no plug-in rate.  The point estimate is
  S·X/(Y + 1), nearly unbiased since E[1/(Y + 1)] ≈ 1/E[Y] for Poisson Y;
* before the first epoch, the same with X = first-epoch defects missing from
  the query;
* between epochs i and i+1, the defects that appeared in that interval have
  uniform onsets (Poisson process), so the fraction of them present in the
  query is binomial with π = (t − t_i)/(t_{i+1} − t_i).

**A single image** (Fridrich & Goljan).  Each catalogue defect's residual in
the image (pixel minus the median of its 8 neighbours of the same colour)
is compared with the local noise: a likelihood for "present" (offset =
the defect's amplitude; stuck: the stuck value) and for "absent".  With the
defects grouped by the epoch they first appeared in, hypothesis J says
groups 1..J are present and the later ones absent; its log-likelihood is the
sum over defects.  The estimate is the maximum-likelihood interval, and
every interval's likelihood is reported.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import stats

from forensics.defects.detection import DetectionResult, detect_dataset
from forensics._shared.errors import InputError
from forensics.defects.growth import Z_RECHECK, GrowthModel, _z_at
from forensics.stats.counts import LEVEL, midp_binomial
from forensics.sensor.catalogue import STUCK
from forensics._shared.progress import Progress, no_progress

if TYPE_CHECKING:
    from forensics._shared.parallel import Executor

#: Weight of the "anything else" component in the per-defect likelihoods (texture, edges).
CONTAMINATION = 0.02


# =========================================================================== sets
@dataclass
class SetDating:
    """The capture date of a query set with its interval."""

    estimate: float
    interval: tuple[float | None, float | None]
    level: float
    position: str
    method: str
    counts: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {"query": "set", "estimate": self.estimate, "interval": list(self.interval), "level": self.level,
                "position": self.position, "method": self.method, "counts": self.counts, "warnings": self.warnings}


def _extrapolate(x: int, y: int, span: float, level: float) -> tuple[float, tuple[float, float]]:
    """Δt estimate and exact interval from X new defects against Y over the span S: X | X+Y ~ Bin(X+Y, Δt/(Δt+S))."""
    if y == 0:
        raise InputError("no defects appeared between the reference epochs: the growth rate is zero at this "
                         "threshold and a date outside the reference span cannot be bounded; use reference sets "
                         "further apart or a lower --sigma")
    lo, hi = midp_binomial(x, x + y, level)
    to_dt = lambda p: span * p / (1 - p) if p < 1 else math.inf  # noqa: E731
    return span * x / (y + 1), (to_dt(lo), to_dt(hi))


def presence(model: GrowthModel, query: DetectionResult, z_recheck: float = Z_RECHECK) -> np.ndarray:
    """For each catalogue defect, whether the query set shows it (z > z_recheck, or constant for stuck ones)."""
    if not model.catalogue:
        return np.zeros(0, bool)
    xs = np.array([c.x for c in model.catalogue])
    ys = np.array([c.y for c in model.catalogue])
    kinds = np.array([c.kind for c in model.catalogue])
    z = _z_at(query, xs, ys)
    stuck_sites = query.sites(STUCK)
    stuck_here = np.array([(x, y) in stuck_sites for x, y in zip(xs.tolist(), ys.tolist())], bool)
    return np.where(kinds == STUCK, stuck_here, (z > z_recheck) | stuck_here)


def date_set(model: GrowthModel, query: DetectionResult, level: float = LEVEL,
             z_recheck: float = Z_RECHECK) -> SetDating:
    """Date a query set of the model's device from its defects (see the module docstring).

    The position relative to the reference epochs is the one that contradicts
    the fewest observations (catalogue defects absent that should be present,
    present that should be absent, and new defects before the last epoch).
    """
    if tuple(query.shape) != tuple(model.shape):
        raise InputError(f"the query images are {query.shape[1]}×{query.shape[0]} but the growth model's are "
                         f"{model.shape[1]}×{model.shape[0]}; date images from the same device at the same size")
    dates = model.dates
    m = len(dates)
    present = presence(model, query, z_recheck)
    first = np.array([c.first_epoch for c in model.catalogue], int)
    known = {(c.x, c.y) for c in model.catalogue} | set(model.near_last)
    new_sites = [s for s in query.sites() if s not in known]
    x_new = len(new_sites)
    y_total = int(sum(model.new["partial"]) + sum(model.new["stuck"]))
    span = dates[-1] - dates[0]
    # hypotheses i = 0..m: query in (t_i, t_{i+1}] with t_0 = -inf, t_{m+1} = +inf
    cost = []
    for i in range(m + 1):
        should = first <= i
        must_not = first >= i + 2
        c = int(np.sum(should & ~present) + np.sum(must_not & present))
        if i < m:
            c += x_new
        cost.append(c)
    best = min(cost)
    candidates = [i for i in range(m + 1) if cost[i] == best]
    counts: dict[str, Any] = {"query_defects": len(query.x), "new_since_last_epoch": x_new,
                              "catalogue": len(model.catalogue), "catalogue_present": int(present.sum()),
                              "reference_new": y_total, "reference_span_years": span, "mismatches": best}
    parts = [_position(i, m, dates, first, present, x_new, y_total, span, level, counts) for i in candidates]
    lows = [p[1] for p in parts]
    highs = [p[2] for p in parts]
    lo = None if any(v is None for v in lows) else min(lows)  # type: ignore[type-var]
    hi = None if any(v is None for v in highs) else max(highs)  # type: ignore[type-var]
    estimate = float(np.median([p[0] for p in parts]))
    position = " or ".join(p[3] for p in parts)
    method = "; ".join(dict.fromkeys(p[4] for p in parts))
    if len(parts) > 1:
        method += " (the observations fit several intervals equally well: the union of their intervals)"
    return SetDating(estimate, (lo, hi), level, position, method, counts, list(query.warnings))


def _position(i: int, m: int, dates: list[float], first: np.ndarray, present: np.ndarray, x_new: int, y_total: int,
              span: float, level: float, counts: dict[str, Any]) -> tuple[float, float | None, float | None, str, str]:
    """Estimate, interval, position and method under "the query lies in (t_i, t_{i+1}]" (t_0 = −∞, t_{m+1} = ∞)."""
    if i == m:
        dt, (lo, hi) = _extrapolate(x_new, y_total, span, level)
        counts.update({"x_after": x_new, "y": y_total})
        return (dates[-1] + dt, dates[-1] + lo, dates[-1] + hi if math.isfinite(hi) else None,
                "after the last reference epoch",
                "exact conditional binomial: X new defects vs Y over the reference span (mid-p interval on "
                "X/(X+Y)), carries both Poisson uncertainties")
    if i == 0:
        missing = int(np.sum((first == 1) & ~present))
        dt, (lo, hi) = _extrapolate(missing, y_total, span, level)
        counts.update({"x_before": missing, "y": y_total})
        return (dates[0] - dt, dates[0] - hi if math.isfinite(hi) else None, dates[0] - lo,
                "before the first reference epoch",
                "exact conditional binomial: first-epoch defects missing vs Y over the reference span")
    group = first == i + 1
    n, x = int(group.sum()), int(np.sum(group & present))
    t0, t1 = dates[i - 1], dates[i]
    if n == 0:
        return ((t0 + t1) / 2, t0, t1, f"between reference epochs {i} and {i + 1}",
                "no defect appeared in this interval: the whole interval")
    lo, hi = midp_binomial(x, n, level)
    counts.update({f"bracket_{i}_defects": n, f"bracket_{i}_present": x})
    return (t0 + (t1 - t0) * x / n, t0 + (t1 - t0) * lo, t0 + (t1 - t0) * hi,
            f"between reference epochs {i} and {i + 1}",
            "uniform onsets within the interval: mid-p binomial interval on the fraction of its new defects present")


def date_dataset(model: GrowthModel, ds: Any, level: float = LEVEL, progress: Progress = no_progress,
                 executor: Executor | None = None) -> SetDating:
    """Detect defects in a query dataset with the model's settings (frames read on ``executor``), then
    :func:`date_set`."""
    from forensics.defects.growth import dataset_device

    device = dataset_device(ds)
    if device and model.device and device != model.device:
        raise InputError(f"{ds.root} is from device '{device}' but the growth model is for '{model.device}'")
    det = model.detection
    if det.get("method") == "dark_series":  # a dark-series model: the query is a dark series, called alike
        from forensics.defects.darkdetect import DarkSettings, detect_dark_dataset

        query = detect_dark_dataset(ds, DarkSettings.from_dict(det), progress=progress, executor=executor)
        return date_set(model, query, level)
    query = detect_dataset(ds, q=int(det.get("q", 9)), sigma=det.get("sigma"), tau=det.get("tau"),
                           mask=model.mask_spec(), stuck_tolerance=float(det.get("stuck_tolerance", 0.0)),
                           progress=progress, executor=executor)
    return date_set(model, query, level)


# =========================================================================== single images
def _neighbour_offsets(step: int) -> list[tuple[int, int]]:
    return [(dy * step, dx * step) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx]


def site_residuals(image: np.ndarray, xs: np.ndarray, ys: np.ndarray, cfa: str | None = None,
                   radius: int = 7) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Value, residual (value − median of the 8 same-colour neighbours) and local noise σ at each site.

    σ is 1.4826·MAD of the same residual over the (2·radius+1)² patch around
    the site (same colour), the site itself excluded.
    """
    img = image.mean(axis=2, dtype=np.float64) if image.ndim == 3 else image.astype(np.float64)
    step = 2 if cfa else 1
    pad = (radius + 1) * step
    padded = np.pad(img, pad, mode="reflect")
    offs = _neighbour_offsets(step)
    span = np.arange(-radius, radius + 1) * step
    py = ys[:, None, None] + pad + span[None, :, None]
    px = xs[:, None, None] + pad + span[None, None, :]
    centre = padded[py, px]
    neigh = np.stack([padded[py + dy, px + dx] for dy, dx in offs], axis=0)
    resid = centre - np.median(neigh, axis=0)
    r_site = resid[:, radius, radius]
    flat = resid.reshape(len(xs), -1)
    flat = np.delete(flat, radius * (2 * radius + 1) + radius, axis=1)
    med = np.median(flat, axis=1, keepdims=True)
    sigma = 1.4826 * np.median(np.abs(flat - med), axis=1)
    sigma = np.maximum(sigma, 0.5)
    value = img[ys, xs]
    return value, r_site, sigma


def defect_log_likelihoods(image: np.ndarray, model: GrowthModel, cfa: str | None = None,
                           contamination: float = CONTAMINATION) -> tuple[np.ndarray, np.ndarray]:
    """log p(observation | defect present) and log p(observation | absent) for each catalogue defect."""
    cat = model.catalogue
    xs = np.array([c.x for c in cat], int)
    ys = np.array([c.y for c in cat], int)
    amp = np.array([c.amplitude for c in cat], float)
    kind = np.array([c.kind for c in cat], int)
    value, r, sigma = site_residuals(image, xs, ys, cfa)
    wide = np.maximum(10 * sigma, 2 * np.abs(amp))
    other = contamination * stats.norm.pdf(r, 0, wide)
    absent = (1 - contamination) * stats.norm.pdf(r, 0, sigma) + other
    partial = (1 - contamination) * stats.norm.pdf(r, amp, sigma) + other
    tol = max(0.5, float(model.detection.get("stuck_tolerance", 0.0)))
    stuck = (1 - contamination) * (np.abs(value - amp) <= tol) + other
    present = np.where(kind == STUCK, stuck, partial)
    tiny = np.finfo(float).tiny
    return np.log(np.maximum(present, tiny)), np.log(np.maximum(absent, tiny))


@dataclass
class ImageDating:
    """Single-image dating: the likelihood of each onset interval and the maximum-likelihood one."""

    estimate: float
    interval: tuple[float | None, float | None]
    best: int
    intervals: list[tuple[float | None, float | None]]
    log_likelihood: list[float]
    groups: list[int]
    group_sizes: list[int]
    n_defects: int
    evidence: list[float]
    warnings: list[str] = field(default_factory=list)

    @property
    def posterior(self) -> np.ndarray:
        """Likelihoods normalised to sum to 1 (a flat prior over intervals)."""
        ll = np.asarray(self.log_likelihood)
        p = np.exp(ll - ll.max())
        return p / p.sum()

    def to_dict(self) -> dict[str, Any]:
        return {"query": "image", "estimate": self.estimate, "interval": list(self.interval),
                "best_interval": self.best,
                "intervals": [{"index": j, "from": lo, "to": hi, "log_likelihood": ll, "relative_likelihood": p,
                               "groups_present": j}
                              for j, ((lo, hi), ll, p) in enumerate(zip(self.intervals, self.log_likelihood,
                                                                         self.posterior.tolist()))],
                "onset_groups": [{"first_epoch": g, "defects": n} for g, n in zip(self.groups, self.group_sizes)],
                "n_defects": self.n_defects, "method": "Fridrich–Goljan: maximum likelihood over onset intervals",
                "warnings": self.warnings}


def date_image(model: GrowthModel, image: np.ndarray, cfa: str | None = None) -> ImageDating:
    """Date one image of the model's device by which catalogue defects it shows.

    Raises
    ------
    InputError
        If the image size differs from the model's or the catalogue is empty.
    """
    if tuple(image.shape[:2]) != tuple(model.shape):
        raise InputError(f"the image is {image.shape[1]}×{image.shape[0]} but the growth model's images are "
                         f"{model.shape[1]}×{model.shape[0]}")
    if not model.catalogue:
        raise InputError("the growth model's catalogue has no defects: nothing to date a single image by; "
                         "use reference sets further apart or a lower --sigma")
    lp, la = defect_log_likelihoods(image, model, cfa)
    first = np.array([c.first_epoch for c in model.catalogue])
    groups = sorted(set(first.tolist()))
    dates = model.dates
    ll = []
    for j in range(len(groups) + 1):
        present = np.isin(first, groups[:j])
        ll.append(float(lp[present].sum() + la[~present].sum()))
    intervals: list[tuple[float | None, float | None]] = []
    estimates = []
    for j in range(len(groups) + 1):
        lo = None if j == 0 or groups[j - 1] == 1 else dates[groups[j - 1] - 2]
        hi = None if j == len(groups) else dates[groups[j] - 1]
        intervals.append((lo, hi))
        core_lo = None if j == 0 else dates[groups[j - 1] - 1]
        core_hi = None if j == len(groups) else dates[groups[j] - 2] if groups[j] >= 2 else None
        if core_lo is not None and core_hi is not None and core_hi >= core_lo:
            estimates.append((core_lo + core_hi) / 2)
        else:
            estimates.append(next(v for v in (core_lo, core_hi, hi, lo) if v is not None))
    best = int(np.argmax(ll))
    warnings = []
    if len(groups) < 3:
        warnings.append(f"the catalogue's defects appeared in only {len(groups)} distinct intervals: the date can "
                        "only be placed that coarsely")
    return ImageDating(float(estimates[best]), intervals[best], best, intervals, ll, groups,
                       [int(np.sum(first == g)) for g in groups], len(model.catalogue), (lp - la).tolist(), warnings)
