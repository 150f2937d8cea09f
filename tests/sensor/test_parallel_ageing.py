"""`simulate age` on the execution layer: identical images on every backend, a killed worker, a resumed run."""
from __future__ import annotations

import os
import signal

import numpy as np
import pytest

from forensics._shared.parallel import Executor
from forensics.io.images import read_image
from forensics.sensor.presets import preset
from forensics.sensor.simulate import age_dataset, make_scenes

AGES = [0.0, 10.0, 20.0]


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    return make_scenes(tmp_path_factory.mktemp("scenes") / "src", 10, (40, 48), rng=3)


def _age(source, out, executor=None, progress=None):
    options = {} if progress is None else {"progress": progress}
    return age_dataset(source, out, preset("H", (40, 48), rate_scale=300.0), AGES, rng=11, sensor_name="H",
                       executor=executor, **options)


def _contents(root):
    """Every output file: decoded pixels for images, text for the rest."""
    files = {}
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        key = str(path.relative_to(root))
        if path.suffix == ".png":
            files[key] = read_image(path)
        else:
            files[key] = path.read_text()
    return files


def _assert_same(a, b):
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], np.ndarray):
            assert np.array_equal(a[key], b[key]), key
        else:
            assert a[key] == b[key], key


@pytest.fixture(scope="module")
def reference(source, tmp_path_factory):
    out = tmp_path_factory.mktemp("ref") / "aged"
    result = _age(source, out, Executor("in-process"))
    assert result.counts["partial"][-1] > 0  # the comparison below involves real defects
    return _contents(out)


def test_processes_and_dask_age_bit_identically(source, reference, dask_cluster, tmp_path):
    with Executor("processes", workers=2) as ex:
        _age(source, tmp_path / "p", ex)
    _assert_same(_contents(tmp_path / "p"), reference)
    with Executor("dask", scheduler=dask_cluster.scheduler_address) as ex:
        _age(source, tmp_path / "d", ex)
    _assert_same(_contents(tmp_path / "d"), reference)


class _KillAfter:
    """A progress wrapper that, after ``n`` finished images, calls ``action`` once (mid-run fault injection)."""

    def __init__(self, n, action):
        self.n, self.action = n, action

    def __call__(self, iterable, total=None, desc=None):
        for count, item in enumerate(iterable):
            if count == self.n:
                self.action()
            yield item


def test_a_killed_dask_worker_costs_only_its_tasks(source, reference, tmp_path):
    pytest.importorskip("distributed")
    from forensics._shared.parallel import start_local_cluster

    with start_local_cluster(2) as cluster, Executor("dask", scheduler=cluster.scheduler_address, window=4) as ex:
        pids = sorted(set(ex.client.run(os.getpid).values()))
        assert len(pids) == 2
        killed = []

        def kill() -> None:
            os.kill(pids[0], signal.SIGKILL)
            killed.append(pids[0])

        _age(source, tmp_path / "k", ex, progress=_KillAfter(3, kill))
        assert killed  # the fault really happened mid-run
    _assert_same(_contents(tmp_path / "k"), reference)


def test_files_of_an_unfinished_write_never_reach_the_output(source, reference, tmp_path):
    out = tmp_path / "aged"

    def interrupt() -> None:
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        _age(source, out, progress=_KillAfter(3, interrupt))
    # What a worker killed while writing leaves behind (atomic writes' temporary sibling).
    stray = tmp_path / ".aged.partial" / "year_010" / ".scene_0007.ab12cd34.part.png"
    stray.write_bytes(b"half an image")
    _age(source, out)
    _assert_same(_contents(out), reference)  # every file compared, hidden ones included


@pytest.mark.parametrize("backend", ["in-process", "processes"])
def test_an_interrupted_run_resumes_to_the_identical_result(source, reference, tmp_path, backend):
    out = tmp_path / "aged"

    def interrupt() -> None:
        raise KeyboardInterrupt

    with Executor(backend, workers=2) as ex, pytest.raises(KeyboardInterrupt):
        _age(source, out, ex, progress=_KillAfter(4, interrupt))
    partial = tmp_path / ".aged.partial"
    assert not out.exists() and partial.is_dir()  # nothing visible at the output; the work kept beside it
    done = len(list((partial / ".items").glob("item-*.npz")))
    assert 4 <= done < 10
    seen = []

    def count(iterable, total=None, desc=None):
        for item in iterable:
            seen.append(item)
            yield item

    with Executor(backend, workers=2) as ex:
        _age(source, out, ex, progress=count)
    assert len(seen) == 10 and not partial.exists()
    _assert_same(_contents(out), reference)


def test_a_resumed_run_refuses_other_settings(source, tmp_path):
    out = tmp_path / "aged"

    def interrupt() -> None:
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        _age(source, out, progress=_KillAfter(2, interrupt))
    from forensics._shared.errors import UsageError

    with pytest.raises(UsageError, match="other settings"):
        age_dataset(source, out, preset("H", (40, 48), rate_scale=300.0), AGES, rng=12)


def test_cli_workers_and_scheduler_give_the_same_images(cli_json, source, dask_cluster, tmp_path):
    common = ["--sensor", "H", "--years", "0,10,20", "--seed", "11", "--rate-scale", "300"]
    one = cli_json("simulate", "age", source.root, tmp_path / "w1", "--workers", "1", *common)
    two = cli_json("simulate", "age", source.root, tmp_path / "w2", "--workers", "2", *common)
    dask = cli_json("simulate", "age", source.root, tmp_path / "d", "--scheduler", dask_cluster.scheduler_address,
                    *common)
    assert [r["execution"]["backend"] for r in (one, two, dask)] == ["in-process", "processes", "dask"]
    assert dask["execution"]["dashboard"]
    _assert_same(_contents(tmp_path / "w2"), _contents(tmp_path / "w1"))
    _assert_same(_contents(tmp_path / "d"), _contents(tmp_path / "w1"))
