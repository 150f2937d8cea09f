"""The issue's acceptance experiment on a reduced synthetic iris set (both built-in matchers).

One run: 30 eyes × 4 images, sensors A (the paper's realistic sensor) and H × 100 (a hundred times the rates
of the paper's most aggressive sensor, stuck levels up to full scale), ages 0, 48 and 96 years.
"""
from __future__ import annotations

import numpy as np
import pytest

from forensics.impact.experiment import parse_sensors, run_impact
from forensics.impact.irises import simulate_irises
from forensics.impact.matchers import compare_all, load_matchers
from forensics.io.dataset import open_dataset


@pytest.fixture(scope="module")
def experiment(tmp_path_factory):
    root = tmp_path_factory.mktemp("irises") / "set"
    simulate_irises(root, 30, 4, rng=3)
    source = open_dataset(root)
    matchers = load_matchers(["masek", "ko"])
    result = run_impact(source, parse_sensors("A,H*100", source.shape()[:2], 8), [0, 48, 96], matchers, rng=5,
                        n_boot=500)
    return source, matchers, result


@pytest.mark.slow
def test_both_matchers_separate_genuine_from_impostor_at_age_0(experiment):
    _, _, result = experiment
    for matcher in ("masek", "ko"):
        unit = result.unit("A", 0.0, matcher, "same-age")
        # The bound; measured on this set: masek ≈ 1 %, ko ≈ 0.3 % (README, "Sensor ageing and recognition").
        assert unit.eer.estimate <= 0.05, (matcher, unit.eer.estimate)
        assert unit.eer.n_genuine == 30 * 6


@pytest.mark.slow
def test_sensor_a_shows_no_trend_and_h_times_100_a_significant_rise(experiment):
    _, _, result = experiment
    for matcher in ("masek", "ko"):
        for protocol in ("same-age", "enrol-0"):
            # Sensor A: ≈ 0.67 partially stuck pixels per megapixel per year of 3 DN: about 5 in this
            # 0.077-megapixel sensor after 96 years; the paper found no trend either.
            assert not result.trend("A", matcher, protocol).significant
    rising = [m for m in ("masek", "ko") if result.trend("H×100", m, "same-age").significant
              and result.trend("H×100", m, "same-age").slope > 0]
    assert rising, [result.trend("H×100", m, "same-age").describe() for m in ("masek", "ko")]


@pytest.mark.slow
def test_all_against_all_equals_a_plain_pairwise_loop_on_a_sample(experiment):
    source, matchers, _ = experiment
    rng = np.random.default_rng(0)
    pick = rng.choice(len(source), 12, replace=False)
    images = [source.frames[k].load() for k in pick]
    for matcher in matchers:
        templates = [matcher.encode(im) for im in images]
        matrix = compare_all(matcher, templates, templates)
        loop = np.array([[matcher.compare(a, b) for b in templates] for a in templates])
        assert np.array_equal(matrix, loop)
