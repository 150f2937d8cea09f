"""Count statistics shared by every domain: exact intervals, Poisson regression, trend and deviance.

One implementation of each, used by defect growth and dating (:mod:`forensics.defects`), the model
check's growth channel (:mod:`forensics.check`) and validation coverage (:mod:`forensics.validate`).

* exact intervals: Garwood (Poisson mean), Clopper–Pearson and mid-p (binomial proportion);
* :func:`poisson_glm`: Poisson regression with log link and an exposure offset (IRLS);
* :func:`trend_test`: likelihood-ratio test of a constant rate against a log-linear trend in time;
* :func:`laplace_trend_z`: the grouped Laplace test of a constant rate (a z statistic, no fit needed);
* :func:`poisson_deviance`: the deviance of observed against expected counts.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

#: Default confidence level of every interval.
LEVEL = 0.95


def garwood(k: int, level: float = LEVEL) -> tuple[float, float]:
    """Exact (Garwood) two-sided interval for the mean of a Poisson count ``k``.

    ``[χ²_{α/2}(2k)/2, χ²_{1−α/2}(2k+2)/2]``, lower bound 0 for ``k = 0``.
    """
    from scipy import stats  # here, not at import: scipy.stats costs 0.3 s, and the model check needs none of it

    if k < 0:
        raise ValueError("a Poisson count cannot be negative")
    alpha = 1.0 - level
    lo = 0.0 if k == 0 else float(stats.chi2.ppf(alpha / 2, 2 * k) / 2)
    hi = float(stats.chi2.ppf(1 - alpha / 2, 2 * k + 2) / 2)
    return lo, hi


def clopper_pearson(x: int, n: int, level: float = LEVEL) -> tuple[float, float]:
    """Exact (Clopper–Pearson) interval for a binomial proportion x/n."""
    from scipy import stats  # here, not at import: scipy.stats costs 0.3 s, and the model check needs none of it

    alpha = 1.0 - level
    if n == 0:
        return 0.0, 1.0
    lo = 0.0 if x == 0 else float(stats.beta.ppf(alpha / 2, x, n - x + 1))
    hi = 1.0 if x == n else float(stats.beta.ppf(1 - alpha / 2, x + 1, n - x))
    return lo, hi


def midp_binomial(x: int, n: int, level: float = LEVEL) -> tuple[float, float]:
    """Mid-p exact interval for a binomial proportion: P(X > x) + ½P(X = x) = α/2 and its mirror.

    Less conservative than Clopper–Pearson; its coverage averages close to the
    nominal level (used for dating, where Clopper–Pearson's excess width adds up).
    """
    from scipy import stats  # here, not at import: scipy.stats costs 0.3 s, and the model check needs none of it
    from scipy.optimize import brentq

    alpha = 1.0 - level
    if n == 0:
        return 0.0, 1.0

    def upper_tail(p: float) -> float:  # P(X > x) + ½P(X = x) under p, increasing in p
        return float(stats.binom.sf(x, n, p) + 0.5 * stats.binom.pmf(x, n, p))

    lo = 0.0 if x == 0 else brentq(lambda p: upper_tail(p) - alpha / 2, 1e-15, 1 - 1e-15)
    hi = 1.0 if x == n else brentq(lambda p: upper_tail(p) - (1 - alpha / 2), 1e-15, 1 - 1e-15)
    return float(lo), float(hi)


# =========================================================================== the paper, as written


@dataclass
class PoissonFit:
    """A Poisson GLM with log link: log μ = log(exposure) + X·β."""

    beta: np.ndarray
    cov: np.ndarray
    deviance: float
    pearson: float
    df: int


def poisson_glm(counts: np.ndarray, exposure: np.ndarray, design: np.ndarray, iterations: int = 100) -> PoissonFit:
    """Fit a Poisson regression with an exposure offset by iteratively reweighted least squares."""
    y = np.asarray(counts, float)
    offset = np.log(np.asarray(exposure, float))
    x = np.asarray(design, float)
    beta = np.zeros(x.shape[1])
    beta[0] = math.log(max(y.sum(), 0.5) / np.exp(offset).sum())
    for _ in range(iterations):
        eta = offset + x @ beta
        mu = np.exp(eta)
        z = eta - offset + (y - mu) / mu
        w = mu
        xtw = x.T * w
        new = np.linalg.solve(xtw @ x, xtw @ z)
        if np.max(np.abs(new - beta)) < 1e-10:
            beta = new
            break
        beta = new
    mu = np.exp(offset + x @ beta)
    with np.errstate(divide="ignore", invalid="ignore"):
        dev = 2 * np.sum(np.where(y > 0, y * np.log(y / mu), 0.0) - (y - mu))
    cov = np.linalg.inv((x.T * mu) @ x)
    pearson = float(np.sum((y - mu) ** 2 / mu))
    return PoissonFit(beta, cov, float(dev), pearson, int(len(y) - x.shape[1]))


@dataclass
class TrendTest:
    """Test of a constant arrival rate (linear growth of the cumulative count) from ≥ 3 epochs."""

    slope: float
    slope_ci: tuple[float, float]
    lr_statistic: float
    p_value: float
    dispersion: float
    p_dispersion: float
    linear: bool

    def to_dict(self) -> dict[str, Any]:
        return {"log_rate_slope_per_year": self.slope, "slope_ci": list(self.slope_ci),
                "lr_statistic": self.lr_statistic, "p_value": self.p_value, "dispersion": self.dispersion,
                "p_dispersion": self.p_dispersion, "linear_growth_consistent": self.linear,
                "test": "likelihood ratio, Poisson regression of new defects per interval on time (log link, "
                        "exposure offset): slope 0 = constant rate = linear growth"}


def trend_test(new_counts: Sequence[int], times: Sequence[float], area_mp: float, level: float = LEVEL) -> TrendTest | None:
    """LR test of slope = 0 in log(rate) = b₀ + b₁·(interval midpoint − mean); None with < 2 intervals."""
    from scipy import stats  # here, not at import: scipy.stats costs 0.3 s, and the model check needs none of it

    counts = np.asarray(new_counts, float)
    t = np.asarray(times, float)
    if len(counts) < 2:
        return None
    exposure = area_mp * np.diff(t)
    mid = (t[1:] + t[:-1]) / 2
    mid = mid - np.average(mid, weights=exposure)
    z = stats.norm.ppf(0.5 + level / 2)
    if counts.sum() == 0:
        return TrendTest(0.0, (-math.inf, math.inf), 0.0, 1.0, float("nan"), 1.0, True)
    full = poisson_glm(counts, exposure, np.column_stack([np.ones_like(mid), mid]))
    null = poisson_glm(counts, exposure, np.ones((len(counts), 1)))
    lr = max(0.0, null.deviance - full.deviance)
    p = float(stats.chi2.sf(lr, 1))
    se = math.sqrt(full.cov[1, 1])
    disp = null.pearson / max(null.df, 1)
    p_disp = float(stats.chi2.sf(null.pearson, null.df)) if null.df > 0 else 1.0
    slope = float(full.beta[1])
    return TrendTest(slope, (slope - z * se, slope + z * se), lr, p, disp, p_disp, p >= 1 - level)


def poisson_deviance(obs: np.ndarray, exp: np.ndarray) -> float:
    """Poisson deviance 2·Σ[o·log(o/e) − (o − e)] of observed counts against expected ones (e floored at 1e-12)."""
    obs = np.asarray(obs, float)
    exp = np.maximum(np.asarray(exp, float), 1e-12)
    term = np.where(obs > 0, obs * np.log(np.where(obs > 0, obs, 1) / exp), 0.0)
    return float(2.0 * np.sum(term - (obs - exp)))


def laplace_trend_z(new_counts: Sequence[float], times: Sequence[float]) -> float | None:
    """Grouped Laplace test of a constant arrival rate: z = (Σ dᵢ·mᵢ − n·m̄) / √(n·v) ~ N(0, 1).

    ``new_counts[i]`` arrivals fell in (``times[i]``, ``times[i+1]``]; under a constant rate each arrival
    time is uniform over the span, so its interval midpoint ``m`` has mean m̄ and variance v (the spread of
    the midpoints weighted by interval length, plus the within-interval variance Δt²/12).  z > 0 means
    arrivals late in the span (an accelerating rate).  None without arrivals or without a span.
    """
    t = np.asarray(times, float)
    d = np.asarray(new_counts, float)
    n = float(d.sum())
    if n <= 0 or len(t) < 2 or t[-1] <= t[0]:
        return None
    mid = (t[1:] + t[:-1]) / 2
    weight = np.diff(t) / (t[-1] - t[0])
    mbar = float(np.sum(weight * mid))
    var = float(np.sum(weight * (mid - mbar) ** 2) + np.sum(weight * np.diff(t) ** 2) / 12)
    return float((np.sum(d * mid) - n * mbar) / math.sqrt(n * var))
