"""The model check on the execution layer: the conditions are read on the workers and assembled in condition
order, so the measurements are bit-identical on every backend; the model and its baseline are fitted side by
side from keyed streams, so the check is too."""
from __future__ import annotations

import csv
import dataclasses
import json
import shutil

import numpy as np
import pytest
from forensics.fixtures.hidden import Design, make_hidden, make_photographs

from forensics._shared.parallel import Executor
from forensics.check import check, load_measurements
from forensics.check.pipeline import fit_executor
from forensics.sensor.model import make_effect

#: 48×64 frames over three epochs: 40 conditions of two frames, a check in about two seconds.
DESIGN = Design(shape=(48, 64), ages=(0, 2, 4))
#: Photographs are told apart by their 32-pixel block means: 9 blocks a frame.
PHOTOS = Design(shape=(96, 96), ages=(0, 2, 4))
SEED = 3


def _one_subject_a_frame(src, out):
    """The photographs again, with no condition repeated: pooled per epoch before they are read."""
    shutil.copytree(src, out)
    with open(src / "manifest.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    with open(out / "manifest.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=[*rows[0], "subject"])
        writer.writeheader()
        writer.writerows({**row, "subject": f"s{i}"} for i, row in enumerate(rows))
    return out


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    """A lab dataset with a hidden PRNU; photographs, found to be different scenes from their content while
    read, and the same photographs pooled per epoch beforehand (the pixel channel's two other paths)."""
    root = tmp_path_factory.mktemp("parallel_check")
    lab = make_hidden("prnu", root / "lab", rng=SEED, design=DESIGN).out
    photos = make_photographs("none", root / "photos", rng=SEED, design=PHOTOS, per_epoch=4).out
    return {"lab": lab, "photos": photos, "pooled": _one_subject_a_frame(photos, root / "pooled")}


def _assert_identical(a: object, b: object, path: str = "measurements") -> None:
    """Every array equal to the last bit (and of the same type), every other field equal, recursively."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        assert isinstance(a, np.ndarray) and isinstance(b, np.ndarray), path
        assert a.dtype == b.dtype and a.shape == b.shape, path
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), path
    elif dataclasses.is_dataclass(a):
        assert type(a) is type(b), path
        for f in dataclasses.fields(a):
            _assert_identical(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_identical(x, y, f"{path}[{i}]")
    elif isinstance(a, float) and np.isnan(a):
        assert isinstance(b, float) and np.isnan(b), path
    else:
        assert a == b, (path, a, b)


def _measure(datasets: dict, ex: Executor) -> dict:
    return {name: load_measurements(folder, executor=ex) for name, folder in datasets.items()}


@pytest.fixture(scope="module")
def measured(datasets):
    return _measure(datasets, Executor("in-process"))


def test_the_measurements_exercise_every_pixel_path(measured):
    lab, photos, pooled = measured["lab"], measured["photos"], measured["pooled"]
    assert len(lab.groups) > 20 and lab.traits.lag1 is not None and lab.half_ms is None
    assert [g.n for g in photos.groups] == [4, 4, 4] and all(g.scenes for g in photos.groups)
    assert photos.half_ms is not None and photos.traits.lag1 is None
    assert [g.n for g in pooled.groups] == [4, 4, 4] and np.array_equal(pooled.half_ms, photos.half_ms)


def test_processes_read_identical_measurements(datasets, measured):
    with Executor("processes", workers=2) as ex:
        got = _measure(datasets, ex)
    for name in datasets:
        _assert_identical(got[name], measured[name], name)


@pytest.mark.slow
def test_dask_cluster_reads_identical_measurements(datasets, measured, dask_cluster):
    with Executor("dask", scheduler=dask_cluster.scheduler_address) as ex:
        got = _measure(datasets, ex)
    for name in datasets:
        _assert_identical(got[name], measured[name], name)


def _canon(result) -> str:
    """A check and its baseline as JSON, every float to its last bit, plus the held-out arrays."""
    arrays = [result.heldout.r2, result.heldout.floor, result.baseline.heldout.r2, result.plots.residual_map]
    return json.dumps([result.to_dict(), result.baseline.to_dict(), [np.asarray(a).tolist() for a in arrays]],
                      sort_keys=True, default=lambda o: o.tolist() if hasattr(o, "tolist") else repr(o))


def test_check_with_its_baseline_is_identical_in_processes(datasets):
    reference = check(datasets["lab"], add=["prnu"], rng=SEED, n_sim=19)
    assert reference.baseline.flagged[0] == "prnu" and reference.flagged == []  # a check worth comparing
    with Executor("processes", workers=2) as ex:
        got = check(datasets["lab"], add=["prnu"], rng=SEED, n_sim=19, executor=ex)
    assert _canon(got) == _canon(reference)


def test_an_effect_no_worker_can_import_is_fitted_in_this_process():
    """An instance of a class defined inside a function does not pickle: its fits stay in this process."""
    from dataclasses import dataclass

    from forensics.sensor.model import Effect, Stage

    @dataclass
    class Local(Effect):
        name = "local"
        description = "defined where no worker can import it"
        stage = Stage.DARK

    with Executor("processes", workers=2) as ex:
        assert fit_executor(ex, [[make_effect("prnu")]]) is ex
        assert fit_executor(ex, [[make_effect("prnu")], [Local()]]).backend == "in-process"
