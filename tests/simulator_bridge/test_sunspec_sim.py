"""The simulated SunSpec inverter, read and written over real Modbus TCP by pysunspec2's own client."""

from __future__ import annotations

import pytest
import sunspec2.modbus.client as sunspec_client
from sunspec2.modbus.modbus import ModbusClientError, ModbusClientException

from schemas.bus import free_port
from simulator_bridge.field.sunspec_sim import SimulatedSunSpecInverter, SunSpecSimError


@pytest.fixture
def inverter(clock):
    inv = SimulatedSunSpecInverter(plant_id="pv1", s_rated_kva=1860.0, v_nominal_v=7200.0, port=free_port(),
                                   clock_ns=clock)
    inv.set_measurements(p_kw=[400.0, 410.0, 420.0], v_v=[7250.0, 7260.0, 7270.0])
    with inv:
        yield inv


@pytest.fixture
def client(inverter):
    dev = sunspec_client.SunSpecModbusClientDeviceTCP(slave_id=1, ipaddr="127.0.0.1", ipport=inverter.port,
                                                      timeout=1.0)
    dev.scan()
    dev.connect()
    yield dev
    dev.disconnect()


def _set_var(client, var: float, revert_s: int = 0) -> None:
    ctl = client.DERCtlAC[0]
    ctl.VarSet.cvalue = var
    ctl.VarSetRvrtTms.value = revert_s
    ctl.write()
    ctl.VarSetEna.value = 1
    ctl.VarSetEna.write()


def test_scan_finds_the_models_and_values_round_trip_with_scale_factors(client):
    assert {1, 701, 702, 704} <= set(client.models)
    assert client.common[0].SN.value == "pv1"
    meas = client.DERMeasureAC[0]
    assert meas.W.cvalue == pytest.approx(1_230_000.0)  # W_SF = 2 for 1860 kVA: 100 W steps
    assert [meas.WL1.cvalue, meas.WL2.cvalue, meas.WL3.cvalue] == [400_000.0, 410_000.0, 420_000.0]
    assert [meas.VL1.cvalue, meas.VL2.cvalue, meas.VL3.cvalue] == [7250, 7260, 7270]
    assert client.DERCapacity[0].VAMax.cvalue == 1_860_000.0
    assert client.DERCtlAC[0].VarSetEna.value == 0  # local default until told otherwise


def test_a_written_set_point_is_held_and_the_output_follows_it(client, inverter):
    _set_var(client, -300_000.0)
    assert inverter.q_command_kvar() == pytest.approx(-300.0)
    inverter.set_measurements(p_kw=[400.0, 410.0, 420.0], v_v=[7250.0] * 3)  # Q: the set point in force
    meas = client.DERMeasureAC[0]
    meas.read()
    assert meas.Var.cvalue == pytest.approx(-300_000.0)
    ctl = client.DERCtlAC[0]
    ctl.read()
    assert (ctl.VarSetEna.value, ctl.VarSet.cvalue) == (1, -300_000)


def test_the_set_point_is_clipped_to_the_headroom_at_the_present_output(client, inverter):
    _set_var(client, 1_800_000.0)  # within VarMaxInj, beyond sqrt(1860² - 1230²) = 1395.2 kvar
    assert inverter.q_command_kvar() == pytest.approx((1860.0**2 - 1230.0**2) ** 0.5)
    inverter.set_measurements(p_kw=[0.0] * 3, v_v=[7250.0] * 3)  # night: no reactive power
    assert inverter.q_command_kvar() == 0.0


def test_a_set_point_beyond_the_rating_is_refused_and_changes_nothing(client, inverter):
    _set_var(client, -100_000.0)
    ctl = client.DERCtlAC[0]
    ctl.VarSet.cvalue = -2_000_000.0  # beyond VarMaxAbs = 1860 kvar
    with pytest.raises(ModbusClientException, match="3"):
        ctl.VarSet.write()
    assert inverter.refused_writes == 1
    assert inverter.q_command_kvar() == pytest.approx(-100.0)
    ctl.read()
    assert ctl.VarSet.cvalue == -100_000


def test_writes_outside_704s_settings_are_refused(client, inverter):
    meas = client.DERMeasureAC[0]
    meas.W.value = 1
    with pytest.raises(ModbusClientException, match="2"):  # illegal address: measurements are read-only
        meas.W.write()
    ctl = client.DERCtlAC[0]
    ctl.VarSetMod.value = 0  # percent of WMax: this inverter takes vars only
    ctl.VarSetEna.value = 1
    with pytest.raises(ModbusClientException, match="3"):
        ctl.write()
    assert inverter.refused_writes == 2
    assert inverter.q_command_kvar() is None


def test_the_revert_timer_returns_the_inverter_to_its_default_by_itself(client, inverter, clock):
    _set_var(client, 250_000.0, revert_s=60)
    clock.t_ns += 59_000_000_000
    assert inverter.q_command_kvar() == pytest.approx(250.0)
    ctl = client.DERCtlAC[0]
    ctl.read()
    assert ctl.VarSetRvrtRem.value == 1
    clock.t_ns += 1_000_000_000  # the deadline itself: still in force, as a command up to its valid_until
    assert inverter.q_command_kvar() == pytest.approx(250.0)
    clock.t_ns += 1  # past it: the timer has run out, and nobody wrote anything
    assert inverter.q_command_kvar() is None
    assert inverter.reverts == 1
    ctl.read()
    assert (ctl.VarSetEna.value, ctl.VarSetRvrtRem.value) == (0, 0)


def test_the_reversion_value_is_taken_when_reversion_is_enabled(client, inverter, clock):
    ctl = client.DERCtlAC[0]
    ctl.VarSetRvrt.cvalue = -50_000.0
    ctl.VarSetEnaRvrt.value = 1
    ctl.write()
    _set_var(client, 250_000.0, revert_s=10)
    clock.t_ns += 10_000_000_001
    assert inverter.q_command_kvar() == pytest.approx(-50.0)


def test_a_stopped_server_is_a_lost_link_and_a_restart_brings_it_back(client, inverter):
    inverter.stop()
    with pytest.raises(ModbusClientError):
        client.DERMeasureAC[0].read()
    client.disconnect()
    inverter.start()
    client.DERMeasureAC[0].read()
    assert client.DERMeasureAC[0].W.cvalue == pytest.approx(1_230_000.0)


@pytest.mark.parametrize("kwargs", [dict(s_rated_kva=0.0), dict(v_nominal_v=float("nan")), dict(phases=("a", "a"))])
def test_a_bad_rating_is_refused_at_construction(kwargs):
    base = dict(plant_id="pv1", s_rated_kva=100.0, v_nominal_v=240.0, port=free_port())
    with pytest.raises(SunSpecSimError):
        SimulatedSunSpecInverter(**{**base, **kwargs})


def _client(inverter) -> sunspec_client.SunSpecModbusClientDeviceTCP:
    dev = sunspec_client.SunSpecModbusClientDeviceTCP(slave_id=1, ipaddr="127.0.0.1", ipport=inverter.port,
                                                      timeout=1.0)
    dev.scan()
    dev.connect()
    return dev


def test_only_the_registered_master_may_write_another_connection_gets_an_exception_counted_logged_once(
        client, inverter, caplog):
    """The first connection is the inverter's one Modbus master (its adapter's); a second connection may read but its
    writes are refused with exception 1 and change nothing. Before, any connection's write was taken."""
    _set_var(client, 250_000.0)
    rogue = _client(inverter)
    try:
        rogue.DERMeasureAC[0].read()  # reading is open to all
        assert rogue.DERMeasureAC[0].W.cvalue == pytest.approx(1_230_000.0)
        with caplog.at_level("WARNING", logger="simulator_bridge.field.sunspec_sim"):
            for var in (-800_000.0, 0.0):
                ctl = rogue.DERCtlAC[0]
                ctl.VarSet.cvalue = var
                with pytest.raises(ModbusClientException, match="1"):  # illegal function
                    ctl.VarSet.write()
                with pytest.raises(ModbusClientException, match="1"):
                    ctl.VarSetEna.write()
        assert inverter.q_command_kvar() == pytest.approx(250.0)  # the master's set point stands
        assert inverter.foreign_master_writes == 4 and inverter.refused_writes == 0
        assert caplog.text.count("not the registered master") == 1
        _set_var(client, 100_000.0)  # the master still writes
        assert inverter.q_command_kvar() == pytest.approx(100.0)
        client.disconnect()  # the master goes: the connection still open does not take its place ...
        with pytest.raises(ModbusClientException, match="1"):
            rogue.DERCtlAC[0].VarSetEna.write()
        again = _client(inverter)  # ... the next one to open does (an adapter that reconnects)
        try:
            _set_var(again, 50_000.0)
            assert inverter.q_command_kvar() == pytest.approx(50.0) and inverter.foreign_master_writes == 5
        finally:
            again.disconnect()
    finally:
        rogue.disconnect()


def test_an_inverter_without_the_master_setting_takes_any_connections_write(clock):
    with SimulatedSunSpecInverter(plant_id="pv1", s_rated_kva=1860.0, v_nominal_v=7200.0, port=free_port(),
                                  clock_ns=clock, single_master=False) as inverter:
        first, second = _client(inverter), _client(inverter)
        try:
            _set_var(second, 250_000.0)
            assert inverter.var_setpoint_kvar() == pytest.approx(250.0) and inverter.foreign_master_writes == 0
        finally:
            first.disconnect()
            second.disconnect()
