"""A decision's burst on the bus: 11 commands then the decision, put express each or batched.

The agent puts a decision's commands, then the decision; the bridge acks each command. Express messages are
written to the socket one by one; a reliable publisher with ``express=False`` lets Zenoh batch the burst, and an
express message of the same priority after it (the decision) flushes the batch in one write. This bench times both
on loopback: this process (router) puts ``bursts`` bursts 4 ms apart to a subscriber in a spawned process, and
reports the publishing thread's CPU per burst and the time until the subscriber has the decision (the last
message; the commands travel before it on the same priority). The two modes alternate ``rounds`` times.

Run: ``python -m benchmarks.bench_burst [BURSTS [ROUNDS]]`` (docs/bridge.md, "Sixth pass").
"""

from __future__ import annotations

import multiprocessing as mp
import statistics
import sys
import time
from typing import Any

from benchmarks.results import BurstBench, to_json

__all__ = ["bench_burst"]

_COMMANDS = 11  # the rural feeder's devices: 8 regulators and 3 PV plants
_PAYLOAD = b"x" * 300  # about a command's JSON [bytes]
_GAP_S = 0.004  # between bursts [s]


def _subscriber(endpoint: str, ready: Any, n: int, out: Any) -> None:
    """Child process: record when each burst's decision arrives [wall ns]; send the list when all came."""
    from schemas.bus import BusConfig, open_session

    times: list[int] = []
    with open_session(BusConfig(mode="peer", connect=(endpoint,))) as session:
        session.declare_subscriber("bench/burst/**", lambda s: times.append(time.time_ns())
                                   if str(s.key_expr).endswith("/decision") else None)
        ready.set()
        deadline = time.monotonic() + 120.0
        while len(times) < n and time.monotonic() < deadline:
            time.sleep(0.01)
        out.put(times)


def _one(endpoint: str, session: Any, n: int, batched: bool) -> tuple[float, float]:
    """(median put CPU per burst [µs], median latency [ms]) of ``n`` bursts."""
    import zenoh

    from schemas.bus import has_subscribers, wait_for

    ctx = mp.get_context("spawn")
    ready, q = ctx.Event(), ctx.Queue()
    proc = ctx.Process(target=_subscriber, args=(endpoint, ready, n, q), daemon=True)
    proc.start()
    kw: dict[str, Any] = {"congestion_control": zenoh.CongestionControl.BLOCK, "priority": zenoh.Priority.REAL_TIME}
    cmds = [session.declare_publisher(f"bench/burst/cmd/{i}", express=not batched, **kw) for i in range(_COMMANDS)]
    dec = session.declare_publisher("bench/burst/decision", express=True, **kw)
    try:
        if not ready.wait(60.0) or not wait_for(lambda: has_subscribers(dec), 20.0):
            raise RuntimeError("the subscriber process did not come up")
        time.sleep(0.3)  # its subscription reaches every publisher
        sent, cpu = [], []
        for _ in range(n):
            c0 = time.thread_time()
            sent.append(time.time_ns())
            for c in cmds:
                c.put(_PAYLOAD)
            dec.put(_PAYLOAD)
            cpu.append(time.thread_time() - c0)
            time.sleep(_GAP_S)
        got = q.get(timeout=120.0)
    finally:
        proc.join(10.0)
        if proc.is_alive():
            proc.kill()
        for p in [*cmds, dec]:
            p.undeclare()
    if len(got) != n:
        raise RuntimeError(f"the subscriber received {len(got)} of {n} decisions")
    return (round(statistics.median(cpu) * 1e6, 1),
            round(statistics.median((g - t) / 1e6 for g, t in zip(got, sent, strict=True)), 3))


def bench_burst(bursts: int = 300, rounds: int = 2) -> BurstBench:
    """Express vs batched bursts, alternating (express first in even rounds); see the module docstring."""
    from schemas.bus import BusConfig, free_port, open_session

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    runs: dict[bool, list[tuple[float, float]]] = {False: [], True: []}
    with open_session(BusConfig(mode="router", listen=(endpoint,))) as session:
        for r in range(rounds):
            for batched in ((False, True) if r % 2 == 0 else (True, False)):
                runs[batched].append(_one(endpoint, session, bursts, batched))
    return BurstBench(bursts=bursts, rounds=rounds,
                      express_put_cpu_us=[c for c, _ in runs[False]], batched_put_cpu_us=[c for c, _ in runs[True]],
                      express_latency_ms=[x for _, x in runs[False]], batched_latency_ms=[x for _, x in runs[True]])


if __name__ == "__main__":  # python -m benchmarks.bench_burst [BURSTS [ROUNDS]]
    print(to_json(bench_burst(int(sys.argv[1]) if len(sys.argv) > 1 else 300,
                              int(sys.argv[2]) if len(sys.argv) > 2 else 2)))
