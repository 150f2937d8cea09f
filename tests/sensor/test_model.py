"""Invariants of the physical sensor model and the arrival process.

Statistical tests use fixed seeds (so they are deterministic) and a 0.1 %
significance level: under a correct model a seed fails with probability
0.001, and each test also shows it *can* fail by rejecting a wrong model.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from forensics.sensor.effects import Growth, Offset, Prnu, ReadNoise, Stuck
from forensics._shared.errors import UsageError
from forensics.sensor.catalogue import PARTIAL, STUCK, DefectCatalogue
from forensics.sensor.model import SensorModel, make_effect, quantize
from forensics.sensor.presets import PRESETS, preset

ALPHA = 1e-3


def _model(shape=(1000, 1000), rate_partial=1.2, rate_stuck=0.0, bits=8, counting="poisson", a_ps=3.0, a_s=255.0):
    growth = Growth(rate_partial=rate_partial, rate_stuck=rate_stuck, amp_partial=a_ps, amp_stuck=a_s, counting=counting)
    return SensorModel(shape=shape, bit_depth=bits, effects=[growth, Offset(), Stuck()], t0=0.0)


def _counts(model, times, seeds, kind=None):
    return np.array([model.realize(np.random.default_rng(s), times).catalogue.counts(times, kind) for s in seeds])


def _poisson_gof(counts: np.ndarray, mu: float) -> float:
    """Chi-square goodness of fit of integer counts to Poisson(mu), bins merged to expected ≥ 5."""
    n = len(counts)
    lo, hi = int(stats.poisson.ppf(1e-4, mu)), int(stats.poisson.ppf(1 - 1e-4, mu))
    edges = list(range(lo, hi + 1))
    expected = np.array([stats.poisson.pmf(k, mu) for k in edges]) * n
    expected[0] += stats.poisson.cdf(lo - 1, mu) * n
    expected[-1] += stats.poisson.sf(hi, mu) * n
    observed = np.array([np.sum(counts == k) for k in edges], float)
    observed[0] += np.sum(counts < lo)
    observed[-1] += np.sum(counts > hi)
    obs_m, exp_m, o, e = [], [], 0.0, 0.0
    for ob, ex in zip(observed, expected):
        o, e = o + ob, e + ex
        if e >= 5:
            obs_m.append(o), exp_m.append(e)
            o = e = 0.0
    obs_m[-1] += o
    exp_m[-1] += e
    chi2 = np.sum((np.array(obs_m) - exp_m) ** 2 / np.array(exp_m))
    return float(stats.chi2.sf(chi2, len(obs_m) - 1))


def test_counts_follow_the_poisson_law():
    model = _model()  # 1 MP, λ = 1.2 /MP/year: mean 12 defects at 10 years
    counts = _counts(model, [5.0, 10.0], range(1500))
    mu = 1.2 * 10.0
    assert _poisson_gof(counts[:, 1], mu) > ALPHA
    # mean within 4 standard errors of λ·MP·t (SE = sqrt(mu/n))
    assert abs(counts[:, 1].mean() - mu) < 4 * np.sqrt(mu / len(counts))
    # independent increments: the two halves are independent Poisson(6); |r| < 4/sqrt(n)
    first, second = counts[:, 0], counts[:, 1] - counts[:, 0]
    assert abs(np.corrcoef(first, second)[0, 1]) < 4 / np.sqrt(len(counts))
    assert _poisson_gof(second, mu / 2) > ALPHA


def test_goodness_of_fit_rejects_non_poisson_counts():
    """The test above has power: deterministic counts (zero variance) are rejected."""
    counts = _counts(_model(counting="deterministic"), [5.0, 10.0], range(300))
    assert np.all(counts[:, 1] == 12)
    assert _poisson_gof(counts[:, 1], 12.0) < ALPHA


def test_deterministic_counting_is_the_papers_formula():
    model = _model(rate_partial=0.6659, shape=(2000, 3000))  # 6 MP
    times = [0.0, 4.0, 8.0, 12.0]
    counts = _counts(_model(rate_partial=0.6659, shape=(2000, 3000), counting="deterministic"), times, [7])[0]
    np.testing.assert_array_equal(counts, np.rint(0.6659 * 6.0 * np.array(times)))
    assert model.megapixels == 6.0


def test_locations_and_amplitudes_are_uniform():
    model = _model(shape=(300, 500), rate_partial=200.0, rate_stuck=100.0, a_ps=7.0)
    cat = model.realize(np.random.default_rng(11), [10.0]).catalogue
    partial, stuck = cat.select(cat.kind == PARTIAL), cat.select(cat.kind == STUCK)
    assert len(partial) > 200 and len(stuck) > 100
    assert stats.kstest(partial.x / 500.0, "uniform").pvalue > ALPHA
    assert stats.kstest(partial.y / 300.0, "uniform").pvalue > ALPHA
    assert stats.kstest(partial.amplitude / 7.0, "uniform").pvalue > ALPHA
    assert stats.kstest(stuck.amplitude / 255.0, "uniform").pvalue > ALPHA
    assert stats.kstest(cat.onset / 10.0, "uniform").pvalue > ALPHA  # homogeneous in time


def test_stuck_overrides_partial_and_sites_keep_their_defect():
    model = _model(shape=(4, 4))
    raw = DefectCatalogue(np.array([1, 1, 1, 2, 2]), np.array([1, 1, 1, 3, 3]),
                          np.array([PARTIAL, STUCK, PARTIAL, PARTIAL, PARTIAL], np.int8),
                          np.array([5.0, 200.0, 9.0, 4.0, 6.0]), np.array([1.0, 2.0, 3.0, 1.5, 2.5]),
                          np.array(["t"] * 5, dtype=object))
    cat = raw.resolved()
    # (1,1): partial at 1, stuck at 2; the later partial is dropped. (2,3): first partial kept.
    assert len(cat) == 3
    device = model.realize(np.random.default_rng(0), [5.0])
    device.catalogue = cat
    scene = np.full((4, 4), 50.0, np.float32)
    at = lambda t: device.expose(scene, device.context(t), np.random.default_rng(0))  # noqa: E731
    assert at(1.0)[1, 1] == 55 and at(1.9)[3, 2] == 54
    assert at(2.0)[1, 1] == 200 and at(4.0)[1, 1] == 200  # stuck overrides from its onset, forever
    assert at(4.0)[3, 2] == 54  # the site kept its first defect
    assert cat.effective(4.0).kind.tolist().count(STUCK) == 1


@settings(max_examples=40, deadline=None)
@given(
    h=st.integers(4, 40), w=st.integers(4, 40), bits=st.sampled_from([8, 12, 16]),
    rate_partial=st.floats(0, 3e4), rate_stuck=st.floats(0, 2e4), a_ps=st.floats(0, 300),
    seed=st.integers(0, 2**32 - 1),
)
def test_ageing_invariants(h, w, bits, rate_partial, rate_stuck, a_ps, seed):
    full = 2**bits - 1
    model = _model((h, w), rate_partial, rate_stuck, bits, a_ps=a_ps * full / 255, a_s=full)
    rng = np.random.default_rng(seed)
    times = [0.0, 1.0, 2.0, 5.0]
    device = model.realize(rng, times)
    scene = rng.integers(0, full + 1, (h, w)).astype(np.float32)
    scene_before = scene.copy()
    previous_sites: dict[int, tuple[int, float]] = {}
    for t in times:
        image = device.expose(scene, device.context(t), rng)
        assert image.dtype == model.dtype and image.min() >= 0 and image.max() <= full
        now = device.catalogue.effective(t)
        sites = {int(y * w + x): (int(k), float(a)) for x, y, k, a in zip(now.x, now.y, now.kind, now.amplitude)}
        # once defective, always defective: a superset of the previous step's sites; a site never changes
        # its defect except partially stuck → stuck
        for site, (kind, amp) in previous_sites.items():
            assert site in sites
            assert sites[site] == (kind, amp) or (kind == PARTIAL and sites[site][0] == STUCK)
        previous_sites = sites
        flat, scene_flat = image.ravel().astype(float), scene.ravel()
        normal = np.ones(h * w, bool)
        normal[list(sites)] = False
        np.testing.assert_array_equal(flat[normal], scene_flat[normal])  # non-defective pixels untouched
        for site, (kind, amp) in sites.items():
            expected = amp if kind == STUCK else scene_flat[site] + amp
            assert flat[site] == np.clip(np.rint(np.float32(expected)), 0, full)  # saturates at the range
    np.testing.assert_array_equal(scene, scene_before)  # the caller's scene is never modified


def test_device_is_deterministic_for_a_seed():
    model = preset("H", (64, 80)).with_effects(Prnu(0.02), ReadNoise(2.0))
    scene = np.full((64, 80), 100.0, np.float32)
    shots = []
    for _ in range(2):
        dev = model.realize(np.random.default_rng(42), [0.0, 50.0])
        shots.append((dev.catalogue.to_rows(), dev.expose(scene, dev.context(50.0), np.random.default_rng(1))))
    assert shots[0][0] == shots[1][0]
    np.testing.assert_array_equal(shots[0][1], shots[1][1])
    other = model.realize(np.random.default_rng(43), [0.0, 50.0])
    assert other.catalogue.to_rows() != shots[0][0]


def test_rgb_defects_apply_to_every_channel():
    model = _model((20, 30), rate_partial=5e4, rate_stuck=5e4, a_ps=40.0)
    device = model.realize(np.random.default_rng(5), [1.0])
    scene = np.full((20, 30, 3), 100.0, np.float32)
    image = device.expose(scene, device.context(1.0), np.random.default_rng(0))
    assert image.shape == (20, 30, 3)
    assert np.all(image[..., 0] == image[..., 1]) and np.all(image[..., 1] == image[..., 2])


def test_effects_apply_in_physical_order():
    """PRNU (gain) acts on light only: partially stuck offsets are added after it, stuck values replace all."""
    model = SensorModel((1, 3), 16, [Stuck(), Offset(), Prnu(0.1), Growth(0, 0)])
    assert [e.name for e in model.effects] == ["growth", "prnu", "offset", "stuck"]
    device = model.realize(np.random.default_rng(0), [1.0])
    device.state["prnu"] = np.array([[0.1, 0.1, 0.1]], np.float32)
    device.catalogue = DefectCatalogue(np.array([1, 2]), np.array([0, 0]), np.array([PARTIAL, STUCK], np.int8),
                                       np.array([10.0, 7.0]), np.array([0.0, 0.0]), np.array(["t", "t"], dtype=object))
    image = device.expose(np.full((1, 3), 1000.0, np.float32), device.context(1.0), np.random.default_rng(0))
    assert image.tolist() == [[1100, 1110, 7]]


def test_quantize_saturates_and_rounds():
    out = quantize(np.array([-5.0, 0.4, 0.6, 254.5, 300.0], np.float32), 255.0, np.dtype(np.uint8))
    assert out.tolist() == [0, 0, 1, 254, 255]  # round half to even at 254.5


def test_presets_match_tables_3_and_4():
    h100, aps, ccd = 0.6659, 0.7432, 0.5694  # table 3
    expected = {"A": (h100, 0, 3), "B": (h100, aps, 3), "C": (aps, 0, 3), "D": (ccd, 0, 3), "E": (0, aps, 0),
                "F": (4 * h100, 0, 6), "G": (4 * h100, 0, 100), "H": (8 * h100, 5 * aps, 100)}  # table 4
    assert set(PRESETS) == set(expected)
    for name, (lps, ls, aps_) in expected.items():
        growth = preset(name, (10, 10)).effect("growth")
        assert (growth.rate_partial, growth.rate_stuck, growth.amp_partial, growth.amp_stuck) == pytest.approx(
            (lps, ls, aps_, 255.0))
    g16 = preset("A", (10, 10), bit_depth=16).effect("growth")
    assert g16.amp_partial == pytest.approx(3 * 65535 / 255) and g16.amp_stuck == 65535
    with pytest.raises(UsageError, match="choose one of"):
        preset("Z", (10, 10))


def test_model_round_trips_through_dict():
    model = preset("B", (30, 40), bit_depth=16, t0=2009.0).with_effects(Prnu(0.03))
    again = SensorModel.from_dict(model.to_dict())
    assert again.to_dict() == model.to_dict()


def test_user_effect_from_file(tmp_path):
    path = tmp_path / "my_effect.py"
    path.write_text(
        "from dataclasses import dataclass\n"
        "from forensics.sensor.model import Effect, Stage, param\n"
        "@dataclass\n"
        "class ColumnOffset(Effect):\n"
        "    name = 'column_offset'\n"
        "    stage = Stage.DARK\n"
        "    step: float = param(2.0, 'DN', 'offset of odd columns')\n"
        "    def apply(self, signal, ctx, rng):\n"
        "        signal[:, 1::2] += self.step\n"
        "        return signal\n")
    effect = make_effect(f"{path}:ColumnOffset", step=5.0)
    model = SensorModel((2, 4), 8, [effect])
    image = model.realize(np.random.default_rng(0), [0.0]).expose(np.zeros((2, 4), np.float32), model.realize(
        np.random.default_rng(0), [0.0]).context(0.0), np.random.default_rng(0))
    assert image.tolist() == [[0, 5, 0, 5], [0, 5, 0, 5]]
    with pytest.raises(UsageError, match="unknown effect"):
        make_effect("no_such_effect")
    with pytest.raises(UsageError, match="no such file"):
        make_effect(f"{tmp_path}/missing.py:X")
