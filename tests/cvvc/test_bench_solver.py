"""The solver bench (``make bench``): the paper-size sections and the growth with the critical nodes."""

import ast
import re

from benchmarks import bench_solver


def test_bench_solver_prints_a_closed_loop_day_at_each_size_asked(capsys):
    assert bench_solver.main(["--problems", "2", "--days", "1", "--gap-every", "1", "--nodes", "30,60"]) == 0
    out = capsys.readouterr().out
    for n in (30, 60):
        line = next(x for x in out.splitlines() if x.startswith(f"{n} critical nodes, a closed-loop day"))
        p50, p99 = (float(v) for v in re.search(r"wall p50 ([\d.]+) ms, p99 ([\d.]+) ms", line).groups())
        assert 0.0 < p50 <= p99
        statuses = ast.literal_eval(line[line.index("{"):])  # the printed statuses and MILP fallbacks
        assert sum(v for k, v in statuses.items() if k != "milp") == 288  # every step of the day solved once
