"""The bridge bench (``make bench``): its figures add up, on a short real run (IEEE 13, trivial responder)."""

from pathlib import Path

import pytest

from benchmarks.bench_bridge import bench_bridge
from benchmarks.results import BridgeBench, decode_result, to_json

pytestmark = [pytest.mark.bus, pytest.mark.process]  # the bench's bridge and its publisher process on a bus

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("publisher", ["inline", "process"])
def test_bench_bridge_figures_add_up(tmp_path: Path, publisher: str) -> None:
    r = bench_bridge(REPO / "feeders" / "ieee13.toml", 30, repeats=1, cache_dir=str(tmp_path), publisher=publisher)
    assert r.steps == 30 and r.control_steps == 6 and r.decisions == 6 and r.lockstep_misses == 0
    # the rates are rounded to 0.1 steps/s and the overhead to 0.001: the overhead from the rounded rates is off by
    # at most ratio * (0.05 / bare + 0.05 / lockstep) + 0.0005 (0.08 on a loaded machine where the ratio is 37)
    ratio = r.bare_steps_per_s / r.lockstep_steps_per_s
    rounding = ratio * (0.05 / r.bare_steps_per_s + 0.05 / r.lockstep_steps_per_s) + 5e-4
    assert r.overhead == pytest.approx(ratio - 1.0, abs=rounding)
    # waiting for six decisions is part of the overhead, and the round trip is what was waited for
    assert 0.0 < r.decision_wait_share < r.overhead + 1.0
    assert r.round_trip_p50_ms is not None and r.round_trip_p99_ms is not None
    assert 0.0 < r.round_trip_p50_ms <= r.round_trip_p99_ms
    assert r.publisher == r.publisher_used == publisher
    assert (r.publisher_cpu_share > 0.0) == (publisher == "process")  # the child's CPU time is counted
    assert decode_result(to_json(r), BridgeBench) == r
