"""The round trip the DNP3 hop adds to a regulator command: command put -> ack received, through ``cvvc adapter
dnp3``'s loop and a simulated regulator control, against the same bus round trip with a responder that acks at
once (measured side by side). Also reported: the DNP3 part alone (select-before-operate of the hold time, the band
and the set point, then the read back: ``Dnp3Device``'s operate of one set point).
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

from benchmarks.results import Dnp3Bench, RoundTrip

__all__ = ["bench_dnp3"]

F, D = "bench", "reg1"
_S = 1_000_000_000


def _cmd(seq: int) -> Any:
    from schemas import messages as m

    now = time.time_ns()
    return m.RegCommand(t_ns=now, seq=seq, source="agent", cmd_id=f"agent:{seq}:{D}", in_reply_to=seq,
                        valid_until_t_ns=now + 600 * _S, regulator_id=D,
                        action=m.SetpointAction(setpoint_v120=118.0 + (seq % 7), band_v120=2.0))


def _round_trips(session: Any, n: int) -> list[float]:
    """Put ``n`` commands one after the other; each one's put -> ack time [s]."""
    from schemas import keys
    from schemas import messages as m
    from schemas.bus import Inbox, TypedPublisher

    inbox = Inbox()
    inbox.subscribe(session, keys.ack(F, "vr", D), m.Ack)
    pub = TypedPublisher(session, keys.cmd(F, "vr", D), m.RegCommand, reliable=True)
    if not pub.wait_matched(20.0):
        raise RuntimeError("no command subscriber")
    out = []
    for i in range(n):
        t0 = time.perf_counter()
        pub.put(_cmd(i + 1))
        item = inbox.get(timeout_s=10.0)
        if item is None or item.msg.status != "accepted":
            raise RuntimeError(f"no accepted ack for command {i + 1}: {item}")
        out.append(time.perf_counter() - t0)
    inbox.undeclare()
    pub.undeclare()
    return out


def _responder(bus: Any, stop: threading.Event, ready: threading.Event) -> None:
    """The baseline device: acks every command at once (``accepted``, the requested set point)."""
    from schemas import keys
    from schemas import messages as m
    from schemas.bus import Inbox, TypedPublisher, open_session

    with open_session(bus) as session:
        inbox = Inbox()
        inbox.subscribe(session, keys.cmd(F, "vr", D), m.RegCommand)
        pub = TypedPublisher(session, keys.ack(F, "vr", D), m.Ack, reliable=True)
        ready.set()
        while not stop.is_set():
            item = inbox.get(timeout_s=0.1)
            if item is not None:
                c = item.msg
                pub.put(m.Ack(t_ns=c.t_ns, seq=c.seq, source=D, cmd_id=c.cmd_id, device_id=D, status="accepted",
                              applied_value=c.action.setpoint_v120))


def _stats(xs: list[float]) -> RoundTrip:
    a = np.asarray(xs) * 1e3
    return RoundTrip(p50_ms=float(np.percentile(a, 50)), p99_ms=float(np.percentile(a, 99)))


def bench_dnp3(n: int = 200) -> Dnp3Bench:
    """Command -> ack round trips [ms] with and without the DNP3 hop, and the DNP3 part alone."""
    from adapters.dnp3 import Dnp3Master
    from adapters.dnp3_device import Dnp3Device, Dnp3DeviceSettings
    from adapters.dnp3_runtime import Dnp3AdapterConfig, run_dnp3_adapter
    from schemas import messages as m
    from schemas.bus import BusConfig, free_port, open_session
    from simulator_bridge.field.dnp3_sim import SimulatedRegulatorControl

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
        sim = SimulatedRegulatorControl(regulator_id=D, tap_max=16, default_setpoint_v120=120.0,
                                        default_band_v120=2.0, port=free_port(), clock_ns=time.time_ns)
        with sim:
            sim.set_measurements(v_compared_120=121.0, tap=0, load_current_a=100.0)
            config = Dnp3AdapterConfig(feeder_id=F, device_id=D, kind="vr", dnp3=sim.endpoint, scan_period_s=60.0)
            stop, ready = threading.Event(), threading.Event()
            t = threading.Thread(target=run_dnp3_adapter, args=(config, peer), kwargs=dict(stop=stop, ready=ready),
                                 daemon=True)
            t.start()
            ready.wait(20.0)
            through_dnp3 = _stats(_round_trips(router, n))
            stop.set()
            t.join(20.0)
            with Dnp3Master(sim.endpoint) as master:
                if not master.wait_open(20.0):
                    raise RuntimeError(f"no DNP3 channel to {sim.endpoint}")
                dev = Dnp3Device(Dnp3DeviceSettings(feeder_id=F, device_id=D, kind="vr"), master)
                dnp3_part = []
                for i in range(n):
                    now = time.time_ns()
                    t0 = time.perf_counter()
                    dev.write_setpoint(m.SetpointAction(setpoint_v120=118.0 + (i % 7), band_v120=2.0),
                                        now + 600 * _S, now)
                    dnp3_part.append(time.perf_counter() - t0)
    return Dnp3Bench(commands=n, bus_only=bus_only, through_dnp3=through_dnp3,
                     dnp3_operates_read_back=_stats(dnp3_part),
                     extra_per_decision_p50_ms=through_dnp3.p50_ms - bus_only.p50_ms,
                     extra_per_decision_p99_ms=through_dnp3.p99_ms - bus_only.p99_ms)
