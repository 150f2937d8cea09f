"""The one matcher of detected defects to the simulated truth (used by the validation trials and the demo)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from forensics.io.stack import StackAccumulator
from forensics.defects.detection import MaskSpec, detect
from forensics.sensor.catalogue import PARTIAL, STUCK, DefectCatalogue
from forensics.validate.truth import count_true, match_truth


def catalogue() -> DefectCatalogue:
    """Five defects on a 20×20 frame: three partially stuck (one outside the mask, one arriving late), two stuck."""
    x = np.array([2, 5, 18, 7, 9])
    y = np.array([3, 5, 18, 7, 1])
    kind = np.array([PARTIAL, PARTIAL, PARTIAL, STUCK, STUCK], np.int8)
    amplitude = np.array([40.0, 10.0, 50.0, 200.0, 220.0])
    onset = np.array([2000.0, 2000.0, 2000.0, 2000.0, 2010.0])
    return DefectCatalogue(x, y, kind, amplitude, onset, np.array(["growth"] * 5, dtype=object))


@dataclass
class _Fit:
    scale: float


@dataclass
class FakeDetection:
    """What the matcher reads of a DetectionResult: the analysed region, the sites per kind, σ of d̂."""

    sites_by_kind: dict[int, set]
    mask: np.ndarray | None
    fits: list = field(default_factory=lambda: [_Fit(5.0)])

    def sites(self, kind: int | None = None) -> set:
        if kind is None:
            return set().union(*self.sites_by_kind.values())
        return self.sites_by_kind.get(kind, set())


def test_match_counts_recall_and_precision():
    mask = np.ones((20, 20), bool)
    mask[15:, 15:] = False  # (18, 18) is outside the analysed region
    # found: the strong partial (2, 3); the stuck (7, 7) but as partially stuck; one false alarm (0, 0)
    det = FakeDetection({PARTIAL: {(2, 3), (7, 7), (0, 0)}, STUCK: set()}, mask)
    m = match_truth(det, catalogue(), 2005.0)
    assert len(m) == 3  # (18, 18) is outside the region, (9, 1) not yet arrived
    assert sorted(zip(m.x.tolist(), m.y.tolist())) == [(2, 3), (5, 5), (7, 7)]
    assert m.n_detected == 3 and m.true_positives == 2 and m.false_positives == 1
    assert math.isclose(m.precision, 2 / 3)
    assert math.isclose(m.recall(), 2 / 3)
    assert m.recall(m.kind == PARTIAL) == 0.5
    assert m.recall(m.amplitude >= 30.0) == 1.0
    assert math.isnan(m.recall(m.amplitude > 1e6))
    stuck = m.kind == STUCK
    assert m.found[stuck].all() and not m.found_same_kind[stuck].any()  # found, but not as stuck
    np.testing.assert_allclose(m.amplitude_sigma, m.amplitude / 5.0)


def test_no_mask_means_whole_frame_and_empty_detection():
    det = FakeDetection({}, None)
    m = match_truth(det, catalogue(), 2020.0)
    assert len(m) == 5 and m.n_detected == 0 and m.precision == 0.0 and m.recall() == 0.0


def test_count_true_by_region_kind_and_threshold():
    cat = catalogue()
    region = np.ones((20, 20), bool)
    region[15:, 15:] = False
    assert count_true(cat, 2005.0) == 3
    assert count_true(cat, 2005.0, region) == 2
    assert count_true(cat, 2005.0, region, above=20.0) == 1
    assert count_true(cat, 2020.0, None, STUCK) == 2
    assert count_true(cat, 2020.0, None, None) == 5


def test_matches_a_real_detection():
    """A stack with two planted defects: both found, nothing else, through the real detector."""
    rng = np.random.default_rng(3)
    acc = StackAccumulator()
    for _ in range(30):
        frame = rng.normal(1000.0, 5.0, (48, 48))
        frame[20, 30] += 80.0  # partially stuck (x=30, y=20)
        frame[10, 12] = 4000.0  # stuck
        acc.add(frame.astype(np.float32))
    det = detect(acc.result(), q=9, sigma=6.0, mask=MaskSpec("all"), threads=1)
    cat = DefectCatalogue(np.array([30, 12]), np.array([20, 10]), np.array([PARTIAL, STUCK], np.int8),
                          np.array([80.0, 4000.0]), np.array([2000.0, 2000.0]), np.array(["t", "t"], dtype=object))
    m = match_truth(det, cat, 2001.0)
    assert m.found.all() and m.found_same_kind.all()
    assert m.false_positives == 0 and m.precision == 1.0
