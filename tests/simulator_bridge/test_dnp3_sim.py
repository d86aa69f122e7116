"""The simulated regulator control and capacitor bank controller through a real DNP3 master over loopback TCP.

The master is the project's (adapters.dnp3.Dnp3Master on opendnp3); the devices' hold timers run on a clock
the test sets, so an expiry is an event the test causes, not a wait.
"""

from __future__ import annotations

import socket

import pytest

from adapters.dnp3 import Dnp3LinkError, Dnp3Master
from schemas.bus import wait_for
from simulator_bridge.field.dnp3_sim import (
    CapBankPoints,
    Dnp3SimError,
    RegulatorPoints,
    RemoteSetpoint,
    SimulatedCapBankController,
    SimulatedRegulatorControl,
    parse_dnp3_endpoint,
)

_OPEN_S = 10.0  # the bound on a channel opening on loopback [s]
_S = 10**9


@pytest.fixture
def regulator(regulator_outstation) -> SimulatedRegulatorControl:
    return regulator_outstation(v_compared_120=121.37, v_120=123.8, tap=3, load_current_a=210.5)


@pytest.fixture
def bank(bank_outstation) -> SimulatedCapBankController:
    return bank_outstation(v_v=2401.5)


def _master(device, *, retry_s: float = 0.5) -> Dnp3Master:
    master = Dnp3Master(device.endpoint, timeout_s=1.0, retry_s=retry_s)
    master.open()
    assert master.wait_open(_OPEN_S), f"no DNP3 channel to {device.endpoint} within {_OPEN_S} s"
    return master


def test_regulator_points_read_as_floats_and_a_set_point_by_select_before_operate_is_in_force_and_read_back(
        regulator: SimulatedRegulatorControl) -> None:
    with _master(regulator) as m:
        r = m.read()
        assert r.analog_inputs[RegulatorPoints.AI_V_COMPARED_120] == 121.37  # g30v6: the double, exactly
        assert r.analog_inputs[RegulatorPoints.AI_V_120] == 123.8
        assert r.analog_inputs[RegulatorPoints.AI_TAP] == 3.0
        assert r.analog_inputs[RegulatorPoints.AI_LOAD_CURRENT_A] == pytest.approx(210.5)
        assert r.analog_inputs[RegulatorPoints.AI_SETPOINT_120] == 120.0  # the local set point
        assert r.binary_inputs[RegulatorPoints.BI_REMOTE] is False
        assert not [p for p in r.offline if p.startswith("ai")]  # every analog input of the map is online

        assert m.operate_analog(RegulatorPoints.AO_HOLD_S, 600.0).ok
        assert m.operate_analog(RegulatorPoints.AO_BAND_120, 3.0).ok
        assert m.operate_analog(RegulatorPoints.AO_SETPOINT_120, 122.25).ok
        assert regulator.setpoint_in_force() == RemoteSetpoint(setpoint_v120=122.25, band_v120=3.0,
                                                               until_ns=1_600 * _S)
        r = m.read()
        assert r.analog_outputs[RegulatorPoints.AO_SETPOINT_120] == 122.25
        assert r.analog_outputs[RegulatorPoints.AO_HOLD_S] == 600.0
        assert r.analog_inputs[RegulatorPoints.AI_SETPOINT_120] == 122.25
        assert r.analog_inputs[RegulatorPoints.AI_BAND_120] == 3.0
        assert r.binary_inputs[RegulatorPoints.BI_REMOTE] is True
        assert regulator.operates == 3 and regulator.refused_operates == 0


def test_regulator_refuses_out_of_range_unknown_and_blocked_operates_counts_them_and_changes_nothing(
        regulator: SimulatedRegulatorControl) -> None:
    with _master(regulator) as m:
        # a set point before any hold time: blocked at select
        out = m.operate_analog(RegulatorPoints.AO_SETPOINT_120, 122.0)
        assert (out.status, out.state) == ("BLOCKED", "SELECT_FAIL")
        assert m.operate_analog(RegulatorPoints.AO_HOLD_S, 600.0).ok
        for index, value, select in ((RegulatorPoints.AO_SETPOINT_120, 999.0, True),
                                     (RegulatorPoints.AO_SETPOINT_120, float("nan"), False),
                                     (RegulatorPoints.AO_BAND_120, 0.0, True),
                                     (RegulatorPoints.AO_HOLD_S, 86_401.0, False)):
            out = m.operate_analog(index, value, select=select)
            assert out.status == "OUT_OF_RANGE", (index, value, out)
        assert m.operate_analog(7, 1.0, select=False).status == "NOT_SUPPORTED"
        assert m.operate_crob(0, close=True).status == "NOT_SUPPORTED"
        assert regulator.refused_operates == 7
        assert regulator.setpoint_in_force() is None
        assert regulator.analog_outputs == {RegulatorPoints.AO_SETPOINT_120: 120.0,
                                            RegulatorPoints.AO_BAND_120: 2.0, RegulatorPoints.AO_HOLD_S: 600.0}


def test_regulator_set_point_ends_in_the_device_at_its_hold_time_and_hold_zero_releases_it(
        regulator: SimulatedRegulatorControl, clock) -> None:
    with _master(regulator) as m:
        assert m.operate_analog(RegulatorPoints.AO_HOLD_S, 300.0).ok
        assert m.operate_analog(RegulatorPoints.AO_SETPOINT_120, 123.0).ok
        clock.t_ns += 300 * _S  # the set point holds up to and including its deadline
        regulator.tick()
        assert regulator.setpoint_in_force() is not None
    clock.t_ns += 1  # no master any more: the device ends the set point on its own
    regulator.tick()
    assert regulator.setpoint_in_force() is None and regulator.expiries == 1
    # the device closes a new connection while it still holds the first master's (CloseNew): on a loaded machine
    # it may not have seen that one close yet
    assert wait_for(lambda: not regulator.master_connected, _OPEN_S), "the device still holds the first master"
    with _master(regulator) as m:
        r = m.read()
        assert r.binary_inputs[RegulatorPoints.BI_REMOTE] is False
        assert r.analog_inputs[RegulatorPoints.AI_SETPOINT_120] == 120.0
        assert m.operate_analog(RegulatorPoints.AO_SETPOINT_120, 123.0).ok
        assert regulator.setpoint_in_force() is not None
        assert m.operate_analog(RegulatorPoints.AO_HOLD_S, 0.0).ok
        assert regulator.setpoint_in_force() is None


def test_bank_switch_takes_select_before_operate_only_holds_then_returns_to_local_control(
        bank: SimulatedCapBankController, clock) -> None:
    with _master(bank) as m:
        r = m.read()
        assert r.binary_inputs[CapBankPoints.BI_CLOSED] is False
        assert r.analog_inputs[CapBankPoints.AI_V] == pytest.approx(2401.5)
        assert m.operate_crob(CapBankPoints.BO_SWITCH, close=True).status == "BLOCKED"  # no hold time yet
        assert m.operate_analog(CapBankPoints.AO_HOLD_S, 900.0).ok
        out = m.operate_crob(CapBankPoints.BO_SWITCH, close=True, select=False)
        assert out.status == "NOT_SUPPORTED"  # direct operate refused
        assert bank.commanded_closed() is None
        assert m.operate_crob(CapBankPoints.BO_SWITCH, close=True).ok
        assert bank.commanded_closed() is True
        bank.set_measurements(closed=True, v_v=2440.0, control_value=None)  # the simulator closed it
        r = m.read()
        assert r.binary_inputs[CapBankPoints.BI_CLOSED] is True
        assert r.binary_inputs[CapBankPoints.BI_REMOTE] is True
        assert r.binary_outputs[CapBankPoints.BO_SWITCH] is True
        assert m.operate_crob(CapBankPoints.BO_SWITCH, close=False).ok
        assert bank.commanded_closed() is False
        assert m.operate_crob(3, close=True).status == "NOT_SUPPORTED"
        assert bank.refused_operates == 3 and bank.operates == 3
        clock.t_ns += 900 * _S + 1
        bank.tick()
        assert bank.commanded_closed() is None
        assert m.read().binary_inputs[CapBankPoints.BI_REMOTE] is False


def test_a_lost_link_fails_reads_and_operates_and_the_master_reconnects_when_the_device_is_back(
        regulator: SimulatedRegulatorControl) -> None:
    with _master(regulator) as m:
        assert m.operate_analog(RegulatorPoints.AO_HOLD_S, 600.0).ok
        regulator.stop()
        with pytest.raises(Dnp3LinkError, match="FAILURE_NO_COMMS|no answer"):
            m.read()
        with pytest.raises(Dnp3LinkError):
            m.operate_analog(RegulatorPoints.AO_SETPOINT_120, 122.0)
        assert not m.link_up
        regulator.start()
        assert m.wait_open(_OPEN_S)
        r = m.read()
        assert r.analog_outputs[RegulatorPoints.AO_HOLD_S] == 600.0  # the device kept its state
        assert m.operate_analog(RegulatorPoints.AO_SETPOINT_120, 122.0).ok


def test_malformed_frames_get_no_answer_and_the_outstation_keeps_serving(
        regulator: SimulatedRegulatorControl) -> None:
    host, port = parse_dnp3_endpoint(regulator.endpoint)
    frames = (b"\x00" * 64, b"\x05\x64\xff\xc4\x0a\x00\x01\x00\xde\xad" + b"\xff" * 40,  # bad CRC
              b"\x05\x64\x05\xc9\x0a\x00\x01\x00", b"GET / HTTP/1.0\r\n\r\n")
    for frame in frames:
        with socket.create_connection((host, port), timeout=_OPEN_S) as s:
            s.sendall(frame)
    # the device closes a new connection while it still holds the last raw one (CloseNew)
    assert wait_for(lambda: not regulator.master_connected, _OPEN_S), "the device still holds a raw connection"
    with _master(regulator) as m:
        assert m.read().analog_inputs[RegulatorPoints.AI_TAP] == 3.0
        assert m.operate_analog(RegulatorPoints.AO_HOLD_S, 60.0).ok


def test_a_second_connection_is_closed_by_the_device_while_its_master_is_connected(
        regulator: SimulatedRegulatorControl) -> None:
    host, port = parse_dnp3_endpoint(regulator.endpoint)
    with _master(regulator, retry_s=60.0) as first:  # a link lost here would stay down for the whole test
        assert first.operate_analog(RegulatorPoints.AO_HOLD_S, 600.0).ok
        with socket.create_connection((host, port), timeout=_OPEN_S) as rogue:
            rogue.settimeout(_OPEN_S)
            assert rogue.recv(16) == b""  # closed by the outstation (a kept connection would time out here)
        assert first.link_up
        assert first.operate_analog(RegulatorPoints.AO_SETPOINT_120, 122.0).ok


@pytest.mark.parametrize("endpoint", ["tcp/10.0.0.1:20000", "tcp/127.0.0.1:0", "tcp/127.0.0.1:x", "udp/127.0.0.1:1",
                                      "127.0.0.1:20000", "tcp/127.0.0.1:70000"])
def test_only_a_loopback_tcp_endpoint_is_taken(endpoint: str) -> None:
    with pytest.raises(Dnp3SimError, match="tcp/127.0.0.1:PORT|port"):
        parse_dnp3_endpoint(endpoint)


@pytest.mark.parametrize("kwargs", [dict(default_setpoint_v120=150.0), dict(default_band_v120=0.0),
                                    dict(tap_max=0), dict(host="0.0.0.0")])
def test_a_regulator_outside_its_ranges_is_refused_at_build(kwargs: dict) -> None:
    args = dict(regulator_id="r", tap_max=16, default_setpoint_v120=120.0, default_band_v120=2.0, port=20000)
    with pytest.raises(Dnp3SimError):
        SimulatedRegulatorControl(**{**args, **kwargs})


def test_a_bank_of_several_steps_is_refused_at_build() -> None:
    with pytest.raises(Dnp3SimError, match="one step"):
        SimulatedCapBankController(capacitor_id="c", port=20000, steps=2)
