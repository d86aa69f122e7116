"""The bridge's DNP3 outstations (``Dnp3Fleet``) on real feeders, driven through a real DNP3 master over loopback.

The outstations run on the fleet's clock (the simulation's time), so a hold ends when the test moves that clock.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from adapters.dnp3 import Dnp3Master
from schemas.bus import free_port
from schemas.devicemap import load_device_map
from simulator_bridge.bus.adapter_frames import AdapterFrames
from simulator_bridge.bus.dnp3_fleet import Dnp3Fleet, regulator_phases
from simulator_bridge.errors import BridgeError
from simulator_bridge.field.dnp3_sim import CapBankPoints, RegulatorPoints
from simulator_bridge.opendss.engine import FeederEngine

REPO = Path(__file__).resolve().parents[2]
_OPEN_S = 10.0  # the bound on a channel opening on loopback [s]
_S = 10**9
T0 = 1_700_000_000 * _S


@pytest.fixture(scope="module")
def engine123():
    engine = FeederEngine(load_device_map(REPO / "feeders" / "ieee123.toml"))
    yield engine
    engine.close()


@pytest.fixture
def fleet(engine123):
    fleet = Dnp3Fleet({"creg1a": f"tcp/127.0.0.1:{free_port()}", "c83": f"tcp/127.0.0.1:{free_port()}"}, engine123)
    fleet.start()
    yield fleet
    fleet.close()


def _master(fleet: Dnp3Fleet, device: str) -> Dnp3Master:
    sims = {d: sim for d, (_, sim) in [*fleet.regs.items(), *fleet.caps.items()]}
    master = Dnp3Master(sims[device].endpoint, timeout_s=1.0)
    master.open()
    assert master.wait_open(_OPEN_S), f"no DNP3 channel to {device} within {_OPEN_S} s"
    return master


def test_the_step_written_is_what_the_master_reads(fleet, engine123):
    r = engine123.regulator_ids.index("creg1a")
    n_reg, n_cap = len(engine123.regulator_ids), len(engine123.capacitor_ids)
    v_cmp, v_raw = np.full(n_reg, 118.0), np.full(n_reg, 250.0)  # a raw voltage past the frames' ceiling: clipped
    v_cmp[r] = 121.123456789
    fleet.measure(T0, v_compared_120=v_cmp, v_120=v_raw, taps=np.full(n_reg, 3), cap_states=np.ones(n_cap, int),
                  cap_v_v=np.full(n_cap, 2401.25), cap_control_value=np.full(n_cap, np.nan))
    with _master(fleet, "creg1a") as m:
        a = m.read().analog_inputs
        assert (a[RegulatorPoints.AI_V_COMPARED_120], a[RegulatorPoints.AI_V_120], a[RegulatorPoints.AI_TAP]) == (
            121.123456789, 200.0, 3.0)
    with _master(fleet, "c83") as m:
        reading = m.read()
        assert reading.binary_inputs[CapBankPoints.BI_CLOSED] is True
        assert (reading.analog_inputs[CapBankPoints.AI_V], reading.analog_inputs[CapBankPoints.AI_CONTROL_VALUE]) == (
            2401.25, 0.0)
    assert fleet.masters_connected() is False  # both masters left


def test_what_the_outstations_hold_reaches_the_simulation_once_and_ends_at_its_hold(fleet, engine123):
    r, c = engine123.regulator_ids.index("creg1a"), engine123.capacitor_ids.index("c83")
    fleet.set_clock(T0)
    assert fleet.commands(T0) == ({}, {})  # local control, as the simulation starts
    with _master(fleet, "creg1a") as m:
        for index, value in ((RegulatorPoints.AO_HOLD_S, 300.0), (RegulatorPoints.AO_BAND_120, 2.5),
                             (RegulatorPoints.AO_SETPOINT_120, 122.4)):
            assert m.operate_analog(index, value).ok
    with _master(fleet, "c83") as m:
        assert m.operate_analog(CapBankPoints.AO_HOLD_S, 120.0).ok
        assert m.operate_crob(CapBankPoints.BO_SWITCH, close=True).ok
    assert fleet.commands(T0 + 60 * _S) == ({r: (122.4, 2.5)}, {c: 1})
    assert fleet.commands(T0 + 120 * _S) == ({}, {})  # unchanged: nothing handed again
    assert fleet.commands(T0 + 180 * _S) == ({}, {c: None})  # the bank's hold ran out on the simulation's clock
    assert fleet.commands(T0 + 301 * _S) == ({r: None}, {})  # then the regulator's


def test_devices_the_feeder_lacks_and_bad_endpoints_are_refused(engine123):
    with pytest.raises(BridgeError, match="neither as regulator nor as bank"):
        Dnp3Fleet({"reg9": "tcp/127.0.0.1:20000"}, engine123)
    with pytest.raises(BridgeError, match="loopback only"):
        Dnp3Fleet({"creg1a": "tcp/10.0.0.1:20000"}, engine123)


def test_regulator_phases_are_their_secondary_nodes(engine123):
    phases = dict(zip(engine123.regulator_ids, regulator_phases(engine123), strict=True))
    assert (phases["creg1a"], phases["creg3c"], phases["creg4b"]) == ("a", "c", "b")


def test_adapter_frames_wait_for_every_device_then_not_for_a_lagging_one():
    frames = AdapterFrames({("pv", "pv1"): "sunspec", ("vr", "reg1"): "dnp3", ("cap", "cap1"): "dnp3"})
    for kind, device in (("pv", "pv1"), ("vr", "reg1")):
        frames.on_frame(kind, device, 60)
    frames.on_frame("vr", "other", 60)  # not behind an adapter: ignored
    assert not frames.frames_in(60)
    assert frames.missed(60) == ["cap/cap1"] and dict(frames.misses) == {"dnp3": 1}
    frames.on_frame("pv", "pv1", 120)
    frames.on_frame("vr", "reg1", 120)
    assert frames.frames_in(120)  # the lagging bank is not waited for
    frames.on_frame("cap", "cap1", 180)
    assert not frames.frames_in(180) and frames.lagging == set()  # back in the wait once its frame came
