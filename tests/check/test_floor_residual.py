"""The pixel channel's noise floor is measured on each frame's residual from its own scene estimate.

It must predict the noise the pixel channel's residuals actually have — also when the temporal noise is
spatially correlated (demosaiced, JPEG frames) and when the frames' level drifts — and keep the meaning it had
on white noise, and a sensible floor for stuck pixels (whose prediction does not use the neighbours).
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from forensics.check.classes import NORMAL, QUANT_VAR, STK
from forensics.check.measurements import level_drift, load_measurements
from forensics.check.pixels import noise_floor
from forensics.check.scene import KERNEL_VAR, scene_estimate
from forensics.io.images import write_image


def frames(folder, rng: np.random.Generator, n: int = 12, size: int = 96, noise: float = 20.0, blur: float = 0.0,
           drift: float = 0.0, stuck: tuple[tuple[int, int, float], ...] = ()):
    """A flat, vignetted 16-bit dataset: (blurred) white temporal noise of ``noise`` DN rms, per-frame level
    changes of ``drift`` DN rms, stuck pixels ``(y, x, value)`` that never change."""
    folder.mkdir(parents=True, exist_ok=True)
    yy, xx = np.mgrid[0:size, 0:size].astype(float)
    c = (size - 1) / 2
    scene = 2000.0 * (1 - 0.2 * ((xx - c) ** 2 + (yy - c) ** 2) / c**2)
    rows = ["file,subject"]
    for i in range(n):
        white = rng.standard_normal((size, size))
        if blur:
            white = ndimage.gaussian_filter(white, blur)
            white /= 0.5 / (np.sqrt(np.pi) * blur)  # back to about unit variance (continuous-kernel factor)
        frame = scene + drift * rng.standard_normal() + noise * white
        for y, x, v in stuck:
            frame[y, x] = v
        name = f"f{i:02d}.png"
        write_image(folder / name, np.clip(np.rint(frame), 0, 65535).astype(np.uint16))
        rows.append(f"{name},flat")
    (folder / "manifest.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    return load_measurements(folder)


def floor_of(meas, classes=None):
    rep = meas.repeated
    usable = meas.interior[None].repeat(len(rep), 0)
    classes = np.zeros((len(rep), *meas.shape), np.int8) if classes is None else classes
    return noise_floor(meas, rep, usable, classes)


def half_mean_residual_var(meas) -> float:
    """Measured variance of the first half-mean's residual from its own scene estimate (interior): the noise
    the pixel channel's residuals have when nothing but noise is left."""
    r = meas.mean_a[0] - scene_estimate(meas.mean_a[0])
    return float(np.var(r[meas.interior]))


@pytest.mark.parametrize("blur, drift", [(0.0, 0.0), (0.8, 0.0), (0.8, 30.0)])
def test_floor_predicts_the_residual_noise(tmp_path, blur, drift):
    meas = frames(tmp_path / "d", np.random.default_rng(1), blur=blur, drift=drift)
    floor = floor_of(meas).floor[0][meas.interior]
    predicted = float(np.mean(floor)) * (1 + KERNEL_VAR) / meas.n_a[0]
    # 6 frames per half, 90² interior pixels: the measured variance itself is known to ≈ 2 % (its pixels'
    # noise is correlated over a few neighbours); the floor must match it within 6 % (it does to ≈ 1 %), where
    # the old floor (raw temporal variance × the white-noise factor) was 1.9× high on this correlated noise and
    # 6.9× with the drift
    assert predicted == pytest.approx(half_mean_residual_var(meas), rel=0.06)


def test_floor_on_white_noise_is_the_pixel_variance(tmp_path):
    meas = frames(tmp_path / "w", np.random.default_rng(2), noise=20.0)
    floor = floor_of(meas).floor[0][meas.interior]
    # on white noise the floor keeps its meaning: one pixel's temporal variance (20² + rounding 1/12); 11 df per
    # pixel × 8100 pixels → ±0.5 % per pixel mean; 2 % allows for the linear law fitted over the vignetting
    assert float(np.mean(floor)) == pytest.approx(400 + QUANT_VAR, rel=0.02)


def test_stuck_pixels_keep_their_own_floor(tmp_path):
    stuck = ((20, 30, 5000.0), (60, 50, 100.0))
    meas = frames(tmp_path / "s", np.random.default_rng(3), stuck=stuck)
    classes = np.zeros((1, *meas.shape), np.int8)
    for y, x, _ in stuck:
        classes[0, y, x] = STK
    nf = floor_of(meas, classes)
    # a stuck pixel that never changed has only the rounding variance, not its neighbours' residual noise
    for y, x, _ in stuck:
        assert nf.floor[0, y, x] == QUANT_VAR and nf.raw[0, y, x] == QUANT_VAR
    normal = meas.interior & (classes[0] == NORMAL)
    assert float(np.median(nf.floor[0][normal])) == pytest.approx(400, rel=0.05)


def test_level_drift_is_found_only_where_frames_move(tmp_path):
    still = frames(tmp_path / "a", np.random.default_rng(4), blur=0.8)
    moving = frames(tmp_path / "b", np.random.default_rng(4), blur=0.8, drift=10.0)
    d0, d1 = still.drift(0), moving.drift(0)
    assert d0.p > 1e-3 and not d0.material(400.0)
    # 12 frames: the spread's estimate has ≈ 20 % relative error; 10 DN drift → 100 DN² ± 45
    assert d1.p < 1e-6 and d1.material(400.0) and 30.0 < d1.var < 250.0
    assert level_drift(np.zeros((1, 9))).p == 1.0  # one frame: nothing to test


def test_noise_correlation_is_measured(tmp_path):
    white = frames(tmp_path / "a", np.random.default_rng(5))
    blurred = frames(tmp_path / "b", np.random.default_rng(5), blur=0.8, drift=10.0)
    # a Gaussian blur of σ = 0.8 correlates neighbours by exp(−1/(4σ²)) ≈ 0.68; white noise by 0 (the box removal
    # lowers both by ≈ 1/15²)
    assert abs(white.traits.lag1) < 0.03
    assert blurred.traits.lag1 == pytest.approx(0.68, abs=0.05)
    assert not white.traits.jpeg


def test_split_half_statistic_is_calibrated_on_correlated_noise():
    from forensics.check.scoretests import split_half_test, tile_index

    rng = np.random.default_rng(6)
    tiles = tile_index((128, 128)).ravel()
    ones = np.ones(128 * 128)

    def noise() -> np.ndarray:
        # blurred white noise of unit variance (σ = 0.8: neighbours correlate by 0.68)
        n = ndimage.gaussian_filter(rng.standard_normal((128, 128)), 0.8)
        return (n / n.std()).ravel()

    nulls = [split_half_test(noise(), noise(), ones, tiles) for _ in range(60)]
    zs = np.array([h.z for h in nulls])
    # the tiles' variance keeps z standard normal under the null (60 draws: mean ± 0.13, sd within ± 0.2)
    assert abs(zs.mean()) < 0.45 and 0.7 < zs.std() < 1.3
    # the statistic's variance is inflated by Σ_δ ρ(δ)² = (Σ_d exp(−d²/(2·0.8²)))² ≈ 4.0 over independence
    assert float(np.mean([h.inflation for h in nulls])) == pytest.approx(4.0, rel=0.15)
    # the noise scale is read off the halves (1: the residuals' variance is what their floor says)
    assert float(np.mean([h.noise for h in nulls])) == pytest.approx(1.0, abs=0.03)
    # a pattern shared by both halves: its variance per block recovered, to its own se
    pattern = 0.5 * rng.standard_normal(128 * 128)
    alt = split_half_test(pattern + noise(), pattern + noise(), ones, tiles)
    assert alt.z > 5 and abs(alt.t - float(np.mean(pattern**2))) < 3 * alt.se
