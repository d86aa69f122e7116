"""The closed-loop bench (``make bench``): its figures add up, on a short real recorded run (IEEE 13, case D)."""

from pathlib import Path

import pytest

from benchmarks.bench_closedloop import bench_closedloop
from benchmarks.results import ClosedLoopBench, decode_result, to_json

pytestmark = [pytest.mark.bus, pytest.mark.process]  # the bench's ``cvvc run``

REPO = Path(__file__).resolve().parents[2]


def test_bench_closedloop_figures_add_up(tmp_path: Path, ieee13_model: Path) -> None:
    r = bench_closedloop(30 / 1440, start="2023-04-01T11:00", cache=str(tmp_path / "cache"), bare_repeats=1,
                         out=str(tmp_path / "run"), feeder=str(REPO / "feeders" / "ieee13.toml"),
                         model=str(ieee13_model))
    assert (r.feeder, r.case, r.steps, r.truth_frames, r.lockstep_misses) == ("ieee13", "D", 30, 30, 0)
    assert r.truth_encoding == "protobuf"  # the compact truth (TruthPack as cvvc.Truth), which Foxglove decodes
    assert 0.0 < r.bare_s and 0.0 < r.loop_wall_s < r.run_wall_s  # the run holds start-up and shut-down
    assert r.ratio == pytest.approx(r.run_wall_s / r.bare_s, rel=0.01, abs=0.01)  # ratios are rounded to 0.01
    assert r.loop_ratio == pytest.approx(r.loop_wall_s / r.bare_s, rel=0.01, abs=0.01)
    assert 0.0 < r.decision_wait_s < r.loop_wall_s
    # a week is 10080 frames; those of IEEE 13 (41 nodes: 164 bytes of voltages) are a few hundred bytes each
    assert 200 * 10080 < r.truth_payload_bytes_per_week < 1000 * 10080
    assert 0 < r.truth_zstd_bytes_per_week < r.truth_payload_bytes_per_week
    assert r.recording_bytes_per_week > r.truth_zstd_bytes_per_week * 0.5
    assert (tmp_path / "run" / "session.mcap").is_file()
    assert decode_result(to_json(r), ClosedLoopBench) == r
