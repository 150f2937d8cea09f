"""The forward models of the pixel and variance channels.

Variance channel: predicted temporal variance of each variance bin — the noise effects' variance plus the
rounding variance 1/12 DN², and, for the conditions near a bound (more than 1 % of the normal pixels touched 0
or the full scale; :func:`~forensics.check.pixels.variance_bins` pools each into one bin), the exact variance
of the quantised, clipped readout (:func:`forensics.stats.censored.readout_moments`), conditional on
no frame touching a bound (pixels that touched one are not usable, so the variance bins hold only the others).

Pixel channel: predicted mean output of every repeated condition.

The scene estimate of each pixel is mapped to incident light through the inverse of the typical pixel's
chain (tabulated once per parameter values and condition) and sent through the device's chain
(:meth:`~forensics.sensor.model.Device.mean_signal`).  Frames known to be dark (the manifest's ``subject``
is ``dark``) have zero light: their prediction is the chain's output for no light (black level, dark
signal, defects), not the neighbours'.  Near 0 or the full scale the predicted mean is that of the quantised
readout conditional on no frame touching a bound (the pixels that touched one are not usable), from the
model's own noise (:func:`forensics.stats.censored.readout_moments`).

A scene estimate averages the neighbours' readings, and with them their own additive fixed patterns (dark
signal non-uniformity, DSNU): K·δ with δ the neighbours' deviation from a typical pixel at zero light.  In a
frame with light the pixel's own pattern would then have to fit δ_p − (K·δ)_p, in a dark frame δ_p — one value
cannot do both (the error grows with the dark signal).  So K·δ of the fitted device is taken out of the scene
estimate before it is mapped to light (:meth:`Predictor.scene_shift`).  It is computed once per fit cycle and
kept frozen in the device's state (:data:`SCENE_SHIFT`): derivatives by a pixel's own pattern value stay local
(perturbing every pixel's value at once would otherwise cancel through the neighbours).  Multiplicative patterns
(PRNU) need no such term: their neighbour average scales with the light like the pixel's own and is absorbed.

Noise laws (:meth:`~forensics.sensor.model.Effect.variance`) see the signal above the readout's offset (the
black level): the output level less :attr:`~forensics.sensor.model.FrameContext.readout_offset`.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from forensics.check.classes import QUANT_VAR, dark_groups
from forensics.check.measurements import Group, Measurements
from forensics.check.pixels import PixelData, VarianceBins
from forensics.check.scene import kernel_estimate
from forensics.sensor.catalogue import DefectCatalogue
from forensics.sensor.model import Device, Effect, FrameContext, Stage
from forensics.stats.censored import readout_moments, readout_variance_harmonics, truncated_readout_mean


#: Key of :meth:`Predictor.scene_shift`'s frozen result in a fitted device's state (absent: no shift).
SCENE_SHIFT = "check:scene_shift"
#: Key of frozen defect refills (:meth:`Predictor.refill`) in a device's state: while present, the
#: neighbours' estimates keep them whatever the defects' own parameters (derivatives by a pixel's own values).
FROZEN_REFILL = "check:frozen_refill"


def intact(device: Device) -> Device:
    """The device without its defects (fixed patterns kept), sharing its state."""
    return Device(model=device.model, times=device.times, catalogue=DefectCatalogue.empty(), state=device.state)


def context(device: Device, g: Group) -> FrameContext:
    return device.context(g.time, g.exposure_s, g.iso, g.temperature_c)


#: Memory the cached tables of non-affine chains may hold before the cache is emptied (bytes): a table has the
#: frame's size, and a fit visits a new parameter set per step and per finite difference.
TABLE_CACHE_BYTES = 256 * 2**20


def rising_branch(chain: np.ndarray, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The part of a tabulated chain (output over an increasing ``grid`` of light) that rises through zero light:
    the branch a sensor's response follows from dark up.

    A response that turns over within the table — a compressive non-linearity y = i − β·i²/full scale with
    β > 0.25 peaks at i = full scale/(2β), inside the grid's 2 × full scale — has two lights for each output
    below its peak.  Sorting the table by output (what this did before) interleaved the two branches, so the
    inverse jumped between them, and a fit whose brightest pixels sat near the peak read its cusp as information:
    tiles of the STL-1001E's whole frame reported β ± 10⁻⁷ against the others' ± 5·10⁻³.  Outputs above the
    branch's end invert to its end (the clamp of :meth:`ChainInverse.invert`), as a sensor's brightest light does.

    Examples
    --------
    >>> g = np.linspace(-1.0, 4.0, 11)
    >>> c, x = rising_branch(g - 0.25 * g ** 2, g)     # peaks at light 2
    >>> float(x[0]), float(x[-1]), bool(np.all(np.diff(c) > 0))
    (-1.0, 2.0, True)
    """
    rises = np.diff(chain) > 0
    zero = int(np.searchsorted(grid, 0.0))
    at = next((j for j in (zero, zero - 1) if 0 <= j < len(rises) and rises[j]), None)  # a rising step at 0
    if at is None:  # no rise at zero light (not a response): the table sorted by output, as before
        order = np.argsort(chain, kind="stable")
        return chain[order], grid[order]
    falls = np.flatnonzero(~rises)
    first = int(falls[falls < at].max()) + 1 if np.any(falls < at) else 0
    last = int(falls[falls > at].min()) if np.any(falls > at) else len(chain) - 1
    return chain[first:last + 1], grid[first:last + 1]


class ChainInverse:
    """The inverse of the typical pixel's chain (output → light), tabulated on a grid of light.

    An affine chain (black level, gains: the base model and most effects) is inverted in closed form — what
    the table's linear interpolation gives up to rounding, at a few operations per pixel where ``np.interp``'s
    search through a table of the frame's size costs ≈ 0.1 µs per pixel at every change of a global parameter
    (6 % of the profiled time on the hidden-effect data; the gain measured was within a shared machine's noise)."""

    def __init__(self, chain: np.ndarray, grid: np.ndarray, full_scale: float):
        slope = (chain[-1] - chain[0]) / (grid[-1] - grid[0])
        offset = chain[0] - slope * grid[0]
        straight = slope > 0 and np.max(np.abs(chain - (slope * grid + offset))) < 1e-9 * full_scale
        self.affine = (slope, offset) if straight else None
        self.ends = (float(grid[0]), float(grid[-1]))
        if self.affine is not None:
            # an affine chain keeps two numbers, not the frame-sized table: the predictor caches one inverse per
            # parameter set and condition, and holding the tables took 9.3 GB on a 320 × 240 series of 105
            # conditions (the tables' grid has the frame's size)
            chain = grid = None
        elif np.any(np.diff(chain) <= 0):
            chain, grid = rising_branch(chain, grid)
        self.chain, self.grid = chain, grid

    @property
    def nbytes(self) -> int:
        """Memory held by the table (0 for an affine chain)."""
        return 0 if self.chain is None else self.chain.nbytes + self.grid.nbytes

    def invert(self, output: np.ndarray) -> np.ndarray:
        """The light whose typical output is ``output`` (clamped to the grid's ends, as ``np.interp``)."""
        if self.affine is None:
            return np.interp(output, self.chain, self.grid)
        slope, offset = self.affine
        return np.clip((np.asarray(output, float) - offset) / slope, *self.ends)


class Predictor:
    """Predicted pixel means for the measurements (caches the typical chain's inverse)."""

    def __init__(self, meas: Measurements, rgroups: Sequence[Group]):
        self.meas = meas
        self.rgroups = list(rgroups)
        self.shape = meas.shape
        self.dark = dark_groups(self.rgroups)
        self.dark_all = dark_groups(meas.groups)
        self._chain_cache: dict[Any, Any] = {}
        self._chain_bytes = 0  # held by the cached non-affine tables
        self._model_key: tuple[Any, Any] = (None, None)
        self._scatter_targets: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def _chain_key(self, typical: Device) -> Any:
        """The chain's parameter values, as a key; computed once per model object (a prediction asks for every
        condition's table of one model: building the key per condition was ≈ 4 % of the hidden-effect check).
        An effect never changes once built (a fit makes new ones), so the effect objects stand for their values."""
        effects = typical.model.effects
        held, key = self._model_key
        if held is None or len(held) != len(effects) or any(a is not b for a, b in zip(held, effects)):
            key = tuple((e.key, tuple(sorted(e.params().items()))) for e in effects
                        if e.stage not in (Stage.ARRIVAL, Stage.NOISE))
            self._model_key = (list(effects), key)
        return key

    def _targets(self, dst: np.ndarray) -> np.ndarray:
        """The sorted distinct targets of a refill scatter (where its correction can be non-zero), once per
        scatter: with the refill's subtraction at the defects only, 38 → 33 ms a prediction on the hidden prnu
        dataset (bit-identical)."""
        held = self._scatter_targets.get(id(dst))
        if held is None or held[0] is not dst:
            seen = np.zeros(int(np.prod(self.shape)), bool)
            seen[dst] = True
            held = (dst, np.flatnonzero(seen))
            self._scatter_targets[id(dst)] = held
        return held[1]

    def table(self, typical: Device, tctx: FrameContext) -> ChainInverse | None:
        """The typical chain's inverse (:class:`ChainInverse`); None where the chain is the identity."""
        key = (self._chain_key(typical), tctx.time, tctx.exposure_s, tctx.iso, tctx.temperature_c)
        cache = self._chain_cache
        if key not in cache:
            if len(cache) > 4096 or self._chain_bytes > TABLE_CACHE_BYTES:
                cache.clear()
                self._chain_bytes = 0
            fs = self.meas.full_scale
            h, w = self.shape
            grid = np.linspace(-0.25 * fs, 2.0 * fs, h * w).reshape(h, w)
            chain = typical.mean_signal(grid, tctx)
            identity = np.max(np.abs(chain - grid)) < 1e-9 * fs
            cache[key] = None if identity else ChainInverse(chain.ravel(), grid.ravel(), fs)
            self._chain_bytes += 0 if cache[key] is None else cache[key].nbytes
        return cache[key]

    def light(self, typical: Device, tctx: FrameContext, scene: np.ndarray) -> np.ndarray:
        """Incident light whose typical-pixel output is ``scene`` (inverse of the typical chain)."""
        table = self.table(typical, tctx)
        return scene if table is None else table.invert(scene)

    def reference(self, device: Device) -> np.ndarray:
        """What a defect-free pixel of ``device`` reads on average in every condition, its frames at 0 or full
        scale included (:func:`readout_mean`; for re-detection against the model, which compares it with the mean
        of every frame).  Why not the latent mean: a pixel whose fixed pattern puts its dark level below 0 DN
        reads 0 DN, and against a latent prediction below 0 showed an offset of the clipped amount — the camera
        convention's DSNU (σ_o = 48 DN about a 48 DN black level) made 186 such "partially stuck" records, a real
        defect arriving later at such a site was merged into one, and its fit missed the early flats by 1,100 DN."""
        meas = self.meas
        clean, typical = intact(device), device.typical()
        ref = np.empty_like(meas.mean_all)
        for g in meas.groups:
            light = (np.zeros(self.shape) if self.dark_all[g.index]
                     else self.light(typical, context(typical, g), meas.scene_all[g.index]))
            ctx = context(clean, g)
            ref[g.index] = readout_mean(clean.mean_signal(light, ctx), ctx, meas.clip_level)
        return ref

    def scene_shift(self, device: Device, pixels: PixelData) -> np.ndarray:
        """Per repeated condition with light, K·δ: the scene kernel applied to the pixels' deviation from a
        typical pixel at zero light (:meth:`deviation`); zeros for dark frames, where nothing deviates, and for
        data without dark frames.  ``(R, H, W)``."""
        delta = self.deviation(device, pixels)
        out = np.zeros_like(delta)
        for r in range(len(self.rgroups)):
            if np.any(np.abs(delta[r]) > 1e-12):
                out[r] = kernel_estimate(delta[r])
        return out

    def deviation(self, device: Device, pixels: PixelData) -> np.ndarray:
        """Per repeated condition with light, δ: the pixels' deviation from a typical pixel at zero light (their
        additive fixed patterns; a known defect's refill keeps its pixel's patterns, so it counts too; outliers
        the scene estimate filled do not) — what the scene estimates average into :meth:`scene_shift`.  Zeros
        for dark frames and for data without dark frames.  ``(R, H, W)``."""
        out = np.zeros((len(self.rgroups), *self.shape))
        if not self.dark.any():
            # without frames predicted from the chain alone every frame sees a pixel's additive pattern through
            # the same (I − K): the fitted pattern is its (I − K) part and the prediction is exact without the
            # term (which would only add a slowly converging direction the data do not determine)
            return out
        clean, typical = intact(device), device.typical()
        zero = np.zeros(self.shape)
        for r, g in enumerate(self.rgroups):
            if self.dark[r]:
                continue
            delta = clean.mean_signal(zero, context(clean, g)) - typical.mean_signal(zero, context(typical, g))
            out[r] = np.where(pixels.scene_excluded[r], 0.0, delta)  # filled outliers: not in the estimate
        return out

    def refill(self, device: Device, pixels: PixelData, half: str = "a") -> np.ndarray:
        """What a typical pixel would have read at each known defect, as :meth:`predict` puts it into the
        neighbours' scene estimates (the defect's reading less its modelled deviation), per repeated condition
        ``(R, H, W)``; zero where no defect is (and in dark frames, whose prediction ignores the scene)."""
        out = np.zeros((len(self.rgroups), *self.shape))
        self.predict(device, pixels, half, clip=False, record=out)
        return out

    def predict(self, device: Device, pixels: PixelData, half: str = "a", clip: bool = True,
                record: np.ndarray | None = None) -> np.ndarray:
        """Predicted mean output ``(R, H, W)`` of every repeated condition for the half's scene estimates.

        Known defects entered the scene estimate through fill values; here they are replaced by the
        defect's reading minus its modelled deviation from a typical pixel (what a typical pixel there
        would have read, noise and fixed patterns included), so that the neighbours' prediction does not
        depend on how the gap was filled.  (The deviation is the defect's: the pixel's fixed patterns,
        which a normal pixel there would show too, stay in.)  With :data:`FROZEN_REFILL` in the device's state
        those values are taken from there; ``record`` (R, H, W), if given, receives them.
        """
        scenes = pixels.scene_a if half == "a" else pixels.scene_b
        fills = pixels.fill_a if half == "a" else pixels.fill_b
        means = self.meas.mean_a if half == "a" else self.meas.mean_b
        typical = device.typical()
        clean = intact(device)
        shift = device.state.get(SCENE_SHIFT)
        frozen = device.state.get(FROZEN_REFILL)
        out = np.empty(scenes.shape)
        h, w = self.shape
        cache = pixels.light_cache
        for r, g in enumerate(self.rgroups):
            ctx = context(device, g)
            if self.dark[r]:  # no light: the chain's own output, whatever the neighbours read
                out[r] = device.mean_signal(np.zeros(self.shape), ctx)
                continue
            table = self.table(typical, context(typical, g))
            if shift is not None and np.any(shift[r]):
                light = scenes[r] - shift[r]
                light = light if table is None else table.invert(light)
            elif table is None:
                light = scenes[r]
            else:  # the light of the fixed scene estimate depends only on the global parameters: cache it
                key = (id(table), half, r)
                if key not in cache:
                    if len(cache) > 6 * len(self.rgroups):
                        cache.clear()
                    cache[key] = (table, table.invert(scenes[r]))
                light = cache[key][1]
            mu = device.mean_signal(light, ctx)
            if pixels.defect_mask[r].any():
                # a defect read at 0 or full scale shows its clipped value: the deviation it shows is the clipped
                # one (a stuck pixel at black level + c beyond full scale would otherwise leak the excess, e.g.
                # the black level, into every neighbour's prediction)
                src, dst, wts = pixels.refill_ops[g.epoch]
                if frozen is not None:
                    typical_reading = frozen[r]
                else:
                    deviation = np.clip(mu, 0.0, self.meas.clip_level) - clean.mean_signal(light, context(clean, g))
                    typical_reading = means[r] - deviation
                if record is not None:
                    record[r] = np.where(pixels.defect_mask[r], typical_reading, 0.0)
                # at the defects only: the same numbers as over the frame and then indexed
                refill = typical_reading.ravel()[src] - fills[r].ravel()[src]
                correction = np.bincount(dst, wts * refill, minlength=h * w)
                reach = self._targets(dst)
                touched = reach[correction[reach] != 0]  # np.flatnonzero(correction) without the frame's scan
                light = light.copy().ravel()
                scene = scenes[r].ravel()[touched] + correction[touched]
                if shift is not None:
                    scene = scene - shift[r].ravel()[touched]
                light[touched] = scene if table is None else table.invert(scene)
                mu = device.mean_signal(light.reshape(h, w), ctx)
            out[r] = mu
        return self.censor(device, out) if clip else out

    def censor(self, device: Device, raw: np.ndarray) -> np.ndarray:
        """The mean readout the data show of latent means ``raw`` (R, H, W): :func:`censored_mean` per condition
        (a new array).  (Every condition's near-bound values computed together, for one table or one sort over
        all of them, was tried: 31.9 against 28.9–30.3 CPU s on the standard series' 64 × 64 region.)"""
        return np.stack([censored_mean(raw[r], context(device, g), self.meas.clip_level)
                         for r, g in enumerate(self.rgroups)])


def censored_mean(mu: np.ndarray, ctx: FrameContext, full_scale: float, reach: float = 6.0) -> np.ndarray:
    """The mean readout of pixels of latent mean ``mu`` that never touched 0 or ``full_scale``: ``mu`` itself
    away from the bounds; within ``reach`` σ of one, the truncated mean of the quantised readout (σ from the
    model's noise effects)."""
    return _near_bound_means(mu, ctx, full_scale, reach, distinct_readout_means)


def readout_mean(mu: np.ndarray, ctx: FrameContext, full_scale: float, reach: float = 6.0) -> np.ndarray:
    """The mean readout of pixels of latent mean ``mu`` over every frame, those at 0 or ``full_scale`` included:
    ``mu`` itself away from the bounds; within ``reach`` σ of one, the mean of the quantised, clipped readout."""
    return _near_bound_means(mu, ctx, full_scale, reach,
                             lambda m, sd, hi, dither, _: readout_moments(m, sd, 0, hi, dither=dither)[0])


def _near_bound_means(mu: np.ndarray, ctx: FrameContext, full_scale: float, reach: float,
                      bounded: Callable[..., np.ndarray]) -> np.ndarray:
    """``mu`` clipped to [0, ``full_scale``], and ``bounded(μ, σ, hi, dither, sigma_of)`` within ``reach`` σ (and the
    dither's half-width) of a bound (σ from the model's noise effects, the dither from its quantiser; ``sigma_of``
    σ as a function of μ where the near values share one electronic offset, else None)."""
    noise = [e for e in ctx.device.model.effects if e.stage == Stage.NOISE]
    dither = ctx.device.model.dither
    out = np.clip(mu, 0.0, full_scale)
    hi = round(float(full_scale))
    elec = np.broadcast_to(ctx.electronic_offset, out.shape)
    sd = np.sqrt(noise_variance(noise, out, ctx, elec) + quantiser_variance(dither))
    near = (out < reach * sd + 1.0 + 0.5 * dither) | (out > hi - reach * sd - 1.0 - 0.5 * dither)
    if hi < 3 or not near.any():
        return out
    sigma = np.sqrt(noise_variance(noise, mu[near], ctx, elec[near]))
    m = mu[near]
    # at one electronic offset the noise law makes σ a function of the level: the tables may run along it alone
    e_near = elec[near]
    sigma_of = None
    if e_near.size and e_near.min() == e_near.max():
        offset = float(e_near[0])
        sigma_of = lambda level: np.sqrt(noise_variance(noise, level, ctx, offset))  # noqa: E731
    if m.size > 1 and m.min() == m.max() and sigma.min() == sigma.max():
        # a frame without pixel patterns (the base model, shot noise, dark current …): every pixel shares (μ, σ)
        # and one value serves them all — on the EMVA 1288 standard series, 40 % of the check's time went to
        # tabulating and interpolating the one value 76,800 times per condition
        out[near] = bounded(m[:1], sigma[:1], hi, dither, None)[0]
        return out
    out[near] = bounded(m, sigma, hi, dither, sigma_of)
    return out


def quantiser_variance(dither: float) -> float:
    """The variance the converter adds away from the bounds on average over the level's fractional part: the
    rounding's 1/12 DN² and a uniform dither's d²/12."""
    return QUANT_VAR * (1.0 + dither * dither)


def distinct_readout_means(mu: np.ndarray, sigma: np.ndarray, hi: int, dither: float = 0.0,
                           sigma_of: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray:
    """:func:`~forensics.stats.censored.readout_moments`' truncated mean, as cheaply as it holds
    (:func:`~forensics.stats.censored.truncated_readout_mean`), one bound at a time: a table across both would
    span the whole range."""
    out = np.empty(mu.shape)
    for side in (mu < 0.5 * hi, mu >= 0.5 * hi):
        if side.any():
            out[side] = truncated_readout_mean(mu[side], sigma[side], 0, hi, dither=dither, sigma_of=sigma_of)
    return out


def bin_offsets(bins: VarianceBins, rgroups: Sequence[Group], device: Device) -> dict[int, np.ndarray]:
    """Per repeated condition with variance bins, each bin's mean electronic offset
    (:attr:`~forensics.sensor.model.FrameContext.electronic_offset` averaged over its pixels): what
    :func:`predicted_variance` reads of the device's effects before the noise stage.

    Why apart: a noise fit evaluates the forward model for tens of trial noise laws on one device, whose offsets
    do not change; averaged anew in every evaluation they were 4 % of a tile's check."""
    return {int(r): bins.bin_means(r, context(device, rgroups[r]).electronic_offset) for r in np.unique(bins.group)}


def predicted_variance(bins: VarianceBins, rgroups: Sequence[Group], noise_effects: Sequence[Effect],
                       device: Device, offsets: dict[int, np.ndarray] | None = None) -> np.ndarray:
    """The variance channel's forward model: predicted temporal variance of each variance bin (the quantisation
    variance plus every noise effect's; near the bounds, the clipped readout's — see :func:`near_bound`).
    ``offsets``: :func:`bin_offsets` of ``device`` when known (the same numbers, averaged once)."""
    dither = device.model.dither
    noise = np.zeros(len(bins.level))
    bounded = []
    for r in np.unique(bins.group):
        sel = bins.group == r
        ctx = context(device, rgroups[r])
        elec = bins.bin_means(r, ctx.electronic_offset) if offsets is None else offsets[int(r)]
        noise[sel] = noise_variance(noise_effects, bins.level[sel], ctx, elec)
        if bins.spread is not None and bins.full_scale is not None:
            bounded.append(near_bound(bins, np.flatnonzero(sel), ctx, noise_effects, elec, dither=dither))
    out = noise + quantiser_variance(dither)
    if bins.phase is not None:  # (every condition's bins in one evaluation)
        at, variance = phase_averaged(bins, np.arange(len(out)), np.sqrt(noise), dither)
        out[at] = variance
    for at, variance in bounded:
        out[at] = variance
    return np.maximum(out, 1e-12)


#: Below this noise σ (DN) a variance bin is predicted from the exact quantised readout at its pixels' latent
#: levels (:func:`phase_averaged`); above it the rounding's share differs from its average 1/12 by a swing of
#: relative size ≈ exp(−2π²σ²) (3 × 10⁻⁹ at σ = 1 DN), far below what a bin resolves.
PHASE_SIGMA = 1.0
#: Levels per DN at which :func:`phase_averaged` evaluates the exact variance (resolving harmonics up to 15).
PHASE_POINTS = 32


def phase_averaged(bins: VarianceBins, idx: np.ndarray, sigma: np.ndarray,
                   dither: float) -> tuple[np.ndarray, np.ndarray]:
    """The predicted variance of those bins ``idx`` (noise σ ``sigma`` at their levels) whose noise is below
    :data:`PHASE_SIGMA`: the quantised readout's exact variance averaged over their pixels' latent levels, conditional
    on the readout never touching a bound.  ``(bins, variances)``.

    The variance V(μ) is even and periodic in the level (period 1 DN, away from the bounds), V = Σ a_k cos(2πkμ), and
    the bin's mean is Σ a_k·mean cos(2πk·μ) with the means of its pixels (``bins.phase``,
    :func:`~forensics.check.pixels.phase_moments`), exact while V's harmonics above
    :data:`~forensics.check.pixels.HARMONICS` vanish (they fall as exp(−2π²k²σ²)).  The a_k are in closed form
    (:func:`~forensics.stats.censored.readout_variance_harmonics`) for a bin :data:`PHASE_CLOSED_REACH` σ from the
    bounds; nearer, the discrete cosine transform of the exact truncated variance at :data:`PHASE_POINTS` fractions
    a 1/32 DN apart (each at the level within ½ DN of the bin's).

    Why: below ≈ 1 DN of noise the rounding's variance swings with the level's fractional part (σ = 0.32 DN with
    EMVA 1288's dither: −5 % at a whole level, +5 % halfway; without it ±36 %), and a camera without a DSNU puts
    every pixel of a dark frame at the same fraction: on the EMVA 1288 standard series the dark bins read 5 % below
    σ² + 1/6 at 2.0 DN and 3 % above it at 2.5 DN (variance gof p = 2 × 10⁻⁸²), and without the dither K came out
    6 % high."""
    rows = np.all(np.isfinite(bins.phase[idx]), axis=1) & (sigma < PHASE_SIGMA)
    if not rows.any():
        return idx[:0], np.zeros(0)
    at, s = idx[rows], sigma[rows]
    coef = np.empty((at.size, bins.phase.shape[1]))
    # away from the bounds the readout's variance is periodic in the level and its cosine coefficients have a closed
    # form (readout_variance_harmonics, agreeing with the sum to 10⁻¹⁴ DN²); within reach of a bound the readouts
    # that touched it are left out of the bins, so there the conditional variance is summed level by level
    reach = bound_distance(bins, at, dither) >= PHASE_CLOSED_REACH * s
    coef[reach] = readout_variance_harmonics(s[reach], dither, bins.phase.shape[1] - 1)
    near = ~reach
    if near.any():
        coef[near] = _summed_harmonics(bins, at[near], s[near], dither)
    return at, np.sum(coef * bins.phase[at], axis=1)


#: A bin further than this many σ (its level less ½ DN for its pixels' spread and the dither's half-width) from
#: both bounds' edges is predicted by the closed form: the readouts that would touch a bound carry < 10⁻¹² of the mass.
PHASE_CLOSED_REACH = 7.0


def bound_distance(bins: VarianceBins, idx: np.ndarray, dither: float) -> np.ndarray:
    """How far (DN) the pixels of bins ``idx`` (within ½ DN of their level) and the dither's half-width stay from
    the nearer bound's edge (½ DN inside 0 or the full scale); infinite without bounds."""
    if bins.full_scale is None:
        return np.full(idx.size, np.inf)
    level = bins.level[idx]
    edge = np.minimum(level - 0.5, float(round(float(bins.full_scale))) - 0.5 - level)
    return edge - 0.5 - 0.5 * dither


def _summed_harmonics(bins: VarianceBins, at: np.ndarray, s: np.ndarray, dither: float) -> np.ndarray:
    """:func:`phase_averaged`'s coefficients from the exact truncated readout, summed at :data:`PHASE_POINTS`
    fractions of a DN (each at the level within ½ DN of the bin's) and transformed."""
    frac = np.arange(PHASE_POINTS) / PHASE_POINTS
    level = bins.level[at][:, None]
    # each fraction at the level nearest the bin's (the period holds away from the bounds; near them this is the
    # closest the bin's pixels come to it: a whole DN lower, a dark bin at 2.0 DN was predicted half its variance)
    mu = level + (frac[None, :] - level + 0.5) % 1.0 - 0.5
    if bins.full_scale is None:
        lo, hi, truncate = -2**40, 2**40, False
    else:
        lo, hi, truncate = 0, round(float(bins.full_scale)), True
    # (levels within 6 σ: the mass beyond, 2 × 10⁻⁹, moves no variance a bin resolves; the default 10 σ summed
    # 40 % more levels)
    _, var = readout_moments(mu, np.broadcast_to(s[:, None], mu.shape), lo, hi, truncate=truncate, dither=dither,
                             reach=6.0)
    k = np.arange(bins.phase.shape[1])
    weight = np.where(k == 0, 1.0, 2.0) / PHASE_POINTS
    return var @ (np.cos(2.0 * np.pi * np.outer(frac, k)) * weight[None, :])  # (bins, harmonics)


def noise_variance(noise_effects: Sequence[Effect], level: np.ndarray, ctx: FrameContext,
                   electronic: np.ndarray | float = 0.0) -> np.ndarray:
    """Temporal variance the noise effects add at output ``level`` (their laws see the charge signal: the level
    above the readout's offset, :attr:`~forensics.sensor.model.FrameContext.readout_offset`, less the
    ``electronic`` offsets of those pixels, :attr:`~forensics.sensor.model.FrameContext.electronic_offset`)."""
    level = np.asarray(level, float)
    above = level - (ctx.readout_offset if ctx is not None else 0.0) - np.asarray(electronic, float)
    out = np.zeros(level.shape)
    for e in noise_effects:
        out += np.asarray(e.variance(above, ctx), float)
    return np.maximum(out, 0.0)


def near_bound(bins: VarianceBins, idx: np.ndarray, ctx: FrameContext, noise_effects: Sequence[Effect],
               electronic: np.ndarray | None = None, iterations: int = 60,
               dither: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The predicted variance of those bins ``idx`` that lie near a bound (those with a ``spread``; see
    :func:`~forensics.check.pixels.variance_bins`), from the quantised, clipped readout: ``(bins, variances)``.

    Each scene level of the bin's spread (a leave-one-out mean of the neighbours' readouts, so the mean of the
    readout y = rint(clip(x, 0, full scale)) of a pixel there) gives the latent mean μ, found by
    :func:`bracketed_root` with the noise σ(μ) of the noise effects; the bin's usable pixels never touched a bound, so its
    prediction is the average of the readout variance at those μ conditional on 0 < y < full scale.  The
    rounding variance is thus exact: 1/12 away from the bounds, less where mass sits on a bound; ``dither``: the
    converter's (:attr:`~forensics.sensor.model.SensorModel.dither`).
    """
    spread = bins.spread[idx]
    near = np.all(np.isfinite(spread), axis=1)
    lo, hi = 0, round(float(bins.full_scale))
    if not near.any() or hi < 3:
        return idx[:0], np.zeros(0)
    m = spread[near]
    elec = (np.zeros(len(idx)) if electronic is None else np.asarray(electronic, float))[near][:, None]
    s = np.sqrt(noise_variance(noise_effects, np.clip(m, lo, hi), ctx, elec) + quantiser_variance(dither))
    flat_m, flat_elec = m.ravel(), np.broadcast_to(elec, m.shape).ravel()

    def excess(x: np.ndarray, at: np.ndarray) -> np.ndarray:
        mean, _ = readout_moments(x, np.sqrt(noise_variance(noise_effects, x, ctx, flat_elec[at])), lo, hi,
                                  dither=dither)
        return mean - flat_m[at]

    mu = m if bins.spread_latent else \
        bracketed_root(excess, (m - 10.0 * s - 2.0).ravel(), (m + 10.0 * s + 2.0).ravel(), iterations).reshape(m.shape)
    _, var = readout_moments(mu, np.sqrt(noise_variance(noise_effects, mu, ctx, elec)), lo, hi, truncate=True,
                             dither=dither)
    return idx[near], var.mean(axis=1)


def bracketed_root(f, a: np.ndarray, b: np.ndarray, iterations: int = 60, xtol: float = 1e-12) -> np.ndarray:
    """The roots of an increasing ``f`` within the brackets ``f(a) < 0 < f(b)`` (1-D arrays): regula falsi with
    the Illinois modification, every third step a bisection, each value iterated only until its own bracket is
    narrower than ``xtol``·(1 + |x|) (or its excess is exactly 0).  ``f(x, at)`` evaluates the values ``at``.

    Why not plain bisection: each evaluation is one :func:`~forensics.stats.censored.readout_moments` over
    every value, and bisection needed 50 of them to reach the bracket's rounding (an interval of 20σ + 4 DN
    halved to 10⁻¹⁴).  The bracket holds, so this is as safe as bisection; most values converge superlinearly
    in ≈ 8 evaluations, and only the slow ones (a nearly quantised readout, σ ≪ 1 DN, whose mean is a
    staircase) are evaluated further.  The roots agree with the bisection's to ≈ 10⁻¹² DN (test)."""
    a, b = np.array(a, float), np.array(b, float)
    every = np.arange(a.size)
    fa, fb = f(a, every), f(b, every)
    active = every
    for k in range(iterations):
        aa, bb, ffa, ffb = a[active], b[active], fa[active], fb[active]
        mid = 0.5 * (aa + bb)
        if k % 3 == 2:
            x = mid
        else:
            den = ffb - ffa
            x = np.where(den > 0, bb - ffb * (bb - aa) / np.where(den > 0, den, 1.0), mid)
            x = np.where((x > aa) & (x < bb), x, mid)
        fx = f(x, active)
        right, left = fx > 0, fx < 0  # the root is left of x (x becomes b) or right of it (x becomes a)
        if k % 3 != 2:  # Illinois: the end that stays has its value halved, so that it moves next time
            ffa = np.where(right, 0.5 * ffa, ffa)
            ffb = np.where(left, 0.5 * ffb, ffb)
        exact = ~(right | left)
        a[active] = np.where(left | exact, x, aa)
        b[active] = np.where(right | exact, x, bb)
        fa[active] = np.where(left, fx, ffa)
        fb[active] = np.where(right, fx, ffb)
        width = b[active] - a[active]
        active = active[width > xtol * (1.0 + np.abs(x))]
        if active.size == 0:
            break
    return 0.5 * (a + b)
