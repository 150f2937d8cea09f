"""The growth channel's count tests take the fitted model's own variance where defects arrive in batches.

A cluster of N detected members adds N records at one time, so with clusters in the model the count increments
vary more than their mean: per cluster λ(1 + λ) against λ (λ: the detected members).  The score tests weight each
increment by that variance (:func:`forensics.check.scoretests.count_dispersion`, from the model's own draws);
without batch arrivals the weight is the Poisson mean, exactly as before.
"""
from __future__ import annotations

import numpy as np
import pytest

from forensics.check.fit import fit_model
from forensics.check.pipeline import base_model, prepare, resolve_effects
from forensics.check.scoretests import count_dispersion
from forensics.fixtures.hidden import make_hidden
from forensics.sensor.catalogue import PARTIAL


@pytest.fixture(scope="module")
def clusters_evidence(tmp_path_factory):
    data = tmp_path_factory.mktemp("batches") / "data"
    make_hidden("clusters", data, rng=2)
    ev, _ = prepare(data, [], 2, 199)
    return ev


def test_the_dispersion_of_a_model_with_clusters_is_that_of_its_batches(clusters_evidence):
    ev = clusters_evidence
    fitted = fit_model(ev, [*base_model(ev.black_level), *resolve_effects(["clusters"])])
    n = len(ev.times) - 1
    disp = count_dispersion(fitted, n)
    clusters = next(e for e in fitted.effects if e.key == "clusters")
    lam = clusters.detected_size(ev)
    # the clusters' share of the expected partially stuck increments, and the compound-Poisson factor it implies
    alone = ev.defects.expected_counts([clusters])[PARTIAL]
    share = (alone[-1] - alone[0]) / (fitted.expected[PARTIAL][-1] - fitted.expected[PARTIAL][0])
    predicted = 1.0 + lam * share
    # 199 draws of 9 increments: the pooled variance is known to ≈ 5 % for Poisson counts, ≈ 10 % for these
    # batches (measured 2.57 against the 2.67 predicted: λ 3.78, clusters 44 % of the arrivals)
    assert abs(disp[0] / predicted - 1.0) <= 0.15, (disp[0], predicted, lam, share)
    # stuck pixels arrive one by one: their factor is 1 but for the draws' noise (≈ 3.4 % for 199 × 9 Poisson
    # increments; 4 sd)
    assert np.all(disp[:n] == disp[0]) and np.all(disp[n:] <= 1.14), disp


def test_without_batch_arrivals_the_weights_are_the_poisson_means(clusters_evidence):
    ev = clusters_evidence
    fitted = fit_model(ev, base_model(ev.black_level))
    assert np.all(count_dispersion(fitted, len(ev.times) - 1) == 1.0)
