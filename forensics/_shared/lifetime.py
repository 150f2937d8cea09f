"""Process lifetime: a run ends as a whole — SIGTERM is handled as Ctrl-C, and workers die with their driver.

What ``timeout``, systemd and batch schedulers send is SIGTERM, whose default action kills the driver on
the spot: no clean-up, and worker processes (children of multiprocessing's fork server, not of the driver)
left blocked forever on their queues.  Two pieces prevent that:

* :func:`sigterm_as_interrupt` (used by the command line around a command) turns SIGTERM into
  :class:`Terminated`, a :class:`KeyboardInterrupt`: every clean-up that runs for Ctrl-C runs for it —
  temporary files removed, resumable work kept, workers stopped — and the command exits 143;
* :func:`exit_with` (run in every worker process) ends the worker as soon as the driver's process ends,
  however it ended (SIGKILL included), so nothing is left behind; the fork server then exits by itself
  when the last holder of its "alive" pipe is gone.
"""
from __future__ import annotations

import contextlib
import os
import select
import signal
import threading
import time
from collections.abc import Iterator


class Terminated(KeyboardInterrupt):
    """The process was asked to stop by a signal (SIGTERM): handled exactly as Ctrl-C, with its own exit code."""

    def __init__(self, signum: int = signal.SIGTERM) -> None:
        self.signum = int(signum)
        super().__init__(f"terminated by {signal.Signals(self.signum).name}")

    @property
    def exit_code(self) -> int:
        """The shell's convention for death by a signal: 128 + its number (143 for SIGTERM)."""
        return 128 + self.signum


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM raises :class:`Terminated` in the main thread (as Ctrl-C raises
    KeyboardInterrupt); the previous handler is restored after.

    Only the first SIGTERM raises: a second one while clean-up runs is ignored, so the clean-up completes (a
    scheduler that insists follows with SIGKILL, after which the workers still exit, :func:`exit_with`).
    Does nothing outside the main thread, where Python cannot install signal handlers.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: object) -> None:
        signal.signal(signal.SIGTERM, lambda *_: None)
        raise Terminated(signum)

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


#: Exit status of a worker that ends because its driver is gone (the driver cannot read it any more).
ORPHAN_EXIT = 70


def exit_with(pid: int) -> None:
    """End this process (``os._exit``) as soon as process ``pid`` ends, watched from a daemon thread.

    Uses a pidfd (Linux ≥ 5.3), which becomes readable when the process exits, whoever its parent is — the
    worker's parent is the fork server, so the kernel's parent-death signal cannot serve.  Elsewhere the
    process is polled once a second.
    """
    try:
        fd = os.pidfd_open(pid)
    except ProcessLookupError:
        os._exit(ORPHAN_EXIT)
    except (AttributeError, OSError):
        fd = None

    def watch() -> None:
        if fd is not None:
            poller = select.poll()  # not select(): a worker may hold descriptors numbered above FD_SETSIZE
            poller.register(fd, select.POLLIN)
            poller.poll()
        else:
            while _alive(pid):
                time.sleep(1.0)
        os._exit(ORPHAN_EXIT)

    threading.Thread(target=watch, name=f"exit-with-{pid}", daemon=True).start()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
