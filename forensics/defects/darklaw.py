"""The temperature law of dark rates: rate ∝ 2^((T − T_ref)/T_d), fitted from series at several temperatures.

Dark current roughly doubles every T_d degrees, but not with one T_d for every pixel: the bulk of a CCD's
pixels (diffusion current, activation energy near the band gap) doubles faster than its hot pixels, whose
dark current comes from generation at defects (activation energy near half the gap, lower still where the
field is strong).  A hot-pixel threshold stated at one temperature can only be carried to another with the
law of the pixels near that threshold, so the law here is fitted by *rate class*:

* **the bulk**: log₂ of each temperature group's median rate against the group's effective temperature
  (generalised least squares over the groups; variances from the medians' intervals — which include the
  frame-to-frame offset jitter — and from the uncertainty of each group's temperature);
* **classes of the hot tail**: pixels are classed by their rate carried to a common temperature with the bulk
  law (the mean over the groups, so that no group's noise selects them), in half-decades from twice the bulk
  median up; in each class, log₂ of the mean rate in each group against temperature, with the full covariance
  of the class means across groups (the same pixels in every group).  Classes start well above the noise of
  single pixels, so selecting by rate does not bias the ratio.

Between the class centres 1/T_d is interpolated linearly in log rate (constant beyond the ends), so every
pixel is carried with the law of pixels like it: :meth:`TemperatureLaw.to_reference`.  A law can be saved and
reused on series taken at a single temperature (``--law``), or be a single given T_d (``--doubling``).
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

from forensics._shared.errors import InputError

if TYPE_CHECKING:
    from forensics.defects.darkseries import GroupFit

LAW_FORMAT = "forensics-dark-law/1"
LEVEL = 0.95
#: Groups closer than this (°C) do not constrain a doubling temperature.
MIN_SPAN_C = 1.0
#: A rate class needs at least this many pixels (fewer are merged into the class below).
MIN_CLASS = 50
#: The hot-tail classes start at this multiple of the bulk median and are half a decade wide.
FIRST_CLASS = 2.0
CLASS_WIDTH = math.sqrt(10.0)


@dataclass
class LawPoint:
    """The law of one class of pixels: β = 1/T_d (per °C) with its standard error, at a rate (ADU/s at ``t_class``)."""

    rate: float
    beta: float
    beta_se: float
    n: int
    lo: float | None = None
    hi: float | None = None
    spread: float | None = None

    @property
    def doubling(self) -> float:
        """T_d = 1/β (°C); inf when β ≤ 0."""
        return 1.0 / self.beta if self.beta > 0 else math.inf

    def doubling_ci(self, level: float = LEVEL) -> tuple[float, float | None]:
        """T_d's interval from β ± z·se (the upper end is None — unbounded — when β − z·se ≤ 0)."""
        z = float(stats.norm.ppf(0.5 + level / 2))
        b_hi, b_lo = self.beta + z * self.beta_se, self.beta - z * self.beta_se
        return (1.0 / b_hi if b_hi > 0 else math.inf), (1.0 / b_lo if b_lo > 0 else None)

    def to_dict(self) -> dict[str, Any]:
        lo, hi = self.doubling_ci()
        return {"rate_adu_per_s": self.rate, "class_lo": self.lo, "class_hi": self.hi, "pixels": self.n,
                "doubling_c": self.doubling, "doubling_ci": [lo, hi], "beta_per_c": self.beta,
                "beta_se": self.beta_se, "beta_pixel_spread": self.spread}

    @classmethod
    def from_dict(cls, obj: dict[str, Any]) -> "LawPoint":
        return cls(float(obj["rate_adu_per_s"]), float(obj["beta_per_c"]), float(obj["beta_se"]), int(obj["pixels"]),
                   obj.get("class_lo"), obj.get("class_hi"), obj.get("beta_pixel_spread"))


@dataclass
class TemperatureLaw:
    """Dark rate against temperature, by rate class (see the module notes).

    ``t_class`` is the temperature the class rates refer to; ``bulk`` the law of the typical pixel (its rate is
    the median); ``classes`` those of the hot tail, in increasing rate.
    """

    t_class: float
    bulk: LawPoint
    classes: list[LawPoint] = field(default_factory=list)
    temperatures: list[float] = field(default_factory=list)
    source: str = ""
    #: the on-chip binning ``(x, y)`` of the frames it was fitted on (None: not stated, or a law file written before
    #: the binning was kept); a binned pixel sums x·y pixels' dark charge, so its rate classes mean other pixels
    binning: tuple[int, int] | None = None
    #: the file it was read from (:meth:`load`; not saved)
    file: str = ""

    # ------------------------------------------------------------------ evaluation
    def _knots(self, shift: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        points = [self.bulk] + self.classes
        x = np.log10([max(p.rate, 1e-30) for p in points])
        y = np.array([p.beta + shift * p.beta_se for p in points])
        return x, y

    def beta(self, rate_at_class: np.ndarray | float, shift: float = 0.0) -> np.ndarray:
        """β = 1/T_d (per °C) for pixels of the given rates at ``t_class``; ``shift`` moves every β by that many SEs."""
        x, y = self._knots(shift)
        r = np.log10(np.maximum(np.asarray(rate_at_class, np.float64), 1e-30))
        return np.interp(r, x, y)

    def factor(self, rate: np.ndarray | float, t_from: float, t_to: float, shift: float = 0.0) -> np.ndarray:
        """The factor that carries rates measured at ``t_from`` to ``t_to``: 2^(β·(t_to − t_from)), β of each pixel's class.

        The class rate is found by a fixed-point iteration (β changes slowly with rate, so it converges in a few
        steps).
        """
        rate = np.asarray(rate, np.float64)
        dt = t_from - self.t_class
        c = rate * np.exp2(-self.beta(rate, shift) * dt)
        for _ in range(8):
            c = rate * np.exp2(-self.beta(c, shift) * dt)
        return np.exp2(self.beta(c, shift) * (t_to - t_from))

    def to_reference(self, rate: np.ndarray | float, t_from: float, t_to: float, shift: float = 0.0) -> np.ndarray:
        """Rates measured at ``t_from`` carried to ``t_to``."""
        return np.asarray(rate, np.float64) * self.factor(rate, t_from, t_to, shift)

    # ------------------------------------------------------------------ constructors and persistence
    @classmethod
    def constant(cls, doubling: float, doubling_se: float = 0.0, source: str = "given") -> "TemperatureLaw":
        """One doubling temperature for every pixel (``--doubling``)."""
        if not doubling > 0:
            raise InputError(f"doubling temperature {doubling}: give a positive number of °C (dark current doubles "
                             "every T_d degrees; 5–9 °C is typical of CCDs)")
        beta = 1.0 / doubling
        se = doubling_se * beta * beta
        return cls(0.0, LawPoint(1.0, beta, se, 0), [], [], source)

    def to_dict(self) -> dict[str, Any]:
        return {"format": LAW_FORMAT, "law": "rate ∝ 2^((T − T_ref)/T_d), T_d by rate class",
                "t_class_c": self.t_class, "bulk": self.bulk.to_dict(),
                "classes": [c.to_dict() for c in self.classes], "temperatures_c": self.temperatures,
                "source": self.source, "binning": list(self.binning) if self.binning else None}

    @classmethod
    def from_dict(cls, obj: dict[str, Any]) -> "TemperatureLaw":
        b = obj.get("binning")  # absent in files written before it was kept: unknown
        return cls(float(obj["t_class_c"]), LawPoint.from_dict(obj["bulk"]),
                   [LawPoint.from_dict(c) for c in obj.get("classes", [])],
                   [float(t) for t in obj.get("temperatures_c", [])], str(obj.get("source", "")),
                   (int(b[0]), int(b[1])) if b else None)

    def binning_warnings(self, binning: tuple[int, int] | None) -> list[str]:
        """Check that the law fits a series of ``binning`` (``(x, y)``; None: not stated): nothing when both agree
        or neither is known, a warning when only one is known.

        Raises
        ------
        InputError
            Both are known and differ, naming the law's file and both binnings: a binned pixel sums x·y pixels'
            dark charge, so its rates (and a hot-pixel threshold in ADU/s) and the rate classes of the law mean
            different pixels.
        """
        name = self.file or f"the temperature law ({self.source or 'given'})"
        if self.binning is not None and binning is not None and self.binning != binning:
            raise InputError(f"{name}: fitted on frames binned {_bins(self.binning)} but this series is binned "
                             f"{_bins(binning)}; a binned pixel sums several pixels' dark charge, so the law's rate "
                             "classes mean other pixels: save a law from a series of this binning (--save-law), or "
                             "give one doubling temperature (--doubling)")
        if (self.binning is None) != (binning is None):
            known = (f"the law's is {_bins(self.binning)}, the series' is not stated" if self.binning else
                     f"the series is binned {_bins(binning)}, the law's binning is not stated")  # type: ignore[arg-type]
            return [f"{name}: cannot check that the law was fitted on frames of this binning ({known}; a law file "
                    "written before the binning was kept has none)"]
        return []

    def save(self, path: str | os.PathLike, force: bool = False) -> Path:
        """Write the law as JSON (atomically)."""
        from forensics._shared.atomic import write_json

        return write_json(path, self.to_dict(), force=force)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "TemperatureLaw":
        """Read a law written by :meth:`save` (``forensics defects detect --save-law``)."""
        path = Path(path)
        try:
            obj = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise InputError(f"{path}: cannot read the temperature law ({exc})") from None
        if obj.get("format") != LAW_FORMAT:
            raise InputError(f"{path}: not a temperature law written by 'forensics defects detect --save-law' "
                             f"(format {obj.get('format')!r})")
        try:
            law = cls.from_dict(obj)
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise InputError(f"{path}: malformed temperature law ({exc})") from None
        law.file = str(path)
        return law


def _bins(binning: tuple[int, int]) -> str:
    return f"{binning[0]}×{binning[1]}"


# =========================================================================== fitting
def can_fit(groups: Sequence["GroupFit"]) -> bool:
    """Whether the groups span enough temperature to fit a law."""
    temps = [g.temperature_c for g in groups if g.temperature_c is not None]
    return len(temps) >= 2 and max(temps) - min(temps) >= MIN_SPAN_C


def fit_temperature_law(groups: Sequence["GroupFit"], pixels: np.ndarray | None = None,
                        min_class: int = MIN_CLASS) -> TemperatureLaw:
    """Fit the law from temperature groups of one sensor (see the module notes).

    Parameters
    ----------
    groups
        The series' groups (:class:`~forensics.defects.darkseries.GroupFit`), at two temperatures or more.
    pixels
        Flat boolean mask of the pixels to fit on (default all): e.g. half of them, to count hot pixels on the
        other half without the law having seen them.
    min_class
        Fewest pixels in a class of the hot tail.

    Raises
    ------
    InputError
        Fewer than two groups with known temperatures :data:`MIN_SPAN_C` apart.
    """
    if not can_fit(groups):
        raise InputError("the series has no two temperatures at least 1 °C apart: the temperature law cannot be fitted; "
                         "give a law from another series (--law) or a doubling temperature (--doubling)")
    groups = [g for g in groups if g.temperature_c is not None]
    temps = np.array([g.temperature_c for g in groups])
    t_se = np.array([g.temperature_se for g in groups])
    t_class = float(temps.mean())
    rates = np.stack([g.rate.astype(np.float64) for g in groups])
    valid = np.isfinite(rates).all(axis=0)
    if pixels is not None:
        valid &= np.asarray(pixels, bool).ravel()
    rates = rates[:, valid]
    medians = np.median(rates, axis=1)
    if (medians <= 0).any():
        raise InputError("a group's median dark rate is not positive: the bulk's temperature law cannot be fitted "
                         "(exposures too short for the dark signal to show above the read noise?)")
    med_se = np.array([g.median_rate_se for g in groups])
    cov = np.diag((med_se / (medians * math.log(2))) ** 2)
    beta, beta_se = _gls_slope(np.log2(medians), cov, temps - t_class, t_se)
    bulk_rate = float(np.median(medians * np.exp2(-beta * (temps - t_class))))
    bulk = LawPoint(bulk_rate, beta, beta_se, int(valid.sum()))
    carried = rates * np.exp2(-beta * (temps - t_class))[:, None]
    score = carried.mean(axis=0)
    common = np.array([g.median_rate_common_se for g in groups])
    errors = np.stack([g.rate_se.astype(np.float64) for g in groups])[:, valid]
    classes = _class_points(rates, errors, score, FIRST_CLASS * bulk_rate, temps - t_class, t_se, common, min_class)
    return TemperatureLaw(t_class, bulk, classes, temps.tolist(),
                          f"fitted on {len(groups)} temperature groups ({', '.join(f'{t:+.2f}' for t in temps)} °C)")


def _class_points(rates: np.ndarray, errors: np.ndarray, score: np.ndarray, start: float, dt: np.ndarray,
                  t_se: np.ndarray, common: np.ndarray, min_class: int) -> list[LawPoint]:
    top = float(score.max()) if score.size else start
    edges = [start]
    while edges[-1] <= top:
        edges.append(edges[-1] * CLASS_WIDTH)
    members = [np.flatnonzero((score >= lo) & (score < hi)) for lo, hi in zip(edges[:-1], edges[1:])]
    bounds = list(zip(edges[:-1], edges[1:]))
    merged: list[tuple[np.ndarray, float, float]] = []
    for idx, (lo, hi) in zip(members, bounds):
        if merged and merged[-1][0].size < min_class:
            prev, plo, _ = merged.pop()
            merged.append((np.concatenate([prev, idx]), plo, hi))
        else:
            merged.append((idx, lo, hi))
    if merged and merged[-1][0].size < min_class and len(merged) > 1:
        last, _, hi = merged.pop()
        prev, plo, _ = merged.pop()
        merged.append((np.concatenate([prev, last]), plo, hi))
    points = []
    for idx, lo, hi in merged:
        if idx.size < min_class:
            continue
        sub = rates[:, idx]
        means = sub.mean(axis=1)
        if (means <= 0).any():
            continue
        cov_means = np.atleast_2d(np.cov(sub)) / idx.size + np.diag(common ** 2)
        jac = np.diag(1.0 / (means * math.log(2)))
        beta, se = _gls_slope(np.log2(means), jac @ cov_means @ jac, dt, t_se)
        centre = float(np.exp(np.mean(np.log(score[idx]))))
        points.append(LawPoint(centre, beta, se, int(idx.size), lo, hi, _pixel_spread(sub, errors[:, idx], dt)))
    return points


def _pixel_spread(rates: np.ndarray, errors: np.ndarray, dt: np.ndarray) -> float | None:
    """How much the pixels' own β differ within a class: the spread of per-pixel slopes of log₂ rate on
    temperature, less what their rates' noise explains (None where a rate is not positive)."""
    positive = (rates > 0).all(axis=0)
    if positive.sum() < 3:
        return None
    logs = np.log2(rates[:, positive])
    u = dt - dt.mean()
    weights = u / (u * u).sum()
    slopes = weights @ logs
    noise = (weights[:, None] ** 2 * (errors[:, positive] / (rates[:, positive] * math.log(2))) ** 2).sum(axis=0)
    excess = float(np.var(slopes, ddof=1) - noise.mean())
    return math.sqrt(excess) if excess > 0 else 0.0


def _gls_slope(y: np.ndarray, cov: np.ndarray, x: np.ndarray, x_se: np.ndarray) -> tuple[float, float]:
    """Slope of y = α + β·x by generalised least squares, the x errors folded in as β²·σ_x² (iterated)."""
    design = np.column_stack([np.ones_like(x), x])
    beta = 0.0
    for _ in range(4):
        total = cov + np.diag((beta * x_se) ** 2)
        weight = np.linalg.pinv(total)
        info = design.T @ weight @ design
        inv = np.linalg.pinv(info)
        coef = inv @ design.T @ weight @ y
        beta = float(coef[1])
    se = math.sqrt(max(float(inv[1, 1]), 0.0))
    if y.size > 2:  # more groups than parameters: widen by the scatter about the line when it exceeds the model
        resid = y - design @ coef
        chi2 = float(resid @ weight @ resid) / (y.size - 2)
        se *= math.sqrt(max(chi2, 1.0))
    return beta, se
