"""Dating: exact set intervals (count and rate uncertainty), single-image maximum likelihood."""
from __future__ import annotations


import numpy as np
import pytest
from scipy import ndimage

from forensics.defects.dating import _extrapolate, date_image, date_set
from forensics.defects.detection import MaskSpec, detect
from forensics.sensor.effects import ReadNoise
from forensics._shared.errors import InputError
from forensics.defects.growth import Epoch, estimate_growth
from forensics.sensor.presets import preset
from forensics.sensor.scenes import scene
from forensics.io.stack import stack_stats


def test_extrapolation_interval_covers_at_nominal_rate():
    """X ~ Poi(λΔt), Y ~ Poi(λS): the conditional-binomial interval for Δt covers about 95 %."""
    rng = np.random.default_rng(0)
    span, lam = 8.0, 6.0
    hits = 0
    n = 2000
    for _ in range(n):
        dt = rng.uniform(0.5, 8.0)
        x, y = rng.poisson(lam * dt), rng.poisson(lam * span)
        if y == 0:
            continue
        _, (lo, hi) = _extrapolate(int(x), int(y), span, 0.95)
        hits += lo <= dt <= hi
    assert 0.93 <= hits / n <= 0.975  # mid-p: close to nominal on average (SE of the estimate 0.005)
    with pytest.raises(InputError, match="rate is zero"):
        _extrapolate(3, 0, 8.0, 0.95)


def _device(seed, shape=(96, 96), scale=600, counting="poisson", dates=None):
    rng = np.random.default_rng(seed)
    model = preset("G", shape, bit_depth=16, t0=2000.0, rate_scale=scale, counting=counting)
    model = model.with_effects(ReadNoise(30.0))
    device = model.realize(rng, dates or [2016.0])
    return device, rng


def _epoch(device, rng, t, k=30):
    shape = device.model.shape
    frames = [device.expose(np.float32(65535) * ndimage.gaussian_filter(scene(shape, rng, 1, "texture"), 4),
                            device.context(t), rng) for _ in range(k)]
    return Epoch(t, detect(stack_stats(frames), mask=MaskSpec("all")), f"{t:g}")


def test_date_set_after_and_within():
    device, rng = _device(1, dates=[2016.0])
    model = estimate_growth([_epoch(device, rng, t) for t in (2004.0, 2006.0, 2008.0)]).model()
    later = date_set(model, _epoch(device, rng, 2013.0).detection)
    assert later.position == "after the last reference epoch"
    assert later.interval[0] <= 2013.0 <= later.interval[1]
    assert abs(later.estimate - 2013.0) < 2.5
    d = later.to_dict()
    assert isinstance(d["estimate"], float) and len(d["interval"]) == 2
    inside = date_set(model, _epoch(device, rng, 2005.0).detection)
    # one realisation: the interval's coverage is checked over many trials in test_validate / the sweep
    assert inside.position == "between reference epochs 1 and 2"
    assert 2004.0 <= inside.interval[0] <= inside.estimate <= inside.interval[1] <= 2006.0
    assert abs(inside.estimate - 2005.0) < 0.75
    with pytest.raises(InputError, match="same size"):
        small = stack_stats([np.zeros((50, 60), np.uint16) + i for i in range(10)])
        date_set(model, detect(small, mask=MaskSpec("all")))


def test_date_single_image_picks_the_interval():
    years = list(np.arange(2001.0, 2013.0))
    device, rng = _device(2, shape=(96, 96), scale=1.0 / (0.009216 * 2.6636), counting="deterministic",
                          dates=[2000.0] + years)
    model = estimate_growth([_epoch(device, rng, t, k=20) for t in years]).model()
    assert len({c.first_epoch for c in model.catalogue}) >= 8
    tq = 2006.5
    image = device.expose(np.float32(65535) * ndimage.gaussian_filter(scene((96, 96), rng, 1, "texture"), 4),
                          device.context(tq), rng)
    res = date_image(model, image)
    assert len(res.log_likelihood) == len(res.groups) + 1
    lo, hi = res.interval
    assert (lo is None or lo < tq) and (hi is None or tq <= hi)
    assert res.posterior.sum() == pytest.approx(1.0)
    d = res.to_dict()
    assert d["estimate"] == res.estimate and len(d["intervals"]) == len(res.groups) + 1
    with pytest.raises(InputError):
        date_image(model, image[:50])


def test_single_image_likelihood_is_robust_to_one_outlier():
    """One defect reading absurdly (texture at the site) cannot overturn many consistent ones."""
    from forensics.defects.dating import defect_log_likelihoods
    from forensics.defects.growth import CatalogueEntry, GrowthModel

    cat = [CatalogueEntry(10 + 5 * i, 20, 0, 500.0, i + 1, None if i == 0 else 2000.0 + i, 2001.0 + i, 1, 1)
           for i in range(10)]
    model = GrowthModel(None, (40, 80), 0.0032, [2001.0 + i for i in range(10)], [""] * 10,
                        {"partial": [1] * 10, "stuck": [0] * 10}, {"partial": [1] * 9, "stuck": [0] * 9}, {}, {}, {},
                        cat)
    rng = np.random.default_rng(3)
    img = 1000 + rng.normal(0, 20, (40, 80))
    for c in cat[:6]:
        img[c.y, c.x] += 500  # six present
    img[20, 10 + 5 * 8] += 5000  # the 9th reads wildly
    res = date_image(model, img)
    assert res.best == 6
    lp, la = defect_log_likelihoods(img, model)
    assert np.all(np.isfinite(lp)) and np.all(np.isfinite(la))
