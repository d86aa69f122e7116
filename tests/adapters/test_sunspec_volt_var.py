"""Model 705 (DER volt-var) read by the adapter from a simulated inverter over real Modbus TCP: the plant's local
default comes from the inverter when it has 705, every curve value is checked, and bad ones are refused and counted.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from adapters.errors import RegisterValueError
from adapters.sunspec import SunSpecLink
from adapters.sunspec_plant import PlantSettings, SunSpecPlant
from schemas.bus import free_port
from simulator_bridge.field.sunspec_sim import SimulatedSunSpecInverter
from simulator_bridge.simulation.qsts import IEEE1547_CAT_B_Q_PU, IEEE1547_CAT_B_V_PU

PERIOD_NS = 300 * 1_000_000_000


def _inverter(volt_var: bool) -> SimulatedSunSpecInverter:
    inv = SimulatedSunSpecInverter(plant_id="pv1", s_rated_kva=1000.0, v_nominal_v=7200.0, port=free_port(),
                                   volt_var=volt_var)
    inv.set_measurements(p_kw=[200.0] * 3, v_v=[7250.0] * 3)
    return inv


def _plant(inv: SimulatedSunSpecInverter, local_mode: str) -> SunSpecPlant:
    return SunSpecPlant(PlantSettings(feeder_id="f1", device_id="pv1", control_period_ns=PERIOD_NS,
                                      local_mode=local_mode),  # type: ignore[arg-type]
                        SunSpecLink("127.0.0.1", inv.port, timeout_s=2.0))


@pytest.fixture
def vv_inverter() -> Iterator[SimulatedSunSpecInverter]:
    with _inverter(True) as inv:
        yield inv


@pytest.mark.parametrize(("enabled", "configured", "reported"), [
    (True, "unity_pf", "volt_var"),   # 705 says what the inverter does, whatever the adapter was told
    (False, "volt_var", "unity_pf"),
])
def test_the_local_mode_in_the_frames_is_the_inverters_705(enabled, configured, reported):
    with _inverter(enabled) as inv:
        plant = _plant(inv, configured)
        try:
            frame = plant.scan(0)
            assert frame is not None and frame.local_mode == reported
            curve = plant.last.volt_var  # type: ignore[union-attr]
            # the curve it holds is the simulated plants' own: IEEE 1547-2018 category B
            assert curve.enabled is enabled
            assert curve.v_pu == pytest.approx(IEEE1547_CAT_B_V_PU) and curve.q_pu == pytest.approx(IEEE1547_CAT_B_Q_PU)
        finally:
            plant.link.close()


def test_without_705_the_configured_local_mode_is_reported(inverter):  # conftest's inverter: models 1-704 only
    plant = _plant(inverter, "volt_var")
    try:
        frame = plant.scan(0)
        assert frame is not None and frame.local_mode == "volt_var" and plant.last.volt_var is None  # type: ignore[union-attr]
    finally:
        plant.link.close()


@pytest.mark.parametrize(("point", "raw", "refused"), [
    ("Ena", 7, "705.Ena"),                 # an enum value 705 does not define
    ("V_SF", None, "705.V_SF"),            # a scale factor not implemented
    ("Crv.DeptRef", 0, "705.DeptRef"),     # Var in percent of WMax: not understood, so not guessed
    ("Crv.ActPt", 9, "705.ActPt"),         # more active points than the curve has
    ("Crv.Pt.2.V", 97, "705.Pt.V"),        # 92, 98, 97, 108 %: voltages that do not rise
    ("Crv.Pt.0.Var", 20_000, "705.Pt.Var"),  # 200 % of VarMax
    ("Crv.Pt.1.Var", None, "705.Pt2"),     # a curve point not implemented
])
def test_a_malformed_705_value_is_refused_counted_and_gives_no_frame(vv_inverter, point, raw, refused):
    plant = _plant(vv_inverter, "unity_pf")
    try:
        assert plant.scan(0) is not None
        vv_inverter.set_raw(705, point, raw)
        with pytest.raises(RegisterValueError, match=refused.replace(".", r"\.")):
            plant.link.read()
        assert plant.scan(PERIOD_NS) is None
        assert plant.state == "refusing" and plant.refused == {refused: 1}
        assert plant.status(PERIOD_NS).refused == {refused: 1}
    finally:
        plant.link.close()


def _setting_plant(inv: SimulatedSunSpecInverter, local_mode: str, set_local_mode: bool) -> SunSpecPlant:
    return SunSpecPlant(PlantSettings(feeder_id="f1", device_id="pv1", control_period_ns=PERIOD_NS,
                                      local_mode=local_mode, set_local_mode=set_local_mode),  # type: ignore[arg-type]
                        SunSpecLink("127.0.0.1", inv.port, timeout_s=2.0))


@pytest.mark.parametrize(("start", "configured"), [(False, "volt_var"), (True, "unity_pf")])
def test_set_local_mode_writes_705_ena_when_the_inverter_is_otherwise(start, configured):
    with _inverter(start) as inv:
        plant = _setting_plant(inv, configured, True)
        try:
            frame = plant.scan(0)
            assert frame is not None and frame.local_mode == configured  # the read-back, after the write
            assert inv.volt_var_enabled() is (configured == "volt_var") and plant.local_mode_writes == 1
            assert plant.scan(PERIOD_NS) is not None and plant.local_mode_writes == 1  # nothing to write now
            inv.set_raw(705, "Ena", int(start))  # someone set it back at the inverter: the next scan writes again
            assert plant.scan(2 * PERIOD_NS).local_mode == configured and plant.local_mode_writes == 2  # type: ignore[union-attr]
        finally:
            plant.link.close()


def test_without_set_local_mode_705_is_only_read(vv_inverter):
    plant = _setting_plant(vv_inverter, "unity_pf", False)
    try:
        assert plant.scan(0).local_mode == "volt_var"  # type: ignore[union-attr]
        assert vv_inverter.volt_var_enabled() is True and plant.local_mode_writes == 0
    finally:
        plant.link.close()


def test_set_local_mode_without_705_writes_nothing_and_fails_nothing(inverter):  # conftest's: no 705
    plant = _setting_plant(inverter, "volt_var", True)
    try:
        assert plant.scan(0).local_mode == "volt_var"  # type: ignore[union-attr]
        assert plant.local_mode_writes == plant.local_mode_failures == 0
    finally:
        plant.link.close()


def test_the_inverter_takes_only_0_or_1_on_705_ena_and_nothing_else_of_705(vv_inverter):
    from sunspec2.modbus.client import SunSpecModbusClientDeviceTCP
    from sunspec2.modbus.modbus import ModbusClientException

    dev = SunSpecModbusClientDeviceTCP(slave_id=1, ipaddr="127.0.0.1", ipport=vv_inverter.port, timeout=2.0)
    try:
        dev.scan()
        vv = dev.models[705][0]
        refused = vv_inverter.refused_writes
        vv.Ena.value = 5
        with pytest.raises(ModbusClientException):
            vv.Ena.write()
        vv.Ena.value = 1
        vv.Crv[0].Pt[0].V.value = 90  # the curve is fixed in this simulated inverter
        with pytest.raises(ModbusClientException):
            vv.write()
        assert vv_inverter.refused_writes == refused + 2 and vv_inverter.volt_var_enabled() is True
        vv.Ena.value = 0
        vv.Ena.write()
        assert vv_inverter.volt_var_enabled() is False
    finally:
        dev.disconnect()
