"""The round trip the SunSpec Modbus hop adds to a PV command: command put -> ack received, through the adapter and
a simulated inverter, against the same bus round trip with a responder that acks at once (measured side by side).

A decision sends one command per plant and every plant has its own adapter, so the extra time per decision is
the extra time of one command (the adapters work in parallel). Also reported: the adapter's Modbus part alone (the
704 write and the read back of 701/702/704, ``SunSpecLink.write_var_setpoint``).
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

from benchmarks.results import RoundTrip, SunspecBench

__all__ = ["bench_sunspec"]

F, D = "bench", "pv1"
_S = 1_000_000_000


def _cmd(seq: int, q_kvar: float) -> Any:
    from schemas import messages as m

    now = time.time_ns()
    return m.PvCommand(t_ns=now, seq=seq, source="agent", cmd_id=f"agent:{seq}:{D}", in_reply_to=seq,
                       valid_until_t_ns=now + 600 * _S, plant_id=D, q_kvar=q_kvar)


def _round_trips(session: Any, n: int) -> list[float]:
    """Put ``n`` commands one after the other; each one's put -> ack time [s]."""
    from schemas import keys
    from schemas import messages as m
    from schemas.bus import Inbox, TypedPublisher

    inbox = Inbox()
    inbox.subscribe(session, keys.ack(F, "pv", D), m.Ack)
    pub = TypedPublisher(session, keys.cmd(F, "pv", D), m.PvCommand, reliable=True)
    if not pub.wait_matched(20.0):
        raise RuntimeError("no command subscriber")
    out = []
    for i in range(n):
        t0 = time.perf_counter()
        pub.put(_cmd(i + 1, -100.0 - (i % 7)))
        if inbox.get(timeout_s=10.0) is None:
            raise RuntimeError(f"no ack for command {i + 1}")
        out.append(time.perf_counter() - t0)
    inbox.undeclare()
    pub.undeclare()
    return out


def _responder(bus: Any, stop: threading.Event, ready: threading.Event) -> None:
    """The baseline device: acks every command at once (``accepted``, the requested value)."""
    from schemas import keys
    from schemas import messages as m
    from schemas.bus import Inbox, TypedPublisher, open_session

    with open_session(bus) as session:
        inbox = Inbox()
        inbox.subscribe(session, keys.cmd(F, "pv", D), m.PvCommand)
        pub = TypedPublisher(session, keys.ack(F, "pv", D), m.Ack, reliable=True)
        ready.set()
        while not stop.is_set():
            item = inbox.get(timeout_s=0.1)
            if item is not None:
                c = item.msg
                pub.put(m.Ack(t_ns=c.t_ns, seq=c.seq, source=D, cmd_id=c.cmd_id, device_id=D, status="accepted",
                              applied_value=c.q_kvar))


def _stats(xs: list[float]) -> RoundTrip:
    a = np.asarray(xs) * 1e3
    return RoundTrip(p50_ms=float(np.percentile(a, 50)), p99_ms=float(np.percentile(a, 99)))


def bench_sunspec(n: int = 200) -> SunspecBench:
    """Command -> ack round trips [ms] with and without the SunSpec hop, and the Modbus part alone."""
    from adapters.sunspec import SunSpecLink
    from adapters.sunspec_runtime import AdapterConfig, run_adapter
    from schemas.bus import BusConfig, free_port, open_session
    from simulator_bridge.field.sunspec_sim import SimulatedSunSpecInverter

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    peer = BusConfig(mode="peer", connect=(endpoint,))
    with open_session(BusConfig(mode="router", listen=(endpoint,))) as router:
        stop, ready = threading.Event(), threading.Event()
        t = threading.Thread(target=_responder, args=(peer, stop, ready), daemon=True)
        t.start()
        ready.wait(20.0)
        bus_only = _stats(_round_trips(router, n))
        stop.set()
        t.join(20.0)
        inv = SimulatedSunSpecInverter(plant_id=D, s_rated_kva=1000.0, v_nominal_v=7200.0, port=free_port())
        inv.set_measurements(p_kw=[200.0] * 3, v_v=[7200.0] * 3)
        with inv:
            config = AdapterConfig(feeder_id=F, device_id=D, modbus=f"tcp/127.0.0.1:{inv.port}", scan_period_s=60.0)
            stop, ready = threading.Event(), threading.Event()
            t = threading.Thread(target=run_adapter, args=(config, peer), kwargs=dict(stop=stop, ready=ready),
                                 daemon=True)
            t.start()
            ready.wait(20.0)
            through_sunspec = _stats(_round_trips(router, n))
            stop.set()
            t.join(20.0)
            link = SunSpecLink("127.0.0.1", inv.port)
            link.read()
            modbus = []
            for i in range(n):
                t0 = time.perf_counter()
                link.write_var_setpoint(-100.0 - (i % 7), 600)
                modbus.append(time.perf_counter() - t0)
            link.close()
    return SunspecBench(commands=n, bus_only=bus_only, through_sunspec=through_sunspec,
                        modbus_write_read_back=_stats(modbus),
                        extra_per_decision_p50_ms=through_sunspec.p50_ms - bus_only.p50_ms,
                        extra_per_decision_p99_ms=through_sunspec.p99_ms - bus_only.p99_ms)
