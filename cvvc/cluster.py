"""Runs as tasks on dask.distributed: a ``LocalCluster`` on loopback, or a running scheduler (``--scheduler``).

``cvvc evaluate`` hands each run to :func:`run_tasks`: one task per run, retried once (``retries=1``) when it
raises, on a worker with one thread (a run drives its own bridge, agent and recorder processes, so one run per
worker process). The caller gets each task's outcome as it finishes, result or error, and the other tasks go on.

The local cluster listens on 127.0.0.1 only and has no dashboard. A running cluster is the user's: ``dask
scheduler --host 127.0.0.1 --port P --no-dashboard --dashboard-address 127.0.0.1:0`` and ``dask worker
tcp://127.0.0.1:P --nthreads 1 --dashboard-address 127.0.0.1:0`` (or other
hosts, docs/results.md); its workers must import this project and see the cache and the output folder at the same
paths, since a run reads the device map and the model and writes its folder by path.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import socket
import sys
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from schemas.errors import CvvcError

if TYPE_CHECKING:
    from distributed import Client

__all__ = ["ClusterError", "Outcome", "Task", "check_scheduler", "dask_client", "run_tasks", "stop_children"]


class ClusterError(CvvcError):
    """The Dask cluster could not be started or reached; the message says which and what to do."""


@dataclass(frozen=True)
class Task:
    """One unit of work: ``fn(*args)`` on a worker; ``label`` names it in the log and in its Dask key."""

    label: str
    fn: Callable[..., Any]
    args: tuple[Any, ...]
    tag: Any = None  # the caller's: what the task stands for (never sent to the workers)


@dataclass(frozen=True)
class Outcome:
    """A finished task: its result, or the error it raised on its last attempt (``result`` is then None)."""

    task: Task
    result: Any
    error: BaseException | None


@contextlib.contextmanager
def dask_client(jobs: int, scheduler: str | None = None, *, timeout_s: float = 60.0) -> Iterator[Client]:
    """A Dask client: of a new ``LocalCluster`` of ``jobs`` worker processes on loopback, or of ``scheduler``.

    The local cluster (and its workers) is closed on leaving the ``with`` block; a running cluster is left running.
    """
    from distributed import Client, LocalCluster

    # Dask's INFO lines (scheduler up, workers registered ...) only at `cvvc -v`: its logger follows the root's level
    logging.getLogger("distributed").setLevel(max(logging.getLogger().getEffectiveLevel(), logging.INFO))
    if jobs < 1:
        raise ClusterError(f"--jobs {jobs} must be at least 1")
    if scheduler is not None:
        check_scheduler(scheduler)
        try:
            client = Client(scheduler, timeout=timeout_s, set_as_default=False)
        except OSError as e:  # TimeoutError is an OSError
            raise ClusterError(f"no Dask scheduler answered at {scheduler} within {timeout_s:g} s ({e}); start "
                               "one with `dask scheduler` and workers with `dask worker`, or leave out "
                               "--scheduler to use a local cluster") from e
        with client:
            _wait_for_a_worker(client, scheduler, timeout_s)
            yield client
        return
    # memory_limit=0: no pause or restart of a worker by its memory; a run's memory is in the processes it starts
    # (bridge, agent, recorder), which the worker's monitor does not see, and a restarted worker would orphan them
    # dashboard_address: the scheduler's HTTP server (health and metrics even without a dashboard) on a free
    # loopback port; None meant port 8787, and a warning when another process held it
    cluster = LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True, host="127.0.0.1",
                           dashboard_address="127.0.0.1:0", protocol="tcp", memory_limit=0)
    try:
        with Client(cluster, set_as_default=False) as client:
            try:
                yield client
            finally:  # interrupted or failed with runs still going: stop their processes before the workers go
                _stop_worker_children(client)
    finally:
        cluster.close()


def _stop_worker_children(client: Client) -> None:
    """Stop what the local workers started (a run's bridge, agent and recorder) before the cluster is closed.

    Closing a cluster kills a busy worker after a few seconds, before the run's own cleanup (``cvvc.launch``
    stops its processes by pid) could finish: without this, those processes would outlive ``cvvc evaluate``.
    """
    try:
        stopped = client.run(stop_children)
    except Exception as e:  # workers already gone (killed, or Ctrl-C reached them): nothing left to ask
        logging.getLogger(__name__).debug("could not ask the workers to stop their processes: %s", e)
        return
    if any(stopped.values()):
        print(f"[cvvc evaluate] stopped {sum(stopped.values())} process(es) of unfinished runs", file=sys.stderr,
              flush=True)


def stop_children(timeout_s: float = 15.0) -> int:
    """On a worker: stop every process it started, and theirs, by pid: SIGINT, then SIGKILL after ``timeout_s``.

    Returns how many there were.
    """
    import psutil

    children = psutil.Process().children(recursive=True)
    for child in children:
        with contextlib.suppress(psutil.NoSuchProcess):
            child.send_signal(signal.SIGINT)
    _, alive = psutil.wait_procs(children, timeout=timeout_s)
    for child in alive:
        with contextlib.suppress(psutil.NoSuchProcess):
            child.kill()
    return len(children)


def check_scheduler(scheduler: str) -> None:
    """Fail at once, not after the client's timeout, when nothing listens at the scheduler's address."""
    host, _, port = scheduler.removeprefix("tcp://").rpartition(":")
    if not scheduler.startswith("tcp://") or not host or not port.isdigit():
        raise ClusterError(f"--scheduler {scheduler!r}: give the scheduler's address as tcp://HOST:PORT")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=10).close()
    except OSError as e:
        raise ClusterError(f"no Dask scheduler answered at {scheduler} ({e.strerror or e}); start one with `dask "
                           "scheduler`, and workers with `dask worker`, or leave out --scheduler to use a local "
                           "cluster") from e


def _wait_for_a_worker(client: Client, scheduler: str, timeout_s: float) -> None:
    try:
        client.wait_for_workers(1, timeout=timeout_s)
    except TimeoutError as e:
        raise ClusterError(f"the Dask scheduler at {scheduler} has no worker after {timeout_s:g} s; start one "
                           f"with `dask worker {scheduler} --nthreads 1`") from e


def run_tasks(client: Client, tasks: Sequence[Task], on_done: Callable[[Outcome], None], *,
              retries: int = 1) -> None:
    """Run every task, each retried ``retries`` times when it raises, and call ``on_done`` as each finishes.

    A task that still fails is an :class:`Outcome` with its error; the other tasks go on. Tasks start in the given
    order, never more at a time than the cluster has worker threads (counted again as each task finishes, so
    workers that join later are used): Dask would otherwise hand out every task at once, two to a worker, and one
    worker could be left with both long runs while the other idles. On an exception in ``on_done`` or an interrupt
    the unfinished tasks are cancelled.
    """
    from distributed import as_completed

    token = uuid.uuid4().hex[:8]
    waiting = list(enumerate(tasks))
    running: dict[Any, Task] = {}
    done = as_completed(loop=client.loop)

    def start_more() -> None:
        slots = max(1, sum(client.nthreads().values()))
        while waiting and len(running) < slots:
            i, t = waiting.pop(0)
            fut = client.submit(t.fn, *t.args, key=f"cvvc-{t.label}-{token}-{i}", pure=False, retries=retries)
            running[fut] = t
            done.add(fut)

    try:
        start_more()
        for fut in done:
            task = running.pop(fut)
            if fut.status == "finished":
                outcome = Outcome(task=task, result=fut.result(), error=None)
            else:
                outcome = Outcome(task=task, result=None, error=_error_of(fut))
            fut.release()
            start_more()
            on_done(outcome)
    except BaseException:
        client.cancel(list(running))
        raise


def _error_of(fut: Any) -> BaseException:
    """The exception a failed future raised (``CancelledError`` for a cancelled one, never raised here)."""
    try:
        err = fut.exception(timeout=30)
    except Exception as e:  # cancelled, or the scheduler lost it: reported as this run's error
        return e
    return err if err is not None else RuntimeError(f"task ended with status {fut.status!r}")
