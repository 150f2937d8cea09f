"""The physical sensor model: a list of composable effects.

A :class:`SensorModel` is an image size, a bit depth and a list of
:class:`Effect` objects.  :meth:`SensorModel.realize` draws one *device*:
its fixed patterns and its whole defect history (a :class:`DefectCatalogue`).
:meth:`Device.expose` turns a scene (incident light in output DN) into an
image taken at a given time and condition.

Effects apply in physical order, by :class:`Stage`:

``ARRIVAL``  defect arrival processes add records to the catalogue (device creation only)
``SCENE``    scene light (vignetting, flat-field level, …)
``GAIN``     per-pixel gain (PRNU)
``DARK``     dark signal and offsets (partially stuck / hot pixels, dark current)
``AMPLIFY``  analog gain (ISO)
``RESPONSE`` global response curve (non-linearity)
``STUCK``    stuck values override the signal
``NOISE``    temporal noise
``READOUT``  the readout chain after the pixel and its noise (black level)
then clipping to the bit depth's range and rounding, done by the model itself.

Because every effect only reads the shared :class:`FrameContext` and
transforms the signal at its own stage, adding an effect never requires a
special case in another: e.g. a stuck pixel overrides a partially stuck one
simply because ``STUCK`` comes after ``DARK``.

The defect history obeys *once defective, always defective*: records are
never removed; a site keeps its first partially stuck record, and a stuck
record (which overrides from its onset on) is kept only if it is the site's
first stuck record.

An effect is a dataclass whose fields are its parameters (declared with
:func:`param`: unit, meaning, and for model checking the *null* value at
which the effect does nothing, whether the parameter is fitted, and its
bounds).  It declares ``name``, ``description``, ``stage`` and the manifest
``fields`` it needs, and implements ``realize`` (device state) and/or
``apply`` (per frame).

Model checking (:mod:`forensics.check`) uses the same objects.  An effect
tells it

* which of its parameters are fitted (``param(..., free=True)``) and their null
  values (``param(..., null=0.0)``);
* its fixed patterns (:meth:`Effect.patterns`): per-pixel or per-block values
  kept in the device (a PRNU map, defect amplitudes, column offsets), which the
  checker fits block by block;
* for ``NOISE`` effects, the temporal variance they add (:meth:`Effect.variance`);
* for ``ARRIVAL`` effects, the expected number of detectable defects against
  time (:meth:`Effect.expected_arrivals`, Monte Carlo by default);
* optionally a bespoke estimator (:meth:`Effect.fit`, which returns a new
  effect and never changes this one) and signature (:meth:`Effect.signature`);
  the defaults are generic (Gauss–Newton through ``apply``; finite differences
  of the prediction away from the null values).  What they may ask of the
  measurements is :class:`forensics.sensor.evidence.Evidence`.

Conventions that make the generic machinery work: ``apply`` is deterministic
except at the ``NOISE`` stage; fixed patterns are stored as *deviations* so
that an all-zero pattern is the typical pixel (the checker evaluates the
chain of a typical pixel with every state array zeroed and no defects).
"""
from __future__ import annotations

import dataclasses
import enum
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from forensics._shared.arrays import bits_full_scale
from forensics._shared.errors import InputError, UsageError
from forensics.sensor.catalogue import PARTIAL, STUCK, DefectCatalogue
from forensics.sensor.evidence import ChannelSignature, Evidence, SignatureEvidence

class Stage(enum.IntEnum):
    """Where an effect acts in the signal chain; effects run in increasing order."""

    ARRIVAL = 0
    SCENE = 10
    GAIN = 20
    DARK = 30
    AMPLIFY = 40
    RESPONSE = 50
    STUCK = 60
    NOISE = 70
    READOUT = 80


# --------------------------------------------------------------------------- frames
@dataclass
class FrameContext:
    """Everything an effect may read while one frame is formed."""

    device: "Device"
    time: float
    exposure_s: float | None = None
    iso: float | None = None
    temperature_c: float | None = None
    _sites: dict[int, DefectCatalogue] = field(default_factory=dict, repr=False)

    @property
    def shape(self) -> tuple[int, int]:
        return self.device.model.shape

    @property
    def full_scale(self) -> float:
        return self.device.model.full_scale

    @property
    def amplification(self) -> float:
        """Analog gain of this frame: the product of the ``AMPLIFY`` effects' :meth:`Effect.amplification`
        (1 without any).  Noise arising before the amplifier (photon shot noise) is amplified by it."""
        out = 1.0
        for effect in self.device.model.effects:
            if effect.stage == Stage.AMPLIFY:
                out *= effect.amplification(self)
        return out

    @property
    def electronic_offset(self) -> np.ndarray | float:
        """The part of the mean signal at the ``NOISE`` stage that is not charge: electronic offsets added before
        it (:meth:`Effect.electronic` — an offset at zero exposure, a per-pixel offset non-uniformity), times
        the analog gain after them.  A number or an ``(H, W)`` array.  Shot noise does not act on it (EMVA 1288:
        the dark offset μ_d0 and the DSNU carry no Poisson noise; the photo- and thermal electrons do)."""
        out: np.ndarray | float = 0.0
        amp = None
        for effect in self.device.model.effects:
            if effect.stage >= Stage.NOISE:
                break
            part = effect.electronic(self)
            if np.ndim(part) == 0 and float(part) == 0.0:
                continue
            if effect.stage < Stage.AMPLIFY:
                amp = self.amplification if amp is None else amp
                part = part * amp
            out = out + part
        return out

    @property
    def readout_offset(self) -> float:
        """What the ``READOUT`` effects add to a zero signal (the black level): the output of a pixel that
        collected nothing.  Noise laws act on the signal before it (:meth:`Effect.variance`)."""
        out = np.zeros((1, 1))
        rng = _SeedZero()  # (a generator made only if an effect draws: the check asks for this thousands of times)
        for effect in self.device.model.effects:
            if effect.stage == Stage.READOUT:
                out = effect.apply(out, self, rng)
        return float(out[0, 0])

    def defects(self, kind: int) -> DefectCatalogue:
        """The defects of ``kind`` in effect at this frame's time (stuck overrides applied)."""
        if kind not in self._sites:
            eff = self.device.catalogue.effective(self.time)
            self._sites[kind] = eff.select(eff.kind == kind)
        return self._sites[kind]

    def require(self, name: str, effect: str) -> float:
        """A condition field the effect needs; raises InputError naming it when absent."""
        value = getattr(self, name)
        if value is None:
            raise InputError(f"the effect '{effect}' needs the field '{name}' for every frame; add it to the manifest")
        return float(value)


def pixel_view(signal: np.ndarray) -> np.ndarray:
    """A ``(H*W, C)`` view of an ``(H, W)`` or ``(H, W, C)`` signal, so site indices address every channel."""
    if signal.ndim == 2:
        return signal.reshape(-1, 1)
    return signal.reshape(signal.shape[0] * signal.shape[1], signal.shape[2])


def per_pixel(pattern: np.ndarray, signal: np.ndarray) -> np.ndarray:
    """Broadcast an ``(H, W)`` pattern against an ``(H, W)`` or ``(H, W, C)`` signal."""
    return pattern if signal.ndim == 2 else pattern[..., None]


# --------------------------------------------------------------------------- effects
@dataclass
class Effect:
    """Base class of every effect.  Subclasses are dataclasses whose fields are parameters.

    Class attributes
    ----------------
    name : str
        Registry name (``forensics model effects`` lists them).
    description : str
        One line of physics.
    stage : Stage
        Where it acts in the chain.
    fields : tuple of str
        Manifest fields it needs (``exposure_s``, ``iso``, ``temperature_c``, ``captured``).
    """

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    stage: ClassVar[Stage] = Stage.SCENE
    fields: ClassVar[tuple[str, ...]] = ()

    def realize(self, device: "Device", rng: np.random.Generator) -> None:
        """Draw this effect's per-device state into ``device.state[self.key]`` (default: nothing)."""

    def arrivals(self, device: "Device", rng: np.random.Generator) -> DefectCatalogue | None:
        """For ``ARRIVAL`` effects: the defect records this process contributes (before resolution)."""
        return None

    def apply(self, signal: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        """Transform the float32 ``signal`` for one frame (may work in place and return it)."""
        return signal

    @property
    def key(self) -> str:
        return self.name or type(self).__name__

    def params(self) -> dict[str, Any]:
        """Parameter values by name."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    @classmethod
    def parameter_info(cls) -> list[dict[str, Any]]:
        """Name, default, unit and meaning of each parameter."""
        out = []
        for f in dataclasses.fields(cls):
            default = f.default if f.default is not dataclasses.MISSING else None
            out.append({"name": f.name, "default": default, "unit": f.metadata.get("unit", ""),
                        "doc": f.metadata.get("doc", ""), "null": f.metadata.get("null"),
                        "free": bool(f.metadata.get("free", False))})
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"effect": self.key, "params": self.params()}

    # ------------------------------------------------------------------ model checking interface
    #: ``"base"`` for the effects of the base model (growth, offset, stuck, read noise);
    #: ``"candidate"`` for effects the diagnosis may propose.
    role: ClassVar[str] = "candidate"
    #: Parameters that :meth:`fit` estimates itself (the generic fit leaves them alone).
    self_fitted: ClassVar[tuple[str, ...]] = ()
    #: Those of :attr:`self_fitted` estimated as the largest of several values (an amplitude's upper end): their
    #: standard error describes a skewed error, so the check does not pool them by their information.
    largest_value_params: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def _meta(cls) -> dict[str, dict[str, Any]]:
        return {f.name: dict(f.metadata) for f in dataclasses.fields(cls)}

    @classmethod
    def free_params(cls) -> list[str]:
        """Names of the parameters the generic fit estimates (``param(..., free=True)``, not self-fitted)."""
        return [n for n, m in cls._meta().items() if m.get("free") and n not in cls.self_fitted]

    @classmethod
    def null_values(cls) -> dict[str, Any]:
        """Parameter values at which the effect changes nothing (``param(..., null=...)``)."""
        return {n: m["null"] for n, m in cls._meta().items() if m.get("null") is not None}

    @classmethod
    def n_params(cls) -> int:
        """Number of parameters adding the effect costs (for BIC): fitted or null-valued ones."""
        return max(1, sum(1 for m in cls._meta().values() if m.get("free") or m.get("null") is not None))

    @classmethod
    def bounds(cls, name: str) -> tuple[float, float]:
        lo, hi = cls._meta()[name].get("bounds", (None, None))
        return (-np.inf if lo is None else float(lo), np.inf if hi is None else float(hi))

    def nulled(self) -> "Effect":
        """A copy with every null-valued parameter at its null value (the effect then does nothing)."""
        return dataclasses.replace(self, **self.null_values())

    def patterns(self, device: "Device") -> list["Pattern"]:
        """The effect's fixed patterns in ``device`` (views the checker may fit in place). Default: none."""
        return []

    def variance(self, mean: np.ndarray, ctx: FrameContext) -> np.ndarray | float:
        """Temporal variance (output DN²) this effect adds to a pixel whose mean charge signal at the ``NOISE``
        stage is ``mean`` — the output mean less the readout offset (:attr:`FrameContext.readout_offset`) and
        the electronic offsets (:attr:`FrameContext.electronic_offset`) — in the frame ``ctx`` (``NOISE``
        effects). Default 0."""
        return 0.0

    def electronic(self, ctx: FrameContext) -> np.ndarray | float:
        """What this effect adds to the signal that is not charge (an electronic offset: amplified by a later
        analog gain, free of shot noise), in the signal's units at its stage — a number or ``(H, W)``.
        Default 0."""
        return 0.0

    def amplification(self, ctx: FrameContext) -> float:
        """For ``AMPLIFY`` effects: the factor this effect applies to the signal in frame ``ctx``.

        Default: the effect applied to a signal of one (exact for any purely multiplicative effect).
        """
        return float(self.apply(np.ones((1, 1)), ctx, _SeedZero())[0, 0])

    def expected_arrivals(self, device: "Device", times: Sequence[float],
                          threshold: dict[int, float]) -> dict[int, np.ndarray]:
        """Expected cumulative number of defect records per kind present at each time whose amplitude exceeds
        ``threshold[kind]`` (``ARRIVAL`` effects).

        The default averages :meth:`arrivals` over Monte-Carlo draws (fixed seed), so a user's arrival
        process needs nothing more; built-in effects override it with the closed form.
        """
        times = np.asarray(times, float)
        out = {PARTIAL: np.zeros(len(times)), STUCK: np.zeros(len(times))}
        if self.stage != Stage.ARRIVAL:
            return out
        rng = np.random.default_rng(20240601)
        draws = 64
        for _ in range(draws):
            cat = self.arrivals(device, rng)
            if cat is None or not len(cat):
                continue
            for kind in out:
                sel = (cat.kind == kind) & (cat.amplitude > threshold.get(kind, -np.inf))
                out[kind] += np.sum(cat.onset[sel][:, None] <= times[None, :], axis=0)
        return {k: v / draws for k, v in out.items()}

    def param_unit(self, name: str) -> str:
        """The unit of parameter ``name`` as the check reports its value: the declared unit, which an effect whose
        values refer to a setting the data chose (a dark rate at its reference temperature) extends with it."""
        for f in dataclasses.fields(self):
            if f.name == name:
                return f.metadata.get("unit", "")
        return ""

    def held(self) -> dict[str, str]:
        """Free parameters this effect holds at their value for the data :meth:`fit` saw (they are then left out
        of :meth:`free_params`), each with why those data cannot determine it; the check reports them as not
        identifiable with that reason.  Default: none."""
        return {}

    def fit(self, evidence: Evidence) -> "Effect":
        """Bespoke estimation of :attr:`self_fitted` parameters from the checker's evidence.

        Returns the effect with the estimated values — a new object (``dataclasses.replace``); an effect
        is never changed in place.  Called before the generic joint fit of the effect's channel, once per
        fitting cycle.  Default: the effect as it is (the generic fit estimates the ``free`` parameters
        and the patterns).
        """
        return self

    def fit_errors(self, evidence: Evidence) -> dict[str, float]:
        """Standard errors of the :attr:`self_fitted` parameters at the values :meth:`fit` returned, where the
        effect's own estimator knows them (the check reports the others without an interval).  Default: none."""
        return {}

    def signature(self, evidence: SignatureEvidence) -> list[ChannelSignature]:
        """How the predicted statistics change when this effect leaves its null values.

        Default: the checker's generic finite-difference signature (through :meth:`apply`,
        :meth:`variance` or :meth:`expected_arrivals`, by stage).
        """
        return evidence.signature(self)

    def probe(self, evidence: Evidence) -> "Effect":
        """The effect at a moderate strength, used where a signature must be simulated (arrival
        placement).  Default: the effect as it is."""
        return self


@dataclass
class Pattern:
    """A fixed pattern of an effect: one value per block of pixels, stored in the device.

    Attributes
    ----------
    name
        Short name (``k``, ``d``, ``rate``…).
    values
        1-D array *view* into the device's state or catalogue; the checker fits it in place.
    blocks
        ``(H, W)`` integer map: index into ``values`` for each pixel, −1 where the pattern does not act.
    hyper
        The effect parameter that summarises the pattern (e.g. ``sigma_k``), set after fitting.
    summary
        How ``hyper`` is computed from the fitted values: ``"rms"``, ``"max"`` or ``"mean"``.
    """

    name: str
    values: np.ndarray
    blocks: np.ndarray
    hyper: str | None = None
    summary: str = "rms"

    @property
    def random_effect(self) -> bool:
        """True when the values are draws of a zero-mean distribution whose spread is ``hyper`` (summary
        ``"rms"``, e.g. PRNU's ``sigma_k``), rather than one free value per defect or block."""
        return self.hyper is not None and self.summary == "rms"

    @property
    def pixel_local(self) -> bool:
        """True when every block is a single pixel (then the checker solves pixel by pixel)."""
        used = self.blocks[self.blocks >= 0]
        return bool(used.size == 0 or np.bincount(used).max() <= 1)


def record_blocks(catalogue: DefectCatalogue, shape: tuple[int, int], kind: int) -> np.ndarray:
    """``(H, W)`` map of the index of each site's record of ``kind`` (−1 elsewhere)."""
    blocks = np.full(shape, -1, np.int64)
    idx = np.flatnonzero(catalogue.kind == kind)
    if idx.size:
        blocks[catalogue.y[idx], catalogue.x[idx]] = idx
    return blocks


def param(default: Any, unit: str = "", doc: str = "", *, null: Any = None, free: bool = False,
          bounds: tuple[float | None, float | None] = (None, None)) -> Any:
    """A dataclass field for an effect parameter.

    Parameters
    ----------
    default
        Value used when the effect is created without this parameter.
    unit, doc
        Unit and one-line meaning (shown by ``forensics model effects``).
    null
        Value at which the effect changes nothing (used by the diagnosis); None if there is none.
    free
        Whether model checking fits this parameter.
    bounds
        Admissible range for the fit.
    """
    return field(default=default, metadata={"unit": unit, "doc": doc, "null": null, "free": free,
                                            "bounds": bounds})


EFFECTS: dict[str, type[Effect]] = {}


def register_effect(cls: type[Effect]) -> type[Effect]:
    """Class decorator adding an effect to the registry under ``cls.name``."""
    if not cls.name:
        raise ValueError(f"{cls.__name__} has no name")
    EFFECTS[cls.name] = cls
    return cls


def make_effect(spec: str, **params: Any) -> Effect:
    """An effect from a registry name, ``module:Class`` or ``path/to/file.py:Class``.

    Raises
    ------
    UsageError
        If the name is unknown or the class cannot be loaded.
    """
    if spec in EFFECTS:
        return EFFECTS[spec](**params)
    if ":" not in spec:
        raise UsageError(f"unknown effect '{spec}'; see 'forensics model effects' or give module:Class or file.py:Class")
    from forensics._shared.plugins import load_class

    cls = load_class(spec, "effect")
    if not (isinstance(cls, type) and issubclass(cls, Effect)):
        raise UsageError(f"'{spec}' is not a subclass of forensics.sensor.model.Effect")
    return cls(**params)


# --------------------------------------------------------------------------- model and device
@dataclass
class SensorModel:
    """An image size, a bit depth, a start of ageing and an ordered list of effects.

    Parameters
    ----------
    shape
        ``(height, width)`` of the pixel array.
    bit_depth
        Output bits (8 → uint8, up to 16 → uint16); output saturates at ``2**bit_depth - 1``.
    effects
        The effects; they run sorted by :class:`Stage` (stable for equal stages).
    t0
        Decimal year from which defects arrive.
    dither
        Width (DN) of a uniform dither the converter adds before rounding (0: none, as most cameras; 1: EMVA
        1288's reference simulator).  Where the noise is below ≈ 1 DN the readout's variance depends on it
        (:func:`forensics.stats.censored.readout_moments`).
    """

    shape: tuple[int, int]
    bit_depth: int = 8
    effects: list[Effect] = field(default_factory=list)
    t0: float = 0.0
    dither: float = 0.0

    def __post_init__(self) -> None:
        self.shape = (int(self.shape[0]), int(self.shape[1]))
        if not 1 <= self.bit_depth <= 16:
            raise UsageError(f"bit depth {self.bit_depth} not supported (1–16)")
        self.effects = sorted(self.effects, key=lambda e: e.stage)

    @property
    def full_scale(self) -> float:
        return bits_full_scale(self.bit_depth)

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(np.uint8 if self.bit_depth <= 8 else np.uint16)

    @property
    def megapixels(self) -> float:
        return self.shape[0] * self.shape[1] / 1e6

    def effect(self, name: str) -> Effect | None:
        """The effect registered under ``name``, if the model has it."""
        return next((e for e in self.effects if e.key == name), None)

    def with_effects(self, *extra: Effect) -> "SensorModel":
        """A copy of the model with further effects."""
        return dataclasses.replace(self, effects=[*self.effects, *extra])

    def realize(self, rng: np.random.Generator, times: Sequence[float]) -> "Device":
        """Draw one device: its defect history up to ``max(times)`` and every fixed pattern.

        ``times`` are the sample points (decimal years) the device will be imaged
        at; deterministic arrival counts use them as the grid.
        """
        device = Device(model=self, times=tuple(sorted(float(t) for t in times)))
        parts = []
        for effect in self.effects:
            if effect.stage == Stage.ARRIVAL:
                part = effect.arrivals(device, rng)
                if part is not None and len(part):
                    parts.append(part)
        device.catalogue = DefectCatalogue.concatenate(parts).resolved()
        for effect in self.effects:
            effect.realize(device, rng)
        return device

    def to_dict(self) -> dict[str, Any]:
        out = {"shape": list(self.shape), "bit_depth": self.bit_depth, "t0": self.t0,
               "effects": [e.to_dict() for e in self.effects]}
        if self.dither:
            out["dither"] = self.dither
        return out

    @classmethod
    def from_dict(cls, obj: dict[str, Any]) -> "SensorModel":
        effects = [make_effect(e["effect"], **e.get("params", {})) for e in obj.get("effects", [])]
        return cls(shape=tuple(obj["shape"]), bit_depth=int(obj.get("bit_depth", 8)), effects=effects,
                   t0=float(obj.get("t0", 0.0)), dither=float(obj.get("dither", 0.0)))


@dataclass
class Device:
    """One realised sensor: a model, its defect catalogue and per-effect fixed state."""

    model: SensorModel
    times: tuple[float, ...] = ()
    catalogue: DefectCatalogue = field(default_factory=DefectCatalogue.empty)
    state: dict[str, Any] = field(default_factory=dict)

    def context(self, time: float, exposure_s: float | None = None, iso: float | None = None,
                temperature_c: float | None = None) -> FrameContext:
        return FrameContext(self, float(time), exposure_s, iso, temperature_c)

    def signal(self, scene: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        """The analogue signal (float32, before clipping and rounding) for ``scene`` under ``ctx``."""
        h, w = self.model.shape
        if scene.shape[:2] != (h, w):
            raise InputError(f"scene of shape {scene.shape[:2]} does not match the sensor's {(h, w)}")
        signal = np.array(scene, dtype=np.float32, copy=True)
        noiseless = None
        for effect in self.model.effects:
            if effect.stage == Stage.ARRIVAL:
                continue
            if effect.stage == Stage.NOISE:
                # independent noise sources, each with its law at the noiseless signal (shot noise counts the
                # collected electrons, not electrons plus a read noise drawn before it): their variances add,
                # as Effect.variance states, whatever the order of the effects
                if noiseless is None:
                    noiseless = signal.copy()
                signal += effect.apply(noiseless.copy(), ctx, rng) - noiseless
            else:
                signal = effect.apply(signal, ctx, rng)
        return signal

    def expose(self, scene: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        """An image: the signal (plus the model's dither, if any) clipped to ``[0, full_scale]`` and rounded to the
        model's dtype."""
        signal = self.signal(scene, ctx, rng)
        if self.model.dither > 0:
            signal += rng.uniform(-0.5 * self.model.dither, 0.5 * self.model.dither, signal.shape).astype(signal.dtype)
        return quantize(signal, self.model.full_scale, self.model.dtype)

    def mean_signal(self, light: np.ndarray, ctx: FrameContext) -> np.ndarray:
        """The expected signal (no temporal noise, no clipping) for incident ``light``, in float64.

        Runs every effect except the ``ARRIVAL`` and ``NOISE`` stages (``READOUT`` included: the black level is
        part of the mean); model checking uses it as the prediction of a pixel's mean output.
        """
        signal = np.array(light, dtype=np.float64, copy=True)
        rng = _SeedZero()
        for effect in self.model.effects:
            if effect.stage not in (Stage.ARRIVAL, Stage.NOISE):
                signal = effect.apply(signal, ctx, rng)
        return signal

    def copy(self, model: "SensorModel | None" = None) -> "Device":
        """A deep copy (catalogue arrays and state arrays copied), optionally with another model."""
        cat = self.catalogue.select(np.arange(len(self.catalogue)))
        state = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in self.state.items()}
        return Device(model=model or self.model, times=self.times, catalogue=cat, state=state)

    def typical(self) -> "Device":
        """The typical pixel's device: no defects and every fixed-pattern array zeroed."""
        # np.zeros, not zeros_like: its pages are mapped zero and touched only when read, and the model check asks
        # for a typical device at every prediction, whose state holds arrays per condition it never reads (filling
        # them was 0.9 s of the EMVA 1288 standard series under the profiler)
        state = {k: (np.zeros(v.shape, v.dtype) if isinstance(v, np.ndarray) else v) for k, v in self.state.items()}
        return Device(model=self.model, times=self.times, catalogue=DefectCatalogue.empty(), state=state)


class _SeedZero:
    """``np.random.default_rng(0)``, made on first use: the mean signal's effects never draw (only the ``NOISE``
    and ``ARRIVAL`` stages do), and the model check asks for tens of thousands of means, each of which paid
    for a generator (18 µs) it did not use.  An effect that does draw gets the seed-0 stream as before."""

    __slots__ = ("_rng",)

    def __init__(self) -> None:
        self._rng: np.random.Generator | None = None

    def __getattr__(self, name: str) -> Any:
        if self._rng is None:
            self._rng = np.random.default_rng(0)
        return getattr(self._rng, name)


def quantize(signal: np.ndarray, full_scale: float, dtype: np.dtype) -> np.ndarray:
    """Clip to ``[0, full_scale]``, round half to even, cast."""
    out = np.clip(signal, 0.0, full_scale, out=signal)
    np.rint(out, out=out)
    return out.astype(dtype)


def load_model(path: str | Path) -> SensorModel:
    """A model from a ``sensor.json`` written by the simulator (its ``model`` entry)."""
    import json

    path = Path(path)
    try:
        obj = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read the sensor description ({exc})") from exc
    return SensorModel.from_dict(obj.get("model", obj))
