"""Built-in effects of the sensor model (see :mod:`forensics.sensor.model`).

Base model of the reference paper (eq. 5 with Poisson arrivals): ``growth``
(defect arrivals), ``offset`` (partially stuck, y = i + d) and ``stuck``
(y = c); saturation and quantisation are done by the model.  ``read_noise`` is
the constant temporal noise that any measurement shows and ``black_level`` the
constant the readout adds under every pixel (stuck ones included).  The others
are the candidate effects a real sensor may add; each acts where the physics
acts: a dark signal on every pixel (hot pixels are its tail), an analog gain on
the whole electron signal and on the noise that arises before it.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from forensics.sensor.catalogue import PARTIAL, STUCK, DefectCatalogue

from forensics.sensor.model import (
    Device,
    Effect,
    FrameContext,
    Pattern,
    Stage,
    param,
    per_pixel,
    pixel_view,
    record_blocks,
    register_effect,
)
from forensics.sensor.evidence import Evidence
from forensics.stats.spatial import pair_excess_se


# --------------------------------------------------------------------------- arrival helpers
def uniform_sites(n: int, shape: tuple[int, int], rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` independent uniformly distributed pixel sites ``(x, y)``."""
    return rng.integers(0, shape[1], n), rng.integers(0, shape[0], n)


def constant_rate_onsets(rate_per_mp_year: float, device: Device, rng: np.random.Generator, counting: str) -> np.ndarray:
    """Onset times of a constant-rate arrival process between ``t0`` and the device's last sample time.

    ``counting='poisson'``: the count in any interval is Poisson(rate·MP·Δt)
    and onsets are uniform (a homogeneous Poisson process).
    ``counting='deterministic'``: the paper's n(T) = (T − T0)·λ, rounded at each
    sample time, with onsets uniform within each sample interval.
    """
    t0 = device.model.t0
    grid = np.array([t for t in device.times if t > t0], dtype=float)
    if rate_per_mp_year <= 0 or not len(grid):
        return np.zeros(0)
    mean_per_year = rate_per_mp_year * device.model.megapixels
    horizon = grid[-1]
    if counting == "poisson":
        n = rng.poisson(mean_per_year * (horizon - t0))
        return np.sort(rng.uniform(t0, horizon, n))
    if counting != "deterministic":
        raise ValueError(f"counting must be 'poisson' or 'deterministic', not {counting!r}")
    cumulative = np.rint(mean_per_year * (grid - t0)).astype(int)
    steps = np.diff(np.concatenate([[0], cumulative]))
    starts = np.concatenate([[t0], grid[:-1]])
    return np.concatenate([np.sort(rng.uniform(a, b, k)) for a, b, k in zip(starts, grid, steps)])


def uniform_detect_fraction(amplitude: float, threshold: float) -> float:
    """Fraction of amplitudes ``r·amplitude``, ``r ~ U[0, 1]``, above ``threshold``."""
    if not np.isfinite(threshold) or threshold <= 0:
        return 1.0
    if amplitude <= threshold:
        return 0.0
    return 1.0 - threshold / amplitude


def elapsed(device: Device, times: Any) -> np.ndarray:
    """Years since the model's ``t0`` at each time (zero before it)."""
    return np.maximum(np.asarray(times, float) - device.model.t0, 0.0)


def records(x: np.ndarray, y: np.ndarray, kind: int, amplitude: np.ndarray, onset: np.ndarray, source: str) -> DefectCatalogue:
    """Raw arrival records of one kind."""
    n = len(x)
    return DefectCatalogue(np.asarray(x, np.int64), np.asarray(y, np.int64), np.full(n, kind, np.int8),
                           np.asarray(amplitude, float), np.asarray(onset, float), np.full(n, source, dtype=object))


# --------------------------------------------------------------------------- base model
@register_effect
@dataclass
class Growth(Effect):
    """Defects arrive at a constant rate at uniform independent sites (cosmic-ray damage)."""

    name = "growth"
    description = "defects arrive as a Poisson process at a constant rate, at uniform independent sites"
    stage = Stage.ARRIVAL
    fields = ("captured",)
    role = "base"
    self_fitted = ("amp_partial", "amp_stuck")
    largest_value_params = ("amp_partial",)

    rate_partial: float = param(0.6659, "defects/MP/year", "arrival rate of partially stuck pixels (λ_ps)",
                                free=True, bounds=(0.0, None))
    rate_stuck: float = param(0.0, "defects/MP/year", "arrival rate of stuck pixels (λ_s)", free=True,
                              bounds=(0.0, None))
    amp_partial: float = param(3.0, "DN", "maximum offset of a partially stuck pixel (a_ps); d = r·a_ps, r ~ U[0, 1]")
    amp_stuck: float = param(255.0, "DN", "maximum value of a stuck pixel (a_s); c = r·a_s")
    counting: str = param("poisson", "", "'poisson' (random counts) or 'deterministic' (the paper's (T − T0)·λ)")

    def expected_arrivals(self, device: Device, times: Any, threshold: dict[int, float]) -> dict[int, np.ndarray]:
        span = elapsed(device, times) * device.model.megapixels
        return {PARTIAL: self.rate_partial * span * uniform_detect_fraction(self.amp_partial, threshold.get(PARTIAL, 0)),
                STUCK: self.rate_stuck * span * uniform_detect_fraction(self.amp_stuck, threshold.get(STUCK, 0))}

    def fit(self, evidence: Evidence) -> "Growth":
        """Amplitudes from the largest detected ones (the paper's a_ps = max d, made unbiased: ·(n+1)/n)."""
        return replace(self, amp_partial=evidence.amplitude_max(PARTIAL, self.amp_partial),
                       amp_stuck=evidence.amplitude_max(STUCK, self.amp_stuck))

    def fit_errors(self, evidence: Evidence) -> dict[str, float]:
        return amplitude_error(evidence, "amp_partial")

    def held(self) -> dict[str, str]:
        return {"amp_stuck": f"held at {self.amp_stuck:g} DN, the full scale: a stuck pixel's value spans the "
                             "output range"}

    def arrivals(self, device: Device, rng: np.random.Generator) -> DefectCatalogue:
        parts = []
        for kind, rate, amp in ((PARTIAL, self.rate_partial, self.amp_partial), (STUCK, self.rate_stuck, self.amp_stuck)):
            onset = constant_rate_onsets(rate, device, rng, self.counting)
            x, y = uniform_sites(len(onset), device.model.shape, rng)
            parts.append(records(x, y, kind, rng.uniform(0.0, 1.0, len(onset)) * amp, onset, self.name))
        return DefectCatalogue.concatenate(parts)


def amplitude_error(evidence: Evidence, name: str) -> dict[str, float]:
    """``{name: se}`` of a partially stuck amplitude taken from the largest detected one
    (:meth:`Evidence.amplitude_se`), empty where that is no estimate (none detected)."""
    se = evidence.amplitude_se(PARTIAL)
    return {} if se is None else {name: se}


def defect_rows(signal: np.ndarray, ctx: FrameContext, kind: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (pixels, channels) view of ``signal``, the rows of the defects of ``kind`` in effect at this
    frame, and their amplitudes as a float32 column (empty when there are none)."""
    sites = ctx.defects(kind)
    rows = sites.y * ctx.shape[1] + sites.x
    return pixel_view(signal), rows, sites.amplitude.astype(np.float32)[:, None]


@register_effect
@dataclass
class Offset(Effect):
    """Partially stuck (hot) pixels add a light-independent offset: y = i + d."""

    name = "offset"
    description = "partially stuck pixels add a constant offset to the light: y = i + d"
    stage = Stage.DARK
    role = "base"

    def patterns(self, device: Device) -> list[Pattern]:
        return [Pattern("d", device.catalogue.amplitude, record_blocks(device.catalogue, device.model.shape, PARTIAL))]

    def apply(self, signal: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        view, rows, amplitude = defect_rows(signal, ctx, PARTIAL)
        view[rows] += amplitude
        return signal


@register_effect
@dataclass
class Stuck(Effect):
    """Stuck pixels output a constant whatever the light: y = c."""

    name = "stuck"
    description = "stuck pixels output a constant value whatever the light: y = c"
    stage = Stage.STUCK
    role = "base"

    def patterns(self, device: Device) -> list[Pattern]:
        return [Pattern("c", device.catalogue.amplitude, record_blocks(device.catalogue, device.model.shape, STUCK))]

    def apply(self, signal: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        view, rows, amplitude = defect_rows(signal, ctx, STUCK)
        view[rows] = amplitude
        return signal


@register_effect
@dataclass
class ReadNoise(Effect):
    """Signal-independent temporal noise of the readout chain."""

    name = "read_noise"
    description = "temporal noise independent of the signal (readout), Gaussian with constant σ"
    stage = Stage.NOISE
    role = "base"

    sigma: float = param(1.0, "DN", "standard deviation of the read noise", free=True, bounds=(0.0, None))

    def variance(self, mean: np.ndarray, ctx: FrameContext) -> np.ndarray | float:
        return self.sigma**2

    def apply(self, signal: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        if self.sigma > 0:
            signal += np.float32(self.sigma) * rng.standard_normal(signal.shape, dtype=np.float32)
        return signal


@register_effect
@dataclass
class BlackLevel(Effect):
    """The readout's black level (pedestal): a constant added to every pixel after the pixel and its noise.

    A pixel that collected nothing reads ``level``; a stuck pixel reads ``level + c``.  Multiplicative effects
    (PRNU, gain, a response curve) act on the signal above it, and noise laws on the signal without it.  The
    checker fits it where the data can tell it apart from the light — frames known to be dark
    (:data:`forensics.io.dataset.DARK_SUBJECT`), or through a multiplicative effect — and says when they
    cannot; a value from the files' metadata or the manifest's ``black_level`` column is used as known.
    """

    name = "black_level"
    description = "the readout adds a constant black level to every pixel (stuck ones too): y = level + signal"
    stage = Stage.READOUT
    role = "base"

    # bounded below by 0: with nothing that fixes it (no dark frame, no clipping), a black level far below zero
    # would let a per-pixel gain mimic a per-pixel offset, and the fit would drift there
    level: float = param(0.0, "DN", "black level (pedestal) the readout adds to every pixel", free=True,
                         bounds=(0.0, None))
    known: bool = param(False, "", "True when the level comes from metadata (then it is not fitted)")

    def free_params(self) -> list[str]:  # type: ignore[override]
        return [] if self.known else ["level"]

    def fit(self, evidence: Any) -> "BlackLevel":
        """The starting level: the darkest dark condition's median readout over the interior pixels (the checker's
        bespoke start; the fit refines it).  Why: from 0 DN the checker's first look at the noise read every dark
        pixel's level as signal and its variance as shot noise (read noise 0), and the pixel fit then predicted
        the dark frames' censored readout with no noise (benchmarks/RESULTS_check.md, issue 27)."""
        from forensics.io.dataset import is_dark_subject

        if self.known:
            return self
        meas = evidence.meas
        dark = [g.index for g in meas.groups if is_dark_subject(g.subject)]
        if not dark:
            return self
        level = min(float(np.median(meas.mean_all[g][meas.interior])) for g in dark)
        return replace(self, level=max(level, 0.0))

    def apply(self, signal: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        if self.level:
            signal += np.asarray(self.level, signal.dtype)
        return signal


# --------------------------------------------------------------------------- candidate effects
@register_effect
@dataclass
class Prnu(Effect):
    """Photo-response non-uniformity: each pixel has its own gain, y = i·(1 + k)."""

    name = "prnu"
    description = "per-pixel gain differences (PRNU): y = i·(1 + k), k ~ N(0, σ_k)"
    stage = Stage.GAIN

    sigma_k: float = param(0.01, "", "standard deviation of the relative gain k", null=0.0)

    def realize(self, device: Device, rng: np.random.Generator) -> None:
        device.state[self.key] = (self.sigma_k * rng.standard_normal(device.model.shape, dtype=np.float32)).astype(np.float32)

    def patterns(self, device: Device) -> list[Pattern]:
        h, w = device.model.shape
        return [Pattern("k", device.state[self.key].reshape(-1), np.arange(h * w).reshape(h, w), hyper="sigma_k")]

    def apply(self, signal: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        k = ctx.device.state[self.key]
        signal *= per_pixel(1.0 + k, signal)
        return signal


@register_effect
@dataclass
class Dsnu(Effect):
    """Dark-signal non-uniformity: each pixel adds its own constant offset, light or not (EMVA 1288 DSNU).

    The offsets are ``offset + o`` with o ~ N(0, σ_o): the fit holds the per-pixel values at zero mean (a random
    effect), so their mean is the parameter ``offset``.  It sits before the analog gain with the pixels'
    electronics: under an ISO gain the dark level grows with it, which the black level after the gain cannot
    follow (without a gain the two trade off exactly and ``offset`` is reported as not identifiable)."""

    name = "dsnu"
    description = "dark-signal non-uniformity: every pixel adds its own constant offset, offset + o, o ~ N(0, σ_o)"
    stage = Stage.DARK

    sigma_o: float = param(1.0, "DN", "standard deviation of the per-pixel offsets", null=0.0)
    offset: float = param(0.0, "DN", "mean of the per-pixel offsets (before any analog gain)", null=0.0,
                          free=True)

    def realize(self, device: Device, rng: np.random.Generator) -> None:
        device.state[self.key] = (self.sigma_o * rng.standard_normal(device.model.shape, dtype=np.float32)).astype(np.float32)

    def apply(self, signal: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        signal += per_pixel(ctx.device.state[self.key], signal)
        if self.offset:
            signal += np.asarray(self.offset, signal.dtype)
        return signal

    def electronic(self, ctx: FrameContext) -> np.ndarray | float:
        # an offset of the pixel's electronics, not collected charge: no shot noise on it
        return ctx.device.state.get(self.key, 0.0) + self.offset

    def patterns(self, device: Device) -> list[Pattern]:
        h, w = device.model.shape
        return [Pattern("o", device.state[self.key].reshape(-1), np.arange(h * w).reshape(h, w), hyper="sigma_o")]


#: Conditions with an exposure whose temperatures all lie within this span (°C) are at one temperature: twice
#: :data:`forensics.io.fits.SETPOINT_TOLERANCE_C`, the band in which the frames of one set point are grouped
#: (:func:`forensics.check.measurements.temperature_key`), so a single set point never determines T_d.
ONE_TEMPERATURE_SPAN_C = 2.0


def thermal_factor(ctx: FrameContext, effect: str, t_ref: float, t_double: float) -> float:
    """Exposure time × 2^((T − T_ref)/T_d): what multiplies a dark-current rate in this frame."""
    t = ctx.require("exposure_s", effect)
    temp = ctx.require("temperature_c", effect)
    return t * 2.0 ** ((temp - t_ref) / t_double)


@register_effect
@dataclass
class DarkCurrent(Effect):
    """Dark signal on every pixel: an offset at zero exposure plus a dark current proportional to exposure time
    and doubling every T_d degrees (EMVA 1288: μ_dark = μ_d0 + μ_therm).

    Every pixel has a rate r̄ + r_p (a mean and a per-pixel non-uniformity, DCNU); hot pixels are the tail:
    a partially stuck defect adds its own rate from its onset on.  The dark signal is charge in the pixel, so
    it passes through everything after the ``DARK`` stage: an analog gain amplifies it (unlike the black level
    the readout adds), shot noise includes it.
    """

    name = "dark_current"
    description = ("dark signal on every pixel: D = D0 + (r̄ + r_p)·t·2^((T − T_ref)/T_d), hot (partially "
                   "stuck) pixels adding their own rate")
    stage = Stage.DARK
    fields = ("exposure_s", "temperature_c")

    offset: float = param(0.0, "DN", "dark signal at zero exposure (μ_d0, before any analog gain)", null=0.0,
                          free=True)
    rate: float = param(0.0, "DN/s", "mean dark-signal rate of a pixel at T_ref (r̄)", null=0.0, free=True,
                        bounds=(0.0, None))
    sigma_rate: float = param(0.0, "DN/s", "standard deviation of the per-pixel rate r_p (dark-current "
                              "non-uniformity)", null=0.0)
    rate_max: float = param(20.0, "DN/s", "largest extra rate of a hot (partially stuck) pixel at T_ref, "
                            "r ~ U[0, rate_max]", null=0.0)
    t_ref: float = param(25.0, "°C", "reference temperature")
    t_double: float = param(7.0, "°C", "temperature increase that doubles the dark current (T_d)", free=True,
                            bounds=(1.0, 100.0))
    t_double_held: bool = param(False, "", "True when every frame with an exposure was taken at one temperature "
                                "(set by the checker's fit): T_d is then held at its value, not fitted")

    @property
    def _defect_key(self) -> str:
        return f"{self.key}.rate"

    def free_params(self) -> list[str]:  # type: ignore[override]
        return [n for n in super().free_params() if n not in self.held()]

    def param_unit(self, name: str) -> str:
        """The rates' unit names the temperature they refer to: :meth:`fit` may move ``t_ref`` into the data (a
        series at 22 °C reports its rate at 22 °C, not at the default 25 °C), and a rate without it cannot be
        compared with another tool's (emva1288's dark current is at the frames' temperature)."""
        base = super().param_unit(name)
        return f"{base} at {self.t_ref:g} °C" if name in ("rate", "sigma_rate", "rate_max") else base

    def held(self) -> dict[str, str]:
        if not self.t_double_held:
            return {}
        return {"t_double": f"every frame with an exposure was taken at one temperature (within "
                            f"{ONE_TEMPERATURE_SPAN_C:g} °C): T_d held at {self.t_double:g} °C, not fitted, and the "
                            f"rate is the one at T_ref = {self.t_ref:g} °C; frames at a second set point determine T_d"}

    def fit(self, evidence: Any) -> "DarkCurrent":
        """The checker's bespoke start: the reference temperature moved into the data when it lies outside the
        temperatures of the dark frames with an exposure (to their exposure-weighted mean, rounded to 1 °C), and
        T_d held (:meth:`held`) when every condition with an exposure lies within :data:`ONE_TEMPERATURE_SPAN_C`.

        Why the reference: the rate is fitted at ``t_ref``; a cooled CCD measured at −10 and −5 °C against the
        default 25 °C has its rate extrapolated 30 °C, where it and T_d trade off almost exactly (correlation
        > 0.999: both reported as not identifiable although the data determine them).  Where ``t_ref`` lies
        among the data's temperatures it is kept (the rate then means what the user set it to mean).

        Why T_d is held: frames at one set point differ only by the thermistor's wander (a few hundredths to
        tenths of a degree between conditions); a T_d fitted from that rests on the readings being exact and on
        nothing else changing between the exposures (a series at one set point, −15 °C, gave "T_d 5.13 ± 0.63
        °C" from conditions whose mean readings differ by hundredths of a degree: not a measured law)."""
        from forensics.io.dataset import is_dark_subject

        groups = [g for g in getattr(getattr(evidence, "meas", None), "groups", [])
                  if g.temperature_c is not None and (g.exposure_s or 0) > 0]
        out = self
        if groups:
            temps = np.array([g.temperature_c for g in groups], float)
            held = bool(temps.max() - temps.min() <= ONE_TEMPERATURE_SPAN_C)
            if held != out.t_double_held:
                out = replace(out, t_double_held=held)
        dark = [g for g in groups if is_dark_subject(g.subject)]
        if not dark:
            return out
        temps = np.array([g.temperature_c for g in dark], float)
        if temps.min() - 1.0 <= out.t_ref <= temps.max() + 1.0:
            return out
        weights = np.array([g.exposure_s * g.n for g in dark], float)
        return replace(out, t_ref=float(np.round(np.average(temps, weights=weights))))

    def realize(self, device: Device, rng: np.random.Generator) -> None:
        device.state[self.key] = (self.sigma_rate * rng.standard_normal(device.model.shape)).astype(np.float32)
        cat = device.catalogue
        # a fit may set rate_max below 0 (the hot pixels' own rates taken over by the non-uniformity values)
        cat.extra[self._defect_key] = np.where(cat.kind == PARTIAL, rng.uniform(0, max(self.rate_max, 0.0), len(cat)),
                                               0.0)

    def patterns(self, device: Device) -> list[Pattern]:
        h, w = device.model.shape
        if self.key not in device.state:
            device.state[self.key] = np.zeros((h, w), np.float32)
        cat = device.catalogue
        if self._defect_key not in cat.extra:
            cat.extra[self._defect_key] = np.zeros(len(cat))
        # A hot pixel has its non-uniformity value too: before its onset it is a normal pixel, and afterwards its
        # record adds its own rate.  Only where it is hot from the first frame on are the two the same column, and
        # the fit would split its rate between them: there the rate is the record's alone.  (The split, carried
        # into the non-uniformity's mean, pulled the normal pixels' rates up by 11 % on a low-rate CCD series;
        # keeping every hot pixel out lost the non-uniformity of those that turn hot later — their readings before
        # the onset misfit, 14-bit sweep: partial class error 6.7.)
        hot = record_blocks(cat, device.model.shape, PARTIAL)
        first = min(device.times) if device.times else -np.inf
        onset = np.full(hot.shape, np.inf)
        onset[hot >= 0] = cat.onset[hot[hot >= 0]]
        from_start = onset <= first
        return [Pattern("r", device.state[self.key].reshape(-1),
                        np.where(from_start, -1, np.arange(h * w).reshape(h, w)), hyper="sigma_rate"),
                Pattern("rate", cat.extra[self._defect_key], record_blocks(cat, device.model.shape, PARTIAL),
                        hyper="rate_max", summary="max")]

    def electronic(self, ctx: FrameContext) -> float:
        # μ_d0, the dark signal at zero exposure, is the electronics' offset; the thermal electrons are charge
        return self.offset

    def apply(self, signal: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        return self.add_signal(signal, ctx, thermal_factor(ctx, self.name, self.t_ref, self.t_double), self.offset)

    def add_signal(self, signal: np.ndarray, ctx: FrameContext, factor: float, offset: float = 0.0) -> np.ndarray:
        """``signal`` plus ``offset`` and every pixel's rate × ``factor`` (the mean rate, the pixel's non-uniformity
        value, a hot pixel's own rate): the dark signal of an integration that ``factor`` describes."""
        per_px = ctx.device.state.get(self.key)
        if offset or self.rate or per_px is not None:
            dark = offset + (self.rate + (per_px if per_px is not None else 0.0)) * factor
            signal += per_pixel(np.asarray(dark, signal.dtype), signal)
        sites = ctx.defects(PARTIAL)
        if len(sites) and self._defect_key in sites.extra:
            pixel_view(signal)[sites.y * ctx.shape[1] + sites.x] += (sites.extra[self._defect_key]
                                                                    * factor).astype(signal.dtype)[:, None]
        return signal


@register_effect
@dataclass
class ReadoutDark(Effect):
    """Dark charge collected while the frame is read out: every pixel integrates its dark current for a further
    t_r seconds after the exposure ends (a CCD's rows wait their turn in the register), so hot pixels show in bias
    frames — brighter at the warmer set point — and a dark frame's signal is rate·(t + t_r)·2^((T − T_ref)/T_d).

    Without it the model's dark signal is zero at zero exposure for every pixel but a per-pixel offset (DSNU), which
    cannot double with the temperature: on the 2017 STL-1001E a pixel of ≈ 4,600 ADU/s reads 4,170 ADU in the
    −10 °C biases and 5,160 ADU in the −5 °C ones.  Needs :class:`DarkCurrent` in the model (its rates and law).
    """

    name = "readout_dark"
    description = ("dark charge collected during the read-out: every pixel's dark signal as if exposed t_r seconds "
                   "longer, rate·(t + t_r)·2^((T − T_ref)/T_d) (hot pixels in bias frames)")
    stage = Stage.DARK
    fields = ("exposure_s", "temperature_c")

    t_read: float = param(0.0, "s", "the extra integration of the read-out (t_r)", null=0.0, free=True,
                          bounds=(0.0, None))

    def apply(self, signal: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        dark = next((e for e in ctx.device.model.effects if isinstance(e, DarkCurrent)), None)
        if dark is None or not self.t_read:
            return signal
        # DarkCurrent's own term for an exposure of t_r at this frame's temperature (its offset excepted)
        factor = self.t_read * 2.0 ** ((ctx.require("temperature_c", self.name) - dark.t_ref) / dark.t_double)
        return dark.add_signal(signal, ctx, factor)


@register_effect
@dataclass
class Gain(Effect):
    """Analog gain: the electron signal (light, dark signal, defects) scales with ISO, and so does the noise
    that arises before the amplifier (shot noise; :class:`InputNoise`).  Stuck values, the black level and
    read noise after the amplifier do not."""

    name = "gain"
    description = ("analog gain: the electron signal (light, dark, defects) and the noise before the amplifier "
                   "scale as (ISO/ISO_ref)^exponent")
    stage = Stage.AMPLIFY
    fields = ("iso",)

    iso_ref: float = param(100.0, "ISO", "ISO at which the gain is one")
    exponent: float = param(1.0, "", "power of the ISO ratio (1 for a linear amplifier)", null=0.0, free=True,
                            bounds=(-3.0, 3.0))

    def amplification(self, ctx: FrameContext) -> float:
        return float((ctx.require("iso", self.name) / self.iso_ref) ** self.exponent)

    def apply(self, signal: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        signal *= np.asarray(self.amplification(ctx), signal.dtype)
        return signal


@register_effect
@dataclass
class Nonlinearity(Effect):
    """A global response curve compressing the highlights: y = i − β·i²/full_scale."""

    name = "nonlinearity"
    description = "global response curve: y = i − β·i²/full_scale (compression near saturation)"
    stage = Stage.RESPONSE

    # β ≤ ½: the curve rises over the whole light range [0, full scale] (its peak, at i = full scale/(2β), beyond
    # it) — a response that falls as the light grows is not a response curve; with β up to 1 the fits of the
    # STL-1001E's tiles settled where the peak met their flat fields' level (β ≈ 0.85, at the inverse's clamp)
    beta: float = param(0.05, "", "fraction of the signal lost at full scale", null=0.0, free=True,
                        bounds=(-1.0, 0.5))

    def apply(self, signal: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        signal -= np.float32(self.beta / ctx.full_scale) * signal * signal
        return signal


@register_effect
@dataclass
class ShotNoise(Effect):
    """Shot noise of the collected electrons (photo- and thermal): σ² = g·A·μ.

    μ is the charge signal — above the black level and the electronic offsets
    (:attr:`FrameContext.electronic_offset`) — and A the frame's analog gain (:attr:`FrameContext.amplification`):
    N electrons read K·A·N DN with variance (K·A)²·N = K·A·μ, so ``g`` is the conversion gain K at the
    reference gain."""

    name = "shot_noise"
    description = ("temporal variance grows with the signal above black: σ² = σ_read² + g·A·μ (shot noise of the "
                   "electrons; A the analog gain)")
    stage = Stage.NOISE

    g: float = param(0.5, "DN", "conversion gain: variance added per DN of mean signal (at unit analog gain)",
                     null=0.0, free=True, bounds=(0.0, None))

    def apply(self, signal: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        if self.g > 0:
            offset = ctx.electronic_offset
            charge = signal - (per_pixel(np.asarray(offset, signal.dtype), signal) if np.ndim(offset) else
                               np.float32(offset))
            sd = np.sqrt(np.float32(self.g * ctx.amplification) * np.maximum(charge, 0.0))
            signal += sd * rng.standard_normal(signal.shape, dtype=np.float32)
        return signal

    def variance(self, mean: np.ndarray, ctx: FrameContext) -> np.ndarray | float:
        return self.g * ctx.amplification * np.maximum(mean, 0.0)


@register_effect
@dataclass
class InputNoise(Effect):
    """Read noise arising before the analog gain (input-referred): its σ in DN scales with the gain, σ = σ_in·A.

    Without an analog gain (A = 1) it is indistinguishable from ``read_noise``; with one, the dark frames'
    temporal variance grows with ISO."""

    name = "input_noise"
    description = "temporal noise before the analog gain: σ² = σ_read² + (σ_in·A)², A the ISO gain"
    stage = Stage.NOISE

    sigma_in: float = param(1.0, "DN", "σ of the noise before the amplifier, in DN at unit analog gain", null=0.0,
                            free=True, bounds=(0.0, None))

    def variance(self, mean: np.ndarray, ctx: FrameContext) -> np.ndarray | float:
        return (self.sigma_in * ctx.amplification) ** 2

    def apply(self, signal: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        if self.sigma_in > 0:
            signal += np.float32(self.sigma_in * ctx.amplification) * rng.standard_normal(signal.shape,
                                                                                           dtype=np.float32)
        return signal


@register_effect
@dataclass
class Clusters(Effect):
    """Defects arrive in clusters (a Thomas process) rather than at independent sites."""

    name = "clusters"
    description = "defects arrive in spatial clusters (Thomas process: parents uniform, offspring Gaussian around them)"
    stage = Stage.ARRIVAL
    fields = ("captured",)

    self_fitted = ("rate", "mean_size", "spread", "amplitude")
    largest_value_params = ("amplitude",)

    rate: float = param(2.0, "clusters/MP/year", "arrival rate of clusters", null=0.0, free=True, bounds=(0.0, None))
    mean_size: float = param(4.0, "defects", "mean number of defects per cluster (Poisson)", free=True,
                             bounds=(0.0, None))
    spread: float = param(3.0, "px", "standard deviation of a defect's offset from its cluster centre", free=True,
                          bounds=(0.1, None))
    amplitude: float = param(3.0, "DN", "maximum offset of a clustered partially stuck pixel")

    def inside_fraction(self, shape: tuple[int, int]) -> float:
        """Expected fraction of offspring landing on the sensor (Gaussian spill-over at the four edges)."""
        h, w = shape
        edge = self.spread / np.sqrt(2 * np.pi)
        return float(max(0.0, 1 - edge / w * 2) * max(0.0, 1 - edge / h * 2))

    def expected_arrivals(self, device: Device, times: Any, threshold: dict[int, float]) -> dict[int, np.ndarray]:
        n = (self.rate * device.model.megapixels * elapsed(device, times) * self.mean_size
             * self.inside_fraction(device.model.shape) * uniform_detect_fraction(self.amplitude, threshold.get(PARTIAL, 0)))
        return {PARTIAL: n, STUCK: np.zeros_like(n)}

    def fit(self, evidence: Evidence) -> "Clusters":
        """Thomas-process parameters from the pairs of sites that arrived together, else from Ripley's K.

        A cluster's members appear at once, so the pairs of sites that arrived at the same epoch within r of each
        other, beyond chance, are the clusters' own pairs: Π·(1 − exp(−r²/4σ²)) with Π = clusters ×
        E[N(N − 1)]/2 = clusters × (m·p·ι)²/2 for N ~ Poisson(m·p·ι) detected members (p: the share of
        amplitudes above the threshold, ι: of offspring landing on the sensor), times the share of those pairs
        whose members do not share a pixel (:meth:`Evidence.distinct_pair_share`: ≈ 0.91 for 4 members 2 px
        apart — the rate came out 0.89 ± 0.09 of the truth without it).  That gives σ and the rate.

        Where no pair arrived together beyond chance (clusters all older than the first epoch, one epoch), K of
        the last epoch's sites: K(r) = πr² + A·(1 − exp(−r²/4σ²)) with A = f·m/λ (f: clustered fraction,
        m: mean detected cluster size, λ: site intensity); the rate follows from f and the sites' arrival rate.
        K (like the counts' dispersion) fixes f·m, so ``mean_size`` keeps its value unless f would exceed one.
        """
        amplitude = evidence.amplitude_max(PARTIAL, self.amplitude)
        excess, sigma = evidence.cluster_excess()
        p_detect = evidence.detect_fraction(PARTIAL, amplitude)
        pairs = evidence.co_arrival_excess()
        if pairs.rate > 0 and p_detect > 0:
            # K's excess (when any) may still say the clusters are bigger than ``mean_size``
            f_m = excess * evidence.site_intensity() if excess > 0 else 0.0
            mean_size = max(self.mean_size, f_m / p_detect)
            shaped = replace(self, amplitude=amplitude, spread=float(pairs.sigma), mean_size=mean_size)
            detected = shaped.detected_size(evidence)
            # a cluster of N detected members makes N(N − 1)/2 pairs, fewer where members share a pixel
            pairs_per_cluster = evidence.distinct_pair_share(detected) * detected**2 / 2.0
            return replace(shaped, rate=float(pairs.rate / pairs_per_cluster))
        if excess <= 0 or p_detect <= 0:
            return replace(self, amplitude=amplitude, rate=0.0)
        f_m = excess * evidence.site_intensity()
        mean_size = self.mean_size
        size = mean_size * p_detect
        if f_m > size:
            mean_size = f_m / p_detect
            size = f_m
        fraction = min(1.0, f_m / size)
        # K's λ counts every defective site of the last epoch, stuck ones included, so ``fraction`` is the
        # clustered share of all of them: the clustered sites arrived at that share of the rate of all sites (of
        # the partially stuck ones alone, the rate came out 0.59 ± 0.07 of the truth on the 8-bit convention, whose
        # stuck pixels are half the base arrivals, and the spatial gof after adding clusters lay in 0.03–0.23)
        per_mp_year = evidence.site_rate()
        shaped = replace(self, amplitude=amplitude, spread=float(sigma), mean_size=mean_size)
        return replace(shaped, rate=float(fraction * per_mp_year
                                          / (mean_size * p_detect * shaped.inside_fraction(evidence.shape))))

    def detected_size(self, evidence: Evidence) -> float:
        """Mean number of a cluster's members detected on the sensor: ``mean_size`` × the share of amplitudes
        above the threshold × the share of offspring landing inside."""
        p_detect = evidence.detect_fraction(PARTIAL, self.amplitude)
        return self.mean_size * p_detect * self.inside_fraction(evidence.shape)

    def fit_errors(self, evidence: Evidence) -> dict[str, float]:
        """Standard errors where the rate and spread were read off the pairs that arrived together: the rate's
        from the clusters' Poisson sizes, which dominate it (:func:`forensics.stats.spatial.pair_excess_se`), the
        spread's from a parametric bootstrap of the pair counts (:meth:`Evidence.co_arrival_draws`) — both
        conditional on ``mean_size``, which the pairs cannot fix (:meth:`held`) —, the amplitude's as the base
        growth's (:func:`amplitude_error`)."""
        amplitude = amplitude_error(evidence, "amplitude")
        pairs = evidence.co_arrival_excess()
        lam = self.detected_size(evidence)
        if pairs.rate <= 0 or pairs.exposure <= 0 or lam <= 0:
            return amplitude
        total = pairs.rate * pairs.exposure
        se_total = pair_excess_se(total, lam, pairs.chance)
        spread = evidence.co_arrival_draws(lam)[:, 1]
        pairs_per_cluster = evidence.distinct_pair_share(lam) * lam * lam / 2.0
        return {**amplitude, "rate": se_total / pairs.exposure / pairs_per_cluster,
                "spread": float(np.std(spread, ddof=1))}

    def held(self) -> dict[str, str]:
        return {"mean_size": (f"held at {self.mean_size:.3g}: the pairs of sites that arrived together fix rate × "
                              "size², and the counts fix rate × size only beside the independent arrivals, so the "
                              "data do not separate rate and size (K raises it where the clusters must be larger); "
                              "the rate and its interval are those for this size")}

    def probe(self, evidence: Evidence) -> "Clusters":
        """Clusters of the default size and spread carrying a third of the observed arrivals."""
        amp = evidence.amplitude_max(PARTIAL, self.amplitude)
        p_detect = max(evidence.detect_fraction(PARTIAL, amp), 1e-3)
        rate = evidence.arrival_rate(PARTIAL) / 3 / (self.mean_size * p_detect)
        return replace(self, rate=rate, amplitude=amp)

    def arrivals(self, device: Device, rng: np.random.Generator) -> DefectCatalogue:
        h, w = device.model.shape
        onset_parent = constant_rate_onsets(self.rate, device, rng, "poisson")
        px, py = rng.uniform(0, w, len(onset_parent)), rng.uniform(0, h, len(onset_parent))
        sizes = rng.poisson(self.mean_size, len(onset_parent))
        parent = np.repeat(np.arange(len(onset_parent)), sizes)
        x = np.floor(px[parent] + self.spread * rng.standard_normal(len(parent))).astype(np.int64)
        y = np.floor(py[parent] + self.spread * rng.standard_normal(len(parent))).astype(np.int64)
        inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        amp = rng.uniform(0, 1, len(parent)) * self.amplitude
        return records(x[inside], y[inside], PARTIAL, amp[inside], onset_parent[parent][inside], self.name)


@register_effect
@dataclass
class AcceleratingGrowth(Effect):
    """Defects arrive at a rate that changes with age: cumulative Λ(t) = θ·t^β per megapixel."""

    name = "accelerating_growth"
    description = "arrival rate changing with age: expected defects Λ(t) = θ·(t − t0)^β per megapixel"
    stage = Stage.ARRIVAL
    fields = ("captured",)

    self_fitted = ("amplitude",)
    largest_value_params = ("amplitude",)

    theta: float = param(0.5, "defects/MP/year^β", "scale of the cumulative intensity", null=0.0, free=True,
                         bounds=(0.0, None))
    beta: float = param(2.0, "", "shape: 1 is constant rate, > 1 accelerating, < 1 decelerating", free=True,
                        bounds=(0.2, 8.0))
    amplitude: float = param(3.0, "DN", "maximum offset of a partially stuck pixel from this process")

    def expected_arrivals(self, device: Device, times: Any, threshold: dict[int, float]) -> dict[int, np.ndarray]:
        n = (self.theta * device.model.megapixels * elapsed(device, times) ** self.beta
             * uniform_detect_fraction(self.amplitude, threshold.get(PARTIAL, 0)))
        return {PARTIAL: n, STUCK: np.zeros_like(n)}

    def fit(self, evidence: Evidence) -> "AcceleratingGrowth":
        return replace(self, amplitude=evidence.amplitude_max(PARTIAL, self.amplitude))

    def fit_errors(self, evidence: Evidence) -> dict[str, float]:
        return amplitude_error(evidence, "amplitude")

    def probe(self, evidence: Evidence) -> "AcceleratingGrowth":
        return replace(self, amplitude=evidence.amplitude_max(PARTIAL, self.amplitude))

    def arrivals(self, device: Device, rng: np.random.Generator) -> DefectCatalogue:
        t0 = device.model.t0
        horizon = max([t for t in device.times if t > t0], default=t0)
        span = horizon - t0
        if span <= 0 or self.theta <= 0:
            return DefectCatalogue.empty()
        n = rng.poisson(self.theta * device.model.megapixels * span**self.beta)
        onset = np.sort(t0 + span * rng.uniform(0, 1, n) ** (1.0 / self.beta))  # inverse of Λ(t)/Λ(T)
        x, y = uniform_sites(n, device.model.shape, rng)
        return records(x, y, PARTIAL, rng.uniform(0, 1, n) * self.amplitude, onset, self.name)


def describe_effects() -> list[dict[str, Any]]:
    """Every registered effect: name, description, stage, needed fields and parameters."""
    from forensics.sensor.model import EFFECTS

    return [{"name": cls.name, "description": cls.description, "stage": cls.stage.name.lower(),
             "role": cls.role, "fields": list(cls.fields), "params": cls.parameter_info()}
            for cls in EFFECTS.values()]
