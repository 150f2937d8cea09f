"""Defect detection, growth and set dating on the execution layer: identical on every backend."""
from __future__ import annotations

import json

import numpy as np
import pytest

from forensics._shared.parallel import Executor
from forensics.defects.dating import date_dataset
from forensics.defects.detection import MaskSpec, detect, detect_dataset, stack_dataset
from forensics.defects.growth import epochs_from_datasets, estimate_growth
from forensics.io.dataset import open_dataset
from forensics.io.stack import stack_stats
from forensics.sensor.presets import preset
from forensics.sensor.simulate import age_dataset, make_scenes

SHAPE = (64, 96)
AGES = (0, 6, 12, 18)
MASK = MaskSpec("all")
#: 12 frames a set in chunks of 5 (5 + 5 + 2): every set is merged from several partial stacks.
CHUNK = 5


@pytest.fixture(scope="module")
def aged(tmp_path_factory):
    """A 16-bit sensor (preset H: partially stuck and stuck pixels) aged over four epochs of 12 scenes."""
    root = tmp_path_factory.mktemp("parallel_defects")
    src = make_scenes(root / "scenes", 12, SHAPE, 0, bit_depth=16)
    age_dataset(src, root / "aged", preset("H", SHAPE, bit_depth=16, rate_scale=150), list(AGES), rng=2,
                start_year=2000.0, sensor_name="H")
    return [open_dataset(root / "aged" / f"year_{a:03d}") for a in AGES]


@pytest.fixture
def small_chunks(monkeypatch):
    """The chunk size is read where the work items are made (in this process): several chunks per set."""
    import forensics.io.stack

    monkeypatch.setattr(forensics.io.stack, "STACK_CHUNK", CHUNK)


def _run(ex: Executor, sets: list) -> dict:
    """Detection of one set, growth over the first three, dating of the last, all on ``ex``."""
    det = detect_dataset(sets[2], mask=MASK, executor=ex)
    growth = estimate_growth(epochs_from_datasets(sets[:3], mask=MASK, executor=ex))
    dated = date_dataset(growth.model(), sets[3], executor=ex)
    return {"detect": det, "growth": growth, "date": dated}


def _same(a: object, b: object) -> bool:
    """Equal as JSON: every float to its last bit (repr round-trips), NaN (γ with no first-epoch defects) included."""
    return json.dumps(a, sort_keys=True, default=str) == json.dumps(b, sort_keys=True, default=str)


def _assert_same(got: dict, ref: dict) -> None:
    assert _same(got["detect"].to_dict(), ref["detect"].to_dict())
    assert np.array_equal(got["detect"].d_hat, ref["detect"].d_hat)
    assert np.array_equal(got["detect"].mask, ref["detect"].mask)
    assert _same(got["growth"].to_dict(), ref["growth"].to_dict())
    assert _same(got["growth"].model().to_dict(), ref["growth"].model().to_dict())  # catalogue, onsets, near sites
    assert _same(got["date"].to_dict(), ref["date"].to_dict())


@pytest.fixture(scope="module")
def reference(aged):
    """In-process, each set read in a single pass (one chunk): the oracle the chunked runs must reproduce."""
    import forensics.io.stack

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(forensics.io.stack, "STACK_CHUNK", 1000)
        return _run(Executor("in-process"), aged)


def test_the_data_has_defects_of_both_kinds_and_growth(reference):
    growth = reference["growth"]
    assert reference["detect"].count() > 10
    assert growth.partial.counts[-1] > growth.partial.counts[0] and growth.stuck.counts[-1] > 0
    assert growth.catalogue and sum(growth.partial.new) > 0


def test_detection_is_the_one_pass_detection(aged, small_chunks):
    """uint16 frames: chunked, merged stack statistics are exact, so detection equals that of one pass."""
    whole = stack_stats(aged[2].images())
    with Executor("processes", workers=2) as ex:
        chunked = stack_dataset(aged[2], executor=ex)
    for name in ("mean", "var", "minimum", "maximum"):
        assert np.array_equal(getattr(chunked, name), getattr(whole, name)), name
    one_pass = detect(whole, mask=MASK)
    got = detect_dataset(aged[2], mask=MASK, executor=Executor("in-process"))
    assert _same(got.to_dict(), one_pass.to_dict()) and np.array_equal(got.d_hat, one_pass.d_hat)


def test_in_process_chunks_and_processes_agree(aged, reference, small_chunks):
    _assert_same(_run(Executor("in-process"), aged), reference)
    with Executor("processes", workers=2) as ex:
        _assert_same(_run(ex, aged), reference)


@pytest.mark.slow
def test_dask_cluster_agrees(aged, reference, small_chunks, dask_cluster):
    with Executor("dask", scheduler=dask_cluster.scheduler_address) as ex:
        _assert_same(_run(ex, aged), reference)
