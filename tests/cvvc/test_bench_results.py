"""The benchmarks' typed results (``benchmarks.results``) and the suite's printing and ``--json`` file
(``python -m benchmarks``): the keys printed before the types, a real short run read back into its types."""

import json
from pathlib import Path

import msgspec
import pytest

from benchmarks import suite
from benchmarks.results import (
    BenchError,
    MemoryKib,
    SolverRun,
    SunspecBench,
    TrainingBench,
    decode_result,
    to_json,
)


def test_every_bench_has_a_result_type() -> None:
    assert list(suite.RESULT_TYPES) == list(suite.BENCHES)


@pytest.mark.parametrize(
    ("result", "printed"),
    [
        # the suite's own results: attributes named with their unit, printed under the keys of before the types
        (TrainingBench(wall_s=12.5, scenarios=40, power_flows=4000, critical_nodes=9, goal_s=60),
         {"seconds": 12.5, "scenarios": 40, "power_flows": 4000, "critical_nodes": 9, "goal_s": 60}),
        (SolverRun(exit_code=1, wall_s=3.0), {"exit": 1, "seconds": 3.0}),
        # a process gone before its memory was read prints {} (as the dict of /proc fields did), in /proc's order
        (MemoryKib(), {}),
        (MemoryKib(vm_rss_kib=20, vm_hwm_kib=30), {"VmHWM": 30, "VmRSS": 20}),
    ],
)
def test_results_print_the_keys_of_before(result: msgspec.Struct, printed: dict) -> None:
    text = to_json(result)
    assert json.loads(text) == printed and list(json.loads(text)) == list(printed)
    assert decode_result(text, type(result)) == result


def test_decode_rejects_what_is_not_the_result() -> None:
    with pytest.raises(msgspec.ValidationError, match="unknown field `wall_s`"):  # the attribute is not the key
        decode_result('{"exit": 0, "seconds": 1.0, "wall_s": 1.0}', SolverRun)
    with pytest.raises(msgspec.ValidationError, match="missing required field `seconds`"):
        decode_result('{"exit": 0}', SolverRun)


@pytest.mark.bus  # the suite's burst bench on a loopback router
def test_suite_prints_and_writes_a_real_run_read_back_typed(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(quick: bool) -> SolverRun:
        raise RuntimeError("no solver today")

    # a benchmark that raises is reported as an error record and the next one still runs
    monkeypatch.setitem(suite.BENCHES, "solver", broken)
    out = tmp_path / "bench.json"
    assert suite.main(["--only", "solver", "sunspec", "--quick", "--json", str(out)]) == 1
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "== solver ==" and lines[1:4] == ["{", '  "error": "RuntimeError: no solver today"', "}"]
    start = lines.index("== sunspec ==")
    end = lines.index("}", start)
    printed = json.loads("\n".join(lines[start + 1:end + 1]))
    back = suite.read_results(out)
    assert list(back) == ["solver", "sunspec"]
    assert back["solver"] == BenchError(error="RuntimeError: no solver today")
    sunspec = back["sunspec"]
    assert isinstance(sunspec, SunspecBench)
    assert msgspec.to_builtins(sunspec) == printed  # the file holds what was printed
    assert sunspec.commands == 50
    assert 0.0 < sunspec.bus_only.p50_ms <= sunspec.bus_only.p99_ms
    assert 0.0 < sunspec.through_sunspec.p50_ms <= sunspec.through_sunspec.p99_ms
    assert sunspec.extra_per_decision_p50_ms == sunspec.through_sunspec.p50_ms - sunspec.bus_only.p50_ms


def test_read_results_names_what_it_does_not_know(tmp_path: Path) -> None:
    path = tmp_path / "bench.json"
    path.write_text('{"warp": {"error": "x"}}')
    with pytest.raises(ValueError, match="unknown benchmark 'warp'"):
        suite.read_results(path)
    path.write_text('{"solver": {"exit": "zero", "seconds": 1.0}}')
    with pytest.raises(msgspec.ValidationError, match=r"Expected `int`, got `str` - at `\$.exit`"):
        suite.read_results(path)
