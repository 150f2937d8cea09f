"""Exact reuse of segmentation steps between aged images of one eye (:class:`forensics.impact.segment.memo.StepMemo`).

An aged image differs from the same eye's image at the sensor's previous age in a few pixels; its segmentation
reuses the costly steps (the pupil's and the limbus's Hough transforms, the limbus fits) whose inputs are
byte-identical, and must give the segmentation of a fresh run bit for bit.  Checked on synthetic eyes always and
on real eyes where ``../shared`` has them, each image segmented with the memo of its previous computed age — as
the experiment's chains do — and compared with a segmentation from scratch, over sensors whose defects leave
most steps unchanged (A) and sensors that add many (G, H, H×100), so that both the reuse and its fallback run.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from forensics._shared.digest import content_digest
from forensics._shared.rng import keyed_generator
from forensics.impact.experiment import parse_sensors
from forensics.impact.segment.caht import segment_caht
from forensics.impact.segment.memo import StepMemo
from forensics.io.dataset import open_dataset
from forensics.sensor.simulate import aged_exposures

IITD = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "iitd-iris-001-040"


def _aged_chain(images: list[np.ndarray], spec, ages: list[float], seed: int = 0):
    """``(age index, aged images)`` of every distinct aged set of one sensor, in age order (as the experiment
    ages them: the sensor's keyed stream, image ``k``'s sub-stream)."""
    rng = keyed_generator(seed, 1, spec.stream_key())
    device = spec.model.realize(rng, [spec.model.t0 + a for a in ages])
    before = None
    for a_index, age in enumerate(ages):
        ctx = device.context(spec.model.t0 + age)
        aged = [aged_exposures(device, image, [ctx], rng, k, first_step=a_index)[0] for k, image in enumerate(images)]
        if before is None or not all(np.array_equal(a, b) for a, b in zip(aged, before)):
            yield a_index, aged
        before = aged


def _check_chains(images: list[np.ndarray], sensors: str, ages: list[float]) -> dict[str, tuple[int, int]]:
    """Every distinct aged image segmented with the memo of its previous computed age equals a fresh
    segmentation, bit for bit; ``{sensor: (steps reused, steps computed)}`` over the ages after the first."""
    counts = {}
    for spec in parse_sensors(sensors, images[0].shape[:2], 8):
        entries: list[dict | None] = [None] * len(images)
        hits = misses = 0
        for a_index, aged in _aged_chain(images, spec, ages):
            for k, image in enumerate(aged):
                memo = StepMemo(entries[k])
                got = segment_caht(image, memo=memo)
                if entries[k] is not None:
                    want = segment_caht(image)
                    assert content_digest(got) == content_digest(want), (spec.name, ages[a_index], k)
                    hits, misses = hits + memo.hits, misses + memo.misses
                entries[k] = memo.entries
        counts[spec.name] = (hits, misses)
    return counts


def _shifted(value):
    """A value of the same shape with every float moved by 7 (a poisoned memo entry)."""
    if isinstance(value, tuple):
        return tuple(_shifted(v) for v in value)
    return value + 7.0 if isinstance(value, float) else value


def test_the_memo_computes_a_step_once_per_distinct_input():
    calls = []

    def step(a, b):
        calls.append((a.tolist(), b))
        return (float(a.sum()) + b,)

    memo = StepMemo()
    x = np.arange(3.0)
    assert memo(step, x, 1.0) == (4.0,) and memo(step, x.copy(), 1.0) == (4.0,) and len(calls) == 1
    assert memo(step, x, 2.0) == (5.0,) and memo(step, x.astype(np.float32), 1.0) == (4.0,) and len(calls) == 3
    later = StepMemo(memo.entries)
    assert later(step, x, 2.0) == (5.0,) and len(calls) == 3 and (later.hits, later.misses) == (1, 0)
    assert len(later.entries) == 1                       # only what this memo's run used is carried on
    assert later(step, x, 3.0) == (6.0,) and len(calls) == 4 and later.misses == 1


def test_synthetic_eyes_aged_give_the_fresh_segmentation_with_the_memo(captures):
    # Four synthetic eyes, sensor A (a few defects), H (many) and H×100 (hundreds), 0–96 years in 24-year steps.
    images = [captures[e, 0] for e in range(4)]
    counts = _check_chains(images, "A,H,H*100", [0.0, 24.0, 48.0, 72.0, 96.0])
    assert counts["A"][0] > counts["A"][1]                 # mostly reused
    hits, misses = counts["H"]
    assert hits > 0 and misses > 0                         # the reuse and its fallback both ran
    assert counts["H×100"][0] == 0 and counts["H×100"][1] > 0


def test_a_poisoned_memo_is_used_only_for_byte_identical_inputs(captures):
    image, other = captures[0, 0], captures[1, 0]
    memo = StepMemo()
    fresh = segment_caht(image, memo=memo)
    poisoned = {key: _shifted(value) for key, value in memo.entries.items()}
    # The same image: every costly step is taken from the memo, so the poisoned values show in the result
    # (the memo is really consulted) ...
    fooled = StepMemo(poisoned)
    assert segment_caht(image, memo=fooled) != fresh and fooled.hits > 0
    # ... but another eye's inputs never match: the fresh result, nothing reused.
    safe = StepMemo(poisoned)
    assert content_digest(segment_caht(other, memo=safe)) == content_digest(segment_caht(other)) and safe.hits == 0
    # A defect on the limbus's right arc: the fits whose profiles it reaches are computed anew, and the result
    # is the fresh one whatever the other entries hold.
    spot = image.copy()
    x, y, r = fresh.iris
    spot[int(round(y)) - 1:int(round(y)) + 2, int(round(x + r)) - 1:int(round(x + r)) + 2] = 255
    clean = StepMemo(memo.entries)
    assert content_digest(segment_caht(spot, memo=clean)) == content_digest(segment_caht(spot))
    assert clean.misses > 0


@pytest.mark.realdata
@pytest.mark.slow
def test_real_eyes_aged_give_the_fresh_segmentation_with_the_memo():
    # Four real eyes (the first image of four classes ten subjects apart), sensors A, D, G and H over the paper's 13
    # ages (eight eyes took 34 s of a CI worker; every step kind is reached with four).
    if not (IITD / "manifest.csv").is_file():
        pytest.skip(f"the IITD iris images are not at {IITD} (research-use data kept outside the repository)")
    frames = open_dataset(IITD).frames
    images = [f.load() for f in frames[::100]]
    counts = _check_chains(images, "A,D,G,H", [float(a) for a in range(0, 97, 8)])
    assert all(hits > 0 for hits, _ in counts.values())
    assert counts["H"][1] > 0
