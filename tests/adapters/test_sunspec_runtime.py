"""``cvvc adapter sunspec``'s loop on loopback: real Zenoh, real Modbus TCP, a simulated inverter.

Every wait is bounded and on a real event (a message received, the inverter's state), never a bare sleep.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import msgspec
import pytest

from adapters.sunspec_runtime import AdapterConfig, run_adapter
from schemas import keys
from schemas import messages as m
from schemas.bus import BusConfig, Inbox, TypedPublisher, open_session, wait_for

F, D = "f1", "pv1"
S = 1_000_000_000


@dataclass
class Running:
    """An adapter running in a thread, and a peer session of the test that sees its keys."""

    stop: threading.Event
    thread: threading.Thread
    result: list
    inbox: Inbox
    commands: TypedPublisher

    def received(self, msg_type: type) -> list:
        out = [r.msg for r in self._all if isinstance(r.msg, msg_type)]
        return out

    def pump(self) -> None:
        self._all.extend(self.inbox.drain())

    def wait(self, predicate, timeout_s: float = 10.0) -> bool:
        def check() -> bool:
            self.pump()
            return bool(predicate())
        return wait_for(check, timeout_s, poll_s=0.02)

    def __post_init__(self) -> None:
        self._all: list = []


@pytest.fixture
def adapter(inverter, router_endpoint) -> Iterator[Running]:
    config = AdapterConfig(feeder_id=F, device_id=D, modbus=f"tcp/127.0.0.1:{inverter.port}", scan_period_s=0.2,
                           status_period_s=0.5, timeout_s=1.0)
    with open_session(BusConfig(mode="peer", connect=(router_endpoint,))) as session:
        inbox = Inbox()
        for key in (keys.meas_pv(F, D), keys.ack(F, "pv", D), keys.link(F, "pv", D)):
            inbox.subscribe(session, key)
        commands = TypedPublisher(session, keys.cmd(F, "pv", D), m.PvCommand, reliable=True)
        stop, ready, result = threading.Event(), threading.Event(), []
        bus = BusConfig(mode="peer", connect=(router_endpoint,))
        thread = threading.Thread(target=lambda: result.append(run_adapter(config, bus, stop=stop, ready=ready)),
                                  daemon=True)
        thread.start()
        assert ready.wait(20.0), "the adapter did not join the bus"
        assert commands.wait_matched(10.0), "the adapter's command subscriber was not seen"
        running = Running(stop=stop, thread=thread, result=result, inbox=inbox, commands=commands)
        try:
            yield running
        finally:
            stop.set()
            thread.join(20.0)
            assert not thread.is_alive(), "the adapter did not stop"
            inbox.undeclare()


def _cmd(q_kvar: float, *, seq: int, valid_s: float) -> m.PvCommand:
    now = time.time_ns()
    return m.PvCommand(t_ns=now, seq=seq, source="agent", cmd_id=f"agent:{seq}:{D}", in_reply_to=seq,
                       valid_until_t_ns=now + int(valid_s * S), plant_id=D, q_kvar=q_kvar)


def test_frames_commands_acks_and_status_flow_over_the_bus(adapter, inverter):
    assert adapter.wait(lambda: len(adapter.received(m.PvFrame)) >= 2)
    frames = adapter.received(m.PvFrame)
    period = int(0.2 * S)
    assert all(f.t_ns % period == 0 for f in frames)  # stamped with the scan's time, aligned on the period
    assert [f.seq for f in frames] == sorted({f.seq for f in frames})
    assert frames[-1].p_kw == pytest.approx(600.0) and frames[-1].q_setpoint_kvar is None
    adapter.commands.put(_cmd(-150.0, seq=1, valid_s=600.0))
    assert adapter.wait(lambda: adapter.received(m.Ack))
    ack = adapter.received(m.Ack)[0]
    assert (ack.status, ack.applied_value, ack.cmd_id, ack.device_id) == ("accepted", -150.0, f"agent:1:{D}", D)
    assert inverter.q_command_kvar() == pytest.approx(-150.0)
    assert adapter.wait(lambda: any(f.q_setpoint_kvar == -150.0 for f in adapter.received(m.PvFrame)))
    assert adapter.wait(lambda: any(s.state == "ok" and s.commands == 1 for s in adapter.received(m.LinkStatus)))


def test_the_revert_timer_returns_the_plant_to_its_default_when_the_agent_and_adapter_stop(adapter, inverter):
    adapter.commands.put(_cmd(300.0, seq=1, valid_s=1.5))  # revert timer: 2 s (whole seconds, rounded up)
    assert adapter.wait(lambda: adapter.received(m.Ack))
    assert adapter.received(m.Ack)[0].status == "accepted"
    assert inverter.q_command_kvar() == pytest.approx(300.0)
    adapter.stop.set()  # nobody will ever tell the inverter to go back
    adapter.thread.join(20.0)
    assert not adapter.thread.is_alive()
    assert inverter.control_state()["VarSetRvrtTms"] == 2
    assert wait_for(lambda: inverter.q_command_kvar() is None, 5.0), "the inverter did not revert by itself"
    assert inverter.reverts == 1
    assert adapter.result[0].state == "ok"  # the last status of a clean stop


def test_a_lost_modbus_link_stops_frames_fails_commands_and_recovers(adapter, inverter):
    assert adapter.wait(lambda: adapter.received(m.PvFrame))
    inverter.stop()
    assert adapter.wait(lambda: any(s.state == "down" for s in adapter.received(m.LinkStatus)))
    down = next(s for s in adapter.received(m.LinkStatus) if s.state == "down")
    assert "did not answer" in down.reason or "no SunSpec device" in down.reason
    n_frames = len(adapter.received(m.PvFrame))
    adapter.commands.put(_cmd(100.0, seq=1, valid_s=600.0))
    assert adapter.wait(lambda: adapter.received(m.Ack))
    ack = adapter.received(m.Ack)[0]
    assert ack.status == "rejected" and ack.reason.startswith("link_down")
    # three scan periods down: not one frame (the scans fail: counted in the status)
    deadline_scans = down.scans + 3
    assert adapter.wait(lambda: any(s.scans >= deadline_scans for s in adapter.received(m.LinkStatus)))
    assert len(adapter.received(m.PvFrame)) == n_frames
    inverter.start()
    assert adapter.wait(lambda: len(adapter.received(m.PvFrame)) > n_frames, 15.0)
    assert adapter.wait(lambda: adapter.received(m.LinkStatus)[-1].state == "ok")
    adapter.commands.put(_cmd(100.0, seq=2, valid_s=600.0))
    assert adapter.wait(lambda: len(adapter.received(m.Ack)) == 2)
    assert adapter.received(m.Ack)[1].status == "accepted"
    assert adapter.received(m.LinkStatus)[-1].commands_failed == 1


def test_a_malformed_register_value_is_refused_counted_in_the_status_and_sends_no_frame(adapter, inverter):
    assert adapter.wait(lambda: adapter.received(m.PvFrame))
    inverter.set_raw(701, "V_SF", None)  # the voltage scale factor vanishes
    assert adapter.wait(lambda: any(s.state == "refusing" for s in adapter.received(m.LinkStatus)))
    refusing = next(s for s in adapter.received(m.LinkStatus) if s.state == "refusing")
    assert refusing.refused == {"701.V_SF": refusing.refused["701.V_SF"]} and refusing.refused["701.V_SF"] >= 1
    assert "701.V_SF" in refusing.reason
    n_frames = len(adapter.received(m.PvFrame))
    assert adapter.wait(lambda: any(s.refused.get("701.V_SF", 0) >= 3 for s in adapter.received(m.LinkStatus)))
    assert len(adapter.received(m.PvFrame)) == n_frames


def test_a_restarted_agent_counts_from_one_again_once_its_token_is_gone(adapter, router_endpoint):
    # the agent's token and commands from one session: the router passes them on in the order they were sent
    with open_session(BusConfig(mode="peer", connect=(router_endpoint,))) as agent_session:
        token = agent_session.liveliness().declare_token(keys.alive(F, "agent", "agent"))
        commands = TypedPublisher(agent_session, keys.cmd(F, "pv", D), m.PvCommand, reliable=True)
        assert commands.wait_matched(10.0)
        commands.put(_cmd(-50.0, seq=40, valid_s=600.0))
        assert adapter.wait(lambda: len(adapter.received(m.Ack)) == 1)
        commands.put(_cmd(-60.0, seq=1, valid_s=600.0))  # the same agent going backwards: a replay
        assert adapter.wait(lambda: len(adapter.received(m.Ack)) == 2)
        assert adapter.received(m.Ack)[1].reason.startswith("replay")
        token.undeclare()  # the agent stops; a new one starts its sequence at 1
        # the token's withdrawal and the command travel apart (liveliness vs put): resend until the adapter has
        # seen the withdrawal; without it every resend stays a replay
        deadline = time.monotonic() + 10.0
        while True:
            n = len(adapter.received(m.Ack))
            commands.put(_cmd(-70.0, seq=1, valid_s=600.0))
            assert adapter.wait(lambda n=n: len(adapter.received(m.Ack)) == n + 1)
            last = adapter.received(m.Ack)[-1]
            if last.status == "accepted" or time.monotonic() > deadline:
                break
            time.sleep(0.1)
        assert (last.status, last.applied_value) == ("accepted", -70.0), last.reason
        commands.undeclare()


def test_the_head_clock_scans_at_each_new_head_frame_and_times_commands_by_it(inverter, router_endpoint):
    from schemas.examples import example

    config = AdapterConfig(feeder_id=F, device_id=D, modbus=f"tcp/127.0.0.1:{inverter.port}", clock="head",
                           status_period_s=0.5, timeout_s=1.0)
    t0 = 1_672_549_200 * S  # a simulated day, far from the wall clock
    with open_session(BusConfig(mode="peer", connect=(router_endpoint,))) as session:
        inbox = Inbox()
        for key in (keys.meas_pv(F, D), keys.ack(F, "pv", D)):
            inbox.subscribe(session, key)
        heads = TypedPublisher(session, keys.meas_head(F), m.HeadFrame, reliable=True)
        commands = TypedPublisher(session, keys.cmd(F, "pv", D), m.PvCommand, reliable=True)
        stop, ready = threading.Event(), threading.Event()
        bus = BusConfig(mode="peer", connect=(router_endpoint,))
        thread = threading.Thread(target=run_adapter, args=(config, bus), kwargs=dict(stop=stop, ready=ready),
                                  daemon=True)
        thread.start()
        try:
            assert ready.wait(20.0) and heads.wait_matched(10.0) and commands.wait_matched(10.0)
            got: list = []

            def seen(pred) -> bool:
                def check() -> bool:
                    got.extend(r.msg for r in inbox.drain())
                    return bool(pred())
                return wait_for(check, 10.0, poll_s=0.02)

            head = example(m.HeadFrame)
            for i, seq in ((0, 1), (0, 2), (60, 3)):  # the repeated time makes no second scan
                heads.put(msgspec.structs.replace(head, feeder_id=F, t_ns=t0 + i * S, seq=seq))
            assert seen(lambda: [x.t_ns for x in got if isinstance(x, m.PvFrame)] == [t0, t0 + 60 * S])
            cmd = m.PvCommand(t_ns=t0 + 60 * S, seq=1, source="agent", cmd_id="agent:1:pv1", in_reply_to=3,
                              valid_until_t_ns=t0 + 180 * S, plant_id=D, q_kvar=-80.0)
            commands.put(cmd)  # valid for 120 s of the feeder's time: far in the wall clock's past
            assert seen(lambda: any(isinstance(x, m.Ack) for x in got))
            ack = next(x for x in got if isinstance(x, m.Ack))
            assert (ack.status, ack.applied_value, ack.t_ns) == ("accepted", -80.0, t0 + 60 * S)
            assert inverter.control_state()["VarSetRvrtTms"] == 120
            heads.put(msgspec.structs.replace(head, feeder_id=F, t_ns=t0 + 181 * S, seq=4))
            assert seen(lambda: any(isinstance(x, m.Ack) and x.status == "expired" for x in got))
        finally:
            stop.set()
            thread.join(20.0)
        assert not thread.is_alive()
