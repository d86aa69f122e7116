import numpy as np
import pytest

from training.powerflows import BASE, COMBINED, PowerFlowSet, q_plan


def test_q_plan_skips_steps_outside_the_headroom():
    # 100 kVA at 80 kW: headroom 60 kvar, so only the +/-20, 40, 60 % steps are feasible
    plan = q_plan(np.array([80.0]), np.array([100.0]), [float(p) for p in range(-100, 101, 20)])
    assert plan[0][0] == BASE and np.all(plan[0][2] == 0)
    assert [p for _, p, _ in plan[1:]] == [-60, -40, -20, 20, 40, 60]
    assert [q[0] for _, _, q in plan[1:]] == [-60, -40, -20, 20, 40, 60]


def test_q_plan_perturbs_one_plant_at_a_time_and_combined_all():
    # plant 0: 100 kVA at night (headroom 100); plant 1: 500 kVA at 300 kW (headroom 400 kvar)
    plan = q_plan(np.array([0.0, 300.0]), np.array([100.0, 500.0]), [-100.0, -80.0, 80.0, 100.0], [50.0])
    single = [(k, q.tolist()) for k, _, q in plan if k >= 0]
    assert single == [
        (0, [-100, 0]),
        (0, [-80, 0]),
        (0, [80, 0]),
        (0, [100, 0]),
        (1, [0, -400]),  # -80 % of 500 = the headroom exactly; -100 % (500 kvar) is skipped
        (1, [0, 400]),
    ]
    combined = [q.tolist() for k, _, q in plan if k == COMBINED]
    assert combined == [[50.0, 200.0]]  # half of each plant's own headroom, all at once


@pytest.mark.process  # a pool of worker processes
def test_worker_processes_give_the_same_flows_as_one_process():
    from schemas.devicemap import load_device_map
    from simulator_bridge.opendss.engine import FeederEngine
    from tests.training.conftest import REPO
    from training.powerflows import ScenarioInput, run_power_flows

    path = REPO / "feeders" / "ieee13.toml"
    engine = FeederEngine(load_device_map(path), tolerance=1e-8)
    rng = np.random.default_rng(0)
    scenarios = [
        ScenarioInput(index=i, load_kw=engine.load_kw_nominal * rng.uniform(0.3, 1.0), pv_kw=engine.pv_pmpp_kw * f)
        for i, f in enumerate((0.0, 0.3, 0.6, 0.9))
    ]
    kw = dict(device_map_path=str(path), tolerance=1e-8, q_steps_pct=[-100.0, -50.0, 50.0, 100.0], progress=False)
    serial = run_power_flows(engine, scenarios, workers=1, **kw)
    parallel = run_power_flows(engine, scenarios, workers=2, parallel_min_s=0.0, **kw)
    assert serial.workers == 1 and parallel.workers == 2
    assert parallel.scenario.tolist() == serial.scenario.tolist()
    np.testing.assert_allclose(parallel.v_pu, serial.v_pu, atol=1e-9)
    np.testing.assert_allclose(parallel.features, serial.features, atol=1e-6)


def _flows(n: int, failed: int, first: int = 0) -> PowerFlowSet:
    """``n`` flows of a 3-node, 2-plant, 1-regulator, 0-bank feeder, numbered from ``first``."""
    rows = np.arange(first, first + n)
    return PowerFlowSet(scenario=rows, plant=np.full(n, BASE), q_pct=np.zeros(n), features=np.zeros((n, 4)),
                        q_head_kvar=rows.astype(float), pv_q_kvar=np.zeros((n, 2)), v_pu=np.ones((n, 3)),
                        taps=np.zeros((n, 1), int), reg_pu=np.ones((n, 1)), cap_v_v=np.zeros((n, 0)), failed=failed)


def test_concat_keeps_the_failures_of_a_scenario_with_no_flow_left():
    """A scenario whose every flow failed is an empty part: its rows are nothing, its failures still count."""
    out = PowerFlowSet.concat([_flows(2, 1), _flows(0, 3), _flows(1, 0, first=2)])
    assert out.n == 3 and out.failed == 4
    assert out.scenario.tolist() == [0, 1, 2] and out.q_head_kvar.tolist() == [0.0, 1.0, 2.0]
    only_failures = PowerFlowSet.concat([_flows(0, 2), _flows(0, 5)])
    assert only_failures.n == 0 and only_failures.failed == 7
