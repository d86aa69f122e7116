"""The live decision bench (``make bench``): case D through the bus on a day's start of each season (IEEE 13), the
agent's own time per decision read back from the runs' recordings."""

from pathlib import Path

import numpy as np
import pytest

from benchmarks.bench_live import LIVE_GOAL_P99_MS, bench_live
from benchmarks.results import LiveDecisionBench, decode_result, to_json
from recordings.offline import recorded_decisions

REPO = Path(__file__).resolve().parents[2]
IEEE13 = REPO / "feeders" / "ieee13.toml"


@pytest.mark.bus
@pytest.mark.process
@pytest.mark.slow
def test_bench_live_pools_the_agent_s_own_time_of_every_decision_of_the_four_seasons(tmp_path, ieee13_model,
                                                                                     profile_cache):
    r = bench_live(IEEE13, days_per_season=0.02, cache=profile_cache.parent, model=ieee13_model, out=tmp_path)
    recordings = sorted(tmp_path.glob("runs/*/session.mcap"))
    assert len(recordings) == 4 and set(r.season_p99_ms) == set(r.first_decision_ms) == {"winter", "spring", "summer",
                                                                                          "fall"}
    times = {rec.parent.name.split("-")[0]: [1e3 * (d.timings.align_s + d.timings.total_s)
                                             for d in recorded_decisions(rec)] for rec in recordings}
    pooled = np.concatenate([np.asarray(t) for t in times.values()])
    assert r.decisions == pooled.size >= 4 * 5
    assert r.p99_ms == round(float(np.percentile(pooled, 99)), 2) and r.max_ms == round(float(pooled.max()), 2)
    assert 0.0 < r.p50_ms <= r.p99_ms <= r.max_ms
    assert r.first_decision_ms == {s: round(t[0], 2) for s, t in times.items()}
    cpu = np.array([1e3 * d.timings.cpu_s for rec in recordings for d in recorded_decisions(rec)])
    assert r.cpu_p99_ms == round(float(np.percentile(cpu, 99)), 2) and 0.0 < r.cpu_p50_ms <= r.p50_ms
    assert r.p99_goal_met == (r.p99_ms <= LIVE_GOAL_P99_MS) and r.lockstep_misses == 0
    assert decode_result(to_json(r), LiveDecisionBench) == r
