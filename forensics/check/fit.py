"""Fitting a model to the evidence: arrival effects on the counts, pixel effects on the first half of the
repeats, noise effects on the binned variances.

A fit never changes the effects it is given: it returns a :class:`FittedModel` carrying new effect objects
(with the fitted values) and its own device (with the fitted fixed patterns).
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import optimize

from forensics.check.arrivals import DefectCounts
from forensics.check.classes import NORMAL, QUANT_VAR
from forensics.check.evidence import Evidence
from forensics.check.identifiability import bounded_step, estimates
from forensics.check.params import bespoke_fit, is_pixel, on_device, on_model, unit, with_clipped_param, with_param
from forensics.check.pixelfit import fit_pixels, used_blocks
from forensics.check.pixels import PixelData, VarianceBins, log_variance, pattern_size, with_latent_spread
from forensics.check.prediction import PHASE_SIGMA, SCENE_SHIFT, bin_offsets, predicted_variance
from forensics.check.joint_solve import coupled_shrink
from forensics.check.local_solve import PixelProjector, shrink_local
from forensics.check.measurements import Group
from forensics.check.result import ParamEstimate, PatternEstimate
from forensics.check.streams import NULL_SIMULATIONS, PATTERN_SIZE_STREAM
from forensics.sensor.catalogue import PARTIAL, STUCK, DefectCatalogue
from forensics.sensor.model import Device, Effect, SensorModel, Stage


#: The converters the check compares where the noise is low enough for the quantiser to show
#: (:func:`fit_noise_and_quantiser`): rounding alone, and rounding after a uniform dither of 1 DN.
DITHERS = (0.0, 1.0)
#: How much better (in the variance channel's χ²) a dithered converter must fit than plain rounding to be taken:
#: a likelihood ratio of e⁵ ≈ 150 between two models with the same parameters.
DITHER_MARGIN = 10.0
#: A converter other than the one assumed is taken only where the noise model fits the variance bins with it to this
#: χ² per bin: a model that lacks a noise effect misfits them by far more than any converter could explain, and its
#: χ² differences say nothing about the converter (the base model took a dither on 8-bit data without one, and
#: each change costs a refit).
CONVERTER_FIT = 4.0


@dataclass(frozen=True)
class FittedModel:
    """A model fitted to the evidence: the fitted effects, the device (fitted defects and patterns), the pixel
    data it was fitted with, and the fit's by-products."""

    device: Device
    effects: list[Effect]
    pixels: PixelData
    mu_a: np.ndarray
    mu_b: np.ndarray
    nuisance: list[np.ndarray]
    projector: PixelProjector
    params: list[ParamEstimate]
    patterns: list[PatternEstimate]
    expected: dict[int, np.ndarray]
    arrival_free: list[tuple[str, str]]
    growth_jac: np.ndarray | None
    variance_pred: np.ndarray
    variance_jac: np.ndarray | None
    spatial_null: dict[str, Any] | None
    sims: dict[str, Any] = field(default_factory=dict)
    #: per (condition, pixel), the variance the fitted pixel-local patterns' estimation noise adds to a held-out
    #: mean's prediction (what error² exceeds 1 by under the fitted model; None without such patterns)
    estimation_var: np.ndarray | None = None
    #: the pixel channel's global parameters' derivative columns at the fit's last step, weighted and profiled
    #: against the pixel-local patterns (:attr:`~forensics.check.pixelfit.PixelFit.global_columns`)
    global_columns: list[np.ndarray] = field(default_factory=list)
    #: the converter the variance channel shows (:func:`fit_noise_and_quantiser`; the device's ``dither``)
    quantiser: "QuantiserChoice | None" = None

    @property
    def not_converged(self) -> list[str]:
        """Parameters whose fit did not settle (``effect.name``); the fit is then not a result."""
        return [p.label for p in self.params if not p.converged]

    def arrival_effects(self) -> list[Effect]:
        return [e for e in self.effects if e.stage == Stage.ARRIVAL]

    def noise_effects(self) -> list[Effect]:
        return [e for e in self.effects if e.stage == Stage.NOISE]


def fit_model(ev: Evidence, effects: Sequence[Effect], max_cycles: int = 48,
              start: Mapping[str, float] | None = None, dither: float | None = None) -> FittedModel:
    """Fit ``effects`` to the evidence (the objects given are left unchanged).

    Pixel classes come from defect detection; when the model has fixed patterns on normal pixels, detection is
    repeated against the fitted model's prediction for defect-free pixels and the model refitted once — unless
    the first fit did not settle (detection against a model that is still moving finds defects everywhere).
    ``start``: the global pixel parameters to start from (:func:`warm_start`; default the effects' own starts).
    The converter is the one the variance channel shows (:func:`fit_noise_and_quantiser`); ``dither``: the one
    the fit assumes until then (None: plain rounding; ``--auto`` passes the previous model's), and where the noise
    fit shows another, the model is refitted with that one.
    """
    pixels = ev.pixels()
    fitted = _fit_once(ev, pixels, effects, max_cycles, start=start, dither=dither)
    if fitted.not_converged:
        return fitted
    device = fitted.device
    covers_normal = any(bool(np.any((p.blocks >= 0) & (pixels.classes[-1] == NORMAL)))
                        for e in device.model.effects if is_pixel(e) and e.null_values() for p in e.patterns(device))
    catalogue = ev.redetect(device) if covers_normal else pixels.catalogue
    same = same_catalogue(catalogue, pixels.catalogue)
    if not same or fitted.quantiser.dither != fitted.quantiser.assumed:
        # the refit starts where the first fit ended: its global parameters and its patterns' values at the
        # same pixels (the new classes move them little; from the patterns' cold start the refit of the
        # hidden dark-current dataset spent four cycles finding them again, from the first fit's two); after the
        # variance channel changed its mind on the converter, so that the pixel channel's means near the bounds
        # follow it too
        fitted = _fit_once(ev, pixels if same else ev.pixels(catalogue), fitted.effects, max_cycles,
                           start=fitted_values(fitted.effects), patterns_from=fitted.device,
                           dither=device.model.dither)
    return fitted


def same_catalogue(a: DefectCatalogue, b: DefectCatalogue | None) -> bool:
    if b is None or len(a) != len(b):
        return False
    ka = sorted(zip(a.y.tolist(), a.x.tolist(), a.kind.tolist(), a.onset.tolist()))
    kb = sorted(zip(b.y.tolist(), b.x.tolist(), b.kind.tolist(), b.onset.tolist()))
    return ka == kb


def at_null(effect: Effect) -> Effect:
    """The effect with every fitted parameter that has a null value at it: fits start from the smaller model
    (arrival effects keep their own starting values, set from the counts)."""
    if effect.stage == Stage.ARRIVAL:
        return effect
    nulls = effect.null_values()
    start = {n: nulls[n] for n in effect.free_params() if n in nulls}
    return dataclasses.replace(effect, **start) if start else effect


def warm_start(effects: Sequence[Effect], start: Mapping[str, float], indices: Sequence[int]) -> list[Effect]:
    """``effects`` with the free parameters of ``effects[indices]`` set from ``start`` (``effect.name`` → value, e.g.
    :func:`fitted_values` of a previous fit of the same model), each clipped to its bounds; everything else —
    patterns, their spreads, the noise — starts as in a cold fit.  Why: the refit after re-detection starts from
    the first fit's global parameters, which the new pixel classes move little (from the nulls it spent as many
    cycles again finding them); a tile of a frame starts from the central tile's."""
    out = list(effects)
    for i in indices:
        values = {}
        for n in out[i].free_params():
            v = start.get(f"{out[i].key}.{n}")
            if v is not None and np.isfinite(v):
                lo, hi = out[i].bounds(n)
                values[n] = float(min(max(v, lo), hi))
        out[i] = dataclasses.replace(out[i], **values) if values else out[i]
    return out


def carry_patterns(source: Device, target: Device, effects: Sequence[Effect]) -> None:
    """Set ``target``'s patterns of ``effects`` (in place: a fit's own new device) to ``source``'s values at the
    same pixels — the same effect (by key), the same pattern (by name), a pixel that both patterns cover; every
    other value keeps its start.  A defect's amplitude follows its pixel, whatever its record's index in either
    catalogue.

    Examples
    --------
    >>> import numpy as np
    >>> from forensics.sensor.effects import Prnu
    >>> from forensics.sensor.model import Device, SensorModel
    >>> model = SensorModel(shape=(2, 3), bit_depth=12, effects=[Prnu()])
    >>> a, b = Device(model=model), Device(model=model)
    >>> for d in (a, b):
    ...     Prnu().realize(d, np.random.default_rng(0))
    >>> a.state[Prnu().key][...] = np.arange(6).reshape(2, 3)
    >>> carry_patterns(a, b, [Prnu()])
    >>> b.state[Prnu().key].tolist()
    [[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]]
    """
    before = {e.key: e for e in source.model.effects}
    for effect in effects:
        old = before.get(effect.key)
        if old is None:
            continue
        old_patterns = {p.name: p for p in old.patterns(source)}
        for pattern in effect.patterns(target):
            previous = old_patterns.get(pattern.name)
            if previous is None or previous.blocks.shape != pattern.blocks.shape:
                continue
            both = (pattern.blocks >= 0) & (previous.blocks >= 0)
            pattern.values[pattern.blocks[both]] = previous.values[previous.blocks[both]]


def fitted_values(effects: Sequence[Effect]) -> dict[str, float]:
    """Every free parameter's value as ``effect.name`` → value (what :func:`warm_start` takes)."""
    return {f"{e.key}.{n}": float(getattr(e, n)) for e in effects for n in e.free_params()}


def _fit_once(ev: Evidence, pixels: PixelData, effects: Sequence[Effect], max_cycles: int,
              start: Mapping[str, float] | None = None, patterns_from: Device | None = None,
              dither: float | None = None) -> FittedModel:
    """One fit of every channel; ``start``: a previous fit of the same model whose global pixel parameters the
    pixel fit starts from (:func:`warm_start`); ``patterns_from``: that fit's device, whose pattern values the
    pixel fit starts from where the same pixel carries the same pattern (:func:`carry_patterns`); ``dither``: the
    converter the pixel fit assumes (None: plain rounding; the noise fit then picks one,
    :func:`fit_noise_and_quantiser`)."""
    effects = [at_null(e) for e in SensorModel(shape=ev.shape, bit_depth=ev.bit_depth, effects=list(effects),
                                               t0=float(ev.times[0])).effects]  # in stage order
    # ---------------------------------------------------------------- arrivals
    a_idx = [i for i, e in enumerate(effects) if e.stage == Stage.ARRIVAL]
    arrival = fit_arrivals(ev, ev.defects, [effects[i] for i in a_idx])
    for i, e in zip(a_idx, arrival.effects):
        effects[i] = e
    # ---------------------------------------------------------------- pixel channel
    device = Device(model=SensorModel(shape=ev.shape, bit_depth=ev.bit_depth, effects=effects, t0=float(ev.times[0]),
                                      dither=DITHERS[0] if dither is None else dither),
                    times=tuple(float(t) for t in ev.times),
                    catalogue=pixels.catalogue.select(np.arange(len(pixels.catalogue))))
    rng = ev.streams.patterns()
    for e in effects:
        if e.stage != Stage.ARRIVAL:
            e.realize(device, rng)
    for e in effects:
        if is_pixel(e) and e.null_values():
            for pat in e.patterns(device):
                pat.values[...] = 0.0
    p_idx = [i for i, e in enumerate(effects) if is_pixel(e)]
    if patterns_from is not None:
        carry_patterns(patterns_from, device, [effects[i] for i in p_idx])
    for i in p_idx:
        effects[i] = bespoke_fit(effects[i], ev)
    if start is not None:
        effects = warm_start(effects, start, p_idx)
    # a first look at the noise (the pixel channel's censored means near 0 and full scale depend on it), under the
    # converter assumed: the bins' fractional levels are the neighbours' until the fit gives the pixels' own, and
    # with an offset pattern those show a swing the pixels do not have (a first look comparing converters took the
    # dither on 8-bit data without one); the converters are compared once the pixels' levels are known
    n_idx = [i for i, e in enumerate(effects) if e.stage == Stage.NOISE]
    first = fit_variance(pixels.bins, ev.rgroups, [bespoke_fit(effects[i], ev) for i in n_idx],
                         on_device(device, effects))
    for i, e in zip(n_idx, first.effects):
        effects[i] = e
    pix = fit_pixels(ev, pixels, device, effects, p_idx, max_cycles)
    effects = pix.effects
    projector = PixelProjector([c * np.sqrt(pixels.weight) for c in pix.nuisance],
                               [p.random_effect for _, p in pix.local])
    effects, patterns = pattern_summaries(on_device(device, effects), effects, p_idx, pix.local, pix.local_var)
    patterns = with_sizes(ev, pixels, patterns, pix.local, effects, pix.nuisance)
    effects, patterns = hypers_from_sizes(effects, patterns)
    # (the near-bound variance bins' latent spread keeps the values shrunk pixel by pixel: the coupled shrinkage's
    # are the best predictions, but their spread is under the pattern's — 8-bit DSNU: input noise flagged, ΔBIC 15)
    # the shrinkage weighs each mean by what it says about the values: the slope of the mean the data show (near
    # 0 DN the truncated mean of the readouts that never touched it: a median 0.14 of the latent mean's at 8 bits)
    slope = censored_slope(ev.predictor, on_device(device, effects), pixels)
    spread_values = shrink_random_effects(pix.pattern_weight, pix.local, [x * slope for x in pix.nuisance], patterns,
                                          effects, pix.coupling, ev.meas.mean_a - pix.mu_a)
    # ---------------------------------------------------------------- variance
    for i in n_idx:
        effects[i] = bespoke_fit(effects[i], ev)
    # the noise laws see the fitted pixel effects (an analog gain amplifies the noise before it)
    device = on_device(device, effects)
    pixels = dataclasses.replace(pixels, bins=with_latent_spread(
        pixels.bins, ev.predictor.predict(with_local_values(device, pix.local, effects, spread_values), pixels, "a",
                                          clip=False)))
    noise, device, quantiser = fit_noise_and_quantiser(pixels.bins, ev.rgroups, [effects[i] for i in n_idx], device)
    for i, e in zip(n_idx, noise.effects):
        effects[i] = e
    device = on_device(device, effects)
    if SCENE_SHIFT in device.state:  # the shrunk patterns' neighbour term
        device.state[SCENE_SHIFT] = ev.predictor.scene_shift(device, pixels)
    mu_b = ev.predictor.predict(device, pixels, "b")
    sims, spatial_null = {}, None
    arrivals, expected = arrival.effects, arrival.expected
    if arrivals and len(ev.times) >= 2:
        sims, spatial_null = ev.simulations(
            NULL_SIMULATIONS, arrivals,
            lambda: ev.defects.simulate_null(arrivals, expected, ev.streams.stream(NULL_SIMULATIONS), ev.streams.n_sim))
    params = [*arrival.params, *pix.params, *noise.params]  # the order of the stages
    return FittedModel(device, effects, pixels, pix.mu_a, mu_b, pix.nuisance, projector, params, patterns, expected,
                       arrival.free, arrival.jacobian, noise.predicted, noise.jacobian, spatial_null, sims,
                       estimation_variance(pix.local, pix.nuisance, pix.local_var, patterns, effects),
                       pix.global_columns, quantiser)


def estimation_variance(local: list, derivatives: list[np.ndarray], local_var: np.ndarray | None,
                        patterns: list[PatternEstimate], effects: list[Effect]) -> np.ndarray | None:
    """Σ_j X_j²·m_j: the variance the pixel-local patterns' estimation error adds to a prediction, with m_j a
    pattern's mean square error at each pixel — its least-squares variance v, or for a shrunk random effect of
    variance τ² the best linear predictor's v·τ²/(τ² + v) (patterns taken as independent)."""
    if not local or local_var is None:
        return None
    rms = {(pe.effect, pe.name): pe.rms for pe in patterns}
    out = np.zeros_like(derivatives[0])
    for (i, p), x, v in zip(local, derivatives, local_var):
        v = np.where(np.isfinite(v), v, 0.0)
        if p.random_effect:
            tau2 = rms.get((effects[i].key, p.name), 0.0) ** 2
            v = v * tau2 / np.maximum(tau2 + v, 1e-300)
        out += x * x * v[None]
    return out


def _log_scale(effect: Effect, name: str) -> bool:
    """Positive, unbounded parameters are optimised on a log scale."""
    lo, hi = effect.bounds(name)
    return lo >= 0 and bool(np.isinf(hi))


@dataclass(frozen=True)
class ArrivalFit:
    """The growth channel's fit (:func:`fit_arrivals`)."""

    effects: list[Effect]  #: the fitted arrival effects
    expected: dict[int, np.ndarray]  #: expected defect counts per kind at every epoch
    free: list[tuple[str, str]]  #: the free parameters, as (effect, name)
    jacobian: np.ndarray | None  #: of the expected increments by the free parameters
    params: list[ParamEstimate]  #: their estimates (and the effects' self-fitted values)


def fit_arrivals(evidence: Evidence, counts: DefectCounts, arrivals: list[Effect]) -> ArrivalFit:
    """Fit the arrival effects to the count increments (Poisson likelihood; bespoke fits first)."""
    times = counts.times
    if not arrivals:
        return ArrivalFit([], {PARTIAL: np.zeros(len(times)), STUCK: np.zeros(len(times))}, [], None, [])
    params: list[ParamEstimate] = []
    arr = list(arrivals)
    free = [(j, n) for j, e in enumerate(arr) for n in e.free_params()]

    def unpack(effs: list[Effect], theta: np.ndarray) -> list[Effect]:
        for (j, n), t in zip(free, theta):
            lo, hi = effs[j].bounds(n)
            effs = with_param(effs, j, n, float(np.exp(t)) if _log_scale(effs[j], n) else float(np.clip(t, lo, hi)))
        return effs

    def increments(effs: list[Effect]) -> tuple[np.ndarray, np.ndarray]:
        return counts.increments(counts.expected_counts(effs))

    converged = True
    for _ in range(3):
        arr = [bespoke_fit(e, evidence) for e in arr]
        if not free or len(times) < 2:
            break
        obs, exp = increments(arr)
        # starting values: scale rates so the total matches the observed count
        total_obs, exp_total = obs.sum(), exp.sum()
        if exp_total > 0 and total_obs > 0:
            for j, n in free:
                if _log_scale(arr[j], n) and arr[j].null_values().get(n) is None:
                    arr = with_param(arr, j, n, getattr(arr[j], n) * total_obs / exp_total)

        def nll(theta: np.ndarray, start: list[Effect] = arr) -> float:
            o, m = increments(unpack(start, theta))
            m = np.maximum(m, 1e-12)
            return float(np.sum(m - o * np.log(m)))

        x0 = np.array([np.log(max(getattr(arr[j], n), 1e-9)) if _log_scale(arr[j], n) else getattr(arr[j], n)
                       for j, n in free], float)
        bounds = []
        for j, n in free:
            lo, hi = arr[j].bounds(n)
            # positive parameters are optimised on a log scale, kept within e^-25 … e^25
            bounds.append((-25.0, 25.0) if _log_scale(arr[j], n) else (lo if np.isfinite(lo) else None,
                                                                       hi if np.isfinite(hi) else None))
        best = optimize.minimize(nll, x0, method="L-BFGS-B", bounds=bounds)
        converged = bool(np.all(np.isfinite(best.x))) and (bool(best.success) or stationary(nll, best.x, bounds))
        arr = unpack(arr, best.x)
    expected = counts.expected_counts(arr)
    jac = None
    if free:
        base = counts.increments(expected)[1]
        cols = []
        for j, n in free:
            v = getattr(arr[j], n)
            d = 1e-4 * (1 + abs(v))
            cols.append((increments(with_param(arr, j, n, v + d))[1] - base) / d)
        jac = np.array(cols)
        m = np.maximum(base, 1e-9)
        params += estimates(arr, free, (jac / m) @ jac.T, converged)
    for e in arr:
        errors = e.fit_errors(evidence)
        held = e.held()
        for n in e.self_fitted:
            if n in held:
                continue  # stated as not identifiable with the effect's reason (identifiability.with_held)
            params.append(ParamEstimate(e.key, n, float(getattr(e, n)), errors.get(n), unit(e, n),
                                        quadratic=n not in e.largest_value_params))
    return ArrivalFit(arr, expected, [(arr[j].key, n) for j, n in free], jac, params)


def stationary(fun: Callable[[np.ndarray], float], x: np.ndarray, bounds: Sequence[tuple[float | None, float | None]],
               step: float = 1e-4, tol: float = 1e-6) -> bool:
    """Whether ``x`` minimises the negative log-likelihood ``fun`` to within ``tol`` (in log-likelihood units):
    along every coordinate the decrease a Newton step would still give, g²/(2h) from central differences, is below
    ``tol`` — or the coordinate sits on a bound with the gradient pointing out of the box.

    Why: L-BFGS-B started *at* its optimum (a refit whose counts did not change) cannot make its line search
    decrease the objective and reports an abnormal termination, which is no failure to converge.

    Examples
    --------
    >>> stationary(lambda t: float((t[0] - 1.0) ** 2), np.array([1.0]), [(None, None)])
    True
    >>> stationary(lambda t: float((t[0] - 1.0) ** 2), np.array([0.9]), [(None, None)])
    False
    """
    f0 = fun(x)
    for i in range(len(x)):
        e = np.zeros_like(x, dtype=float)
        e[i] = step
        up, down = fun(x + e), fun(x - e)
        g = (up - down) / (2 * step)
        h = (up - 2 * f0 + down) / step**2
        lo, hi = bounds[i]
        if (lo is not None and x[i] - lo <= step and g > 0) or (hi is not None and hi - x[i] <= step and g < 0):
            continue  # on a bound, pushed against it
        if not (h > 0 and g * g / (2 * h) < tol):
            return False
    return True


def pattern_summaries(device: Device, effects: list[Effect], p_idx: list[int], local: list,
                      local_var: np.ndarray | None) -> tuple[list[Effect], list[PatternEstimate]]:
    """Each fixed pattern's size (rms of its fitted values less their estimation noise), and the effects with
    the parameters that summarise their patterns (``Pattern.hyper``) set from it."""
    var_by_id = {}
    if local_var is not None:
        for (i, p), v in zip(local, local_var):
            var_by_id[p.name, effects[i].key] = (p.blocks, v)
    out = []
    for i in p_idx:
        e = effects[i]
        for p in e.patterns(device):
            used = used_blocks(p)
            if used.size == 0:
                out.append(PatternEstimate(e.key, p.name, 0, 0.0, 0.0, p.hyper, None))
                continue
            vals = p.values[used].astype(float)
            item = var_by_id.get((p.name, e.key))
            noise = 0.0
            if item is not None:
                # NaN: not determined at that pixel (no data, or collinear with another pattern) or not scored
                # (the border): the value there is not a measurement of the pattern
                blocks, var = item
                m = blocks >= 0
                block_var = np.full(len(p.values), np.nan)
                block_var[blocks[m]] = var[m]
                measured = np.isfinite(block_var[used])
                if measured.any():
                    vals = vals[measured]
                    noise = float(block_var[used][measured].mean())
            ms = float(np.mean(vals**2))
            rms = math.sqrt(max(ms - noise, 0.0))
            hyper_value = None
            if p.hyper:
                hyper_value = {"rms": rms, "max": float(vals.max()), "mean": float(vals.mean())}[p.summary]
                effects = with_param(effects, i, p.hyper, hyper_value)
            out.append(PatternEstimate(e.key, p.name, int(used.size), rms, float(np.max(np.abs(vals))), p.hyper,
                                       hyper_value))
    return effects, out


def with_sizes(ev: Evidence, pixels: PixelData, patterns: list[PatternEstimate], local: list,
               effects: list[Effect], derivatives: list[np.ndarray]) -> list[PatternEstimate]:
    """Each pixel-local pattern's size as the frames show it, with its standard error
    (:func:`~forensics.check.pixels.pattern_size`: split-half cross-product, free of the noise floor; the fitted
    values' rms depends on the floor's accuracy and on how much of the pattern the 7 × 7 scene estimate absorbs),
    each profiled against the model's other pixel-local patterns.
    """
    sized = {}
    ok = ev.usable & (pixels.classes == NORMAL)
    for n, ((i, p), x) in enumerate(zip(local, derivatives)):
        if not p.random_effect:
            continue
        others = [d for m, d in enumerate(derivatives) if m != n]
        est = pattern_size(ev.meas, pixels, x, ok, ev.streams.stream(PATTERN_SIZE_STREAM), others)
        if est is not None and math.isfinite(est.se):
            sized[effects[i].key, p.name] = est
    return [dataclasses.replace(pe, size=sized[pe.effect, pe.name].sigma, size_se=sized[pe.effect, pe.name].se)
            if (pe.effect, pe.name) in sized else pe for pe in patterns]


def hypers_from_sizes(effects: Sequence[Effect], patterns: Sequence[PatternEstimate]
                      ) -> tuple[list[Effect], list[PatternEstimate]]:
    """The random-effect patterns' spreads (``sigma_k``, ``sigma_o``…) set to their size as the frames show it
    (:attr:`PatternEstimate.size`, the split-half cross-product), where it was measured; elsewhere they stay the
    fitted values' rms less their estimation noise.

    Why: the rms less the per-pixel noise misses the noise of the modes only some frames determine.  8-bit DSNU
    at a 0 DN black level (truth σ_o 0.19 DN): the rms read 0.31 DN, the split-half size 0.195 ± 0.002 DN.  The
    spread is a summary only (the fit zeroes and refits the values), so no prediction changes.

    Examples
    --------
    >>> from forensics.sensor.effects import Dsnu
    >>> pe = PatternEstimate("dsnu", "o", 4, rms=0.31, maximum=0.9, hyper="sigma_o", hyper_value=0.31, size=0.195)
    >>> effects, (out,) = hypers_from_sizes([Dsnu(sigma_o=0.31)], [pe])
    >>> effects[0].sigma_o, out.hyper_value
    (0.195, 0.195)
    """
    out_effects, out_patterns = list(effects), []
    index = {e.key: i for i, e in enumerate(out_effects)}
    for pe in patterns:
        i = index.get(pe.effect)
        # (only random-effect patterns are sized: :func:`with_sizes`)
        if pe.size is not None and pe.hyper and i is not None and math.isfinite(pe.size):
            out_effects = with_param(out_effects, i, pe.hyper, float(pe.size))
            pe = dataclasses.replace(pe, hyper_value=float(pe.size))
        out_patterns.append(pe)
    return out_effects, out_patterns


def shrink_random_effects(weight: np.ndarray, local: list, derivatives: list[np.ndarray],
                          patterns: list[PatternEstimate], effects: list[Effect],
                          coupling: tuple[list[np.ndarray], np.ndarray] | None = None,
                          residual: np.ndarray | None = None) -> np.ndarray | None:
    """Move the pixel-local patterns' fitted values, in place, to the best linear unbiased predictor: each
    random-effect pattern (:attr:`~forensics.sensor.model.Pattern.random_effect`) gets a zero-mean prior of
    its fitted variance τ² (the values' mean square less their estimation noise), the other patterns none
    (:func:`~forensics.check.local_solve.shrink_local`).

    Why: a pattern fitted from one half of the frames carries that half's noise, and the held-out half is
    predicted from it.  Where the pattern is weak against the noise (a JPEG flat's PRNU with five frames a
    half: τ² ≈ 0.1–0.2 of the estimation variance) the unshrunk values add more noise than pattern and the
    held-out error rises (1.06 → 1.41 on the shared Nikon flats, docs/CHECK_ON_JPEG_FLATS.md); shrunk, it
    falls.  Where the pattern is strong the prior is weak against the data and nothing changes.  A pattern
    fitted to nothing (τ² = 0) is set to 0.

    ``derivatives`` are the slopes of the means the data show (near 0 DN, the truncated means of the readouts that
    never touched it, whose slope is a fraction of the latent mean's: :func:`censored_slope`) — what each mean
    says about the values.  ``coupling``: the fit's neighbour coupling (Z, F) where dark frames make the scene
    estimates' term matter.  An additive pattern (Z ≠ 0) is then shrunk with it
    (:func:`~forensics.check.joint_solve.coupled_shrink`): its smooth modes, which the scene estimates absorb in
    the light frames, carry the dark frames' information only — so its prior τ is the pattern's size as the
    frames show it (:attr:`PatternEstimate.size`, the split-half cross-product), where measured, not the values'
    rms less the per-pixel noise, which misses the smooth modes' noise.  8-bit DSNU (σ_o 0.19 DN, black level
    0 DN, most dark means censored; seed 4): the values' error against the truth 0.26 DN shrunk pixel by pixel
    with the latent slopes, 0.16 DN coupled, 0.13 DN coupled with the censored slopes (median 0.14, quartiles
    0.10–0.23 at the kept dark means: the latent slope of 1 read 16.9 units of information per pixel in the dark
    frames where there are 0.97, median 0.12); the
    smooth error they left in both halves' light-frame predictions had flagged prnu after `dsnu` (ΔBIC 14.7;
    with both corrections nothing is flagged).  Returns, where the coupling was used, the values the
    pixel-by-pixel shrinkage gives
    (k, H, W), else None.
    """
    if not local or not any(p.random_effect for _, p in local):
        return None
    moves = [False] * len(local) if coupling is None else [bool(np.any(z)) for z in coupling[0]]
    rms = {(pe.effect, pe.name): pe.rms for pe in patterns}
    size = {(pe.effect, pe.name): pe.size for pe in patterns}
    precision = np.zeros(len(local))  # the local shrinkage's prior: τ from the values' rms
    for j, (i, p) in enumerate(local):
        if p.random_effect:
            tau = rms.get((effects[i].key, p.name), 0.0)
            precision[j] = 1.0 / tau**2 if tau > 0 else np.inf
    coupled_precision = precision.copy()  # the coupled one's: τ from the size, for the patterns that move
    for j, (i, p) in enumerate(local):
        if p.random_effect and moves[j] and size.get((effects[i].key, p.name)):
            coupled_precision[j] = 1.0 / size[effects[i].key, p.name] ** 2
    coef = np.zeros((len(local), *weight.shape[1:]))
    for j, (_, p) in enumerate(local):
        m = p.blocks >= 0
        coef[j][m] = p.values[p.blocks[m]]
    coupled = any(m and p.random_effect and 0 < q < np.inf for m, (_, p), q in zip(moves, local, coupled_precision))
    local_only = shrink_local(weight, derivatives, coef, precision)
    shrunk = coupled_shrink(derivatives, coupling[0], coupling[1], weight, coef, coupled_precision, residual) \
        if coupled else local_only
    for j, (_, p) in enumerate(local):
        m = p.blocks >= 0
        p.values[p.blocks[m]] = shrunk[j][m].astype(p.values.dtype)
    return local_only if coupled else None


def censored_slope(predictor, device: Device, pixels, step: float = 1e-3) -> np.ndarray:
    """(R, H, W): the slope of the mean readout the data show (:meth:`Predictor.censor`) by the latent mean, at the
    fitted model — 1 away from the bounds, under 1 where the means kept are truncated (the pixels that never
    touched 0 or full scale).  The pixel fit's derivatives are the latent mean's."""
    raw = predictor.predict(device, pixels, "a", clip=False)
    return (predictor.censor(device, raw + step) - predictor.censor(device, raw)) / step


def with_local_values(device: Device, local: list, effects: list[Effect], coef: np.ndarray | None) -> Device:
    """``device`` with the pixel-local patterns' values replaced by ``coef`` (k, H, W) in a copy of their state
    (``device`` itself if None)."""
    if coef is None:
        return device
    state = {k: (np.array(v, copy=True) if isinstance(v, np.ndarray) else v) for k, v in device.state.items()}
    out = Device(model=device.model, times=device.times, catalogue=device.catalogue, state=state)
    for j, (i, p) in enumerate(local):
        mine = next((q for q in effects[i].patterns(out) if q.name == p.name), None)
        if mine is not None and np.shares_memory(mine.values, state.get(effects[i].key, np.empty(0))):
            m = mine.blocks >= 0
            mine.values[mine.blocks[m]] = coef[j][m].astype(mine.values.dtype)
    return out


#: The variance fit has settled when a step lowers χ² by less than this (absolute: a move of ≈ 10⁻³ of a
#: standard error, where χ² is in units of its own noise; the relative 10⁻¹⁰ of χ² used before ran ≈ 10 more
#: Gauss–Newton steps on the EMVA 1288 standard series, each moving the noise by under 10⁻⁴ of its SE).
VARIANCE_SETTLED = 1e-6


@dataclass(frozen=True)
class NoiseFit:
    """The variance channel's fit (:func:`fit_variance`)."""

    effects: list[Effect]  #: the fitted noise effects
    predicted: np.ndarray  #: predicted variance per bin
    jacobian: np.ndarray | None  #: of the log prediction by the free parameters
    params: list[ParamEstimate]  #: their estimates
    chi2: float = 0.0  #: the weighted squared misfit of the log variances at the fit


def fit_variance(bins: VarianceBins, rgroups: Sequence[Group], noise: list[Effect], device: Device) -> NoiseFit:
    """Fit the noise effects to the log binned variances (weighted Gauss–Newton with step halving).

    Two starts: the effects as given (the null values: the smaller model), and each free parameter that sits
    at its null value moved to its default; the better fit is kept, so the result is never worse than the
    smaller model.  Why a second start: a noise σ enters the variance as σ², whose derivative is 0 at σ = 0,
    so a fit started there never leaves it.

    """
    free = [(j, n) for j, e in enumerate(noise) for n in e.free_params()]
    params: list[ParamEstimate] = []
    y = log_variance(bins.observed, bins.df)
    w = bins.df / 2.0
    jac = None

    offsets = bin_offsets(bins, rgroups, device)  # the device is fixed: only the noise laws change

    def log_pred(effs: list[Effect]) -> np.ndarray:
        return np.log(predicted_variance(bins, rgroups, effs, device, offsets))

    def jacobian(effs: list[Effect], pred: np.ndarray) -> np.ndarray:
        cols = []
        for j, n in free:
            v = getattr(effs[j], n)
            d = 1e-4 * (1 + abs(v))
            cols.append((log_pred(with_param(effs, j, n, v + d)) - pred) / d)
        return np.array(cols)

    def chi2(effs: list[Effect]) -> float:
        return float(np.sum(w * (y - log_pred(effs)) ** 2))

    converged = True
    if free and len(y):
        lower = np.array([noise[j].bounds(n)[0] for j, n in free])
        upper = np.array([noise[j].bounds(n)[1] for j, n in free])

        def descend(effs: list[Effect]) -> tuple[list[Effect], float, bool]:
            chi_old = chi2(effs)
            for _ in range(50):
                pred = log_pred(effs)
                J = jacobian(effs, pred)
                old = np.array([getattr(effs[j], n) for j, n in free], float)
                step = bounded_step((J * w) @ J.T, (J * w) @ (y - pred), old, lower, upper)
                for _ in range(20):
                    trial = effs
                    for (j, n), v, s in zip(free, old, step):
                        trial = with_clipped_param(trial, j, n, v + s)
                    chi_new = chi2(trial)
                    if chi_new <= chi_old:
                        break
                    step = step / 2
                else:
                    return effs, chi_old, True  # no step lowers χ²: a (bounded) minimum
                effs, gain = trial, chi_old - chi_new
                chi_old = chi_new
                if np.all(np.abs(step) <= 1e-7 * (1 + np.abs(old))) or gain <= VARIANCE_SETTLED:
                    return effs, chi_new, True
            return effs, chi_old, False

        starts = [noise]
        moved = list(noise)
        for j, n in free:
            if getattr(noise[j], n) == noise[j].null_values().get(n, None):
                moved = with_param(moved, j, n, next(p["default"] for p in noise[j].parameter_info()
                                                     if p["name"] == n))
        if any(a is not b for a, b in zip(moved, noise)):
            starts.append(moved)
        fits = [descend(start) for start in starts]
        noise, _, converged = min(fits, key=lambda f: f[1])
        jac = jacobian(noise, log_pred(noise))
        params = estimates(noise, free, (jac * w) @ jac.T, converged)
    predicted = predicted_variance(bins, rgroups, noise, device, offsets)
    return NoiseFit(noise, predicted, jac, params, float(np.sum(w * (y - np.log(predicted)) ** 2)))


@dataclass(frozen=True)
class QuantiserChoice:
    """Which converter the variance channel shows (:func:`fit_noise_and_quantiser`)."""

    dither: float  #: the width of the uniform dither before rounding (DN; 0: none)
    chi2: dict[float, float]  #: the variance channel's χ² under each converter compared (empty: not compared)
    assumed: float  #: the converter the fit assumed until then (the device's: the pixel channel was fitted with it)

    def to_dict(self) -> dict[str, Any]:
        return {"dither": self.dither, "compared": bool(self.chi2),
                "variance_chi2": {f"dither {d:g} DN": c for d, c in self.chi2.items()}}


def quantiser_shows(bins: VarianceBins) -> bool:
    """Whether any variance bin is quiet enough for the converter to show: a binned variance below that of noise
    of :data:`~forensics.check.prediction.PHASE_SIGMA` DN with rounding and a dither."""
    return bool(len(bins.observed)) and float(np.min(bins.observed)) < PHASE_SIGMA ** 2 + 2 * QUANT_VAR


def fit_noise_and_quantiser(bins: VarianceBins, rgroups: Sequence[Group], noise: list[Effect],
                            device: Device) -> tuple[NoiseFit, Device, QuantiserChoice]:
    """:func:`fit_variance` under each converter of :data:`DITHERS` where the data can tell them apart
    (:func:`quantiser_shows`), keeping plain rounding unless a dither fits better by :data:`DITHER_MARGIN`; the
    noise fit, the device with the chosen converter, and the choice.

    Why: below ≈ 1 DN of noise the readout's variance depends on the converter — EMVA 1288's reference simulator
    dithers, most cameras do not — and the two laws differ by up to 8 % in a dark frame's variance at σ ≈ 0.4 DN
    (:func:`~forensics.check.prediction.phase_averaged`); the wrong one moves the conversion gain.  The device's
    converter is fitted first (the others start from its fit: the noise moves little, σ² by about the dither's
    d²/12); another than the device's is taken only where it fits the bins to :data:`CONVERTER_FIT` per bin."""
    assumed = device.model.dither
    if not quantiser_shows(bins):
        return fit_variance(bins, rgroups, noise, device), device, QuantiserChoice(assumed, {}, assumed)
    fits = {assumed: fit_variance(bins, rgroups, noise, device)}
    for d in DITHERS:
        if d not in fits:
            fits[d] = fit_variance(bins, rgroups, fits[assumed].effects, with_dither(device, d))
    chi2 = {d: fits[d].chi2 for d in DITHERS}
    best = min(DITHERS, key=lambda d: chi2[d])
    chosen = best if chi2[best] < chi2[DITHERS[0]] - DITHER_MARGIN else DITHERS[0]
    if chosen != assumed and chi2[chosen] > CONVERTER_FIT * len(bins.observed):
        chosen = assumed  # a model that misfits the bins either way says nothing about the converter
    return fits[chosen], with_dither(device, chosen), QuantiserChoice(chosen, chi2, assumed)


def with_dither(device: Device, dither: float) -> Device:
    """``device`` (sharing its times, catalogue and state) with a converter that dithers by ``dither`` DN."""
    if device.model.dither == dither:
        return device
    return on_model(device, dataclasses.replace(device.model, dither=float(dither)))
