"""``cvvc.cluster.run_tasks`` on a real local Dask cluster of two workers: in-flight limit, retry, failure."""

from __future__ import annotations

import socket
import threading
import uuid
from pathlib import Path

import pytest

from cvvc.cluster import ClusterError, Outcome, Task, dask_client, run_tasks
from schemas.bus import wait_for

pytestmark = pytest.mark.process  # local Dask clusters of worker processes


def _holds_its_worker(release: str) -> str:
    """Task: holds its worker thread until the Dask event ``release`` is set (bounded: 60 s)."""
    from distributed import Event

    if not Event(release).wait(timeout=60):
        raise TimeoutError(f"the event {release} was never set")
    return "released"


def _scheduler_transitions(dask_scheduler, prefix: str) -> list[tuple[str, str, str]]:
    """On the scheduler: its transitions (key, from, to) of the tasks whose key starts with ``prefix``, in order."""
    return [(str(t.key), t.start, t.finish) for t in dask_scheduler.transition_log if str(t.key).startswith(prefix)]


def _fails_the_first_time(marker: str) -> str:
    """Task: raises on its first attempt (no marker file yet), returns on the second."""
    path = Path(marker)
    if not path.exists():
        path.write_text("tried\n")
        raise RuntimeError("first attempt fails")
    return "second attempt"


def _always_fails(marker: str) -> None:
    """Task: counts its attempts in ``marker`` and always raises."""
    with open(marker, "a") as f:
        f.write("attempt\n")
    raise ValueError("always")


def test_never_more_tasks_on_the_workers_than_worker_threads(dask_scheduler):
    """Five tasks on two one-thread workers, the first two holding both workers until the test releases them: the
    scheduler's own log shows never more than two handed out at a time, in the given order (Dask alone would hand
    all five out at once)."""
    from distributed import Client, Event

    label = f"held{uuid.uuid4().hex[:8]}"
    release = f"{label}-release"
    outcomes: list[Outcome] = []
    with Client(dask_scheduler, set_as_default=False) as client:
        tasks = [Task(label=f"{label}-{i}", fn=_holds_its_worker, args=(release,)) for i in range(5)]
        runner = threading.Thread(target=run_tasks, args=(client, tasks, outcomes.append), daemon=True)
        runner.start()
        try:
            # both workers hold a task: whatever run_tasks would hand out more is at the scheduler by now
            both_busy = wait_for(lambda: sum(len([k for k in keys if label in str(k)])
                                             for keys in client.processing().values()) >= 2, 60)
        finally:
            Event(release, client=client).set()
            runner.join(timeout=60)
        log = client.run_on_scheduler(_scheduler_transitions, prefix=f"cvvc-{label}-")
    assert both_busy and not runner.is_alive()
    assert [o.error for o in outcomes] == [None] * 5 and [o.result for o in outcomes] == ["released"] * 5
    handed_out, peak, started = 0, 0, []
    for key, start, finish in log:
        if finish == "processing":
            handed_out += 1
            started.append(key)
        elif start == "processing":
            handed_out -= 1
        peak = max(peak, handed_out)
    assert peak == 2, log
    assert [key.split("-")[2] for key in started] == ["0", "1", "2", "3", "4"], started  # in the given order


def test_a_task_is_retried_once_then_reported_and_the_others_go_on(dask_scheduler, tmp_path):
    from distributed import Client

    outcomes: list[Outcome] = []
    tasks = [Task(label="flaky", fn=_fails_the_first_time, args=(str(tmp_path / "flaky"),)),
             Task(label="broken", fn=_always_fails, args=(str(tmp_path / "broken"),)),
             Task(label="fine", fn=str.upper, args=("ok",))]
    with Client(dask_scheduler, set_as_default=False) as client:
        run_tasks(client, tasks, outcomes.append)
    by_label = {o.task.label: o for o in outcomes}
    assert by_label["flaky"].result == "second attempt" and by_label["flaky"].error is None
    assert isinstance(by_label["broken"].error, ValueError) and by_label["broken"].result is None
    assert (tmp_path / "broken").read_text().count("attempt") == 2  # the first try and one retry
    assert by_label["fine"].result == "OK"


def test_bad_cluster_arguments_are_clear_errors():
    with pytest.raises(ClusterError, match="--jobs 0 must be at least 1"):
        with dask_client(0):
            pass
    with pytest.raises(ClusterError, match="give the scheduler's address as tcp://HOST:PORT"):
        with dask_client(1, "127.0.0.1:8786"):
            pass


def _start_a_child() -> int:
    """Task: start a long-lived process, as a run starts its bridge, and return without stopping it."""
    import subprocess

    return subprocess.Popen(["sleep", "120"]).pid


def test_the_processes_of_unfinished_runs_are_stopped_on_the_workers(dask_scheduler):
    """What ``dask_client`` does before closing its local cluster: each worker stops what it started, by pid."""
    import psutil
    from distributed import Client

    from cvvc.cluster import stop_children

    with Client(dask_scheduler, set_as_default=False) as client:
        pid = client.submit(_start_a_child, pure=False).result(timeout=60)
        assert psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
        stopped = client.run(stop_children, timeout_s=10.0)
    assert sum(stopped.values()) >= 1
    try:
        assert psutil.Process(pid).status() == psutil.STATUS_ZOMBIE  # ended, not yet reaped by its worker
    except psutil.NoSuchProcess:
        pass


def test_a_local_cluster_starts_on_loopback_when_dasks_default_http_port_is_taken():
    """Dask's HTTP server defaulted to port 8787 and warned when another process held it (pytest made the warning
    an error: seven evaluate tests failed in CI); the local cluster listens on free loopback ports only."""
    held = socket.socket()
    try:
        try:
            held.bind(("127.0.0.1", 8787))
            held.listen()
        except OSError:
            pass  # taken already: the case under test
        with dask_client(1) as client:
            assert client.submit(pow, 2, 5).result(timeout=60) == 32
            http = client.scheduler_info()["services"].get("dashboard")
            assert http is not None and http != 8787
            assert _listening_hosts(http) == {"127.0.0.1"}
    finally:
        held.close()


def _listening_hosts(port: int) -> set[str]:
    """The IPv4 addresses with a socket listening on ``port`` (Linux /proc/net/tcp: state 0A is LISTEN)."""
    hosts = set()
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        local, state = line.split()[1], line.split()[3]
        addr, hex_port = local.split(":")
        if state == "0A" and int(hex_port, 16) == port:
            hosts.add(socket.inet_ntoa(bytes.fromhex(addr)[::-1]))
    return hosts
