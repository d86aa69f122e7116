"""One long-lived thread that runs every in-process bridge of a test session, one after another.

Introduced against a segfault in OpenDSS's ``ctx_New`` met three times in CI, always in a fresh bridge thread.
Its cause turned out to be elsewhere (the library read the C environment through a pointer glibc had freed once
pytest set ``PYTEST_CURRENT_TEST``; fixed by ``simulator_bridge.opendss.pinned_environ``: with it, the crash that the
re-laid simulator_bridge made deterministic, 2 of 2 runs of ``test_bridge.py`` with ``test_engine.py``, is gone,
3 of 3). The thread stays: a bridge of the tests runs where a bridge runs in production, on one thread that
outlives its engines, and a stuck bridge shows as a job that never ends, not as a stray thread.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable
from typing import Any

__all__ = ["Job", "run_in_dss_thread"]


class Job:
    """A call queued on the OpenDSS thread; ``out`` gets its result or exception (the ``threading.Thread`` shape
    the tests used: ``join``/``is_alive``)."""

    def __init__(self) -> None:
        self.out: list[Any] = []
        self._done = threading.Event()

    def join(self, timeout: float | None = None) -> None:
        self._done.wait(timeout)

    def is_alive(self) -> bool:
        return not self._done.is_set()


_jobs: queue.SimpleQueue[tuple[Callable[[], Any], Job]] = queue.SimpleQueue()
_started = threading.Lock()
_thread: threading.Thread | None = None


def _loop() -> None:
    while True:
        fn, job = _jobs.get()
        try:
            job.out.append(fn())
        except BaseException as e:  # noqa: BLE001 - surfaced by the test through ``out``
            job.out.append(e)
        finally:
            job._done.set()


def _warm_up() -> None:
    from simulator_bridge.opendss.dss_context import new_context

    new_context()  # made and dropped in this thread: FreePascal's per-thread state exists from now on


def run_in_dss_thread(fn: Callable[[], Any]) -> Job:
    """Queue ``fn`` on the session's OpenDSS thread (started and warmed up on first use) and return its job."""
    global _thread
    with _started:
        if _thread is None:
            _thread = threading.Thread(target=_loop, name="dss-bridges", daemon=True)
            _thread.start()
            warm = Job()
            _jobs.put((_warm_up, warm))
            warm.join(120.0)
            assert not warm.is_alive() and warm.out == [None], f"the OpenDSS thread did not start: {warm.out}"
    job = Job()
    _jobs.put((fn, job))
    return job
