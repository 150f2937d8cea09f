"""The execution layer: same results on every backend, order kept, faults survived, runs resumed."""
from __future__ import annotations

import numpy as np
import pytest

from forensics._shared.errors import UsageError
from forensics._shared.parallel import Checkpoint, Executor, chunks, open_executor
from forensics.fixtures import workitems


def _sum_blocks(executor: Executor) -> np.ndarray:
    return executor.reduce(workitems.noisy_block, [(7, i) for i in range(12)], np.add)


def test_processes_give_bit_identical_reductions_in_item_order():
    reference = _sum_blocks(Executor("in-process"))
    with Executor("processes", workers=2, window=3) as ex:
        parallel = _sum_blocks(ex)
        order = list(ex.map(workitems.noisy_block, [(7, i) for i in range(12)]))
    # Ordered folding makes the float sum identical, not merely equal to rounding.
    assert np.array_equal(reference, parallel)
    assert all(np.array_equal(a, workitems.noisy_block((7, i))) for i, a in enumerate(order))


def test_shared_object_reaches_every_worker_once():
    shared = np.arange(10.0)
    with Executor("processes", workers=2) as ex:
        got = list(ex.map(workitems.scaled, range(6), shared=shared))
    assert got == [45.0 * i for i in range(6)]


def test_workers_get_their_share_of_the_cores():
    with Executor("processes", workers=2) as ex:
        seen = set(ex.map(workitems.threads_seen, range(4)))
    assert seen and all(int(s) >= 1 for s in seen)


def test_a_dead_worker_costs_only_its_items(tmp_path):
    marker = tmp_path / "died"
    with Executor("processes", workers=2) as ex:
        got = list(ex.map(workitems.die_once, [(str(marker), i) for i in range(8)]))
    assert marker.exists()  # a worker really died
    assert got == [i * i for i in range(8)]


def test_interrupted_run_resumes_from_its_checkpoint(tmp_path):
    config = {"what": "test", "seed": 1}
    ck = Checkpoint(tmp_path / "ck", config)
    ex = Executor("in-process")
    with pytest.raises(RuntimeError, match="interrupted at 5"):
        list(ex.map(workitems.fail_on, [(i, 5) for i in range(9)], checkpoint=ck))
    assert ck.completed() == 5
    ck = Checkpoint(tmp_path / "ck", config)
    resumed = list(ex.map(workitems.fail_on, [(i, -1) for i in range(9)], checkpoint=ck))
    assert resumed == [i + 100 for i in range(9)]
    with pytest.raises(UsageError, match="other settings"):
        Checkpoint(tmp_path / "ck", {"what": "test", "seed": 2})


def test_open_executor_picks_the_backend():
    assert open_executor(1).backend == "in-process"
    assert open_executor(2, environ={}).backend == "processes"
    with pytest.raises(UsageError):
        open_executor(0, environ={})


def test_chunks_depend_on_the_data_only():
    assert [list(c) for c in chunks(7, 3)] == [[0, 1, 2], [3, 4, 5], [6]]


@pytest.mark.slow
def test_dask_cluster_matches_in_process(dask_cluster):
    reference = _sum_blocks(Executor("in-process"))
    with Executor("dask", scheduler=dask_cluster.scheduler_address) as ex:
        assert np.array_equal(_sum_blocks(ex), reference)
        shared = np.arange(10.0)
        assert list(ex.map(workitems.scaled, range(6), shared=shared)) == [45.0 * i for i in range(6)]
        pids = set(ex.map(workitems.worker_pid, range(40)))
        assert ex.info().dashboard
    assert len(pids) == 2  # both workers took part


@pytest.mark.slow
def test_a_dask_item_cancelled_under_it_is_computed_again(dask_cluster):
    """An item whose future is cancelled mid-run — what the scheduler does when a killed worker held scattered data
    it needs ("lost scattered data, which can't be recovered") — is submitted again with the shared data scattered
    anew.  Before, ``as_completed`` yielded its FutureCancelledError as the item's result: a run whose worker was
    killed wrote an output without the images that depended on it (seen once in CI)."""
    from distributed import Future

    cancelled = []

    def cancel_running(iterable, total=None, desc=None):
        for count, item in enumerate(iterable):
            if count == 1:  # one item done: cancel every item still on a worker
                keys = [k for ks in ex.client.processing().values() for k in ks]
                ex.client.cancel([Future(k, client=ex.client) for k in keys])
                cancelled.extend(keys)
            yield item

    shared = np.arange(10.0)
    with Executor("dask", scheduler=dask_cluster.scheduler_address, window=4) as ex:
        got = list(ex.map(workitems.scaled_slowly, range(8), shared=shared, progress=cancel_running))
    assert cancelled  # the fault really happened mid-run
    assert got == [45.0 * i for i in range(8)]


def test_small_work_runs_in_process_unless_workers_are_given():
    from forensics._shared.parallel import open_executor

    assert open_executor(None, small=True, environ={}).backend == "in-process"
    assert open_executor(2, small=True, environ={}).backend == "processes"
    assert open_executor(1, small=False, environ={}).backend == "in-process"
