"""Process lifetime: an interrupted or killed run leaves no process behind, and resumes to the same result.

The command runs in a session of its own, so that every process it starts — the fork server, the workers,
multiprocessing's resource tracker, a Dask cluster's nannies and workers — is found by its session id in
/proc, whoever its parent is by then.  Zombies (exited, waiting for whoever adopted them to collect their
status) hold no memory and are not counted.
"""
from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from forensics._shared.lifetime import Terminated, signals_deferred, sigterm_as_interrupt
from forensics._shared.parallel import Executor
from forensics.fixtures import workitems

FORENSICS = [sys.executable, "-m", "forensics.cli.main"]
AGE = ["--sensor", "H", "--years", "0:100:10", "--seed", "3", "--quiet"]


def _session_processes(sid: int) -> list[int]:
    """Live (not zombie) processes of session ``sid``."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:  # gone meanwhile
            continue
        state, session = fields[0], int(fields[3])
        if session == sid and state != "Z":
            found.append(int(entry.name))
    return found


def _wait_for_no_processes(sid: int, seconds: float) -> list[int]:
    deadline = time.monotonic() + seconds
    while (left := _session_processes(sid)) and time.monotonic() < deadline:
        time.sleep(0.1)
    return left


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> Path:
    """24 images of 256 × 192: ageing them over 11 steps takes seconds on two workers, long enough to interrupt."""
    from forensics.sensor.simulate import make_scenes

    return make_scenes(tmp_path_factory.mktemp("scenes") / "src", 24, (192, 256), bit_depth=16, rng=2).root


@pytest.fixture(scope="module")
def reference(scenes, tmp_path_factory) -> dict[str, bytes]:
    out = tmp_path_factory.mktemp("ref") / "aged"
    done = subprocess.run([*FORENSICS, "simulate", "age", scenes, out, *AGE, "--workers", "1"], capture_output=True,
                          text=True)
    assert done.returncode == 0, done.stderr
    return _tree(out)


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@contextlib.contextmanager
def _interrupted(command: list, items: Path, signum: int, logs: Path) -> Iterator[tuple[subprocess.Popen, str]]:
    """Run ``command`` in a new session and send ``signum`` once its first work item is saved in ``items``.

    Yields ``(process, stderr)`` after the command has ended.  Output goes to files, which processes left
    behind cannot hold open; whatever is left of the session when the test ends is killed, so a failing test
    leaves no orphans either.
    """
    with open(logs / "stdout", "w") as out, open(logs / "stderr", "w") as err:
        proc = subprocess.Popen([*map(str, command)], stdout=out, stderr=err, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while not any(items.glob("item-*.npz")) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert proc.poll() is None, f"the run ended before it could be interrupted: {(logs / 'stderr').read_text()}"
        os.kill(proc.pid, signum)
        proc.wait(timeout=60)
        yield proc, (logs / "stderr").read_text()
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)


def test_sigterm_stops_the_run_like_ctrl_c_and_leaves_no_process(scenes, tmp_path):
    out = tmp_path / "aged"
    with _interrupted([*FORENSICS, "simulate", "age", scenes, out, *AGE, "--workers", "2"],
                      tmp_path / ".aged.partial" / ".items", signal.SIGTERM, tmp_path) as (proc, err):
        assert proc.returncode == 143
        assert err.strip().splitlines() == ["forensics: terminated by SIGTERM"]
        assert not out.exists() and (tmp_path / ".aged.partial" / ".items").is_dir()  # resumable work kept
        assert _wait_for_no_processes(proc.pid, 5.0) == []


def test_sigkill_leaves_no_process_and_the_run_resumes_identically(scenes, reference, tmp_path):
    out = tmp_path / "aged"
    with _interrupted([*FORENSICS, "simulate", "age", scenes, out, *AGE, "--workers", "2"],
                      tmp_path / ".aged.partial" / ".items", signal.SIGKILL, tmp_path) as (proc, _):
        assert proc.returncode == -signal.SIGKILL
        assert _wait_for_no_processes(proc.pid, 5.0) == []
    resumed = subprocess.run([*FORENSICS, "simulate", "age", scenes, out, *AGE, "--workers", "2"], capture_output=True,
                             text=True)
    assert resumed.returncode == 0, resumed.stderr
    assert _tree(out) == reference  # byte for byte, hidden files included


@pytest.mark.slow
def test_sigkill_leaves_no_dask_process(scenes, tmp_path):
    pytest.importorskip("distributed")
    with _interrupted([*FORENSICS, "simulate", "age", scenes, tmp_path / "aged", *AGE, "--scheduler", "local",
                       "--workers", "2"], tmp_path / ".aged.partial" / ".items", signal.SIGKILL, tmp_path) as (proc, _):
        assert _wait_for_no_processes(proc.pid, 10.0) == []


def test_an_interrupted_map_stops_its_running_workers_at_once(tmp_path):
    with Executor("processes", workers=2) as ex:
        results = ex.map(workitems.note_pid_then_sleep, [(str(tmp_path), i) for i in range(6)])
        assert next(results) == 0
        time.sleep(0.5)  # both workers busy with minute-long items
        started = time.monotonic()
        results.close()  # what an exception in the consumer (Ctrl-C, SIGTERM, a failed item) does
        stopped = time.monotonic() - started
    pids = [int(p.name.split("-")[1]) for p in tmp_path.glob("pid-*")]
    assert pids and stopped < 5.0  # not the minute the running items would take
    assert all(not Path(f"/proc/{pid}").exists() or _state(pid) == "Z" for pid in pids)


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return "gone"


def test_signals_wait_for_the_end_of_a_deferred_block():
    """Found by the adversarial replay: SIGTERM while the pool started a worker left that worker unrecorded,
    never stopped, and the pool's shutdown waiting for it forever (or the worker printed an EOFError
    traceback).  Starting a worker is now deferred-signal work: the signal arrives as the block ends."""
    reached = False
    # as they were before (a test run started in the background of a shell inherits SIGINT ignored)
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    with pytest.raises(Terminated), sigterm_as_interrupt():
        with signals_deferred():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.2)  # without the deferral, Terminated is raised here
            reached = True
    assert reached
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before  # every handler back


def test_stopping_workers_waits_for_the_pools_manager_thread():
    """After a stop, the pool's manager thread has closed its wake-up pipe: an exit right then prints nothing.

    (Without the wait, the interpreter's exit hook raced the thread closing that pipe and printed a traceback
    under the command's one line — seen once in CI after SIGTERM.)
    """
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from forensics._shared.parallel import _stop_workers

    pool = ProcessPoolExecutor(max_workers=2, mp_context=multiprocessing.get_context("spawn"))
    futures = [pool.submit(time.sleep, 30) for _ in range(2)]
    deadline = time.monotonic() + 60
    while not all(f.running() for f in futures) and time.monotonic() < deadline:
        time.sleep(0.05)
    manager = pool._executor_manager_thread
    started = time.monotonic()
    _stop_workers(pool)
    assert not manager.is_alive()
    assert time.monotonic() - started < 10.0  # the sleeping items were stopped, not waited for
