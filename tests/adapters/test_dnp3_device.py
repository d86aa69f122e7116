"""The DNP3 device adapter (adapters/dnp3_device.py) against the simulated outstations over real TCP on loopback,
without the bus: frames, commands operated and read back, refused values, a lost link, a rogue master's operate.

The outstations' hold timers and the adapter share one clock the test sets.
"""

from __future__ import annotations

import time

import pytest

from adapters.dnp3 import Dnp3Master
from adapters.dnp3_device import Dnp3Device, Dnp3DeviceSettings
from schemas import messages as m
from simulator_bridge.field.dnp3_sim import RegulatorPoints

S = 1_000_000_000
PERIOD_NS = 300 * S
_OPEN_S = 10.0


@pytest.fixture
def reg_sim(regulator_outstation):
    return regulator_outstation(v_compared_120=121.5, v_120=123.5, tap=4, load_current_a=180.0)


@pytest.fixture
def cap_sim(bank_outstation):
    return bank_outstation(v_v=2400.0)


def _device(sim, kind: str) -> Dnp3Device:
    master = Dnp3Master(sim.endpoint, timeout_s=1.0)
    master.open()
    assert master.wait_open(_OPEN_S)
    settings = Dnp3DeviceSettings(feeder_id="f1", device_id="reg1" if kind == "vr" else "cap1", kind=kind,
                                  control_period_ns=PERIOD_NS, phase="b", kvar_rated=600.0)
    return Dnp3Device(settings, master)


@pytest.fixture
def reg(reg_sim):
    dev = _device(reg_sim, "vr")
    yield dev
    dev.master.close()


@pytest.fixture
def cap(cap_sim):
    dev = _device(cap_sim, "cap")
    yield dev
    dev.master.close()


def _reg_cmd(sp: float, now: int, *, seq: int = 1, valid_s: float = 600.0, band: float = 2.5) -> m.RegCommand:
    return m.RegCommand(t_ns=now, seq=seq, source="agent", cmd_id=f"agent:{seq}:reg1", in_reply_to=seq,
                        valid_until_t_ns=now + int(valid_s * S), regulator_id="reg1",
                        action=m.SetpointAction(setpoint_v120=sp, band_v120=band))


def _cap_cmd(steps: int | None, now: int, *, seq: int = 1, valid_s: float = 600.0) -> m.CapCommand:
    return m.CapCommand(t_ns=now, seq=seq, source="agent", cmd_id=f"agent:{seq}:cap1", in_reply_to=seq,
                        valid_until_t_ns=now + int(valid_s * S), capacitor_id="cap1", closed_steps=steps)


def test_a_regulator_read_makes_its_frame_and_a_set_point_is_operated_read_back_and_acked(reg, reg_sim, clock):
    now = clock.t_ns
    frame = reg.scan(now)
    assert isinstance(frame, m.RegFrame) and reg.state == "ok"
    assert (frame.regulator_id, frame.tap, frame.setpoint_v120, frame.band_v120) == ("reg1", 4, 120.0, 2.0)
    assert (frame.v_compared_120, frame.phases[0].v_120, frame.phases[0].phase) == (121.5, 123.5, "b")
    ack = reg.command(_reg_cmd(122.25, now), now)
    assert (ack.status, ack.applied_value) == ("accepted", 122.25)
    held = reg_sim.setpoint_in_force()
    assert held is not None and (held.setpoint_v120, held.band_v120) == (122.25, 2.5)
    assert held.until_ns == now + 600 * S  # the hold follows the command's validity
    frame = reg.scan(now + 60 * S)
    assert frame is not None and (frame.setpoint_v120, frame.band_v120) == (122.25, 2.5)
    # a tap command is refused before anything is operated
    tap = m.RegCommand(t_ns=now, seq=2, source="agent", cmd_id="agent:2:reg1", in_reply_to=2,
                       valid_until_t_ns=now + 600 * S, regulator_id="reg1", action=m.TapAction(tap=3))
    assert reg.command(tap, now).reason.startswith("device_refused")
    assert reg_sim.operates == 3 and reg.foreign_writes == 0


def test_the_set_point_ends_in_the_device_and_the_adapter_acks_expired(reg, reg_sim, clock):
    now = clock.t_ns
    reg.scan(now)
    assert reg.command(_reg_cmd(123.0, now, valid_s=300.0), now).status == "accepted"
    clock.t_ns = now + 300 * S + 1
    reg_sim.tick()
    assert reg_sim.setpoint_in_force() is None
    ack = reg.expired(clock.t_ns)
    assert ack is not None and ack.status == "expired"
    frame = reg.scan(clock.t_ns)
    assert frame is not None and frame.setpoint_v120 == 120.0 and reg.foreign_writes == 0


def test_a_bank_is_switched_by_select_before_operate_acked_and_released(cap, cap_sim, clock):
    now = clock.t_ns
    frame = cap.scan(now)
    assert isinstance(frame, m.CapFrame) and (frame.closed_steps, frame.mode) == (0, "local")
    ack = cap.command(_cap_cmd(1, now), now)
    assert (ack.status, ack.applied_value) == ("accepted", 1.0)
    assert cap_sim.commanded_closed() is True
    cap_sim.set_measurements(closed=True, v_v=2450.0, control_value=None)
    frame = cap.scan(now + 60 * S)
    assert frame is not None and (frame.closed_steps, frame.mode) == (1, "commanded")
    assert cap.command(_cap_cmd(2, now, seq=2), now).reason.startswith("out_of_range")
    assert cap.command(_cap_cmd(None, now, seq=3), now).status == "accepted"
    assert cap_sim.commanded_closed() is None


@pytest.mark.parametrize(("measurements", "point"), [
    (dict(v_compared_120=121.0, v_120=122.0, tap=20, load_current_a=1.0), "ai1"),
    (dict(v_compared_120=121.0, v_120=122.0, tap=1, load_current_a=-5.0), "ai2"),
    (dict(v_compared_120=float("nan"), v_120=122.0, tap=1, load_current_a=1.0), "ai0"),
    (dict(v_compared_120=250.0, v_120=122.0, tap=1, load_current_a=1.0), "ai0"),
    (dict(v_compared_120=121.0, v_120=-1.0, tap=1, load_current_a=1.0), "ai5"),
])
def test_a_value_out_of_range_is_refused_by_point_and_gives_no_frame(reg, reg_sim, clock, measurements, point):
    reg_sim.set_measurements(**measurements)
    assert reg.scan(clock.t_ns) is None
    assert reg.state == "refusing" and reg.refused == {point: 1}
    status = reg.status(clock.t_ns)
    assert (status.kind, status.protocol, status.state, status.refused) == ("vr", "dnp3", "refusing", {point: 1})


def test_a_lost_link_gives_no_frame_rejects_commands_and_recovers(reg, reg_sim, clock):
    now = clock.t_ns
    assert reg.scan(now) is not None
    reg_sim.stop()
    assert reg.scan(now) is None and reg.state == "down"
    assert reg.command(_reg_cmd(122.0, now), now).reason.startswith("link_down")
    assert reg.status(now).state == "down"
    reg_sim.start()
    assert reg.master.wait_open(_OPEN_S)
    assert reg.scan(now) is not None and reg.state == "ok"
    assert reg.command(_reg_cmd(122.0, now, seq=2), now).status == "accepted"


def test_a_rogue_masters_operate_is_found_at_the_next_read_counted_and_undone(reg, reg_sim, clock):
    now = clock.t_ns
    reg.scan(now)
    assert reg.command(_reg_cmd(122.0, now), now).status == "accepted"
    reg.master.close()  # the adapter's link is away: another master gets the device
    with Dnp3Master(reg_sim.endpoint, timeout_s=1.0) as rogue:
        assert rogue.wait_open(_OPEN_S)
        assert rogue.operate_analog(RegulatorPoints.AO_SETPOINT_120, 130.0).ok
    assert reg_sim.setpoint_in_force().setpoint_v120 == 130.0
    reg.master.open()
    assert reg.master.wait_open(_OPEN_S)
    # the next read that reaches the device (on a loaded machine the first one after the link reopens can fail:
    # FAILURE_NO_COMMS, no frame, nothing read)
    deadline = time.monotonic() + _OPEN_S
    while (frame := reg.scan(now + 60 * S)) is None and time.monotonic() < deadline:
        time.sleep(0.1)
    assert reg.foreign_writes == 1 and "foreign write" in reg.reason
    assert reg_sim.setpoint_in_force().setpoint_v120 == 122.0  # ours again
    assert frame is not None and frame.setpoint_v120 == 122.0
    assert reg.scan(now + 120 * S) is not None and reg.foreign_writes == 1


def test_a_set_point_the_device_refuses_is_rejected_with_its_status_and_counted_by_point(regulator_outstation, clock):
    sim = regulator_outstation(setpoint_range_v120=(114.0, 126.0),  # a control with narrower limits
                               v_compared_120=121.5, v_120=123.5, tap=4, load_current_a=180.0)
    dev = _device(sim, "vr")
    try:
        now = clock.t_ns
        assert dev.scan(now) is not None
        ack = dev.command(_reg_cmd(130.0, now), now)  # within the command contract, beyond the device's
        assert ack.status == "rejected" and ack.reason.startswith("device_refused")
        assert "OUT_OF_RANGE" in ack.reason
        assert dev.refused == {"ao0:OUT_OF_RANGE": 1} and dev.commands_failed == 1
        assert sim.setpoint_in_force() is None and sim.refused_operates == 1
        assert dev.command(_reg_cmd(125.0, now, seq=2), now).status == "accepted"
    finally:
        dev.master.close()
