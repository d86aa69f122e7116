"""Training with capacitor banks: a feeder with banks and no regulator trains, and the banks' per-step
sensitivities match what OpenDSS gives when a bank switches at another operating point (real power flows)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from schemas.devicemap import load_device_map
from simulator_bridge.opendss.engine import FeederEngine

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def banks_only(tmp_path_factory, profile_cache):
    """IEEE 13 with its two banks and one plant in the map, no regulator: banks and PV Q are the levers."""
    from schemas.settings import TrainingOptions
    from training.train import train

    master = (REPO.parent / "shared" / "feeders" / "ieee13" / "IEEE13Nodeckt.dss").resolve()
    text = (f'[feeder]\nname = "t13caps"\nmaster = "{master}"\nhead_element = "Line.650632"\nsource_bus = "650"\n'
            '[[pv]]\nid = "pv1"\nbus = "675"\nkv_ll = 4.16\nkva = 500.0\npmpp_kw = 450.0\n'
            '[[capacitor]]\nid = "cap1"\ncapacitor = "Cap1"\ncost_per_switch = 2.0\n'
            '[[capacitor]]\nid = "cap2"\ncapacitor = "Cap2"\n')
    path = tmp_path_factory.mktemp("capmap") / "map.toml"
    path.write_text(text)
    return path, train(path, TrainingOptions(blocks=(3, 3)), cache_dir=profile_cache, progress=False).model


def test_banks_are_in_the_model_without_a_regulator(banks_only):
    _, model = banks_only
    assert model.regulators == [] and model.tap0 == []
    assert [(c.id, c.steps, c.kvar_rated, c.phases, c.cost_per_switch) for c in model.capacitors] == [
        ("cap1", 1, 600.0, [1, 2, 3], 2.0), ("cap2", 1, 100.0, [3], 1.0)]
    dv = np.asarray(model.dv_dcap_pu)
    assert dv.shape == (len(model.critical_nodes), 2)
    assert np.all(dv[:, 0] > 0.0)  # closing a bank raises every node
    assert 0.005 < dv[:, 0].max() < 0.05


def test_bank_sensitivity_matches_a_switching_at_another_load(banks_only):
    path, model = banks_only
    engine = FeederEngine(load_device_map(path), tolerance=1e-8)
    names = list(engine.node_names)
    idx = [names.index(c.name) for c in model.critical_nodes]
    engine.set_loads_kw(engine.load_kw_nominal * 0.7)  # not a training scenario
    engine.set_pv(np.array([300.0]), np.zeros(1))
    closed = np.array([c.closed0 for c in model.capacitors])
    engine.set_cap_states(closed)
    engine.solve()
    v0 = engine.node_voltages_pu()[idx]
    engine.set_cap_states(np.where(np.arange(2) == 0, 1 - closed, closed))
    engine.solve()
    measured = (engine.node_voltages_pu()[idx] - v0) / (1 - 2 * closed[0])
    predicted = np.asarray(model.dv_dcap_pu)[:, 0]
    assert np.max(np.abs(measured - predicted)) < 0.15 * np.max(np.abs(measured))


def test_a_banks_local_control_is_predicted_linearly(tmp_path):
    """``bank_controls``: the CapControl's type and settings, and its monitored current's change per kvar of the plant
    (below the monitored line) and per tap, by finite differences at training scenarios; checked against OpenDSS at
    another load and a larger Q step (within 15 %)."""
    from training.capbanks import bank_controls, bank_infos
    from training.powerflows import ScenarioInput

    master = (REPO.parent / "shared" / "feeders" / "ieee13" / "IEEE13Nodeckt.dss").resolve()
    text = (f'[feeder]\nname = "t13cc"\nmaster = "{master}"\nhead_element = "Line.650632"\nsource_bus = "650"\n'
            'extra_commands = ["New CapControl.cc1 Capacitor=Cap1 Element=Line.692675 Terminal=1 Type=Current '
            'CTratio=1 ON=300 OFF=200 Delay=30 DelayOFF=30 VoltOverride=Y PTratio=1 Vmin=2300 Vmax=2600"]\n'
            '[[pv]]\nid = "pv1"\nbus = "675"\nkv_ll = 4.16\nkva = 500.0\npmpp_kw = 450.0\n'
            '[[regulator]]\nid = "reg1"\nregcontrol = "Reg1"\n'
            '[[capacitor]]\nid = "cap1"\ncapacitor = "Cap1"\ncapcontrol = "cc1"\n'
            '[[capacitor]]\nid = "cap2"\ncapacitor = "Cap2"\n')
    path = tmp_path / "map.toml"
    path.write_text(text)
    dm = load_device_map(path)
    engine = FeederEngine(dm, tolerance=1e-8)
    tap0, cap0 = np.asarray(engine.taps(), int), np.asarray(engine.cap_states(), int)
    base = engine.load_kw_nominal
    inputs = [ScenarioInput(index=i, load_kw=base * s, pv_kw=np.array([200.0])) for i, s in enumerate((0.5, 0.8, 1.0))]
    banks = bank_controls(engine, inputs, tap0, cap0, bank_infos(engine, dm, cap0))
    cap1, cap2 = banks
    assert (cap1.control_kind, cap1.control_on, cap1.control_off) == ("current", 300.0, 200.0)
    assert cap2.control_kind == "none" and cap2.control_dq == []
    assert len(cap1.control_dq) == 1 and len(cap1.control_dtap) == 1 and abs(cap1.control_dq[0]) > 1e-3

    def sensed(q_kvar: float, taps: np.ndarray, p_kw: float = 300.0) -> float:
        engine.set_taps(taps)
        engine.set_pv(np.array([p_kw]), np.array([q_kvar]))
        engine.solve()
        return float(engine.sense()[1][engine.cap_control_index[0]])

    engine.set_loads_kw(base * 0.65)  # not a training scenario
    engine.set_cap_states(cap0)
    x0 = sensed(0.0, tap0)
    assert abs((sensed(-150.0, tap0) - x0) / -150.0 - cap1.control_dq[0]) < 0.15 * abs(cap1.control_dq[0])
    # a current's change per tap depends on the load (from +0.1 to -1.1 A/tap between half and full load here): the
    # model keeps its mean over the training scenarios, which one tap down at each of them gives again
    down = []
    for s in inputs:
        engine.set_loads_kw(s.load_kw)
        x_at = sensed(0.0, tap0, 200.0)
        down.append(sensed(0.0, tap0 - 1, 200.0) - x_at)
    assert np.mean(down) / -1.0 == pytest.approx(cap1.control_dtap[0], rel=0.15, abs=0.02)
    # its VoltOverride: the limits, the tested voltage per volt of the bank's bus reading, its change per kvar
    assert (cap1.override_vmin_v, cap1.override_vmax_v) == (2300.0, 2600.0) and cap2.override_vmin_v == 0.0
    engine.set_loads_kw(base * 0.65)
    x0 = sensed(0.0, tap0)
    v_test = float(engine.sense()[2][engine.cap_control_index[0]])
    assert v_test == pytest.approx(cap1.override_per_v * float(engine.readings().cap_v_v[0]), rel=0.01)
    sensed(-150.0, tap0)
    dv = (float(engine.sense()[2][engine.cap_control_index[0]]) - v_test) / -150.0
    assert cap1.override_dq[0] == pytest.approx(dv, rel=0.15) and abs(dv) > 1e-3
    assert len(cap1.override_dtap) == 1
