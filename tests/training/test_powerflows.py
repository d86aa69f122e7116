import numpy as np

from training.powerflows import BASE, COMBINED, q_plan


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


def test_worker_processes_give_the_same_flows_as_one_process():
    from schemas.devicemap import load_device_map
    from simulator_bridge.engine import FeederEngine
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
