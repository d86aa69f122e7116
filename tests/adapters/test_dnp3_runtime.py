"""``cvvc adapter dnp3``'s loop on loopback: real Zenoh, real DNP3 over TCP, a simulated regulator control.

Every wait is bounded and on a real event (a message received, the device's state), never a bare sleep.
"""

from __future__ import annotations

import threading
import time

import pytest

from adapters.dnp3_runtime import Dnp3AdapterConfig, run_dnp3_adapter
from schemas import keys
from schemas import messages as m
from schemas.bus import BusConfig, Inbox, TypedPublisher, free_port, open_session, wait_for
from simulator_bridge.field.dnp3_sim import Dnp3SimError, SimulatedCapBankController, SimulatedRegulatorControl

F, D = "f1", "reg1"
S = 1_000_000_000


def _cmd(sp: float, *, seq: int, valid_s: float = 600.0) -> m.RegCommand:
    now = time.time_ns()
    return m.RegCommand(t_ns=now, seq=seq, source="agent", cmd_id=f"agent:{seq}:{D}", in_reply_to=seq,
                        valid_until_t_ns=now + int(valid_s * S), regulator_id=D,
                        action=m.SetpointAction(setpoint_v120=sp, band_v120=2.0))


def test_frames_commands_acks_link_loss_and_recovery_over_the_bus(router_endpoint):
    sim = SimulatedRegulatorControl(regulator_id=D, tap_max=16, default_setpoint_v120=120.0, default_band_v120=2.0,
                                    port=free_port(), clock_ns=time.time_ns)
    config = Dnp3AdapterConfig(feeder_id=F, device_id=D, kind="vr", dnp3=sim.endpoint, scan_period_s=0.2,
                               status_period_s=0.5, timeout_s=1.0, phase="c")
    bus = BusConfig(mode="peer", connect=(router_endpoint,))
    got: list = []

    def seen(msg_type: type) -> list:
        got.extend(r.msg for r in inbox.drain())
        return [x for x in got if isinstance(x, msg_type)]

    with sim, open_session(bus) as session:
        sim.set_measurements(v_compared_120=121.0, v_120=122.5, tap=2, load_current_a=150.0)
        inbox = Inbox()
        for key in (keys.meas_vr(F, D), keys.ack(F, "vr", D), keys.link(F, "vr", D)):
            inbox.subscribe(session, key)
        commands = TypedPublisher(session, keys.cmd(F, "vr", D), m.RegCommand, reliable=True)
        stop, ready, result = threading.Event(), threading.Event(), []
        thread = threading.Thread(target=lambda: result.append(run_dnp3_adapter(config, bus, stop=stop,
                                                                                 ready=ready)), daemon=True)
        thread.start()
        try:
            assert ready.wait(20.0), "the adapter did not join the bus"
            assert commands.wait_matched(10.0), "the adapter's command subscriber was not seen"
            assert wait_for(lambda: len(seen(m.RegFrame)) >= 2, 10.0)
            frame = seen(m.RegFrame)[-1]
            assert (frame.tap, frame.setpoint_v120, frame.phases[0].phase) == (2, 120.0, "c")
            assert frame.t_ns % int(0.2 * S) == 0  # stamped with the scan's time
            commands.put(_cmd(122.5, seq=1))
            assert wait_for(lambda: seen(m.Ack), 10.0)
            ack = seen(m.Ack)[0]
            assert (ack.status, ack.applied_value, ack.device_id) == ("accepted", 122.5, D)
            assert sim.setpoint_in_force().setpoint_v120 == 122.5
            assert wait_for(lambda: any(f.setpoint_v120 == 122.5 for f in seen(m.RegFrame)), 10.0)

            sim.stop()  # the link is lost
            assert wait_for(lambda: any(s.state == "down" for s in seen(m.LinkStatus)), 20.0)
            status = next(s for s in seen(m.LinkStatus) if s.state == "down")
            assert (status.kind, status.protocol, status.device_id) == ("vr", "dnp3", D)
            commands.put(_cmd(123.0, seq=2))
            assert wait_for(lambda: len(seen(m.Ack)) >= 2, 20.0)
            assert seen(m.Ack)[1].reason.startswith("link_down")
            n = len(seen(m.RegFrame))
            sim.start()  # and restored: frames again, the device kept its set point
            assert wait_for(lambda: len(seen(m.RegFrame)) > n, 20.0)
            assert seen(m.RegFrame)[-1].setpoint_v120 == 122.5
            assert wait_for(lambda: any(s.state == "ok" and s.commands == 2 for s in seen(m.LinkStatus)), 10.0)
        finally:
            stop.set()
            thread.join(20.0)
            inbox.undeclare()
        assert not thread.is_alive(), "the adapter did not stop"
        assert result[0].foreign_writes == 0 and result[0].commands_failed == 1


def test_a_non_loopback_endpoint_is_refused_before_the_bus():
    with pytest.raises(Dnp3SimError, match="tcp/127.0.0.1:PORT"):
        run_dnp3_adapter(Dnp3AdapterConfig(feeder_id=F, device_id=D, kind="vr", dnp3="tcp/192.0.2.1:20000"),
                         BusConfig(mode="peer", connect=("tcp/127.0.0.1:1",)), stop=threading.Event())


def test_a_bank_over_the_bus_and_a_malformed_command_answered_by_nothing(router_endpoint):
    sim = SimulatedCapBankController(capacitor_id="cap1", port=free_port(), clock_ns=time.time_ns)
    config = Dnp3AdapterConfig(feeder_id=F, device_id="cap1", kind="cap", dnp3=sim.endpoint, scan_period_s=0.2,
                               status_period_s=0.5, timeout_s=1.0, kvar_rated=300.0)
    bus = BusConfig(mode="peer", connect=(router_endpoint,))
    got: list = []
    with sim, open_session(bus) as session:
        sim.set_measurements(closed=False, v_v=2400.0, control_value=None)
        inbox = Inbox()
        for key in (keys.meas_cap(F, "cap1"), keys.ack(F, "cap", "cap1")):
            inbox.subscribe(session, key)

        def seen(msg_type: type) -> list:
            got.extend(r.msg for r in inbox.drain())
            return [x for x in got if isinstance(x, msg_type)]

        commands = TypedPublisher(session, keys.cmd(F, "cap", "cap1"), m.CapCommand, reliable=True)
        stop, ready, result = threading.Event(), threading.Event(), []
        thread = threading.Thread(target=lambda: result.append(run_dnp3_adapter(config, bus, stop=stop,
                                                                                 ready=ready)), daemon=True)
        thread.start()
        try:
            assert ready.wait(20.0) and commands.wait_matched(10.0)
            assert wait_for(lambda: seen(m.CapFrame), 10.0)
            assert seen(m.CapFrame)[-1].kvar_rated == 300.0
            session.put(keys.cmd(F, "cap", "cap1"), b"\x05\x64 not a command {")  # malformed: dropped, counted
            now = time.time_ns()
            commands.put(m.CapCommand(t_ns=now, seq=1, source="agent", cmd_id="agent:1:cap1", in_reply_to=1,
                                      valid_until_t_ns=now + 600 * S, capacitor_id="cap1", closed_steps=1))
            assert wait_for(lambda: seen(m.Ack), 10.0)
            assert [(a.status, a.applied_value) for a in seen(m.Ack)] == [("accepted", 1.0)]  # one ack: ours
            assert sim.commanded_closed() is True
        finally:
            stop.set()
            thread.join(20.0)
            inbox.undeclare()
        assert not thread.is_alive() and result[0].commands == 1
