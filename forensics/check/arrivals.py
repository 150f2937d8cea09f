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
from forensics.sensor.catalogue import PARTIAL, STUCK, DefectCatalogue
from forensics.sensor.model import Device, Effect, SensorModel
from forensics.stats.counts import poisson_deviance


def _unique_sites(cat: DefectCatalogue) -> np.ndarray:
    return np.unique(np.column_stack([cat.y, cat.x]), axis=0) if len(cat) else np.zeros((0, 2), int)


class DefectCounts:
    """Cumulative detected counts per kind at every epoch, the sites, and the arrival model's predictions."""

    def __init__(self, meas: Measurements, detection: Detection, bit_depth: int):
        self.meas = meas
        self.shape = meas.shape
        self.window = meas.window
        self.bit_depth = bit_depth
        self.times = times = meas.epoch_times
        self.detection = detection
        self.threshold = {PARTIAL: detection.threshold, STUCK: -np.inf}
        cat = self.catalogue = detection.catalogue
        self.counts = {k: np.array([np.sum((cat.kind == k) & (cat.onset <= t)) for t in times]) for k in (PARTIAL, STUCK)}
        self.sites = _unique_sites(cat.at(times[-1]) if len(cat) else cat)  # (n, 2): row, column
        self.first_sites = _unique_sites(cat.at(times[0]) if len(cat) else cat)
        interior = meas.interior
        self.area_fraction = float(interior.sum() / interior.size)
        self.interior_mp = interior.sum() / 1e6

    # ------------------------------------------------------------------ what arrival effects ask
    def amplitude_max(self, kind: int, default: float) -> float:
        """Largest detected amplitude of ``kind``, unbiased as (n + 1)/n · max (``default`` when none)."""
        cat = self.catalogue
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

    def site_rate(self) -> float:
        """The defective sites of the last epoch (every kind, interior) per megapixel per year between the first
        and last epoch: what a fraction of the sites, read off their pattern (Ripley's K), arrived at."""
        t = self.times
        if len(t) < 2 or t[-1] <= t[0]:
            return 0.0
        return float(len(self.sites) / (t[-1] - t[0]) / self.interior_mp)

    def cluster_excess(self) -> tuple[float, float]:
        """Thomas-cluster excess of Ripley's K at the last epoch: (A, σ) by minimum contrast."""
        if len(self.sites) < 10:
            return 0.0, 1.0
        radii = np.array([1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 12.0])
        k = sp.ripley_k(self.sites[:, 1], self.sites[:, 0], self.window, radii)
        return sp.fit_thomas_excess(radii, k)

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

    def simulate(self, effects: Sequence[Effect], rng: np.random.Generator) -> tuple[dict[int, np.ndarray], np.ndarray]:
        """One Monte-Carlo draw of the arrival model: counts per kind at each epoch and the sites at the last."""
        dev = self._model(effects).realize(rng, self.times)
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

    def ripley_l(self, pts: np.ndarray) -> np.ndarray:
        if len(pts) < 2:
            return np.full(len(sp.DEFAULT_RADII), np.nan)
        return sp.ripley_l(pts[:, 1], pts[:, 0], self.window, sp.DEFAULT_RADII)

    def simulate_null(self, arrivals: Sequence[Effect], expected: dict[int, np.ndarray], rng: np.random.Generator,
                      n_sim: int) -> tuple[dict[str, Any], dict[str, Any] | None]:
        """Monte-Carlo draws of the fitted arrival model: the count distribution (with the deviance and Pearson
        statistic of each draw) and, with at least 10 sites, the Ripley-L envelope."""
        counts: dict[int, list[np.ndarray]] = {PARTIAL: [], STUCK: []}
        ls, devs, pearson = [], [], []
        _, exp = self.increments(expected)
        exp = np.maximum(exp, 1e-9)
        for _ in range(n_sim):
            c, pts = self.simulate(arrivals, rng)
            for k in counts:
                counts[k].append(c[k])
            ls.append(self.ripley_l(pts))
            o = np.concatenate([np.diff(c[PARTIAL]), np.diff(c[STUCK])]).astype(float)
            devs.append(poisson_deviance(o, exp))
            pearson.append(float(np.sum((o - exp) ** 2 / exp)))
        sims = {"counts": {k: np.array(v) for k, v in counts.items()}, "deviance": np.array(devs),
                "pearson": np.array(pearson)}
        ls = np.array(ls)
        spatial = None
        if len(self.sites) >= 10 and np.isfinite(ls).all():
            spatial = {"sims": ls, "mean": ls.mean(0), "sd": np.maximum(ls.std(0, ddof=1), 1e-9)}
        return sims, spatial
