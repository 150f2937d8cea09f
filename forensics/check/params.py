"""Changing effect parameters without mutating effects.

A fit never sets an attribute on an effect: a new value makes a new effect (``dataclasses.replace``) and a
new list of effects; a device for new effects is a new :class:`~forensics.sensor.model.Device` sharing the
old one's catalogue and state (the fixed patterns the fit owns).  The caller's effect objects, and any
model built from them, never change.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from forensics.sensor.evidence import Evidence
from forensics.sensor.model import Device, Effect, SensorModel, Stage


def is_pixel(effect: Effect) -> bool:
    """Whether the effect acts on the pixel channel (every stage but arrival and noise)."""
    return effect.stage not in (Stage.ARRIVAL, Stage.NOISE)


def with_param(effects: Sequence[Effect], index: int, name: str, value: Any) -> list[Effect]:
    """A new list in which ``effects[index]`` is replaced by a copy with ``name = value``."""
    out = list(effects)
    out[index] = dataclasses.replace(out[index], **{name: value})
    return out


def with_clipped_param(effects: Sequence[Effect], index: int, name: str, value: float) -> list[Effect]:
    """:func:`with_param` with the value clipped to the parameter's bounds."""
    lo, hi = effects[index].bounds(name)
    return with_param(effects, index, name, float(np.clip(value, lo, hi)))


def on_device(device: Device, effects: Sequence[Effect]) -> Device:
    """A device for ``effects`` (the rest of its model as ``device``'s) sharing ``device``'s times, catalogue and
    state."""
    return on_model(device, dataclasses.replace(device.model, effects=list(effects)))


def on_model(device: Device, model: SensorModel) -> Device:
    """A device for ``model`` sharing ``device``'s times, catalogue and state."""
    return Device(model=model, times=device.times, catalogue=device.catalogue, state=device.state)


def bespoke_fit(effect: Effect, evidence: Evidence) -> Effect:
    """The effect after its own :meth:`~forensics.sensor.model.Effect.fit` (a new object; an effect written
    for the older in-place interface, whose ``fit`` returns None, updates a copy)."""
    trial = dataclasses.replace(effect)
    out = trial.fit(evidence)
    return trial if out is None else out


def unit(effect: Effect, name: str) -> str:
    """The unit a fitted value of ``effect.name`` is reported in (:meth:`~forensics.sensor.model.Effect.param_unit`)."""
    return effect.param_unit(name)
