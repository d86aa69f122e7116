"""Benchmark of the CVVC solver at the paper's size (47 critical nodes, 3 plants, 8 regulators).

``python -m benchmarks.bench_solver [--problems N] [--days D] [--seed S] [--nodes N,...]`` prints, for independent
random problems (cold start) and for closed-loop synthetic days (5-minute steps, warm start from the previous solution,
the way the agent runs): solve time p50/p99/max, OSQP iterations, statuses, and the rounding's cost gap to the
exact MILP (``scipy.optimize.milp``); then how the closed-loop days' solve time grows with the critical nodes
(``--nodes``: one day at each size, the same 8 regulators and 3 plants). Wall times depend on the machine's load
(printed); thread CPU times much less.
"""

from __future__ import annotations

import argparse
import os
import time
from collections import Counter

import numpy as np

from agent.solve import solve_cvvc, solve_milp_reference
from benchmarks.synthetic import cvvc_day_sequence, random_cvvc_inputs

__all__ = ["main"]


def _summary(
    name: str, seconds: list[float], cpu: list[float], iterations: list[int], statuses: Counter, gaps: list[float]
) -> str:
    ms = np.array(seconds) * 1e3
    cpu_ms = np.array(cpu) * 1e3
    it = np.array(iterations)
    g = np.array(gaps) if gaps else np.array([np.nan])
    return (
        f"{name}: n={ms.size} wall p50 {np.percentile(ms, 50):.3f} ms, p99 {np.percentile(ms, 99):.3f} ms, "
        f"max {ms.max():.3f} ms; thread CPU p50 {np.percentile(cpu_ms, 50):.3f} ms, "
        f"p99 {np.percentile(cpu_ms, 99):.3f} ms; iterations p50 {np.percentile(it, 50):.0f}, "
        f"p99 {np.percentile(it, 99):.0f}; "
        f"statuses {dict(statuses)}; MILP gap (n={len(gaps)}) mean {100 * np.nanmean(g):.2f} %, "
        f"max {100 * np.nanmax(g):.2f} %"
    )


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print one line per scenario."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_solver", description=__doc__)
    parser.add_argument("--problems", type=int, default=300, help="independent random problems (cold start)")
    parser.add_argument("--days", type=int, default=2, help="closed-loop synthetic days of 288 steps (warm start)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--gap-every", type=int, default=3, help="compare with the MILP every N-th problem")
    parser.add_argument("--nodes", default="", help="critical-node counts for the growth section, e.g. 50,100,300")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)

    secs, cpu, its, gaps = [], [], [], []
    stats: Counter[str] = Counter()
    for i in range(args.problems):
        inputs = random_cvvc_inputs(rng)
        t_cpu = time.thread_time()
        sol = solve_cvvc(inputs)
        cpu.append(time.thread_time() - t_cpu)
        secs.append(sol.seconds.total_s)
        its.append(sol.iterations)
        stats[sol.status] += 1
        if i % args.gap_every == 0:
            milp = solve_milp_reference(inputs)
            if milp.status == "optimal" and sol.status == "optimal":
                gaps.append((sol.cost - milp.cost) / max(milp.cost, 1e-9))
            elif milp.status == "optimal":
                stats["soft_where_milp_feasible"] += 1
    print(_summary("random problems, cold start", secs, cpu, its, stats, gaps))

    secs, cpu, its, gaps = [], [], [], []
    stats = Counter()
    for _ in range(args.days):
        _closed_loop_day(rng, secs, cpu, its, stats, gaps, gap_every=args.gap_every)
    print(_summary("closed-loop days, warm start", secs, cpu, its, stats, gaps))
    for n_nodes in [int(n) for n in args.nodes.split(",") if n.strip()]:
        secs, cpu, its, gaps = [], [], [], []
        stats = Counter()
        _closed_loop_day(np.random.default_rng(args.seed), secs, cpu, its, stats, gaps, n_nodes=n_nodes)
        ms, cpu_ms = np.array(secs) * 1e3, np.array(cpu) * 1e3
        wall_p50, wall_p99, cpu_p50, cpu_p99 = *np.percentile(ms, [50, 99]), *np.percentile(cpu_ms, [50, 99])
        print(f"{n_nodes} critical nodes, a closed-loop day: wall p50 {wall_p50:.3f} ms, p99 {wall_p99:.3f} ms, "
              f"max {ms.max():.3f} ms; thread CPU p50 {cpu_p50:.3f} ms, p99 {cpu_p99:.3f} ms; ADMM iterations p99 "
              f"{np.percentile(its, 99):.0f}; {dict(stats)}")
    print(f"load average during the run: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    return 0


def _closed_loop_day(rng: np.random.Generator, secs: list[float], cpu: list[float], its: list[int],
                     stats: Counter[str], gaps: list[float], *, n_nodes: int | None = None, gap_every: int = 0) -> None:
    """Solve one synthetic closed-loop day (``cvvc_day_sequence``, ``n_nodes`` critical nodes, default its own), each
    step warm-started from the previous solution, appending each solve's wall and thread CPU time [s] and OSQP
    iterations, counting its status and MILP fallbacks, and every ``gap_every``-th step (0: none) its cost gap to the
    exact MILP.
    """
    days = cvvc_day_sequence(rng) if n_nodes is None else cvvc_day_sequence(rng, n_nodes=n_nodes)
    inputs, previous, step = next(days), None, 0
    while True:
        t_cpu = time.thread_time()
        sol = solve_cvvc(inputs, warm_start=previous)
        cpu.append(time.thread_time() - t_cpu)
        secs.append(sol.seconds.total_s)
        its.append(sol.iterations)
        stats[sol.status] += 1
        stats["milp"] += sol.milp_solves
        if gap_every and step % gap_every == 0:
            milp = solve_milp_reference(inputs)
            if milp.status == "optimal" and sol.status == "optimal":
                gaps.append((sol.cost - milp.cost) / max(milp.cost, 1e-9))
        previous, step = sol, step + 1
        try:
            inputs = days.send((sol.taps_new, sol.q_new_kvar))
        except StopIteration:
            return


if __name__ == "__main__":
    raise SystemExit(main())
