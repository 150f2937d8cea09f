"""A pixel's derivative by its own pattern value, all pixels perturbed at once, next to a known defect.

The neighbours' scene estimates refill a known defect with what a typical pixel would have read there, which
carries the defect pixel's own patterns: perturbing every pixel at once, a pixel next to a stuck defect read
the defect's change through its scene estimate as its own — five times its true derivative after the onset,
and the joint pattern solve (:mod:`forensics.check.joint_solve`) stalled.  With the refills held fixed the
all-at-once derivative is each pixel's own, as perturbing that pixel alone gives it.
"""
import dataclasses

import numpy as np
import pytest

from forensics.check.classes import STK
from forensics.check.fit import fit_model
from forensics.check.pixelfit import pattern_derivative
from forensics.check.pipeline import base_model, prepare
from forensics.fixtures.hidden import convention, make_hidden


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    design = dataclasses.replace(convention("camera"), shape=(48, 64), stuck_fraction=0.5)
    data = tmp_path_factory.mktemp("refill") / "data"
    make_hidden("dsnu", data, rng=4, design=design)
    ev, extra = prepare(data, ["gain", "dsnu"], 4, 19)
    fit = fit_model(ev, [*base_model(ev.black_level), *extra], max_cycles=2)
    return ev, fit


def test_all_at_once_derivative_is_each_pixels_own_next_to_a_stuck_defect(fitted):
    ev, fit = fitted
    dev, pixels = fit.device, fit.pixels

    def predict(d, clip=True):
        return ev.predictor.predict(d, pixels, "a", clip)

    pat = next(p for e in fit.effects if e.key == "dsnu" for p in e.patterns(dev))
    base = predict(dev, clip=False)
    refill = ev.predictor.refill(dev, pixels)
    frozen = pattern_derivative(predict, dev, pat, base, refill)
    loose = pattern_derivative(predict, dev, pat, base)
    light = np.flatnonzero(~ev.predictor.dark)
    r = next(i for i in light[::-1] if (pixels.classes[i] == STK).any())  # a light frame with stuck pixels
    ys, xs = np.nonzero(pixels.classes[r] == STK)
    h, w = ev.shape
    checked = 0
    for y0, x0 in zip(ys, xs):
        y, x = y0, x0 + 1  # the stuck pixel's right-hand neighbour, inside the scored interior
        if not (3 <= y < h - 3 and 3 <= x < w - 3) or pixels.classes[r, y, x] != 0:
            continue
        q = y * w + x
        delta = 1e-3 * (1.0 + float(np.max(np.abs(pat.values))))
        pat.values[pat.blocks[y, x]] += delta
        own = (predict(dev, clip=False)[r, y, x] - base[r, y, x]) / delta
        pat.values[pat.blocks[y, x]] -= delta
        # a single pixel's perturbation is its own derivative exactly (its refill and shift terms are frozen or
        # do not reach it); finite differences in float64 of a piecewise-linear chain: 1e-6 relative
        assert frozen[r, y, x] == pytest.approx(own, rel=1e-4, abs=1e-6), q
        checked += 1
    assert checked >= 3
    # and the loose all-at-once derivative is not (else this test would not guard anything)
    assert np.max(np.abs(loose[r] - frozen[r])) > 1e-2
