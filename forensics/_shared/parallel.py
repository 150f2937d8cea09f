"""The one execution layer: map independent work items, reduce their results, on any of three backends.

Every batch workload of the toolkit (ageing, fingerprints, score matrices, defect statistics, validation
trials, the model-check sweep, the recognition experiment) is a list of independent *items* — an image, a
chunk of images, a device, an age, a trial — processed by a module-level function and, where needed,
folded into one result.  This module runs such a list

* ``in-process`` — a plain loop (the library's default; tests and debugging);
* ``processes`` — local worker processes (the command line's default, all cores);
* ``dask`` — a :mod:`dask.distributed` cluster (``--scheduler ADDRESS`` or ``FORENSICS_SCHEDULER``;
  ``local`` starts a :class:`~distributed.LocalCluster` on this machine).

Results are identical across backends because nothing depends on which process ran an item or when:

* each item's random stream is part of the item (a child of ``SeedSequence.spawn`` or a keyed sub-stream,
  :mod:`forensics._shared.rng`), never the order of execution;
* results are handed back *in item order* (:meth:`Executor.map`) and reductions fold them in item order
  (:meth:`Executor.reduce`), so a float sum over chunks is bit-identical whichever backend computed the
  chunks — the chunking is the caller's (fixed by the data, never by the number of workers).

Items carry paths, indices and seeds, never image bytes: workers read their inputs themselves (shared
storage on a cluster) and write only into the output's working folder.  Data every item needs (a simulated
device, a fingerprint) is ``shared``: shipped once per worker process (processes) or broadcast once
(Dask), not once per item.

Faults: a worker process that dies costs only the items in flight, which are resubmitted (up to
``retries`` times each); Dask reschedules a lost worker's tasks itself.  A run interrupted as a whole
resumes from its completed items when given a :class:`~forensics._shared.checkpoint.Checkpoint` (one file
per finished item, written atomically, beside the output), and gives the same result as an uninterrupted run.

Lifetime: local workers see exactly the driver's ``sys.path`` (wherever the command runs, the source
checkout included) and its umask; they ignore Ctrl-C (the driver stops them), are stopped at once when a
map is interrupted, and end by themselves when the driver's process ends, however it ends
(:mod:`forensics._shared.lifetime`): no orphans.

Inner parallelism (FFT and wavelet threads) is limited to the cores left per worker:
:func:`thread_budget`.
"""
from __future__ import annotations

import contextlib
import os
import pickle
import signal
import sys
import warnings
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from forensics._shared import safecodec
from forensics._shared.atomic import current_umask
from forensics._shared.checkpoint import (  # noqa: F401 — part of this module's interface since it began
    Checkpoint,
    config_digest,
    resumable_checkpoint,
    resumable_directory,
)
from forensics._shared.errors import UsageError
from forensics._shared.lifetime import exit_with, signals_deferred
from forensics._shared.progress import Progress, no_progress

T = TypeVar("T")
R = TypeVar("R")

#: Environment variable naming a Dask scheduler (``tcp://host:8786``, or ``local``).
SCHEDULER_ENV = "FORENSICS_SCHEDULER"
#: Environment variable capping the threads one process uses for FFTs, wavelets and filters.
THREADS_ENV = "FORENSICS_THREADS"
BACKENDS = ("in-process", "processes", "dask")
_NO_SHARED = object()


def available_cores() -> int:
    """The CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


def thread_budget(cap: int = 4) -> int:
    """Threads one process should use for its inner loops: ``FORENSICS_THREADS`` if set (a worker of this
    layer gets its share of the cores), else the available cores, at most ``cap``."""
    text = os.environ.get(THREADS_ENV)
    if text:
        with contextlib.suppress(ValueError):
            return max(1, min(cap, int(text)))
    return max(1, min(cap, available_cores()))


# --------------------------------------------------------------------------------------------------------------
# Worker side
# --------------------------------------------------------------------------------------------------------------

# Per worker process: the current map's shared object, installed once by the pool's initializer.  This is
# the worker's own state (one pool per map), never the driver's.
_WORKER_SHARED: dict[str, Any] = {}


#: BLAS thread variables: worker processes are the parallelism, so each runs its matrix products on one thread.
_BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


#: What the fork server's start changes in the environment, restored in every worker (see below).
_PATH_VARIABLES = ("PYTHONPATH", "PYTHONSAFEPATH")


def _server_environment() -> dict[str, str]:
    """The environment the fork server starts with: single-threaded BLAS, and exactly this process's sys.path.

    Multiprocessing starts the server with ``python -c``, which puts the *current folder* first on its
    ``sys.path``.  Run from a source checkout of an installed (not editable) copy, the checkout's
    ``forensics/`` (which lacks ``cli``, installed from ``cli/``) then shadows the installed package and every
    worker dies unpickling its first item.  The server is given ``PYTHONSAFEPATH`` (no implicit folder) and
    this process's own ``sys.path`` as ``PYTHONPATH`` — what the spawn start method passes as ``sys_path`` —
    with relative entries made absolute (``''`` is this process's real use of its current folder).  ``site``
    drops the duplicates that the default entries then make, so the order is this process's.
    """
    path = [os.path.abspath(entry) for entry in sys.path]
    return {**{k: "1" for k in _BLAS_THREAD_VARIABLES}, "PYTHONSAFEPATH": "1", "PYTHONPATH": os.pathsep.join(path)}


def _start_forkserver(context: Any) -> None:
    """Start the fork server (once per process) with numpy preloaded, single-threaded BLAS and this sys.path.

    Workers fork from it in milliseconds instead of importing numpy and scipy each.  BLAS reads its thread
    count when it is loaded, so the variables are set only while the server starts (it inherits them) and
    this process's own environment is restored at once; the path variables are restored in each worker
    (:func:`_init_process_worker`), so that programs a worker runs see the user's environment.
    """
    from multiprocessing import forkserver

    context.set_forkserver_preload(["numpy", "scipy.fft", "forensics._shared.parallel"])
    changes = _server_environment()
    saved = {k: os.environ.get(k) for k in changes}
    os.environ.update(changes)
    try:
        forkserver.ensure_running()
    finally:
        _restore_environment(saved)


def _restore_environment(saved: dict[str, str | None]) -> None:
    for key, value in saved.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value


def _init_process_worker(threads: int, shared_blob: bytes | None, driver: int, umask: int,
                         environ: dict[str, str | None]) -> None:
    """Set up one worker process of the driver ``driver``: its lifetime, environment and shared object."""
    exit_with(driver)  # no orphans: the worker ends when the driver's process does, even by SIGKILL
    # Ctrl-C reaches the whole process group; the driver handles it and stops its workers, which would
    # otherwise each print a traceback.  A handler, not SIG_IGN, which programs the worker runs would inherit.
    signal.signal(signal.SIGINT, _ignore_signal)
    os.umask(umask)  # files the worker writes get the driver's permissions (the server may predate a change)
    _restore_environment(environ)
    os.environ[THREADS_ENV] = str(threads)
    _WORKER_SHARED.clear()
    if shared_blob is not None:
        _WORKER_SHARED["value"] = pickle.loads(shared_blob)


def _ignore_signal(signum: int, frame: Any) -> None:
    """Nothing: the worker carries on until its driver stops it."""


def _run_process_item(fn: Callable[..., Any], item: Any, with_shared: bool) -> Any:
    return fn(_WORKER_SHARED["value"], item) if with_shared else fn(item)


def _run_dask_item(fn: Callable[..., Any], item: Any, shared: Any = _NO_SHARED, threads: int = 1) -> Any:
    os.environ[THREADS_ENV] = str(threads)
    return fn(item) if shared is _NO_SHARED else fn(shared, item)


# --------------------------------------------------------------------------------------------------------------
# The executor
# --------------------------------------------------------------------------------------------------------------


@dataclass
class ExecutionInfo:
    """What a run used (for summaries and ``--json``)."""

    backend: str
    workers: int
    scheduler: str | None = None
    dashboard: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"backend": self.backend, "workers": self.workers, "scheduler": self.scheduler,
                "dashboard": self.dashboard}


class Executor:
    """Runs work items in-process, in local processes or on a Dask cluster; results in item order.

    Make one per command run (``with open_executor(...) as ex``) and pass it to every library function
    that takes ``executor``; the library never makes its own.  The one stateful object of this module: it
    owns the Dask client (or local cluster) for the duration of the run.

    Parameters
    ----------
    backend
        ``"in-process"``, ``"processes"`` or ``"dask"``.
    workers
        Worker processes (processes backend); for Dask, the workers of a ``local`` cluster.
    scheduler
        Dask scheduler address, or ``"local"`` for a :class:`distributed.LocalCluster`.
    retries
        Times an item is resubmitted after its worker died (processes), or after its input was lost with one
        (Dask: scattered data a killed worker held).
    window
        Items in flight at once (default 4 per worker process, 16 per Dask thread): bounds the memory of
        out-of-order results.
    """

    def __init__(self, backend: str = "in-process", workers: int = 1, scheduler: str | None = None,
                 retries: int = 3, window: int | None = None) -> None:
        if backend not in BACKENDS:
            raise UsageError(f"unknown execution backend '{backend}'; choose one of {', '.join(BACKENDS)}")
        if workers < 1:
            raise UsageError(f"--workers must be at least 1, not {workers}")
        self.backend = backend
        self.workers = workers
        self.scheduler = scheduler
        self.retries = retries
        self._window = window
        self._client: Any = None
        self._cluster: Any = None
        if backend == "dask":
            self._connect()

    # -- lifetime ----------------------------------------------------------------------------------------------
    def _connect(self) -> None:
        try:
            from distributed import Client
        except ImportError:
            raise UsageError("a Dask scheduler was given but dask.distributed is not installed; "
                             "pip install 'dask[distributed]'") from None
        address = self.scheduler
        if address in (None, "", "local"):
            self._cluster = start_local_cluster(self.workers)
            address = self._cluster.scheduler_address
        try:
            self._client = Client(address, timeout="20s", set_as_default=False)
        except OSError as exc:
            if self._cluster is not None:
                self._cluster.close()
            raise UsageError(f"cannot reach the Dask scheduler at {address} ({exc}); start it with "
                             "'dask scheduler' or check --scheduler / FORENSICS_SCHEDULER") from None
        self.scheduler = address

    def close(self) -> None:
        if self._client is not None:
            with contextlib.suppress(Exception):
                self._client.close()
            self._client = None
        if self._cluster is not None:
            with contextlib.suppress(Exception):
                self._cluster.close()
            self._cluster = None

    def __enter__(self) -> "Executor":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    @property
    def local_disk(self) -> bool:
        """Whether every worker runs on this machine (in-process, local processes, or the local cluster this
        executor started), so that a file written here is readable by all of them; False for a Dask scheduler
        given by address, whose workers may be anywhere."""
        return self.backend != "dask" or self._cluster is not None

    @property
    def client(self) -> Any:
        """The :class:`distributed.Client` of the Dask backend (None otherwise)."""
        return self._client

    def info(self) -> ExecutionInfo:
        dashboard = None
        workers = self.workers
        if self._client is not None:
            with contextlib.suppress(Exception):
                dashboard = self._client.dashboard_link
            with contextlib.suppress(Exception):
                workers = len(self._client.scheduler_info()["workers"])
        return ExecutionInfo(self.backend, workers, self.scheduler, dashboard)

    def _slots(self) -> int:
        if self.backend == "dask":
            with contextlib.suppress(Exception):
                return max(1, sum(w.get("nthreads", 1) for w in self._client.scheduler_info()["workers"].values()))
        return self.workers

    # -- mapping -----------------------------------------------------------------------------------------------
    def map(self, fn: Callable[..., R], items: Sequence[Any], *, shared: Any = _NO_SHARED,
            progress: Progress = no_progress, desc: str | None = None,
            checkpoint: Checkpoint | None = None, keys: Sequence[str] | None = None) -> Iterator[R]:
        """Yield ``fn(item)`` (or ``fn(shared, item)``) for every item, **in item order**.

        ``fn`` must be a module-level function and items small and picklable (paths, indices, seeds).
        With a ``checkpoint``, finished items are loaded instead of recomputed and every new result is saved
        as soon as it arrives; ``keys`` name the items in it (default: their index).  The progress bar
        counts completed items (out of order), so it moves however the work is scheduled.
        """
        items = list(items)
        n = len(items)
        if keys is None:
            keys = [f"{i:07d}" for i in range(n)]
        elif len(keys) != n:
            raise ValueError("one key per item")
        done: dict[int, Any] = {}
        todo = list(range(n))
        if checkpoint is not None:
            todo = [i for i in range(n) if not checkpoint.has(keys[i])]
        bar = iter(progress(range(n), total=n, desc=desc))
        for _ in range(n - len(todo)):
            next(bar, None)

        def completions() -> Iterator[tuple[int, Any]]:
            if not todo:
                return
            if self.backend == "in-process" or (self.backend == "processes" and (self.workers == 1 or len(todo) == 1)):
                for i in todo:
                    yield i, (fn(items[i]) if shared is _NO_SHARED else fn(shared, items[i]))
            elif self.backend == "processes":
                yield from self._process_completions(fn, items, todo, shared)
            else:
                yield from self._dask_completions(fn, items, todo, shared)

        pending = set(todo)
        next_index = 0

        def ready() -> Iterator[Any]:
            nonlocal next_index
            while next_index < n and (next_index in done or next_index not in pending):
                if next_index in done:
                    yield done.pop(next_index)
                else:  # finished by an earlier, interrupted run
                    yield stored(next_index)
                next_index += 1

        def stored(i: int) -> Any:
            """Item ``i`` from the checkpoint; computed here if its file passed the check but does not decode."""
            assert checkpoint is not None
            try:
                return checkpoint.load(keys[i])
            except safecodec.Undecodable as exc:
                warnings.warn(f"{checkpoint.folder}: item {keys[i]} does not decode ({exc}); computing it again",
                              stacklevel=3)
            value = fn(items[i]) if shared is _NO_SHARED else fn(shared, items[i])
            checkpoint.save(keys[i], value)
            return value

        yield from ready()
        for i, value in completions():
            next(bar, None)
            if checkpoint is not None:
                checkpoint.save(keys[i], value)
            pending.discard(i)
            done[i] = value
            yield from ready()
        for _ in bar:  # close the bar
            pass

    def reduce(self, fn: Callable[..., R], items: Sequence[Any], combine: Callable[[Any, R], Any],
               initial: Any = None, **options: Any) -> Any:
        """Fold ``fn``'s results into one value **in item order**: ``combine(...combine(initial, r0)..., r_n)``.

        With ``initial=None`` the first result is the start.  Order makes float reductions bit-identical
        across backends; ``options`` as :meth:`map`.
        """
        acc = initial
        first = initial is None
        for value in self.map(fn, items, **options):
            if first:
                acc, first = value, False
            else:
                acc = combine(acc, value)
        return acc

    # -- backends ----------------------------------------------------------------------------------------------
    def _window_size(self) -> int:
        # Enough items in flight to hide the round trip to the workers (longer for Dask's scheduler), few
        # enough that out-of-order results held for ordering stay small.
        return self._window or (16 if self.backend == "dask" else 4) * self._slots()

    def _process_completions(self, fn: Callable[..., Any], items: list[Any], todo: list[int],
                             shared: Any) -> Iterator[tuple[int, Any]]:
        import multiprocessing

        with_shared = shared is not _NO_SHARED
        blob = pickle.dumps(shared, protocol=pickle.HIGHEST_PROTOCOL) if with_shared else None
        workers = min(self.workers, len(todo))
        threads = max(1, available_cores() // workers)
        context = multiprocessing.get_context("forkserver" if sys.platform.startswith("linux") else "spawn")
        forkserver = context.get_start_method() == "forkserver"
        if forkserver:
            _start_forkserver(context)
        environ = {k: os.environ.get(k) for k in _PATH_VARIABLES}
        attempts = {i: 0 for i in todo}
        queue = list(todo)
        while queue:
            pool = ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=_init_process_worker,
                                       initargs=(threads, blob, os.getpid(), current_umask(), environ))
            running: dict[Any, int] = {}
            broken = False
            try:
                while queue or running:
                    while queue and len(running) < self._window_size():
                        i = queue.pop(0)
                        # submit() may start a worker: whole (recorded, so it can be stopped) or not at all.
                        with signals_deferred() if forkserver else contextlib.nullcontext():
                            running[pool.submit(_run_process_item, fn, items[i], with_shared)] = i
                    finished, _ = wait(list(running), return_when=FIRST_COMPLETED)
                    for future in finished:
                        i = running.pop(future)
                        try:
                            value = future.result()
                        except BrokenProcessPool:
                            broken = True
                            attempts[i] += 1
                            if attempts[i] > self.retries:
                                raise RuntimeError(f"work item {i} lost its worker {attempts[i]} times; giving up") from None
                            queue.insert(0, i)
                            continue
                        yield i, value
                    if broken:  # every future of a broken pool fails: requeue them all, start a new pool
                        for future, i in running.items():
                            queue.insert(0, i)
                        running.clear()
                        queue.sort()
                        break
            except BaseException:  # interrupted (Ctrl-C, SIGTERM), an item failed, or the consumer stopped
                _stop_workers(pool)
                raise
            finally:
                _shutdown(pool, wait=not broken)

    def _dask_completions(self, fn: Callable[..., Any], items: list[Any], todo: list[int],
                          shared: Any) -> Iterator[tuple[int, Any]]:
        from distributed import as_completed

        client = self._client
        kwargs: dict[str, Any] = {"threads": 1}
        if shared is not _NO_SHARED:
            kwargs["shared"] = client.scatter(shared, broadcast=True, hash=False)
        name = getattr(fn, "__name__", "item")
        token = os.urandom(4).hex()
        queue = list(todo)
        index_of: dict[str, int] = {}
        lost = {i: 0 for i in todo}

        def submit(i: int) -> Any:
            key = f"forensics-{name}-{token}-{i}" + (f"-{lost[i]}" if lost[i] else "")
            index_of[key] = i
            # No task retries: an exception is an answer (bad input); a lost worker is rescheduled by the
            # scheduler itself (distributed.scheduler.allowed-failures).
            return client.submit(_run_dask_item, fn, items[i], key=key, pure=False, **kwargs)

        window = self._window_size()
        stream = as_completed([submit(queue.pop(0)) for _ in range(min(window, len(queue)))], loop=client.loop,
                              with_results=True)
        try:
            for future, value in stream:
                i = index_of.pop(future.key)
                status = future.status
                future.release()
                if status != "finished":
                    # cancelled, not failed (a failure raises here): its input was lost with a worker — the
                    # scheduler cannot recover scattered data a killed worker held, and as_completed then yields
                    # the FutureCancelledError as if it were the item's result (a killed worker's run wrote an
                    # output without the items that depended on it).  Scatter the shared data again and resubmit.
                    lost[i] += 1
                    if lost[i] > self.retries:
                        raise RuntimeError(f"item {i} of {name} was lost {lost[i]} times with its workers; "
                                           "check the cluster's workers and their memory")
                    if shared is not _NO_SHARED:
                        kwargs["shared"] = client.scatter(shared, broadcast=True, hash=False)
                    stream.add(submit(i))
                    continue
                if queue:
                    stream.add(submit(queue.pop(0)))
                yield i, value
        finally:
            with contextlib.suppress(Exception):
                client.cancel([f for f in stream.futures])
            if "shared" in kwargs:
                with contextlib.suppress(Exception):
                    client.cancel(kwargs["shared"])


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """Stop the pool's worker processes now, whatever item they are running.

    ``shutdown`` lets running items finish, which for a long item (a model check's measurement) means
    minutes after the user asked to stop; their results would be thrown away.  A worker killed mid-write
    leaves only a temporary ``.part`` file, which a resumed run sweeps.  ProcessPoolExecutor has no public
    way to do this before Python 3.14 (``terminate_workers``); its ``_processes`` is the table it keeps.
    """
    terminate = getattr(pool, "terminate_workers", None)
    if callable(terminate):
        terminate()
        return
    processes = list((getattr(pool, "_processes", None) or {}).values())
    for process in processes:
        with contextlib.suppress(Exception):
            process.terminate()
    for process in processes:
        with contextlib.suppress(Exception):
            process.join(5.0)
    _shutdown(pool, wait=False)


def _shutdown(pool: ProcessPoolExecutor, wait: bool) -> None:
    """Shut the pool down (pending items cancelled; ``wait``: let running ones finish) and wait for its manager
    thread, whatever ``wait`` says.

    Why the thread: after workers died (stopped, or lost) it notices and closes its wake-up pipe; if the
    interpreter exits meanwhile, concurrent.futures' exit hook writes to that pipe as it closes and prints a
    traceback under the command's one line (an unlocked check-then-write in concurrent.futures; seen in CI after
    SIGTERM).  ``shutdown(wait=False)`` forgets the thread, so it is taken first."""
    manager = getattr(pool, "_executor_manager_thread", None)
    pool.shutdown(wait=wait, cancel_futures=True)
    if manager is not None:
        with contextlib.suppress(Exception):
            manager.join(10.0)


def start_local_cluster(workers: int = 2) -> Any:
    """A :class:`distributed.LocalCluster` of ``workers`` single-threaded worker processes, set up for image work.

    Dask's nanny starts workers with ``MALLOC_TRIM_THRESHOLD_`` set, which switches off glibc's adaptive mmap
    threshold: every image-sized temporary is then a fresh ``mmap`` whose pages fault in one by one, and the
    image workloads here ran at half speed (a fingerprint chunk took 2.2 s of CPU instead of 1.2 s).  The
    variable is left unset for these workers; on a cluster of your own, see the README.
    """
    import dask
    from distributed import LocalCluster

    with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
        return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                            silence_logs=40)


def open_executor(workers: int | None = None, scheduler: str | None = None, *, default_backend: str = "processes",
                  environ: dict[str, str] | None = None, retries: int = 3, small: bool = False) -> Executor:
    """The executor a command asked for.

    ``scheduler`` (or ``FORENSICS_SCHEDULER`` in ``environ``) selects Dask; otherwise ``workers`` local
    processes (default: every available core), or in-process with ``workers=1``.  ``small``: the command's
    work is too small to pay for starting worker processes, so without an explicit ``workers`` it runs in this
    process (an explicit count is always obeyed).
    """
    environ = os.environ if environ is None else environ
    scheduler = scheduler or environ.get(SCHEDULER_ENV) or None
    if scheduler:
        return Executor("dask", workers=workers or available_cores(), scheduler=scheduler, retries=retries)
    n = (1 if small else available_cores()) if workers is None else workers
    if n < 1:
        raise UsageError(f"--workers must be at least 1, not {n}")
    backend = default_backend if n > 1 else "in-process"
    return Executor(backend, workers=n, retries=retries)


def in_process() -> Executor:
    """The library's default executor: a plain loop in this process."""
    return Executor("in-process")


def resolve(executor: Executor | None) -> Executor:
    """``executor`` or the in-process default (what library functions do with ``executor=None``)."""
    return executor if executor is not None else in_process()


def chunks(n: int, size: int) -> list[range]:
    """``range(n)`` cut into consecutive pieces of ``size`` (the last may be shorter).

    The chunking of a reduction must depend on the data only — never on the number of workers — for the
    result to be identical on every backend.
    """
    if size < 1:
        raise ValueError("chunk size must be ≥ 1")
    return [range(s, min(n, s + size)) for s in range(0, n, size)]
