"""Validation trials on the execution layer: every trial draws from its own keyed streams, so the records and
the summaries are identical in-process, in worker processes and on a Dask cluster, and do not depend on
which trials run or in what order."""
from __future__ import annotations

import json

import numpy as np
import pytest

from forensics._shared.parallel import Executor
from forensics.validate.trials import (
    ValidationSettings,
    defects_records,
    validate_dating,
    validate_defects,
)

#: Tiny trials (48×48 frames, 10 images an epoch, 6 yearly references): a few hundredths of a second each.
SMALL = ValidationSettings(shape=(48, 48), pool=6, images=10, dating_years=6, dating_images=6)
SEED = 5


def _canon(obj: object) -> str:
    """JSON with every float to its last bit (repr round-trips), NaN included: equal strings, identical values."""
    return json.dumps(obj, sort_keys=True, default=lambda o: o.tolist() if hasattr(o, "tolist") else repr(o))


def _run(ex: Executor) -> str:
    defects = validate_defects(SMALL, trials=4, rng=SEED, executor=ex)
    dating = validate_dating(SMALL, trials=3, rng=SEED, executor=ex)
    return _canon([defects.to_dict(), defects.records, dating.to_dict(), dating.records])


@pytest.fixture(scope="module")
def reference() -> str:
    return _run(Executor("in-process"))


def test_trials_do_something_worth_comparing(reference):
    defects, records = json.loads(reference)[:2]
    assert len(records) == 4 and sum(r["n_big"] for r in records) > 0
    assert len({r["rate"] for r in records}) > 1  # trials differ from each other: their streams differ
    assert defects["metrics"][0]["name"].startswith("detection recall")


def test_a_trial_does_not_depend_on_the_others_or_their_order():
    every = defects_records(SMALL, SEED, range(4))
    assert _canon(defects_records(SMALL, SEED, [3, 1])) == _canon([every[3], every[1]])
    generator = np.random.default_rng(SEED)
    generator.random(5)  # a used generator: its state is not what a trial draws from, its seed is
    assert _canon(defects_records(SMALL, generator, [2])) == _canon([every[2]])


def test_processes_give_identical_summaries(reference):
    with Executor("processes", workers=2) as ex:
        assert _run(ex) == reference


@pytest.mark.slow
def test_dask_cluster_gives_identical_summaries(reference, dask_cluster):
    with Executor("dask", scheduler=dask_cluster.scheduler_address) as ex:
        assert _run(ex) == reference
