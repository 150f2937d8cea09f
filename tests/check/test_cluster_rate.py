"""The clusters' arrival rate is unbiased (now read off the pairs of sites that arrived together:
``tests/check/test_co_arrival.py``; where none did, off the sites' pattern, as below).

Ripley's K of the detected sites (every kind: stuck pixels are sites too) gives the clustered share f of all
the sites of the last epoch; the clusters then arrive at f times the rate of all sites.  Taken as f times the rate
of the partially stuck pixels alone, the rate came out 0.57 ± 0.07 of the truth on the 8-bit convention (its stuck
pixels are half of the base arrivals), the fitted model's simulations clustered less than the data, and the spatial
gof after adding clusters lay between 0.025 and 0.23 in every seed (2 of 10 below the sweep's 0.05).
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from forensics.check.pipeline import prepare
from forensics.fixtures.hidden import convention, make_hidden
from forensics.sensor.effects import Clusters

SEEDS = range(1, 9)


@pytest.fixture(scope="module")
def fitted_over_true(tmp_path_factory):
    ratios = []
    for seed in SEEDS:
        data = tmp_path_factory.mktemp(f"clusters{seed}") / "data"
        make_hidden("clusters", data, rng=seed, design=convention("8bit"))
        truth = json.loads((data / "truth.json").read_text())["hidden_params"]["clusters"]
        ev, _ = prepare(data, [], seed, 19)
        ratios.append(Clusters(**truth).fit(ev).rate / truth["rate"])
    return np.array(ratios)


def test_the_cluster_rate_is_unbiased_within_its_spread(fitted_over_true):
    r = fitted_over_true
    se = r.std(ddof=1) / np.sqrt(r.size)
    # measured 0.964 ± 0.090 over these 8 seeds from the pairs that arrived together, divided by the distinct
    # pairs per cluster (members landing on each other are one site: before, 0.893 ± 0.086; from K: 0.84 ± 0.11;
    # from K and the partially stuck rate alone: 0.57 ± 0.07); 3 standard errors of the seeds' own spread
    assert abs(r.mean() - 1.0) <= 3 * se, (r.mean(), se)
