"""The growth and spatial channels: detected defect counts and sites, and the arrival model's predictions.

:class:`DefectCounts` holds what the counts channel measured — defects detected at every epoch on the
conditions common to all epochs with one threshold — and answers the questions arrival effects ask when
they fit themselves (:class:`forensics.sensor.evidence.Evidence`): the largest detected amplitude, the
fraction of amplitudes above the threshold, the arrival rate, the site intensity, the cluster excess.
It also predicts: expected counts of a list of arrival effects, and Monte-Carlo draws of them.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

import forensics.stats.spatial as sp
from forensics.check.detection import Detection
from forensics.check.measurements import Measurements
from forensics.check.streams import PAIR_EXCESS_STREAM
from forensics.sensor.catalogue import PARTIAL, STUCK
from forensics.sensor.evidence import PairExcess
from forensics._shared.rng import RngLike, keyed_generator
from forensics.sensor.model import Device, Effect, SensorModel
from forensics.stats.counts import poisson_deviance


#: The pair excess's parametric bootstrap: its number of refits: the spread's standard error to ≈ 5 % (1/√(2·200)).
PAIR_EXCESS_DRAWS = 200

#: Radii (px) at which clusters are fitted: the spatial channel's, and one more to see the excess level off
CLUSTER_RADII = np.append(sp.DEFAULT_RADII, 12.0)


def _sites_with_epochs(rows: np.ndarray, cols: np.ndarray, epochs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique sites (row, column) and the first epoch each was seen at (a site may carry several records)."""
    if len(rows) == 0:
        return np.zeros((0, 2), int), np.zeros(0, int)
    sites, inverse = np.unique(np.column_stack([rows, cols]), axis=0, return_inverse=True)
    first = np.full(len(sites), np.iinfo(np.int64).max)
    np.minimum.at(first, inverse.ravel(), np.asarray(epochs, np.int64))
    return sites, first


def uniform_maximum(values: np.ndarray, floor: float = 0.0) -> tuple[float, float]:
    """The upper end a of uniform values (the paper's a_ps = max d), and its standard error.

    The estimate is (n + 1)/n times the largest of the n values, unbiased for U[0, a].  Detected amplitudes are
    uniform between the detection threshold ``floor`` and a, where its standard deviation is (a − floor)/√(n(n + 2))
    and its bias floor/n (smaller than that by √n: kept as it is, which the fits were validated with).  The
    largest value's distribution is skewed, but (a − max)·n/(a − floor) tends to Exp(1), so estimate ± 1.96 se
    covers 1 − e^{−2.96} ≈ 95 %.

    Examples
    --------
    >>> a, se = uniform_maximum(np.linspace(1.0, 99.0, 98), floor=0.0)
    >>> round(a, 2), round(se, 2)
    (100.01, 1.01)
    """
    values = np.asarray(values, float)
    n = values.size
    estimate = float(values.max() * (n + 1) / n)
    return estimate, float(max(estimate - floor, 0.0) / np.sqrt(n * (n + 2.0)))


class DefectCounts:
    """Cumulative detected counts per kind at every epoch, the sites, and the arrival model's predictions."""

    def __init__(self, meas: Measurements, detection: Detection, bit_depth: int, rng: RngLike = 0):
        self.meas = meas
        self.shape = meas.shape
        self.window = meas.window
        self.bit_depth = bit_depth
        self.times = times = meas.epoch_times
        self.detection = detection
        self.threshold = {PARTIAL: detection.threshold, STUCK: -np.inf}
        cat = self.catalogue = detection.catalogue
        self.counts = {k: np.array([np.sum((cat.kind == k) & (cat.onset <= t)) for t in times]) for k in (PARTIAL, STUCK)}
        last = cat.at(times[-1]) if len(cat) else cat
        # (n, 2): row, column; and the epoch each site first appeared at (0: present at the first epoch)
        self.sites, self.site_epochs = _sites_with_epochs(last.y, last.x, self.epoch_of(last.onset))
        first = cat.at(times[0]) if len(cat) else cat
        self.first_sites = _sites_with_epochs(first.y, first.x, np.zeros(len(first), int))[0]
        interior = meas.interior
        self.area_fraction = float(interior.sum() / interior.size)
        self.interior_mp = interior.sum() / 1e6
        self._pair_excess: PairExcess | None = None
        self._rng = rng  #: the root of the check's streams (the pair excess's bootstrap draws from its own key)
        self._pair_draws: dict[Any, Any] = {}  #: the pair excess's simulations, per argument

    def epoch_of(self, onset: np.ndarray) -> np.ndarray:
        """The epoch at which a defect of this ``onset`` is first seen: the first epoch time ≥ the onset."""
        t = np.asarray(self.times, float)
        tol = 1e-9 * (1.0 + np.abs(t).max()) if len(t) else 0.0  # detected onsets are epoch times themselves
        return np.searchsorted(t, np.asarray(onset, float) - tol, side="left")

    # ------------------------------------------------------------------ what arrival effects ask
    def amplitude_max(self, kind: int, default: float) -> float:
        """Largest detected amplitude of ``kind``, unbiased as (n + 1)/n · max (``default`` when none)."""
        cat = self.catalogue
        amp = cat.amplitude[cat.kind == kind]
        if kind == STUCK:
            return float(self.meas.full_scale)
        if amp.size == 0:
            return float(default)
        return uniform_maximum(amp, self._floor(kind))[0]

    def amplitude_se(self, kind: int) -> float | None:
        """Standard error of :meth:`amplitude_max` (:func:`uniform_maximum`); None for stuck pixels (full scale,
        no estimate) and where none was detected."""
        cat = self.catalogue
        amp = cat.amplitude[cat.kind == kind]
        if kind == STUCK or amp.size == 0:
            return None
        return uniform_maximum(amp, self._floor(kind))[1]

    def _floor(self, kind: int) -> float:
        """The lowest amplitude detection lets through: the threshold, where there is one."""
        tau = self.threshold.get(kind, -np.inf)
        return float(tau) if np.isfinite(tau) and tau > 0 else 0.0

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

    def site_rate(self) -> float:
        """The defective sites of the last epoch (every kind, interior) per megapixel per year between the first
        and last epoch: what a fraction of the sites, read off their pattern (Ripley's K), arrived at."""
        t = self.times
        if len(t) < 2 or t[-1] <= t[0]:
            return 0.0
        return float(len(self.sites) / (t[-1] - t[0]) / self.interior_mp)

    def co_arrival_excess(self) -> PairExcess:
        """Pairs of sites that arrived at the same epoch after the first, within r of each other, beyond those of
        sites placed independently (exact on the pixel grid): a Thomas fit, per megapixel per year (computed once:
        the sites are the data's)."""
        if self._pair_excess is None:
            self._pair_excess = self._fit_pair_excess()
        return self._pair_excess

    def _fit_pair_excess(self) -> PairExcess:
        t = self.times
        new = self.site_epochs > 0
        if new.sum() < 2 or len(t) < 2 or t[-1] <= t[0]:
            return PairExcess(0.0, 1.0, 0.0, 0.0)
        exposure = float((t[-1] - t[0]) * self.interior_mp)
        radii = CLUSTER_RADII
        pts, epochs = self.sites[new], self.site_epochs[new]
        observed = sp.co_arrival_pairs(pts[:, 1], pts[:, 0], epochs, radii)
        per_epoch = np.bincount(epochs).astype(float)
        x0, y0, x1, y1 = self.window
        chance = float(np.sum(per_epoch * (per_epoch - 1) / 2)) * sp.lattice_pair_fraction(int(x1 - x0), int(y1 - y0),
                                                                                          radii)
        pairs, sigma = sp.fit_pair_excess(radii, observed - chance, chance)
        near = float(np.interp(min(3.0 * sigma, radii[-1]), radii, chance))  # where the clusters' pairs lie
        return PairExcess(float(pairs / exposure), sigma, near, exposure, tuple(radii.tolist()),
                          tuple(np.asarray(chance, float).tolist()))

    def distinct_pair_share(self, mean_members: float) -> float:
        """:func:`forensics.stats.spatial.distinct_pair_share` at the fitted spread, from the check's own stream
        (the same value for the same argument)."""
        key = ("share", round(float(mean_members), 12))
        if key not in self._pair_draws:
            self._pair_draws[key] = sp.distinct_pair_share(mean_members, self.co_arrival_excess().sigma,
                                                           keyed_generator(self._rng, PAIR_EXCESS_STREAM, 1))
        return self._pair_draws[key]

    def co_arrival_draws(self, mean_members: float) -> np.ndarray:
        """Parametric bootstrap of the pair excess (:func:`forensics.stats.spatial.pair_excess_draws`) for
        clusters of ``mean_members`` detected members: ``(draws, 2)`` refits (Π*, σ*), Π in pairs (not per
        megapixel-year).  From the check's own stream, afresh for every argument: the same draws whatever asked
        before; kept per argument."""
        fit = self.co_arrival_excess()
        key = ("draws", round(float(mean_members), 12))
        if key not in self._pair_draws:
            self._pair_draws[key] = sp.pair_excess_draws(
                np.asarray(fit.radii, float), fit.rate * fit.exposure, fit.sigma, mean_members,
                np.asarray(fit.chance_within, float), keyed_generator(self._rng, PAIR_EXCESS_STREAM), PAIR_EXCESS_DRAWS)
        return self._pair_draws[key]

    def cluster_excess(self) -> tuple[float, float]:
        """Thomas-cluster excess of Ripley's K at the last epoch: (A, σ) by minimum contrast."""
        if len(self.sites) < 10:
            return 0.0, 1.0
        k = sp.ripley_k(self.sites[:, 1], self.sites[:, 0], self.window, CLUSTER_RADII)
        return sp.fit_thomas_excess(CLUSTER_RADII, k)

    # ------------------------------------------------------------------ predictions
    def _model(self, effects: Sequence[Effect]) -> SensorModel:
        return SensorModel(shape=self.shape, bit_depth=self.bit_depth, effects=[dataclasses.replace(e) for e in effects],
                           t0=float(self.times[0]))

    def expected_counts(self, effects: Sequence[Effect]) -> dict[int, np.ndarray]:
        """Expected cumulative detected records per kind at every epoch (interior), from the arrival effects."""
        dev = Device(model=self._model(effects), times=tuple(float(t) for t in self.times))
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

    def simulate(self, effects: Sequence[Effect],
                 rng: np.random.Generator) -> tuple[dict[int, np.ndarray], np.ndarray, np.ndarray]:
        """One Monte-Carlo draw of the arrival model: counts per kind at each epoch, the sites at the last and the
        epoch each site first appeared at (the sites of the first epoch are the observed ones, epoch 0)."""
        dev = self._model(effects).realize(rng, self.times)
        cat = dev.catalogue
        interior = self.meas.interior
        if len(cat):
            keep = interior[cat.y, cat.x] & ((cat.kind == STUCK) | (cat.amplitude > self.threshold[PARTIAL]))
            cat = cat.select(keep)
        counts = {k: np.array([np.sum((cat.kind == k) & (cat.onset <= t)) for t in self.times]) + self.counts[k][0]
                  for k in (PARTIAL, STUCK)}
        last = cat.at(self.times[-1])
        rows = np.concatenate([np.asarray(last.y, int), self.first_sites[:, 0]])
        cols = np.concatenate([np.asarray(last.x, int), self.first_sites[:, 1]])
        epochs = np.concatenate([self.epoch_of(last.onset), np.zeros(len(self.first_sites), int)])
        pts, first = _sites_with_epochs(rows, cols, epochs)
        return counts, pts, first

    def ripley_l(self, pts: np.ndarray) -> np.ndarray:
        if len(pts) < 2:
            return np.full(len(sp.DEFAULT_RADII), np.nan)
        return sp.ripley_l(pts[:, 1], pts[:, 0], self.window, sp.DEFAULT_RADII)

    def spatial_statistic(self, pts: np.ndarray, epochs: np.ndarray) -> np.ndarray:
        """The spatial channel's statistic: Ripley's L of the sites at :data:`~forensics.stats.spatial.DEFAULT_RADII`,
        then the pairs within the same radii that arrived at the same epoch after the first
        (:func:`~forensics.stats.spatial.co_arrival_pairs`).

        Why both: L sees clustering of the final pattern, however it arose; the co-arrival pairs see defects that
        arrive together (a cluster's members appear at once), free of the noise of the pairs that arrived apart —
        where accelerating growth adds independent sites, L's excess drowns (z ≈ 5 against ≈ 10 alone) while the
        co-arrival count keeps it."""
        new = epochs > 0
        pairs = sp.co_arrival_pairs(pts[new, 1], pts[new, 0], epochs[new], sp.DEFAULT_RADII)
        return np.concatenate([self.ripley_l(pts), pairs])

    def observed_spatial(self) -> np.ndarray:
        """:meth:`spatial_statistic` of the detected sites."""
        return self.spatial_statistic(self.sites, self.site_epochs)

    def simulate_null(self, arrivals: Sequence[Effect], expected: dict[int, np.ndarray], rng: np.random.Generator,
                      n_sim: int) -> tuple[dict[str, Any], dict[str, Any] | None]:
        """Monte-Carlo draws of the fitted arrival model: the count distribution (with the deviance and Pearson
        statistic of each draw) and, with at least 10 sites, the Ripley-L envelope."""
        counts: dict[int, list[np.ndarray]] = {PARTIAL: [], STUCK: []}
        ls, devs, pearson = [], [], []
        _, exp = self.increments(expected)
        exp = np.maximum(exp, 1e-9)
        for _ in range(n_sim):
            c, pts, epochs = self.simulate(arrivals, rng)
            for k in counts:
                counts[k].append(c[k])
            ls.append(self.spatial_statistic(pts, epochs))
            o = np.concatenate([np.diff(c[PARTIAL]), np.diff(c[STUCK])]).astype(float)
            devs.append(poisson_deviance(o, exp))
            pearson.append(float(np.sum((o - exp) ** 2 / exp)))
        sims = {"counts": {k: np.array(v) for k, v in counts.items()}, "deviance": np.array(devs),
                "pearson": np.array(pearson)}
        ls = np.array(ls)
        spatial = None
        if len(self.sites) >= 10 and np.isfinite(ls).all():
            spatial = {"sims": ls, "mean": ls.mean(0), "sd": spatial_sd(ls)}
        return sims, spatial


def spatial_sd(sims: np.ndarray) -> np.ndarray:
    """The spread of each component of the simulated spatial statistics, floored: at 10⁻⁹ for Ripley's L and at
    one pair for the co-arrival counts (rare pairs, absent from most draws, would otherwise make one observed pair
    a deviation of thousands of σ)."""
    sd = sims.std(0, ddof=1)
    floor = np.concatenate([np.full(len(sp.DEFAULT_RADII), 1e-9), np.ones(sims.shape[1] - len(sp.DEFAULT_RADII))])
    return np.maximum(sd, floor)
