"""Detection (eq. 11–15): the exact median network, masks, thresholds, CFA mosaics, warnings."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage, stats

from forensics.defects.detection import (
    MaskSpec,
    accumulated_histogram,
    centre_mask,
    detect,
    expected_false_alarms,
    median_filter,
    parse_mask,
    prefetch,
    robust_normal,
    texture_mask,
)
from forensics.sensor.effects import ReadNoise
from forensics._shared.errors import InputError, UsageError
from forensics.sensor.catalogue import PARTIAL, STUCK
from forensics.sensor.presets import preset
from forensics.sensor.scenes import scene
from forensics.io.stack import StackStats, stack_stats


# --------------------------------------------------------------------------- median
@pytest.mark.parametrize("q", [1, 3, 5, 7, 9, 11, 13])
@pytest.mark.parametrize("shape", [(37, 53), (6, 90), (64, 64)])
def test_median_filter_equals_scipy(q, shape):
    rng = np.random.default_rng(q * 100 + shape[0])
    ties = rng.integers(0, 4, shape).astype(np.float32)  # many equal values
    smooth = rng.random(shape, dtype=np.float32) * 1000
    for img in (ties, smooth):
        expected = ndimage.median_filter(img, q, mode="reflect")
        assert np.array_equal(median_filter(img, q, tile=(8, 16)), expected)
        assert np.array_equal(median_filter(img, q, threads=2), expected)


def test_median_filter_integer_input_and_errors():
    img = np.arange(400, dtype=np.uint16).reshape(20, 20)
    out = median_filter(img, 9)
    assert out.dtype == np.float32
    assert np.array_equal(out, ndimage.median_filter(img.astype(np.float32), 9, mode="reflect"))
    with pytest.raises(UsageError):
        median_filter(img, 4)
    with pytest.raises(ValueError):
        median_filter(np.zeros((4, 4, 3)), 3)


# --------------------------------------------------------------------------- helpers
def synthetic_stack(shape=(96, 128), k=40, seed=0, noise=2.0, extra=None):
    """Frames of a smooth scene + noise with planted offsets and one stuck pixel; returns (stats, truth)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    base = 1000 + 0.05 * xx + 0.02 * yy  # gentle: on steep ramps the median tracks the pixel itself
    offsets = {(10, 12): 60.0, (100, 20): 40.0, (30, 70): 25.0, **(extra or {})}
    stuck = (50, 80)
    frames = []
    for _ in range(k):
        f = base + rng.normal(0, noise, shape) + rng.uniform(-200, 200)
        for (x, y), d in offsets.items():
            f[y, x] += d
        f[stuck[1], stuck[0]] = 777
        frames.append(np.clip(np.rint(f), 0, 65535).astype(np.uint16))
    return stack_stats(frames), offsets, stuck


def test_detect_finds_planted_defects_with_all_mask():
    st, offsets, stuck = synthetic_stack()
    res = detect(st, mask=MaskSpec("all"))
    sites = res.sites(PARTIAL)
    assert set(offsets) <= sites
    assert res.sites(STUCK) == {stuck}
    assert res.count() == len(offsets) + 1  # no false alarm at 5σ in 12k pixels of Gaussian noise
    # threshold = center + 5·scale; scale ≈ σ of d̂ ≈ noise/√K·(1 + median variance) — order of 2/√40
    fit = res.fits[0]
    assert fit.tau == pytest.approx(fit.center + 5 * fit.scale)
    assert 0.25 < fit.scale < 0.5
    row = next(r for r in res.defect_rows() if (r["x"], r["y"]) == (10, 12))
    assert row["kind"] == "partial" and row["amplitude"] == pytest.approx(60, abs=2)
    assert row["z"] == pytest.approx((row["amplitude"] - fit.center) / fit.scale, rel=1e-4)
    stuck_row = next(r for r in res.defect_rows() if r["kind"] == "stuck")
    assert stuck_row["amplitude"] == 777
    d = res.to_dict()
    assert {"x", "y", "kind", "amplitude", "z"} <= set(d["defects"][0])
    assert d["counts"] == {"partial": 3, "stuck": 1}


def test_given_tau_and_sigma():
    st, offsets, _ = synthetic_stack()
    res = detect(st, tau=30.0, mask=MaskSpec("all"))
    assert res.sites(PARTIAL) == {(10, 12), (100, 20)}  # 25 DN is below τ = 30
    assert res.threshold_dict()["tau"] == 30.0 and res.sigma is None
    with pytest.raises(UsageError):
        detect(st, sigma=None, tau=None)


def test_centre_mask_leaves_out_the_centre():
    m = centre_mask((100, 200), 0.5)
    assert not m[50, 100] and m[0, 0] and m[99, 199]
    assert m.sum() == 100 * 200 - 50 * 100
    st, offsets, stuck = synthetic_stack(extra={(64, 48): 50.0})
    res = detect(st, mask=MaskSpec("centre", 0.5))
    # the centre rectangle is rows 24..71, columns 32..95: the defect at (64, 48) is left out
    assert res.sites() == {(10, 12), (100, 20), (30, 70), stuck}
    assert (64, 48) in detect(st, mask=MaskSpec("all")).sites()
    assert res.n_analysed == (96 - 8) * (128 - 8) - 48 * 64  # the q//2 border is never analysed


def test_texture_mask_drops_textured_block():
    rng = np.random.default_rng(1)
    d = rng.normal(0, 1, (80, 80)).astype(np.float32)
    d[20:40, 20:40] *= 20  # strong texture
    d[60, 60] = 50  # an isolated defect stays analysed
    m = texture_mask(d, 15, 3.0)
    assert not m[30, 30] and m[60, 60] and m[5, 70]


def test_parse_mask(tmp_path):
    assert parse_mask(None) == MaskSpec()
    assert parse_mask("centre:0.3").fraction == 0.3
    assert parse_mask("auto").kind == "auto" and parse_mask("all").kind == "all"
    with pytest.raises(UsageError):
        parse_mask("centre:x")
    with pytest.raises(InputError, match="no such mask"):
        parse_mask(str(tmp_path / "nope.png"))


def test_mask_image(tmp_path):
    from forensics.io.images import write_image

    st, offsets, _ = synthetic_stack()
    mask = np.zeros((96, 128), np.uint8)
    mask[:, :64] = 255
    write_image(tmp_path / "m.png", mask)
    res = detect(st, mask=parse_mask(str(tmp_path / "m.png")))
    assert res.sites(PARTIAL) == {(10, 12), (30, 70)}
    with pytest.raises(InputError, match="mask is"):
        detect(st, mask=MaskSpec("file", path=str(tmp_path / "m.png")), q=3) if False else \
            detect(StackStats(st.n, st.mean[:50], st.var[:50], st.minimum[:50], st.maximum[:50]),
                   mask=MaskSpec("file", path=str(tmp_path / "m.png")))


def test_stuck_tolerance():
    rng = np.random.default_rng(3)
    frames = [rng.integers(1000, 1100, (40, 40)).astype(np.uint16) for _ in range(20)]
    for i, f in enumerate(frames):
        f[15, 17] = 500 + (i % 2)  # stuck, but with one DN of noise
    st = stack_stats(frames)
    assert (17, 15) not in detect(st, mask=MaskSpec("all")).sites(STUCK)
    assert (17, 15) in detect(st, mask=MaskSpec("all"), stuck_tolerance=1).sites(STUCK)


def test_constant_patch_is_not_stuck():
    rng = np.random.default_rng(4)
    frames = [rng.integers(1000, 1100, (40, 40)).astype(np.uint16) for _ in range(20)]
    for f in frames:
        f[10:20, 10:20] = 65535  # clipped highlight in every frame
    assert detect(stack_stats(frames), mask=MaskSpec("all")).count(STUCK) == 0


def test_cfa_channels_fitted_separately():
    rng = np.random.default_rng(5)
    h, w = 64, 96
    level = np.array([[4000, 8000], [8000, 2000]])
    noise = np.array([[2.0, 4.0], [4.0, 1.0]])
    lv = np.tile(level, (h // 2, w // 2))
    ns = np.tile(noise, (h // 2, w // 2))
    frames = []
    for _ in range(30):
        f = lv + ns * rng.standard_normal((h, w))
        f[10, 20] += 30  # R site (even, even)
        f[11, 21] += 30  # B site (odd, odd): 30 DN = big against σ 1
        frames.append(np.rint(f).astype(np.uint16))
    res = detect(stack_stats(frames), cfa="RGGB", mask=MaskSpec("all"))
    assert [f.name for f in res.fits] == ["R", "G1", "G2", "B"]
    scales = [f.scale for f in res.fits]
    assert scales[1] > scales[0] > scales[3]  # per-channel noise is recovered
    assert {(20, 10), (21, 11)} <= res.sites(PARTIAL)
    rows = {(r["x"], r["y"]): r for r in res.defect_rows()}
    assert rows[(20, 10)]["channel"] == "R" and rows[(21, 11)]["channel"] == "B"
    with pytest.raises(InputError):
        detect(stack_stats([f[:63] for f in frames]), cfa="RGGB")


def test_few_images_warn_with_expected_false_alarms():
    st, _, _ = synthetic_stack(k=5)
    res = detect(st, mask=MaskSpec("all"))
    assert len(res.warnings) == 1
    expected = expected_false_alarms(res.fits[0].n_pixels, 5.0)
    assert f"{expected:.2g}" in res.warnings[0] and "false" in res.warnings[0]


def test_accumulated_histogram():
    rng = np.random.default_rng(6)
    v = rng.normal(10, 2, 100_000).astype(np.float32)
    c, s = robust_normal(v)
    assert c == pytest.approx(10, abs=0.05) and s == pytest.approx(2, rel=0.02)
    x, n, e = accumulated_histogram(v, c, s)
    assert np.all(np.diff(n) <= 0) and n[0] == pytest.approx(50_000, rel=0.02)
    i = np.searchsorted(x, c + 2 * s)
    assert n[i] == pytest.approx(e[i], rel=0.1)  # the normal model fits normal data
    assert e[0] == pytest.approx(len(v) / 2)


def test_prefetch_yields_everything_and_reraises():
    assert list(prefetch(iter(range(50)), depth=3)) == list(range(50))

    def broken():
        yield 1
        raise InputError("bad file")

    with pytest.raises(InputError, match="bad file"):
        list(prefetch(broken()))


def test_simulated_device_recall_and_precision():
    """A device from preset F, 16-bit with read noise: every defect ≥ 6σ of d̂ is found, no false alarm."""
    rng = np.random.default_rng(7)
    shape = (96, 128)
    model = preset("F", shape, bit_depth=16, rate_scale=500).with_effects(ReadNoise(30.0))
    device = model.realize(rng, [10.0])
    frames = [device.expose(np.float32(65535) * ndimage.gaussian_filter(scene(shape, rng, 1, "texture"), 3),
                            device.context(10.0), rng) for _ in range(50)]
    res = detect(stack_stats(frames), mask=MaskSpec("all"))
    truth = device.catalogue.effective(10.0)
    truth = truth.select(res.mask[truth.y, truth.x])
    assert len(truth) > 50
    found = res.sites()
    hit = np.array([s in found for s in zip(truth.x.tolist(), truth.y.tolist())])
    rel = truth.amplitude / res.fits[0].scale
    # a defect of amplitude a is missed when the noise of d̂ pulls it under τ = 5σ: P = Φ(5 − a/σ);
    # over the uniform amplitudes ≥ 6σ that is a few per cent, and ≈ 3e-5 at ≥ 9σ
    assert hit[rel >= 6].mean() >= 0.9
    assert hit[rel >= 9].all()
    assert found <= set(zip(truth.x.tolist(), truth.y.tolist()))  # no false alarm (≈ 3e-3 expected)
    assert stats.norm.sf(5) * res.fits[0].n_pixels < 0.01


def test_median_filter_parallel_processes_match():
    """≥ 2 MP images are split over forked processes on Linux: same result as one process and as scipy."""
    rng = np.random.default_rng(8)
    img = rng.integers(0, 50, (1500, 1400)).astype(np.float32)
    one = median_filter(img, 9, threads=1)
    assert np.array_equal(median_filter(img, 9, threads=2), one)
    crop = img[:200, :300]
    assert np.array_equal(one[:196, :296], ndimage.median_filter(crop, 9, mode="reflect")[:196, :296])


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_integer_accumulator_matches_the_float_one(dtype):
    """The exact integer sums agree with float64 sums of the same frames (the float path as the oracle)."""
    from forensics.io.stack import StackAccumulator

    rng = np.random.default_rng(9)
    top = np.iinfo(dtype).max
    frames = [rng.integers(0, top + 1, (30, 40)).astype(dtype) for _ in range(25)]
    frames[3][0, 0] = top
    acc = StackAccumulator()
    for f in frames:
        acc.add(f)
    got, ref = acc.result(), stack_stats([f.astype(np.float64) for f in frames])
    assert got.n == ref.n and np.array_equal(got.minimum, ref.minimum) and np.array_equal(got.maximum, ref.maximum)
    assert got.minimum.dtype == dtype
    assert np.allclose(got.mean, ref.mean, rtol=1e-6) and np.allclose(got.var, ref.var, rtol=1e-4)
    with pytest.raises(InputError):
        acc.add(frames[0][:10])


def test_colour_images_are_averaged_over_channels():
    rng = np.random.default_rng(10)
    frames = []
    for _ in range(20):
        f = 3000 + rng.normal(0, 2, (48, 64, 3))
        f[20, 30, :] += 40  # a hot pixel shows in every channel after demosaicing
        f[10, 12, :] = 900  # stuck in every channel
        frames.append(np.rint(f).astype(np.uint16))
    res = detect(stack_stats(frames), mask=MaskSpec("all"))
    assert res.sites(PARTIAL) == {(30, 20)} and res.sites(STUCK) == {(12, 10)}


def test_static_scenes_disable_the_stuck_test_with_a_warning():
    rng = np.random.default_rng(11)
    frames = [np.full((40, 40), 1000, np.uint16) + rng.integers(0, 2, (40, 40)).astype(np.uint16) for _ in range(12)]
    res = detect(stack_stats(frames), mask=MaskSpec("all"), stuck_tolerance=1)
    assert res.count(STUCK) == 0
    assert any("stuck test cannot" in w for w in res.warnings)
