"""``benchmarks.bench_burst``: a real short run on loopback (Zenoh, a subscriber process) read back typed."""

import pytest

from benchmarks.bench_burst import bench_burst
from benchmarks.results import BurstBench, decode_result, to_json

pytestmark = [pytest.mark.bus, pytest.mark.process]  # a Zenoh router and a subscriber process


def test_a_short_burst_bench_delivers_every_decision_both_ways() -> None:
    r = bench_burst(bursts=20, rounds=2)  # raises if the subscriber missed a decision
    assert (r.bursts, r.rounds) == (20, 2)
    for values in (r.express_put_cpu_us, r.batched_put_cpu_us, r.express_latency_ms, r.batched_latency_ms):
        assert len(values) == 2 and all(v > 0 for v in values)
    assert decode_result(to_json(r), BurstBench) == r
