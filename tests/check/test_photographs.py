"""Ordinary photographs as measurements (issue 9 item 6): a folder of pictures — different scenes, no dark
frames, no exposure metadata, the reference paper's own setting — is checked for what it allows.

Frames of one condition are recognised as different scenes from their content (no metadata needed); each
half's mean is predicted from its own scene estimate and scored against its own photographs' texture, so
the held-out error of the base model sits at the noise floor; defects are detected only where both halves
show them, so a scene's edge is not taken for a defect.
"""
from __future__ import annotations

import numpy as np
import pytest

from forensics.check.measurements import PHOTOGRAPHS_NOTE, block_means, different_scenes
from forensics.check.pipeline import base_model, prepare, run_check
from forensics.fixtures.hidden import Design, apply_convention, hidden_effects, hidden_model, make_photographs
from forensics._shared.rng import keyed_generator
from forensics.sensor.scenes import scene

DESIGN = Design(ages=(0, 2, 4, 6, 8))
SEED = 1


def true_defects(design: Design, seed: int) -> set[tuple[int, int]]:
    """(y, x) of the device's defective pixels at the last epoch (the fixture's device, rebuilt)."""
    model, _ = apply_convention(hidden_model("none", design), hidden_effects("none"), design)
    times = [design.start_year + a for a in design.ages]
    cat = model.realize(keyed_generator(seed), times).catalogue
    keep = cat.onset <= times[-1]
    return set(zip(cat.y[keep].tolist(), cat.x[keep].tolist()))


@pytest.fixture(scope="module")
def photographs(tmp_path_factory):
    out = tmp_path_factory.mktemp("photos") / "pictures"
    make_photographs("none", out, rng=SEED, design=DESIGN)
    ev, _ = prepare(out, [], SEED, 99)
    return ev, run_check(ev, base_model(ev.black_level))


def test_two_photographs_are_told_from_two_repeats():
    rng = np.random.default_rng(0)
    a, b = (scene((128, 128), rng) * 3000 for _ in range(2))
    noise = lambda: rng.normal(0, 2.0, (128, 128))  # noqa: E731
    first = block_means(a + noise())
    assert different_scenes(first, block_means(b + noise()), 4.0)
    # the same scene again, also with its level changed by 20 % (flicker, auto-exposure): not different scenes
    assert not different_scenes(first, block_means(a + noise()), 4.0)
    assert not different_scenes(first, block_means(1.2 * a + 15 + noise()), 4.0)


def test_photographs_are_checked_at_their_noise_floor(photographs):
    """The base model is the device's model, so the held-out error of normal pixels is near 1; above it by the
    partially stuck pixels too weak to be seen under the photographs' texture (about 40 % of them stay in the
    normal class, a per-pixel offset the base model does not predict): measured 1.02–1.29 over seeds 1–6, and
    0.999 on five real JPEG photographs of one Nikon D70s (512² centre).  A floor estimated wrongly — from a
    level law, or pooled over both halves' photographs — gives 0.35 or 1.2–8 here."""
    ev, r = photographs
    assert PHOTOGRAPHS_NOTE in r.warnings
    assert all(g.scenes for g in ev.rgroups)
    assert r.error["variance"] is None  # a pixel's spread over scenes is not its temporal variance
    assert 0.9 < r.error["classes"]["normal"] < 1.35, r.error


def test_defects_in_photographs_are_real_defects(photographs):
    """What is detected as partially stuck is a defect of the device (precision ≥ 0.9; a stuck pixel with noise
    after it reads as partially stuck here: with one condition per epoch its value cannot be seen not to follow
    the light), and a fair share of them is found: a scene's edge in one photograph is not a defect."""
    ev, _ = photographs
    cat = ev.initial_catalogue
    found = set(zip(cat.y[cat.kind == 0].tolist(), cat.x[cat.kind == 0].tolist()))
    truth = true_defects(DESIGN, SEED)
    assert len(found) >= 0.2 * len(truth), (len(found), len(truth))
    assert len(found & truth) >= 0.9 * len(found), (len(found & truth), len(found))
