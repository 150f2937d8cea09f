"""The evidence a model is fitted to: measurements, detected defects, pixel data and the forward models.

:class:`Evidence` is built once per dataset and does not change while models are fitted to it.  It is
made of cohesive parts:

* :attr:`Evidence.meas` — the per-condition statistics (:mod:`forensics.check.measurements`);
* :attr:`Evidence.defects` — defect counts and sites for the growth and spatial channels, and the arrival
  model's predictions (:class:`~forensics.check.arrivals.DefectCounts`);
* :meth:`Evidence.pixels` — per catalogue of pixel classes, the pixel and variance channels' data
  (:class:`~forensics.check.pixels.PixelData`);
* :attr:`Evidence.predictor` — the pixel channel's forward model (:class:`~forensics.check.prediction.Predictor`);
* :attr:`Evidence.streams` — the Monte-Carlo streams (:class:`~forensics.check.streams.Streams`).

It satisfies :class:`forensics.sensor.evidence.Evidence`, the protocol effects' own estimators use.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from forensics._shared.rng import RngLike
from forensics.check.arrivals import DefectCounts
from forensics.check.detection import detect_defects
from forensics.check.measurements import Measurements
from forensics.check.pixels import PixelData, pixel_data
from forensics.check.prediction import Predictor
from forensics.check.singles import single_frames, singles_note, without_hits
from forensics.check.streams import Streams
from forensics.sensor.catalogue import DefectCatalogue
from forensics.sensor.evidence import PairExcess
from forensics.sensor.model import Device, Effect

#: z of the look-back that dates the pixel classes' onsets.
CLASS_LOOK_BACK_Z = 3.0


class EffectQuestions:
    """The answers effects may ask for (:class:`forensics.sensor.evidence.Evidence`), from :attr:`defects`."""

    defects: DefectCounts
    shape: tuple[int, int]

    def amplitude_max(self, kind: int, default: float) -> float:
        return self.defects.amplitude_max(kind, default)

    def detect_fraction(self, kind: int, amplitude: float) -> float:
        return self.defects.detect_fraction(kind, amplitude)

    def amplitude_se(self, kind: int) -> float | None:
        return self.defects.amplitude_se(kind)

    def arrival_rate(self, kind: int) -> float:
        return self.defects.arrival_rate(kind)

    def site_intensity(self) -> float:
        return self.defects.site_intensity()

    def site_rate(self) -> float:
        return self.defects.site_rate()

    def cluster_excess(self) -> tuple[float, float]:
        return self.defects.cluster_excess()

    def co_arrival_excess(self) -> PairExcess:
        return self.defects.co_arrival_excess()

    def distinct_pair_share(self, mean_members: float) -> float:
        return self.defects.distinct_pair_share(mean_members)

    def co_arrival_draws(self, mean_members: float) -> np.ndarray:
        return self.defects.co_arrival_draws(mean_members)


class Evidence(EffectQuestions):
    """Measurements reduced for checking: detected defects, pixel data per catalogue, forward models."""

    def __init__(self, meas: Measurements, rng: RngLike = 0, n_sim: int = 199, black_level: float | None = None):
        self.meas = meas
        #: the black level stated by the files' metadata or the manifest (None: the fit estimates it)
        self.black_level = black_level
        self.streams = Streams(rng, n_sim)
        self.shape = meas.shape
        self.window = meas.window
        #: bit depth of the fitted model: effects that scale with full scale (a response curve) must see the data's
        self.bit_depth = int(np.clip(round(math.log2(meas.full_scale + 1)), 1, 16))
        self.times = times = meas.epoch_times
        self.notes: list[str] = []
        # --- pixel channel: the repeated conditions (fitted on half a, scored on half b), then the single dark
        # frames (fitted only: :mod:`forensics.check.singles`)
        self.rep = meas.fitted
        self.rgroups = [meas.groups[g] for g in self.rep]
        self.censored = np.stack([meas.censored(g) for g in self.rep])
        n_rep = len(meas.repeated)
        #: the single frames' noise law, cosmic-ray hits and floor (None without single dark frames)
        self.singles = single_frames(meas, ~self.censored)
        readable = ~self.censored  # border included (the dark frames' patterns are measured there)
        if self.singles is not None:
            readable[n_rep:] &= ~self.singles.hits if self.singles.law is not None else False
            self.notes += singles_note(meas, self.singles)
        self._readable = readable
        #: the measurements defect detection sees (:func:`~forensics.check.singles.without_hits`)
        self.detect_meas = without_hits(meas, self.singles)
        fit_ok = meas.interior[None] & readable
        #: (R, H, W) the pixel means the pixel channel fits (cosmic-ray hits and censored means excluded)
        self.fit_usable = fit_ok
        #: (R, H, W) the pixel means it scores: those of the repeated conditions (the single frames have no
        #: held-out half)
        self.usable = fit_ok & (np.arange(len(self.rep)) < n_rep)[:, None, None]
        # --- detection: classes from every frame of an epoch; counts from the conditions every epoch has
        # (cosmic-ray hits of the single frames replaced by their pixel's line: a one-frame excess is no defect)
        seen = self.detect_meas
        self.by_epoch_all = [[g.index for g in meas.groups if g.epoch == e] for e in range(len(times))]
        self.initial_catalogue = detect_defects(seen, self.by_epoch_all, common_threshold=False,
                                                look_back_z=CLASS_LOOK_BACK_Z).catalogue
        conditions = [{g.condition for g in meas.groups if g.epoch == e} for e in range(len(times))]
        common = set.intersection(*conditions) if conditions else set()
        if not common:
            common = set().union(*conditions)
            if len(times) > 1:
                self.notes.append("no condition is measured at every epoch: defect counts use every frame "
                                  "(detection sensitivity may differ between epochs)")
        self.reference_conditions = sorted(common, key=str)
        by_epoch_ref = [[g.index for g in meas.groups if g.epoch == e and g.condition in common]
                        for e in range(len(times))]
        self.defects = DefectCounts(seen, detect_defects(seen, by_epoch_ref, common_threshold=True), self.bit_depth,
                                    rng=rng)
        self.predictor = Predictor(meas, self.rgroups)
        self._initial_pixels: PixelData | None = None
        self._simulations: dict[Any, Any] = {}

    # ------------------------------------------------------------------ arrival simulations
    def simulations(self, stream: int, effects: Sequence[Effect], simulate: Callable[[], Any]) -> Any:
        """``simulate()``'s result, computed once per Monte-Carlo ``stream`` and arrival ``effects`` (their values).

        Why: the arrival effects are fitted to the defect counts alone, so every model of a ``--auto`` path has
        the same fitted arrivals, and their null simulations and the arrival candidates' simulated signatures
        (:attr:`streams`: a fresh, identical generator per stream at every call) are the same numbers — ≈ 10 % of
        the hidden-effect check, once per model.  Unhashable parameter values: not kept."""
        try:
            key = (stream, tuple((e.key, tuple(sorted(e.params().items()))) for e in effects))
            hash(key)
        except TypeError:
            return simulate()
        if key not in self._simulations:
            self._simulations[key] = simulate()
        return self._simulations[key]

    # ------------------------------------------------------------------ pixel data
    def pixels(self, catalogue: DefectCatalogue | None = None) -> PixelData:
        """Pixel data for the classes of ``catalogue`` (default: the defects detected from the data alone)."""
        if catalogue is None or catalogue is self.initial_catalogue:
            if self._initial_pixels is None:
                self._initial_pixels = pixel_data(self.meas, self.rgroups, self.times, self.usable,
                                                  self.initial_catalogue, self._readable, self.fit_usable,
                                                  self.singles)
            return self._initial_pixels
        return pixel_data(self.meas, self.rgroups, self.times, self.usable, catalogue, self._readable,
                          self.fit_usable, self.singles)

    def redetect(self, device: Device) -> DefectCatalogue:
        """Detect the pixel classes again against the model's prediction for defect-free pixels, so that fixed
        patterns the model now explains (a per-pixel gain, column offsets) no longer raise the threshold."""
        return detect_defects(self.detect_meas, self.by_epoch_all, common_threshold=False, look_back_z=CLASS_LOOK_BACK_Z,
                              reference=self.predictor.reference(device)).catalogue
