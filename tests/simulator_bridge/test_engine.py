"""FeederEngine against real OpenDSS solves of the shared IEEE feeders (no mocks)."""

from __future__ import annotations

from pathlib import Path

import msgspec
import numpy as np
import pytest

from schemas.devicemap import DeviceMap, DeviceMapError, load_device_map
from simulator_bridge.opendss.engine import EngineError, FeederEngine
from simulator_bridge.survey.circuit_survey import opendss_snapshot

REPO = Path(__file__).resolve().parents[2]
MAPS = REPO / "feeders"


@pytest.fixture(scope="module")
def map13() -> DeviceMap:
    return load_device_map(MAPS / "ieee13.toml")


@pytest.fixture
def eng123(map123: DeviceMap) -> FeederEngine:
    return FeederEngine(map123, tolerance=1e-8)


@pytest.mark.parametrize("name", ["ieee13", "ieee123"])
def test_snapshot_equals_opendss_own_solution(name: str) -> None:
    """Engine (controls off, taps set to OpenDSS's, PV at 0) == OpenDSS's own snapshot of the plain model.

    Both solved to 1e-8; we require 1e-6 pu at every node (seen: ~1e-8).
    """
    dm = load_device_map(MAPS / f"{name}.toml")
    ref = opendss_snapshot(dm.master_path, tolerance=1e-8)
    eng = FeederEngine(dm, tolerance=1e-8)
    assert eng.node_names == ref.node_names
    eng.set_taps(np.array([ref.taps[r.regcontrol.lower()] for r in dm.regulator]))
    eng.set_pv(np.zeros(len(eng.pv_ids)), np.zeros(len(eng.pv_ids)))
    eng.solve()
    v = eng.node_voltages_pu()
    assert np.max(np.abs(v - ref.v_pu)) < 1e-6
    assert 0.95 < v.min() and v.max() < 1.06  # a sane operating point, not two identical zero vectors


def test_snapshot_differs_when_taps_differ(map13: DeviceMap) -> None:
    """The comparison above can fail: with OpenDSS's taps off by one the voltages move by ~0.6 %."""
    ref = opendss_snapshot(map13.master_path, tolerance=1e-8)
    eng = FeederEngine(map13, tolerance=1e-8)
    eng.set_taps(np.array([ref.taps[r.regcontrol.lower()] for r in map13.regulator]) - 1)
    eng.solve()
    assert np.max(np.abs(eng.node_voltages_pu() - ref.v_pu)) > 3e-3


def test_inventory_ieee123(eng123: FeederEngine) -> None:
    e = eng123
    assert len(e.node_names) == 278 and all(n == n.lower() and "." in n for n in e.node_names)
    assert len(e.load_names) == 91 and e.load_kw_nominal.sum() == pytest.approx(3490.0)
    assert e.regulator_ids == ("creg1a", "creg2a", "creg3a", "creg3c", "creg4a", "creg4b", "creg4c")
    assert [e.node_names[i] for i in e.reg_secondary_node] == ["150r.1", "9r.1", "25r.1", "25r.3",
                                                               "160r.1", "160r.2", "160r.3"]
    assert [e.node_names[i] for i in e.reg_primary_node] == ["150.1", "9.1", "25.1", "25.3",
                                                             "160.1", "160.2", "160.3"]
    # 1 V on the 120 V base is ptratio 20 / 2401.8 V base = 1/120.09 pu
    np.testing.assert_allclose(e.reg_pu_per_v120, 20.0 / (4160.0 / np.sqrt(3.0)), rtol=1e-4)
    np.testing.assert_array_equal(e.reg_default_setpoint_v120, [120, 120, 120, 120, 124, 124, 124])
    np.testing.assert_array_equal(e.reg_default_band_v120, [2, 2, 1, 1, 2, 2, 2])
    assert [[e.node_names[i] for i in ix] for ix in e.pv_node_index] == [
        ["66.1", "66.2", "66.3"], ["83.1", "83.2", "83.3"], ["300.1", "300.2", "300.3"]]
    np.testing.assert_array_equal(e.pv_kva, [1200, 1150, 1140])
    np.testing.assert_allclose(e.pv_pmpp_kw, 0.9 * e.pv_kva)


def test_electrical_distance_ieee13(map13: DeviceMap) -> None:
    """|Z1·length| from 650: regulators add 0; 650 -> 632 is 2000 ft of mtx601 (ohm/mile matrices)."""
    e = FeederEngine(map13)
    d = dict(zip(e.node_names, e.node_distance_ohm, strict=True))
    r = np.array([[0.3465, 0.1560, 0.1580], [0.1560, 0.3375, 0.1535], [0.1580, 0.1535, 0.3414]])
    x = np.array([[1.0179, 0.5017, 0.4236], [0.5017, 1.0478, 0.3849], [0.4236, 0.3849, 1.0348]])
    z = r + 1j * x
    z1 = np.mean(np.diag(z)) - np.mean(z[~np.eye(3, dtype=bool)])
    assert d["650.1"] == 0.0 and d["rg60.2"] == 0.0
    assert d["632.1"] == pytest.approx(abs(z1 * 2000 / 5280), rel=1e-6)
    assert d["632.1"] < d["671.1"] < d["680.1"]
    assert np.all(np.isfinite(e.node_distance_ohm))
    assert e.load_distance_ohm.shape == (len(e.load_names),)
    assert e.pv_distance_ohm[1] == pytest.approx(d["680.1"])


def test_pv_q_clipped_to_headroom_and_applied(eng123: FeederEngine) -> None:
    e = eng123
    p = e.pv_pmpp_kw.copy()
    headroom = np.sqrt(e.pv_kva**2 - p**2)  # 0.436 kVA at P = 0.9 kVA
    q = e.set_pv(p, np.array([5000.0, -5000.0, 100.0]))
    np.testing.assert_allclose(q, [headroom[0], -headroom[1], 100.0])
    e.solve()
    r = e.readings()
    np.testing.assert_allclose(r.pv_q_kvar.sum(axis=1), q, atol=1e-3)
    np.testing.assert_allclose(r.pv_p_kw.sum(axis=1), p, rtol=1e-6)
    # the engine itself applies Q with no sun (night rules are qsts.py's); P clips at [0, Pmpp]
    q = e.set_pv(np.array([0.0, 2 * p[1], -5.0]), np.array([-300.0, 0.0, 10.0]))
    e.solve()
    r = e.readings()
    np.testing.assert_allclose(r.pv_q_kvar.sum(axis=1), [-300.0, 0.0, 10.0], atol=1e-3)
    np.testing.assert_allclose(r.pv_p_kw.sum(axis=1), [0.0, p[1], 0.0], atol=1e-3)
    np.testing.assert_allclose(e.pv_setpoints()[0], [0.0, p[1], 0.0])


def test_readings_units_and_balance(eng123: FeederEngine) -> None:
    e = eng123
    e.set_loads_kw(e.load_kw_nominal)
    e.set_pv(np.zeros(3), np.zeros(3))
    e.solve()
    r0 = e.readings()
    load_kw = e.load_kw_nominal.sum()
    assert r0.head_p_kw.shape == (3,) and r0.pv_p_kw.shape == (3, 3) and r0.reg_v120.shape == (7,)
    # head P = load + losses (a few %), within a loose band (some loads are constant-impedance)
    assert 0.9 * load_kw < r0.head_p_kw.sum() < 1.1 * load_kw
    # reactive power from load_pf 0.95 plus line vars, minus 4 x capacitors (600 + 3 x 50 kvar)
    assert 0 < r0.head_q_kvar.sum() < 2 * load_kw * np.tan(np.arccos(0.95))
    # L-N volts near 2401.8 V, phases 120 degrees apart; |S| = |V||I| per phase
    np.testing.assert_allclose(r0.head_v_mag_v, 2401.8, rtol=0.05)
    np.testing.assert_allclose(r0.head_v_ang_deg, [0.0, -120.0, 120.0], atol=2.0)
    s_kva = np.abs(r0.head_p_kw + 1j * r0.head_q_kvar)
    np.testing.assert_allclose(s_kva, r0.head_v_mag_v * r0.head_i_mag_a / 1000.0, rtol=1e-9)
    # PV voltage readings match the truth at the plant's nodes
    v = e.node_voltages_pu()
    for k, ix in enumerate(e.pv_node_index):
        np.testing.assert_allclose(r0.pv_v_v[k], v[list(ix)] * 4160 / np.sqrt(3), rtol=1e-3)
    # regulator raw secondary voltage is the secondary node's voltage on the 120 V base
    np.testing.assert_allclose(r0.reg_v120, v[e.reg_secondary_node] / e.reg_pu_per_v120, rtol=1e-9)
    # creg1a line-drop compensation: R=3, X=7.5 V at 700 A CT -> compared several volts below raw
    assert 3.0 < r0.reg_v120[0] - r0.reg_v120_compared[0] < 7.0
    # adding PV output lowers the head import by about the PV output (losses change a little)
    e.set_pv(e.pv_pmpp_kw, np.zeros(3))
    e.solve()
    r1 = e.readings()
    drop = r0.head_p_kw.sum() - r1.head_p_kw.sum()
    assert drop == pytest.approx(r1.pv_p_kw.sum(), rel=0.05)
    np.testing.assert_array_equal(r1.reg_tap, e.taps())


def test_ldc_compared_voltage_matches_opendss_control(map13: DeviceMap) -> None:
    """OpenDSS's own regulator control leaves its compared voltage inside vreg ± band/2 (122 ± 1 V):
    our compared value at OpenDSS's taps must be inside too, while the raw value (~126 V) is not."""
    ref = opendss_snapshot(map13.master_path, tolerance=1e-8)
    e = FeederEngine(map13, tolerance=1e-8)
    e.set_taps(np.array([ref.taps[r.regcontrol.lower()] for r in map13.regulator]))
    e.solve()
    r = e.readings()
    assert np.all(np.abs(r.reg_v120_compared - 122.0) <= 1.0)
    assert np.all(r.reg_v120 > 124.0)


def test_perturbation_sensitivities_and_restoration(eng123: FeederEngine) -> None:
    e = eng123
    e.set_loads_kw(0.6 * e.load_kw_nominal)
    e.set_pv(0.5 * e.pv_pmpp_kw, np.array([50.0, -80.0, 0.0]))
    e.set_taps(np.array([2, 1, 0, 0, 3, 3, 3]))
    e.solve()
    v0, p0, q0 = e.node_voltages_pu(), *e.pv_setpoints()
    s = e.perturbation_sensitivities(dq_kvar=100.0, dp_kw=100.0)
    dv_dq, dv_dtap, dv_dp = s.dv_dq, s.dv_dtap, s.dv_dp
    assert dv_dq.shape == (278, 3) and dv_dtap.shape == (278, 7) and dv_dp.shape == (278, 3)
    for k, ix in enumerate(e.pv_node_index):
        assert np.all(dv_dq[list(ix), k] > 1e-5)  # ~3-4e-5 pu/kvar at the plant's own nodes
    for r, node in enumerate(e.reg_secondary_node):
        assert 0.005 < dv_dtap[node, r] < 0.007  # 0.00625 pu per step of the secondary's own voltage
    # restored exactly: taps, set points, voltages
    np.testing.assert_array_equal(e.taps(), [2, 1, 0, 0, 3, 3, 3])
    np.testing.assert_array_equal(e.pv_setpoints()[1], q0)
    np.testing.assert_array_equal(e.pv_setpoints()[0], p0)
    np.testing.assert_allclose(e.node_voltages_pu(), v0, atol=1e-7)
    assert 0.0 <= s.restore_drift_pu < 1e-7  # IEEE 123 lands where it was
    # the sensitivity predicts an independent change of 200 kvar at plant 1 to a few percent
    e.set_pv(p0, q0 + np.array([0.0, 200.0, 0.0]))
    e.solve()
    dv = e.node_voltages_pu() - v0
    np.testing.assert_allclose(dv, dv_dq[:, 1] * 200.0, atol=0.05 * np.max(np.abs(dv)))
    # ... and dV/dP an independent cloud on plant 0 (its measured output 150 kW lower) to a few percent
    for k, ix in enumerate(e.pv_node_index):
        assert np.all(dv_dp[list(ix), k] > 1e-6)  # more output raises the plant's own voltage
    out0 = e.readings().pv_p_kw.sum(axis=1)
    e.set_pv(p0 - np.array([150.0, 0.0, 0.0]), q0)
    e.solve()
    dv = e.node_voltages_pu() - v0
    moved = e.readings().pv_p_kw.sum(axis=1)[0] - out0[0]
    assert moved == pytest.approx(-150.0, rel=0.05)
    np.testing.assert_allclose(dv, dv_dp[:, 0] * moved, atol=0.05 * np.max(np.abs(dv)))


def test_single_phase_plant(map123: DeviceMap) -> None:
    """A 1-phase plant on node 114.1: kV is line-to-neutral, readings only on phase a."""
    extra = msgspec.convert({"id": "pv114", "bus": "114.1", "phases": 1, "kv_ll": 4.16, "kva": 50.0,
                             "pmpp_kw": 45.0}, type=type(map123.pv[0]))
    e = FeederEngine(_edit(map123, pv=[*map123.pv, extra]), tolerance=1e-8)
    assert [e.node_names[i] for i in e.pv_node_index[3]] == ["114.1"]
    q = e.set_pv(np.array([0.0, 0.0, 0.0, 45.0]), np.array([0.0, 0.0, 0.0, 30.0]))
    assert q[3] == pytest.approx(np.sqrt(50.0**2 - 45.0**2))  # 21.8 kvar headroom
    e.solve()
    r = e.readings()
    np.testing.assert_allclose(r.pv_p_kw[3], [45.0, 0.0, 0.0], atol=1e-3)
    np.testing.assert_allclose(r.pv_q_kvar[3], [q[3], 0.0, 0.0], atol=1e-3)
    v114 = e.node_voltages_pu()[e.pv_node_index[3][0]] * 4160 / np.sqrt(3)
    assert r.pv_v_v[3, 0] == pytest.approx(v114, rel=1e-4) and r.pv_v_v[3, 1] == 0.0


def test_engines_are_independent(map13: DeviceMap, map123: DeviceMap) -> None:
    """Each engine has its own OpenDSS context: changing one does not move the other."""
    a, b = FeederEngine(map13), FeederEngine(map123)
    vb = b.node_voltages_pu()
    a.set_loads_kw(2.0 * a.load_kw_nominal)
    a.set_taps(-a.taps() - 1)
    a.solve()
    b.solve()
    np.testing.assert_allclose(b.node_voltages_pu(), vb, atol=1e-9)
    assert len(a.readings().reg_tap) == 3 and len(b.readings().reg_tap) == 7


def test_set_taps_rejects_out_of_range(eng123: FeederEngine) -> None:
    with pytest.raises(EngineError, match="integer taps"):
        eng123.set_taps(np.array([17, 0, 0, 0, 0, 0, 0]))
    with pytest.raises(EngineError, match="expected 91 loads"):
        eng123.set_loads_kw(np.ones(3))


def _edit(dm: DeviceMap, **changes) -> DeviceMap:
    return msgspec.structs.replace(dm, **changes)


def test_unknown_bus_names_it(map123: DeviceMap) -> None:
    pv = [msgspec.structs.replace(map123.pv[0], bus="no_such_bus")] + list(map123.pv[1:])
    with pytest.raises(DeviceMapError, match=r"pv66.*no_such_bus.*IEEE123Master\.dss"):
        FeederEngine(_edit(map123, pv=pv))


def test_unknown_regcontrol_names_it(map123: DeviceMap) -> None:
    reg = [msgspec.structs.replace(map123.regulator[1], regcontrol="creg9z")]
    with pytest.raises(DeviceMapError, match=r"creg2a.*creg9z.*IEEE123Master\.dss"):
        FeederEngine(_edit(map123, regulator=reg))


def test_unknown_head_element_and_source_bus(map123: DeviceMap) -> None:
    with pytest.raises(DeviceMapError, match="Line.nope"):
        FeederEngine(_edit(map123, feeder=msgspec.structs.replace(map123.feeder, head_element="Line.nope")))
    with pytest.raises(DeviceMapError, match="source_bus 'x9'"):
        FeederEngine(_edit(map123, feeder=msgspec.structs.replace(map123.feeder, source_bus="x9")))


def test_feeder_that_does_not_compile(tmp_path: Path) -> None:
    master = tmp_path / "broken.dss"
    master.write_text("Clear\nNew Circuit.broken basekv=12.47\nNew Lyne.l1 bus1=sourcebus bus2=b2\n")
    (tmp_path / "broken.toml").write_text(
        '[feeder]\nname = "broken"\nmaster = "broken.dss"\nhead_element = "Line.l1"\nsource_bus = "sourcebus"\n'
    )
    dm = load_device_map(tmp_path / "broken.toml")
    cwd = Path.cwd()
    with pytest.raises(EngineError, match=r"broken\.dss.*does not compile"):
        FeederEngine(dm)
    assert Path.cwd() == cwd  # OpenDSS's compile changes the working directory; the engine restores it


def test_extra_commands_apply_before_setup(map123: DeviceMap) -> None:
    feeder = msgspec.structs.replace(map123.feeder, extra_commands=["Edit RegControl.creg1a vreg=122 band=3"])
    e = FeederEngine(_edit(map123, feeder=feeder))
    assert e.reg_default_setpoint_v120[0] == 122.0 and e.reg_default_band_v120[0] == 3.0


def test_bad_extra_command(map13: DeviceMap) -> None:
    feeder = msgspec.structs.replace(map13.feeder, extra_commands=["New Bogus.thing x=1"])
    with pytest.raises(EngineError, match="extra command"):
        FeederEngine(_edit(map13, feeder=feeder))


def test_ieee8500_map_compiles_and_reads() -> None:
    """One compile of IEEE 8500: 12 regulators, 3 plants on three-phase primary buses, sane readings."""
    e = FeederEngine(load_device_map(MAPS / "ieee8500.toml"))
    assert len(e.regulator_ids) == 12 and len(e.load_names) == 1177
    assert [len(ix) for ix in e.pv_node_index] == [3, 3, 3]
    assert e.pv_kva.sum() == pytest.approx(e.load_kw_nominal.sum(), rel=0.01)
    assert np.all(np.isfinite(e.node_distance_ohm))
    r = e.readings()
    np.testing.assert_allclose(r.head_v_mag_v, 7200 * 1.05, rtol=0.05)  # source at 1.05 pu, 12.47 kV
    assert 0.9 * e.load_kw_nominal.sum() < r.head_p_kw.sum() < 1.15 * e.load_kw_nominal.sum()
    np.testing.assert_allclose(e.reg_pu_per_v120, 60.0 / 7200.0, rtol=1e-3)


# --------------------------------------------------------------------------- capacitor banks
def _with_caps(dm: DeviceMap, caps: list[dict], extra: list[str] = ()) -> DeviceMap:
    from schemas.devicemap import CapacitorSpec

    feeder = msgspec.structs.replace(dm.feeder, extra_commands=[*dm.feeder.extra_commands, *extra])
    return msgspec.structs.replace(dm, feeder=feeder, capacitor=[CapacitorSpec(**c) for c in caps])


def test_capacitor_inventory_and_switching(map13: DeviceMap) -> None:
    """IEEE 13's Cap1 (600 kvar at 675, 3 phases) as a map bank: rated kvar, steps, state; opening it lowers
    the voltage at its bus by about its kvar times the Thevenin reactance (a fraction of a per cent).
    """
    dm = _with_caps(map13, [{"id": "c675", "capacitor": "Cap1"},
                            {"id": "c611", "capacitor": "cap2", "capcontrol": "cc611"}],
                    ["new capcontrol.cc611 capacitor=cap2 element=line.684611 terminal=2 type=voltage "
                     "ptratio=20 on=118 off=126"])
    eng = FeederEngine(dm, tolerance=1e-8)
    assert eng.capacitor_ids == ("c675", "c611")
    np.testing.assert_allclose(eng.cap_kvar, [600.0, 100.0])
    np.testing.assert_array_equal(eng.cap_steps, [1, 1])
    assert eng.cap_control_type == ("none", "voltage")
    np.testing.assert_array_equal(eng.cap_states(), [1, 1])
    eng.solve()
    closed = eng.readings()
    assert closed.cap_states.tolist() == [1, 1]
    assert 2300 < closed.cap_v_v[0] < 2600 and 2300 < closed.cap_v_v[1] < 2600  # 4.16 kV L-L: ~2.4 kV L-N
    assert np.isnan(closed.cap_control_value[0])
    eng.set_cap_states(np.array([0, 1]))
    eng.solve()
    opened = eng.readings()
    assert opened.cap_states.tolist() == [0, 1]
    assert 0.003 < (closed.cap_v_v[0] - opened.cap_v_v[0]) / closed.cap_v_v[0] < 0.05
    with pytest.raises(EngineError, match="set_cap_states"):
        eng.set_cap_states(np.array([2, 0]))


@pytest.mark.parametrize(("caps", "extra", "match"), [
    ([{"id": "x", "capacitor": "nosuchcap"}], [], "Capacitor 'nosuchcap' not found"),
    ([{"id": "x", "capacitor": "cap1", "capcontrol": "nosuch"}], [], "CapControl 'nosuch' not found"),
    ([{"id": "x", "capacitor": "cap1", "capcontrol": "cc611"}],
     ["new capcontrol.cc611 capacitor=cap2 element=line.684611 terminal=2 type=voltage on=118 off=126"],
     "switches Capacitor 'cap2'"),
])
def test_capacitor_map_errors(map13: DeviceMap, caps: list[dict], extra: list[str], match: str) -> None:
    with pytest.raises(DeviceMapError, match=match):
        FeederEngine(_with_caps(map13, caps, extra))
