"""The converter in the variance channel: the exact rounding variance at low noise, with and without a dither.

Below ≈ 1 DN of noise the readout's variance swings with the fractional part of the level (±5 % at σ = 0.32 DN with
EMVA 1288's dither of 1 DN, more without); a camera without a DSNU puts every pixel of a frame at one fraction.
"""
from __future__ import annotations

import numpy as np
import pytest

from forensics.check.classes import QUANT_VAR
from forensics.check.pixels import VarianceBins, phase_moments
from forensics.check.prediction import phase_averaged
from forensics.sensor.model import SensorModel, make_effect

#: Readouts simulated per bin: the sample variance's relative SE is √(2/N) ≈ 0.2 %, the swing 5–8 %.
N = 400_000


def _bins(levels_per_bin: list[np.ndarray]) -> VarianceBins:
    """Variance bins whose pixels sit at the given latent levels (one row of pixels per bin)."""
    width = max(len(v) for v in levels_per_bin)
    labels = np.full((1, len(levels_per_bin), width), -1)
    levels = np.zeros(labels.shape)
    for b, v in enumerate(levels_per_bin):
        labels[0, b, :len(v)] = b
        levels[0, b, :len(v)] = v
    n = len(levels_per_bin)
    phase = phase_moments(labels, levels, n, np.zeros(n, bool))
    return VarianceBins(np.zeros(n, int), np.array([float(np.mean(v)) for v in levels_per_bin]), np.ones(n),
                        np.full(n, 1e4), None, 4095.0, labels, phase=phase)


@pytest.mark.parametrize("dither", [0.0, 1.0])
def test_phase_averaged_variance_matches_simulated_readouts(dither):
    """Bins of pixels at (a hair below) one whole level 2 DN above the 0-DN bound, a quarter, a half, and pixels
    spread over three DN (a DSNU): the prediction is the simulated readouts' variance within 5 relative SEs; the
    smooth law σ² + (1 + d²)/12 misses the single-fraction bins by 10–40 SEs."""
    sigma = 0.32
    rng = np.random.default_rng(7)
    spread = np.linspace(2.0, 5.0, 97)[:-1]
    bins = _bins([np.array([1.999]), np.array([2.25]), np.array([2.5]), spread])
    at, predicted = phase_averaged(bins, np.arange(4), np.full(4, sigma), dither)
    assert list(at) == [0, 1, 2, 3]
    smooth = sigma**2 + QUANT_VAR * (1 + dither**2)
    missed = 0
    for b, levels in enumerate([[1.999], [2.25], [2.5], spread]):
        mu = rng.choice(np.asarray(levels), N)
        x = rng.normal(mu, sigma) + rng.uniform(-0.5 * dither, 0.5 * dither, N)
        y = np.rint(x)
        # the bin's variance: each pixel's temporal variance about its own mean, pooled
        own = np.rint(rng.normal(mu, sigma) + rng.uniform(-0.5 * dither, 0.5 * dither, N))
        simulated = 0.5 * np.mean((y - own) ** 2)
        # half the mean squared difference of two readouts has SE V·√(2/N) for normal differences; the readouts on
        # two or three levels have another kurtosis, allowed for by half as much again
        se = simulated * np.sqrt(2.0 / N) * 1.5
        assert abs(predicted[b] - simulated) < 5 * se, (b, predicted[b], simulated)
        missed += abs(smooth - simulated) > 10 * se
    assert missed >= 2


def test_no_phase_above_one_dn_of_noise():
    """At σ ≥ 1 DN the swing (≈ exp(−2π²σ²)) is below any bin's resolution: those bins keep the smooth law."""
    bins = _bins([np.array([2.0]), np.array([2.5])])
    at, _ = phase_averaged(bins, np.arange(2), np.array([1.0, 0.5]), 0.0)
    assert list(at) == [1]


def test_a_dithering_model_dithers_its_frames():
    """``SensorModel.dither`` adds a uniform draw before rounding (variance σ² + 1/12 + 1/12 on average over the
    level), and survives the model's description."""
    model = SensorModel(shape=(200, 200), bit_depth=12, effects=[make_effect("read_noise", sigma=0.3)], dither=1.0)
    assert SensorModel.from_dict(model.to_dict()).dither == 1.0
    device = model.realize(np.random.default_rng(1), [0.0])
    scene = np.random.default_rng(2).uniform(100.0, 110.0, model.shape)  # levels spread over whole DNs
    ctx = device.context(0.0)
    a, b = (device.expose(scene, ctx, np.random.default_rng(s)).astype(float) for s in (3, 4))
    variance = 0.5 * np.mean((a - b) ** 2)
    expected = 0.3**2 + 2 * QUANT_VAR
    assert abs(variance - expected) < 5 * expected * np.sqrt(2.0 / a.size), variance
    plain = SensorModel(shape=(200, 200), bit_depth=12, effects=[make_effect("read_noise", sigma=0.3)])
    assert "dither" not in plain.to_dict()
