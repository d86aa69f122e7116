"""The harness of the field-protocol hop benchmarks (``bench_sunspec``, ``bench_dnp3``): command put -> ack received
on one bus, first against a responder that acks at once, then through an adapter's loop and its simulated device.

Each benchmark says what is particular to its protocol in a :class:`Hop` and times the protocol's part alone itself.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from benchmarks.results import RoundTrip

__all__ = ["Hop", "HopBench", "command_fields", "hop_bench", "stats", "timed"]

FEEDER = "bench"
VALID_S = 600  # a benchmark command's validity [s]


def command_fields(seq: int, device_id: str) -> dict[str, Any]:
    """The fields every benchmark command shares: the ``seq``-th of agent ``agent``, valid ``VALID_S`` from now."""
    now = time.time_ns()
    return dict(t_ns=now, seq=seq, source="agent", cmd_id=f"agent:{seq}:{device_id}", in_reply_to=seq,
                valid_until_t_ns=now + VALID_S * 1_000_000_000)


@dataclass(frozen=True)
class Hop:
    """One device's commands on the bus.

    Parameters
    ----------
    kind, device_id : the device's keys (``cvvc/bench/cmd/<kind>/<device_id>``). cmd_type : its command type.
    make_cmd : the ``seq``-th command (from 1). applied_value : what the baseline responder acks as applied.
    accepted_only : an ack of another status than ``accepted`` ends the benchmark with an error.
    """

    kind: Literal["pv", "vr", "cap"]
    device_id: str
    cmd_type: type
    make_cmd: Callable[[int], Any]
    applied_value: Callable[[Any], float]
    accepted_only: bool


def stats(xs: list[float]) -> RoundTrip:
    """The percentiles [ms] of times ``xs`` [s]."""
    a = np.asarray(xs) * 1e3
    return RoundTrip(p50_ms=float(np.percentile(a, 50)), p99_ms=float(np.percentile(a, 99)))


def timed(n: int, step: Callable[[int], object]) -> list[float]:
    """The time of each of ``step(0)`` ... ``step(n - 1)`` [s], one after the other."""
    out = []
    for i in range(n):
        t0 = time.perf_counter()
        step(i)
        out.append(time.perf_counter() - t0)
    return out


def _round_trips(session: Any, hop: Hop, n: int) -> list[float]:
    """Put ``n`` commands one after the other; each one's put -> ack time [s]."""
    from schemas import keys
    from schemas import messages as m
    from schemas.bus import Inbox, TypedPublisher

    inbox = Inbox()
    inbox.subscribe(session, keys.ack(FEEDER, hop.kind, hop.device_id), m.Ack)
    key = keys.cmd(FEEDER, hop.kind, hop.device_id)
    pub: TypedPublisher[Any] = TypedPublisher(session, key, hop.cmd_type, reliable=True)
    if not pub.wait_matched(20.0):
        raise RuntimeError("no command subscriber")
    out = []
    for i in range(n):
        t0 = time.perf_counter()
        pub.put(hop.make_cmd(i + 1))
        item = inbox.get(timeout_s=10.0)
        if hop.accepted_only and (item is None or item.msg.status != "accepted"):
            raise RuntimeError(f"no accepted ack for command {i + 1}: {item}")
        if item is None:
            raise RuntimeError(f"no ack for command {i + 1}")
        out.append(time.perf_counter() - t0)
    inbox.undeclare()
    pub.undeclare()
    return out


def _responder(bus: Any, hop: Hop, stop: threading.Event, ready: threading.Event) -> None:
    """The baseline device: acks every command at once (``accepted``, the requested value)."""
    from schemas import keys
    from schemas import messages as m
    from schemas.bus import Inbox, TypedPublisher, open_session

    d = hop.device_id
    with open_session(bus) as session:
        inbox = Inbox()
        inbox.subscribe(session, keys.cmd(FEEDER, hop.kind, d), hop.cmd_type)
        pub = TypedPublisher(session, keys.ack(FEEDER, hop.kind, d), m.Ack, reliable=True)
        ready.set()
        while not stop.is_set():
            item = inbox.get(timeout_s=0.1)
            if item is not None:
                c = item.msg
                pub.put(m.Ack(t_ns=c.t_ns, seq=c.seq, source=d, cmd_id=c.cmd_id, device_id=d, status="accepted",
                              applied_value=hop.applied_value(c)))


@dataclass(frozen=True)
class HopBench:
    """The bus of a hop benchmark: its router session, the peers' configuration, the hop."""

    router: Any
    peer: Any
    hop: Hop
    n: int

    def through_adapter(self, run: Callable[..., object], config: object) -> RoundTrip:
        """Round trips [ms] of ``n`` commands through ``run(config, bus, stop=, ready=)`` in a thread."""
        stop, ready = threading.Event(), threading.Event()
        t = threading.Thread(target=run, args=(config, self.peer), kwargs=dict(stop=stop, ready=ready), daemon=True)
        t.start()
        ready.wait(20.0)
        out = stats(_round_trips(self.router, self.hop, self.n))
        stop.set()
        t.join(20.0)
        return out


@contextmanager
def hop_bench(hop: Hop, n: int) -> Iterator[tuple[HopBench, RoundTrip]]:
    """A router on a free port, and the round trips [ms] of ``n`` commands to the baseline responder on it."""
    from schemas.bus import BusConfig, free_port, open_session

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    peer = BusConfig(mode="peer", connect=(endpoint,))
    with open_session(BusConfig(mode="router", listen=(endpoint,))) as router:
        stop, ready = threading.Event(), threading.Event()
        t = threading.Thread(target=_responder, args=(peer, hop, stop, ready), daemon=True)
        t.start()
        ready.wait(20.0)
        bus_only = stats(_round_trips(router, hop, n))
        stop.set()
        t.join(20.0)
        yield HopBench(router, peer, hop, n), bus_only
