"""The agent's decision time live: case D through the bus (bridge, agent, recorder in lockstep), a day of each season.

What a user lives with: the agent's own time per decision (``Decision.timings``: the step's alignment and snapshot,
then the decision, ``align_s + total_s``) read from each run's recording, the bridge and the recorder working beside
it on the same cores. ``cvvc evaluate`` makes the runs (``cases = D``, its first ``days_per_season`` days of January,
April, July and October), one at a time (``jobs = 1``: a second run beside it would time the machine, not the agent).

``python -m benchmarks.bench_live [FEEDER.toml ...] [--days-per-season D]`` prints one result per feeder (the
embedded rural feeder without a map).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from benchmarks.results import LiveDecisionBench, to_json

__all__ = ["LIVE_GOAL_P99_MS", "bench_live", "main"]

#: The goal of every feeder's live p99 [ms].
LIVE_GOAL_P99_MS = 5.0


def bench_live(device_map_path: str | Path | None, *, days_per_season: float = 1.0, cache: Path | None = None,
               model: Path | None = None, out: Path | None = None) -> LiveDecisionBench:
    """Run case D on a day of each season through the bus and time the agent's every decision.

    Parameters
    ----------
    device_map_path : the feeder's device map; None: the embedded rural feeder (its model trained into ``cache`` if
        absent, as ``cvvc evaluate`` does).
    days_per_season : the days of each season's month from its first (1: 288 decisions a season).
    cache : the cache root (``schemas.cache.cache_root``); None: the default one.
    model : the trained model to run; None: the feeder's in ``cache`` (trained there if absent).
    out : where the runs and their recordings go; None: a temporary folder, removed afterwards.

    Returns
    -------
    LiveDecisionBench
        The pooled p50 / p99 / max over every decision of the four days, each season's p99, the first (cold)
        decision of each run, the deciding thread's CPU time (``Timings.cpu_s``: p50, p99), the machine's load
        average before the first run.

    Raises
    ------
    cvvc.evaluate.EvaluateError
        A run failed (its folder keeps the logs).
    """
    from agent.decision import decision_time_ms
    from cvvc.evaluate import EvaluateConfig, evaluate
    from recordings.offline import recorded_decisions

    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench-live-") as tmp:
        folder = Path(tmp) if out is None else out
        config = EvaluateConfig(feeder=None if device_map_path is None else str(device_map_path), cases=("D",),
                                model=None if model is None else str(model), days_per_season=days_per_season,
                                jobs=1, out=str(folder / "runs"),
                                cache=None if cache is None else str(cache), progress=False)
        evaluation = evaluate(config)
        seasons: dict[str, list[float]] = {}  # each decision's time [s], by season
        cpu: list[float] = []
        first: dict[str, float] = {}
        misses = 0
        for run in evaluation.runs:
            if run.recording is None:
                raise ValueError(f"run {run.spec.name} left no recording: its decision times cannot be read")
            decisions = recorded_decisions(run.recording)
            if not decisions:
                raise ValueError(f"run {run.spec.name} recorded no decision")
            seasons[run.spec.season] = [d.timings.align_s + d.timings.total_s for d in decisions]
            cpu += [d.timings.cpu_s for d in decisions]
            first[run.spec.season] = round(1e3 * seasons[run.spec.season][0], 2)
            misses += run.lockstep_misses
    pooled = decision_time_ms(t for times in seasons.values() for t in times)  # the agent's own figures' rule
    cpu_ms = decision_time_ms(cpu)
    return LiveDecisionBench(
        feeder=evaluation.feeder_id, decisions=sum(len(t) for t in seasons.values()), days_per_season=days_per_season,
        p50_ms=pooled["p50"], p99_ms=pooled["p99"], max_ms=pooled["max"], cpu_p50_ms=cpu_ms["p50"],
        cpu_p99_ms=cpu_ms["p99"], season_p99_ms={s: decision_time_ms(t)["p99"] for s, t in seasons.items()},
        first_decision_ms=first, lockstep_misses=misses, p99_goal_met=pooled["p99"] <= LIVE_GOAL_P99_MS,
        load_average=round(load, 2),
        wall_s=round(time.perf_counter() - t0, 1),
        method="cvvc evaluate --cases D, jobs 1: each decision's align_s + total_s from its run's recording",
        goal=f"p99 <= {LIVE_GOAL_P99_MS:g} ms on every feeder; p50 <= 1 ms on the rural feeder",
    )


def main(argv: list[str] | None = None) -> int:
    """Print the live decision bench of each feeder given (none: the rural feeder) as JSON."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_live", description=__doc__.split("\n\n")[0])
    parser.add_argument("feeders", nargs="*", help="device maps (none: the embedded rural feeder)")
    parser.add_argument("--days-per-season", type=float, default=1.0, help="days of each season's month [d]")
    args = parser.parse_args(argv)
    for path in args.feeders or [None]:
        print(to_json(bench_live(path, days_per_season=args.days_per_season)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
