"""Signatures: how a candidate effect (not in the model) would move each channel's statistics.

The generic signature is a finite difference through the effect's own ``apply`` (pixel channel),
``variance`` (variance channel) or ``expected_arrivals`` (growth channel, plus a simulated placement
direction for the spatial channel), away from its null values, at the fitted model.  An effect may
replace it (:meth:`~forensics.sensor.model.Effect.signature`); it receives a :class:`SignatureContext`,
which satisfies :class:`forensics.sensor.evidence.SignatureEvidence`.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from forensics.check.evidence import EffectQuestions, Evidence
from forensics.check.fit import FittedModel
from forensics.check.params import on_device
from forensics.check.pixelfit import used_blocks
from forensics.check.prediction import bin_offsets, predicted_variance
from forensics.check.streams import ARRIVAL_SIGNATURES
from forensics.sensor.model import Device, Effect, Stage


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
    random_effect: bool = False  #: a zero-mean pattern (:attr:`~forensics.sensor.model.Pattern.random_effect`)


def _names(effect: Effect) -> list[str]:
    return list(dict.fromkeys([*effect.null_values(), *effect.free_params()]))


class SignatureContext(EffectQuestions):
    """The evidence of a fitted model, as candidate effects see it when their signature is computed."""

    def __init__(self, ev: Evidence, fitted: FittedModel):
        self.ev = ev
        self.fitted = fitted
        self.shape = ev.shape
        self.defects = ev.defects
        self._null: np.ndarray | None = None

    def _null_prediction(self) -> np.ndarray:
        """The fitted model's unclipped prediction: every candidate's at its null values (computed once: it
        was one full prediction per candidate, 2 of the 4 s of the hidden prnu dataset's diagnosis)."""
        if self._null is None:
            self._null = self._predict(self.fitted.device)
        return self._null

    # ------------------------------------------------------------------ generic signature
    def signature(self, effect: Effect) -> list[Signature]:
        """Generic signature of ``effect`` (not in the model) at its null values, by finite differences."""
        if effect.stage == Stage.ARRIVAL:
            return self._arrival(effect)
        if effect.stage == Stage.NOISE:
            return self._variance(effect)
        return self._pixel(effect)

    def _predict(self, device: Device) -> np.ndarray:
        return self.ev.predictor.predict(device, self.fitted.pixels, clip=False)

    def _pixel(self, effect: Effect) -> list[Signature]:
        fitted = self.fitted
        probe = effect.nulled()
        dev = fitted.device.copy(fitted.device.model.with_effects(probe))  # the signature's own device
        probe.realize(dev, self.ev.streams.patterns())
        for pat in probe.patterns(dev):
            pat.values[...] = 0.0
        base = self._null_prediction()  # a candidate at its null values and zero patterns does not move it
        sigs = []
        for pat in probe.patterns(dev):
            used = used_blocks(pat)
            if used.size == 0:
                continue
            delta = 1e-2
            pat.values[used] += delta
            x = (self._predict(dev) - base) / delta * (pat.blocks >= 0)[None]
            pat.values[used] -= delta
            sigs.append(Signature("pixel", f"{effect.key}.{pat.name}", x, pat.blocks, pat.pixel_local,
                                  pat.random_effect))
        for name in _names(probe):
            value = getattr(probe, name)
            delta = 1e-3 * (1.0 + abs(value))
            lo, hi = probe.bounds(name)
            if value + delta > hi:
                delta = -delta
            moved = dataclasses.replace(probe, **{name: value + delta})
            x = (self._predict(on_device(dev, [*fitted.device.model.effects, moved])) - base) / delta
            sigs.append(Signature("pixel", f"{effect.key}.{name}", x))
        return sigs

    def _variance(self, effect: Effect) -> list[Signature]:
        fitted, ev = self.fitted, self.ev
        probe = effect.nulled()
        noise = fitted.noise_effects()

        bins = fitted.pixels.bins
        offsets = bin_offsets(bins, ev.rgroups, fitted.device)  # one device for every trial law below

        def log_var(e: Effect) -> np.ndarray:
            return np.log(predicted_variance(bins, ev.rgroups, [*noise, e], fitted.device, offsets))

        base = log_var(probe)
        sigs = []
        for name in _names(probe):
            value = getattr(probe, name)
            delta = 1e-3 * (1.0 + abs(value))
            x = (log_var(dataclasses.replace(probe, **{name: value + delta})) - base) / delta
            sigs.append(Signature("variance", f"{effect.key}.{name}", x))
        return sigs

    def _arrival(self, effect: Effect) -> list[Signature]:
        fitted, counts = self.fitted, self.ev.defects
        sigs = []
        if len(counts.times) < 3:
            return sigs
        strong = effect.probe(self)
        probe = dataclasses.replace(strong, **effect.null_values())
        arrivals = fitted.arrival_effects()

        def increments(e: Effect) -> np.ndarray:
            return counts.increments(counts.expected_counts([*arrivals, e]))[1]

        base = increments(probe)
        for name in _names(probe):
            value = getattr(probe, name)
            delta = 1e-3 * (1.0 + abs(getattr(strong, name)))
            x = (increments(dataclasses.replace(probe, **{name: value + delta})) - base) / delta
            sigs.append(Signature("growth", f"{effect.key}.{name}", x))
        if len(counts.sites) >= 10 and fitted.spatial_null is not None:
            n_sim = self.ev.streams.n_sim

            def simulate() -> np.ndarray:
                rng = self.ev.streams.stream(ARRIVAL_SIGNATURES)
                return np.array([counts.spatial_statistic(*counts.simulate([*arrivals, strong], rng)[1:])
                                 for _ in range(n_sim)])

            ls = self.ev.simulations(ARRIVAL_SIGNATURES, [*arrivals, strong], simulate)
            m0, s0 = fitted.spatial_null["mean"], fitted.spatial_null["sd"]
            direction = (np.nanmean(ls, 0) - m0) / s0
            noise = np.sqrt(1.0 / n_sim + 1.0 / n_sim)
            if np.nanmax(np.abs(direction)) > 4.0 * noise:
                sigs.append(Signature("spatial", f"{effect.key}.placement", np.nan_to_num(direction)))
        return sigs
