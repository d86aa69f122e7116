"""One long-lived thread that runs every in-process bridge of a test session, one after another.

OpenDSS (DSS C-API, a FreePascal library) segfaulted in ``ctx_New`` three times in the test suite, each time in a
fresh short-lived thread running ``run_bridge``, the first time in the session's very first bridge thread (CI of
2026-11-26, ``test_commands_are_acked_and_show_in_the_next_frames[inline]``). FreePascal sets up its per-thread
state (thread variables, a per-thread heap) lazily the first time a foreign thread calls in, and a context made in
a thread that then exits is freed later from another thread's heap; neither can be reproduced on demand (300
contexts made in short-lived threads and dropped in the main thread ran clean here). In production every engine
lives in a process's main thread (``cvvc bridge``, evaluation workers); the tests now match that as closely as a
thread can: all in-process bridges run in this one thread, which is set up once, while nothing else runs, by
making and dropping one context.
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
    from simulator_bridge.dss_context import new_context

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
