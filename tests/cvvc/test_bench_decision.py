"""The decision bench (``make bench``): on IEEE 13, its case A runs on its own engine, so the agent's frames are
those of an undisturbed simulation, and the oracle's state is the simulation's; the agent's figures are one run's,
beside the labelled best-of-N figure, OSQP's own solve and case A on sampled steps."""

import shutil
from pathlib import Path

from benchmarks.bench_decision import bench_decision
from benchmarks.results import DecisionBench, decode_result, to_json
from schemas.devicemap import load_device_map
from training.train import TRAINING_REVISION

REPO = Path(__file__).resolve().parents[2]
IEEE13 = REPO / "feeders" / "ieee13.toml"


def test_bench_decision_times_the_agent_and_case_a_on_the_same_states(tmp_path, ieee13_model, profile_cache):
    dm = load_device_map(IEEE13)
    models = tmp_path / "models"
    models.mkdir()
    shutil.copy(ieee13_model, models / f"{dm.feeder.name}-{dm.fingerprint()}-y1-r{TRAINING_REVISION}.json")
    shutil.copytree(profile_cache, tmp_path / "profiles")
    r = bench_decision(IEEE13, control_steps=4, cache=tmp_path, repeats=2, case_a_every=2)
    assert r.control_steps == 4 and r.nodes > 0
    assert r.case_a_state_max_dv_pu < 1e-5  # the oracle engine solved the simulation's state
    assert 0.0 < r.agent_p50_ms <= r.agent_p99_ms <= r.agent_max_ms
    # the best-of-2 figure takes per step the faster of two runs, the first of which gives the figures above
    assert r.best_of_n == 2 and 0.0 < r.agent_best_of_n_p50_ms <= r.agent_p50_ms
    assert r.case_a_steps == 2  # steps 0 and 2 of 4
    assert r.case_a_mean_ms > r.case_a_oracle_mean_ms > 0.0
    assert r.osqp_p50_ms > 0.0 and r.ratio_agent_to_osqp_p50 > 0.0  # OSQP solved each decision's relaxation
    assert r.load_average >= 0.0
    # what ``make bench`` prints decodes back into the same result, under the keys it printed before the types
    printed = to_json(r)
    assert '"agent_ms_p99": ' in printed and '"case_a_ms_mean": ' in printed
    assert decode_result(printed, DecisionBench) == r
