"""The effect interface used by both the simulator and the model check."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from forensics.sensor.effects import Clusters, DarkCurrent, Gain, Growth, Nonlinearity, Prnu, ReadNoise, ShotNoise, describe_effects
from forensics._shared.errors import UsageError
from forensics.sensor.catalogue import PARTIAL, STUCK
from forensics.sensor.model import EFFECTS, Effect, Pattern, SensorModel, Stage, make_effect, param
from forensics.sensor.presets import preset

CANDIDATES = ("prnu", "dark_current", "gain", "nonlinearity", "shot_noise", "clusters", "accelerating_growth")
SHAPE = (32, 48)


def test_registry_roles_and_names():
    names = set(EFFECTS)
    assert set(CANDIDATES) <= names
    assert {n for n, c in EFFECTS.items() if c.role == "base"} == {"growth", "offset", "stuck", "read_noise",
                                                                   "black_level"}
    for name in CANDIDATES:
        cls = EFFECTS[name]
        assert cls.role == "candidate"
        assert cls.null_values(), f"{name} declares no null value"
        assert cls.n_params() >= 1


def test_describe_effects_lists_fields_and_parameters():
    rows = {r["name"]: r for r in describe_effects()}
    assert rows["dark_current"]["fields"] == ["exposure_s", "temperature_c"]
    assert rows["gain"]["fields"] == ["iso"]
    assert rows["growth"]["fields"] == ["captured"]
    beta = next(p for p in rows["nonlinearity"]["params"] if p["name"] == "beta")
    assert beta["null"] == 0.0 and beta["free"] and beta["unit"] == ""


@pytest.mark.parametrize("name", ["prnu", "dsnu", "dark_current", "gain", "nonlinearity"])
def test_null_values_change_nothing(name):
    """At its null values an effect leaves the mean signal exactly as the base model makes it."""
    base = preset("B", SHAPE, bit_depth=12, rate_scale=5000.0)
    times = [0.0, 5.0]
    effect = make_effect(name).nulled()
    with_effect = base.with_effects(effect)
    d0 = base.realize(np.random.default_rng(3), times)
    d1 = with_effect.realize(np.random.default_rng(3), times)
    scene = np.full(SHAPE, 800.0, np.float32)
    ctx0 = d0.context(5.0, exposure_s=1.0, iso=400.0, temperature_c=40.0)
    ctx1 = d1.context(5.0, exposure_s=1.0, iso=400.0, temperature_c=40.0)
    np.testing.assert_allclose(d1.mean_signal(scene, ctx1), d0.mean_signal(scene, ctx0), atol=1e-9)


def test_noise_effects_declare_their_variance():
    ctx = SensorModel(SHAPE).realize(np.random.default_rng(0), [0.0]).context(0.0)
    mean = np.array([0.0, 100.0, 1000.0])
    assert ReadNoise(sigma=3.0).variance(mean, ctx) == 9.0
    np.testing.assert_allclose(ShotNoise(g=0.5).variance(mean, ctx), [0.0, 50.0, 500.0])
    # the simulated variance matches the declared one
    model = SensorModel((64, 64), bit_depth=16, effects=[ReadNoise(sigma=2.0), ShotNoise(g=0.5)])
    dev = model.realize(np.random.default_rng(0), [0.0])
    frames = np.stack([dev.signal(np.full((64, 64), 400.0, np.float32), dev.context(0.0), np.random.default_rng(i))
                       for i in range(40)])
    measured = frames.var(axis=0, ddof=1).mean()
    assert measured == pytest.approx(4.0 + 200.0, rel=0.03)  # 64²·39 df: relative SE ≈ 0.0035


def test_patterns_are_views_into_the_device():
    model = SensorModel(SHAPE, bit_depth=12, effects=[Growth(rate_partial=2e4, amp_partial=100.0), Prnu(sigma_k=0.01),
                                                       DarkCurrent(rate_max=10.0)], t0=0.0)
    dev = model.realize(np.random.default_rng(1), [0.0, 10.0])
    prnu = model.effect("prnu").patterns(dev)[0]
    assert prnu.pixel_local and prnu.hyper == "sigma_k"
    prnu.values[:] = 0.0
    assert np.all(dev.state["prnu"] == 0.0)
    per_pixel, hot = model.effect("dark_current").patterns(dev)
    assert per_pixel.pixel_local and per_pixel.blocks.size == SHAPE[0] * SHAPE[1]  # every pixel has a dark signal
    idx = hot.blocks[hot.blocks >= 0]
    assert len(idx) == np.sum(dev.catalogue.kind == PARTIAL)  # hot pixels add their own rate
    assert hot.pixel_local
    # the non-uniformity stays on a pixel that turns hot later (its readings before the onset are a normal
    # pixel's); only where the record is there from the first time on do the two coincide, and the record takes it
    # (frames from year 5 on: the defects that arrived before are there from the first frame)
    later = model.realize(np.random.default_rng(1), [5.0, 10.0])
    per_pixel, hot = model.effect("dark_current").patterns(later)
    onset = np.full(SHAPE, np.inf)
    onset[hot.blocks >= 0] = later.catalogue.onset[hot.blocks[hot.blocks >= 0]]
    assert np.any(onset <= 5.0) and np.any((onset > 5.0) & np.isfinite(onset))
    assert np.all(per_pixel.blocks[onset <= 5.0] == -1)
    assert np.all(per_pixel.blocks[onset > 5.0] >= 0)


def test_expected_arrivals_closed_form_matches_simulation():
    """Built-in closed forms agree with the Monte-Carlo default (which a user's arrival effect relies on)."""
    times = np.array([0.0, 2.0, 4.0, 8.0])
    for effect in (Growth(rate_partial=3e4, rate_stuck=5e3, amp_partial=100.0, amp_stuck=255.0),
                   Clusters(rate=5e3, mean_size=3.0, spread=1.5, amplitude=100.0),
                   make_effect("accelerating_growth", theta=2e3, beta=1.7, amplitude=100.0)):
        model = SensorModel((100, 100), effects=[effect], t0=0.0)
        dev = model.realize(np.random.default_rng(0), times)
        threshold = {PARTIAL: 30.0, STUCK: -np.inf}
        closed = effect.expected_arrivals(dev, times, threshold)
        generic = Effect.expected_arrivals(effect, dev, times, threshold)  # 64 Monte-Carlo draws
        for kind in (PARTIAL, STUCK):
            np.testing.assert_allclose(closed[kind], generic[kind], rtol=0.08, atol=1.0)


def test_user_effect_loads_from_a_file(tmp_path):
    source = '''
from dataclasses import dataclass
import numpy as np
from forensics.sensor.model import Effect, Pattern, Stage, param

@dataclass
class RowOffset(Effect):
    name = "row_offset"
    description = "each row adds its own offset"
    stage = Stage.DARK
    sigma: float = param(2.0, "DN", "spread of the row offsets", null=0.0)

    def realize(self, device, rng):
        device.state[self.key] = self.sigma * rng.standard_normal(device.model.shape[0])

    def apply(self, signal, ctx, rng):
        signal += ctx.device.state[self.key][:, None]
        return signal

    def patterns(self, device):
        h, w = device.model.shape
        return [Pattern("offset", device.state[self.key], np.broadcast_to(np.arange(h)[:, None], (h, w)))]
'''
    path = tmp_path / "rows.py"
    path.write_text(source)
    effect = make_effect(f"{path}:RowOffset", sigma=5.0)
    assert effect.key == "row_offset" and effect.null_values() == {"sigma": 0.0}
    model = SensorModel(SHAPE, bit_depth=12, effects=[effect])
    dev = model.realize(np.random.default_rng(0), [0.0])
    out = dev.mean_signal(np.zeros(SHAPE), dev.context(0.0))
    np.testing.assert_allclose(out[:, 0], dev.state["row_offset"])
    assert not effect.patterns(dev)[0].pixel_local
    with pytest.raises(UsageError):
        make_effect(f"{path}:Nope")


def test_simulation_is_unchanged_by_the_checking_interface():
    """Backward compatibility: the same seed gives the same images and catalogue as before the interface grew."""
    model = preset("H", (40, 40), bit_depth=8, rate_scale=3000.0).with_effects(Gain(), Nonlinearity(beta=0.05))
    a = model.realize(np.random.default_rng(5), [0.0, 1.0, 2.0])
    b = model.realize(np.random.default_rng(5), [0.0, 1.0, 2.0])
    scene = np.full((40, 40), 100.0, np.float32)
    img_a = a.expose(scene, a.context(2.0, iso=200.0), np.random.default_rng(1))
    img_b = b.expose(scene, b.context(2.0, iso=200.0), np.random.default_rng(1))
    np.testing.assert_array_equal(img_a, img_b)
    cat = a.catalogue
    eff = cat.effective(2.0)
    # the cached effective index equals a fresh computation
    fresh = dataclasses.replace(cat)
    assert np.array_equal(fresh.effective(2.0).x, eff.x)
    assert len(cat.effective(1.0)) <= len(eff)


def test_param_metadata_defaults():
    @dataclasses.dataclass
    class Toy(Effect):
        name = "toy"
        stage = Stage.RESPONSE
        a: float = param(1.0, "DN", "a thing", null=0.0, free=True, bounds=(0.0, 5.0))
        b: float = param(2.0)

    assert Toy.free_params() == ["a"]
    assert Toy.null_values() == {"a": 0.0}
    assert Toy.bounds("a") == (0.0, 5.0) and Toy.bounds("b") == (-np.inf, np.inf)
    assert Toy().nulled().a == 0.0 and Toy().nulled().b == 2.0
    assert isinstance(Pattern("x", np.zeros(3), np.array([[0, 1, 2]])).pixel_local, bool)


def test_dark_signal_grows_with_exposure_and_temperature_and_is_amplified():
    """D = D0 + r̄·t·2^((T − T_ref)/T_d) on every pixel, multiplied by the analog gain (charge in the pixel)."""
    model = SensorModel((16, 16), bit_depth=12, effects=[DarkCurrent(offset=5.0, rate=10.0, sigma_rate=0.0,
                                                                     rate_max=0.0, t_ref=25.0, t_double=8.0),
                                                          make_effect("gain", iso_ref=100.0, exponent=1.0),
                                                          make_effect("black_level", level=32.0)], t0=0.0)
    dev = model.realize(np.random.default_rng(0), [0.0])
    dark = np.zeros((16, 16))
    for t, temp, iso in ((1.0, 25.0, 100.0), (2.0, 33.0, 100.0), (1.0, 25.0, 400.0)):
        mean = dev.mean_signal(dark, dev.context(0.0, exposure_s=t, iso=iso, temperature_c=temp))
        expect = 32.0 + iso / 100.0 * (5.0 + 10.0 * t * 2 ** ((temp - 25.0) / 8.0))
        np.testing.assert_allclose(mean, expect, rtol=1e-6)


def test_shot_noise_is_amplified_and_ignores_the_black_level():
    """σ² = g·A·(μ − black): the electrons' Poisson noise scaled by the analog gain A."""
    model = SensorModel((64, 64), bit_depth=16, effects=[make_effect("gain", iso_ref=100.0, exponent=1.0),
                                                          make_effect("shot_noise", g=0.5),
                                                          make_effect("black_level", level=100.0)], t0=0.0)
    dev = model.realize(np.random.default_rng(0), [0.0])
    ctx = dev.context(0.0, iso=200.0)
    assert ctx.amplification == pytest.approx(2.0) and ctx.readout_offset == pytest.approx(100.0)
    frames = np.stack([dev.signal(np.full((64, 64), 300.0, np.float32), ctx, np.random.default_rng(i))
                       for i in range(40)])
    assert frames.mean() == pytest.approx(100.0 + 600.0, abs=0.5)
    # signal above black 600 DN at gain 2: σ² = 0.5·2·600 = 600; 64²·39 df → relative SE ≈ 0.0035
    assert frames.var(axis=0, ddof=1).mean() == pytest.approx(600.0, rel=0.03)
    assert model.effect("shot_noise").variance(np.array([600.0]), ctx)[0] == pytest.approx(600.0)


@pytest.mark.parametrize("order", ["read_first", "shot_first"])
def test_noise_sources_see_the_noiseless_signal(order):
    """Noise effects are independent sources, each with its law at the noiseless signal: in the dark, shot noise
    adds nothing, whatever read noise came before it in the list.  (Drawn on the noisy signal, the shot noise saw
    max(read noise, 0): a dark variance growing with the ISO gain, and the check flagged an input-referred noise
    that was not there.)"""
    read, shot = make_effect("read_noise", sigma=3.0), make_effect("shot_noise", g=0.4)
    noise = [read, shot] if order == "read_first" else [shot, read]
    model = SensorModel((64, 64), bit_depth=16, effects=[make_effect("gain", iso_ref=100.0, exponent=1.0), *noise],
                        t0=0.0)
    dev = model.realize(np.random.default_rng(0), [0.0])
    ctx = dev.context(0.0, iso=200.0)
    for level, expected in ((0.0, 9.0), (500.0, 9.0 + 0.4 * 2.0 * 1000.0)):
        frames = np.stack([dev.signal(np.full((64, 64), level, np.float32), ctx, np.random.default_rng(i))
                           for i in range(40)])
        # 64²·39 df: relative SE of the mean variance ≈ 0.0035; the bug this guards against added 0.96 DN² (11 %)
        assert frames.var(axis=0, ddof=1).mean() == pytest.approx(expected, rel=0.02)


class _Dither(Effect):
    """A user's effect that draws in the mean signal's stages (the mean then takes the seed-0 stream)."""

    name, stage = "dither", Stage.GAIN

    def apply(self, signal, ctx, rng):
        return signal + rng.standard_normal(signal.shape)


def test_the_mean_signal_gives_a_drawing_effect_the_seed_zero_stream():
    # The mean signal makes its generator only when an effect uses it (the built-ins never do); one that does sees
    # exactly np.random.default_rng(0), as it always has.
    dev = SensorModel(SHAPE, bit_depth=16, effects=[_Dither()]).realize(np.random.default_rng(3), [0.0])
    light = np.full(SHAPE, 10.0)
    want = light + np.random.default_rng(0).standard_normal(SHAPE)
    np.testing.assert_array_equal(dev.mean_signal(light, dev.context(0.0)), want)
