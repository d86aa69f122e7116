"""``make bench``: every benchmark of the project, each with a baseline measured in the same run.

``python -m benchmarks [--only NAME ...] [--quick] [--json FILE]`` prints one block per benchmark (its typed
result from ``benchmarks.results`` as JSON; ``read_results`` reads a ``--json`` file back into those types):

- ``qsts``: QSTS steps/s on the rural feeder, IEEE 123, IEEE 8500 and the EPRI feeders vs bare OpenDSS solves
  (goal < 1.3x);
- ``bridge``: lockstep steps/s through Zenoh with a trivial responder vs the bare QSTS (goal overhead < 20 %),
  and the frame -> decision round trip p50/p99;
- ``training``: training time on the rural feeder (goal < 60 s), IEEE 123 and IEEE 8500 (goal < 10 min);
- ``solver``: the CVVC solver at the paper's size, cold and warm, and the rounding gap to the exact MILP; the
  growth of its time with the critical nodes (50 to 600);
- ``decision``: the agent's decision time (aligned frames in -> commands out) over whole days, one run, p50/p99/max,
  beside OSQP's own solve of each decision's relaxation and case A's per-interval cost (perturbation power flows +
  all-node problem) on the rural feeder, IEEE 13, IEEE 123, IEEE 8500 and the EPRI feeders (goals: p99 <= 5 ms,
  >= 50x);
- ``live``: the agent's own decision time live, case D through the bus on a day of each season (the runs of
  ``cvvc evaluate``, one at a time), p50/p99/max over the four days and each season's p99, on every feeder above
  (goals: p99 <= 5 ms, p50 <= 1 ms on the rural feeder);
- ``recording``: messages/s through Zenoh into MCAP vs the bare MCAP writer (goal: >= 60 %), offline
  replay speed;
- ``closedloop``: a recorded ``cvvc run`` of case D on the rural feeder vs bare OpenDSS of the same steps and taps,
the truth's bytes per simulated week;
- ``soak``: a simulated month in lockstep: memory growth of every process (goal < 10 %), dropped/late frames;
- ``sunspec``: the round trip a PV plant behind SunSpec Modbus adds per decision (command -> ack through the
  adapter and a simulated inverter vs the same bus round trip acked at once);
- ``dnp3``: the same for a regulator control behind DNP3 (``cvvc adapter dnp3`` and a simulated outstation).

The machine is shared and small (2 cores): every ratio compares runs made side by side in this process.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import msgspec

from benchmarks.results import (
    BenchError,
    BridgeBench,
    ClosedLoopBench,
    DecisionBench,
    Dnp3Bench,
    LiveDecisionBench,
    QstsBench,
    RecordingBench,
    SoakBench,
    SolverRun,
    SunspecBench,
    TrainingBench,
    to_json,
)
from schemas.cache import cache_root, profiles_dir

REPO = Path(__file__).resolve().parents[1]
FEEDERS = REPO / "feeders"

__all__ = ["BENCHES", "RESULT_TYPES", "Result", "main", "read_results"]


def _rural() -> Path:
    from simulator_bridge.rural.default_feeder import ensure_default_feeder

    return ensure_default_feeder(cache_root(None))


# The EPRI feeders, through their device maps in feeders/ (every RegControl and CapControl of the model is
# simulated whether the map lists it or not).
_EPRI = ("epri-k1", "epri-m1", "epri-ckt5", "epri-ckt24")

#: What one benchmark of the suite returns: its result, or one result per feeder.
Result = (dict[str, QstsBench] | dict[str, BridgeBench] | dict[str, TrainingBench] | SolverRun
          | dict[str, DecisionBench] | RecordingBench | SoakBench | SunspecBench | ClosedLoopBench
          | Dnp3Bench | dict[str, LiveDecisionBench])


def bench_qsts_all(quick: bool) -> dict[str, QstsBench]:
    from benchmarks.bench_qsts import bench_qsts

    steps = 240 if quick else 1440
    out = {}
    feeders = [("rural", _rural()), ("ieee123", FEEDERS / "ieee123.toml"), ("ieee8500", FEEDERS / "ieee8500.toml")]
    feeders += [(name, FEEDERS / f"{name}.toml") for name in _EPRI]
    for name, path in feeders:
        big = name != "rural" and name != "ieee123"
        out[name] = bench_qsts(path, steps // 4 if big else steps)
    return out


def bench_bridge_all(quick: bool) -> dict[str, BridgeBench]:
    from benchmarks.bench_bridge import bench_bridge

    steps = 240 if quick else 1440
    return {name: bench_bridge(path, steps, cache_dir=str(profiles_dir(None)))
            for name, path in (("rural", _rural()), ("ieee123", FEEDERS / "ieee123.toml"))}


def bench_training(quick: bool) -> dict[str, TrainingBench]:
    from training.train import train

    out = {}
    feeders = [("rural", _rural()), ("ieee123", FEEDERS / "ieee123.toml")]
    if not quick:
        feeders.append(("ieee8500", FEEDERS / "ieee8500.toml"))
    for name, path in feeders:
        train(path, cache_dir=profiles_dir(None), progress=False)  # profiles cached: not timed
        t0 = time.perf_counter()
        result = train(path, cache_dir=profiles_dir(None), progress=False)
        out[name] = TrainingBench(wall_s=round(time.perf_counter() - t0, 2), scenarios=result.summary.scenarios,
                                  power_flows=result.summary.power_flows,
                                  critical_nodes=result.summary.critical_nodes,
                                  goal_s=60 if name != "ieee8500" else 600)
    return out


def bench_solver(quick: bool) -> SolverRun:
    from benchmarks import bench_solver

    argv = ["--problems", "50" if quick else "300", "--days", "1" if quick else "3",
            "--nodes", "50,300" if quick else "50,100,200,300,400,600"]
    t0 = time.perf_counter()
    code = bench_solver.main(argv)
    return SolverRun(exit_code=code, wall_s=round(time.perf_counter() - t0, 1))


def bench_decision(quick: bool) -> dict[str, DecisionBench]:
    from benchmarks.bench_decision import bench_decision as run

    cache = cache_root(None)
    if quick:
        return {"rural": run(_rural(), control_steps=48, cache=cache, start_hour=10.0)}
    # whole days (288 decisions from midnight, July), each decision timed once; case A on sampled steps where its
    # perturbation flows are costly; the rural feeder also gives the older best-of-3 figure
    out = {
        "rural": run(_rural(), cache=cache, repeats=3),
        "ieee13": run(FEEDERS / "ieee13.toml", cache=cache),
        "ieee123": run(FEEDERS / "ieee123.toml", cache=cache, case_a_every=4),
        "ieee8500": run(FEEDERS / "ieee8500.toml", cache=cache, case_a_every=12),
    }
    # every EPRI feeder over its whole day too (epri-ckt24, 7522 nodes: 15 s with case A on 1 step in 24)
    every = {"epri-k1": 4, "epri-m1": 4, "epri-ckt5": 12, "epri-ckt24": 24}
    return out | {name: run(FEEDERS / f"{name}.toml", cache=cache, case_a_every=every[name]) for name in _EPRI}


def bench_live_all(quick: bool) -> dict[str, LiveDecisionBench]:
    from benchmarks.bench_live import bench_live

    cache = cache_root(None)
    if quick:
        return {"rural": bench_live(None, days_per_season=0.1, cache=cache)}
    feeders: list[tuple[str, Path | None]] = [("rural", None), ("ieee13", FEEDERS / "ieee13.toml"),
                                               ("ieee123", FEEDERS / "ieee123.toml"),
                                               ("ieee8500", FEEDERS / "ieee8500.toml")]
    feeders += [(name, FEEDERS / f"{name}.toml") for name in _EPRI]
    return {name: bench_live(path, cache=cache) for name, path in feeders}


def bench_recording(quick: bool) -> RecordingBench:
    from benchmarks.bench_recording import bench_recording as run

    return run(5_000 if quick else 20_000)


def bench_closedloop(quick: bool) -> ClosedLoopBench:
    from benchmarks.bench_closedloop import bench_closedloop as run

    return run(days=1.0 if quick else 2.0)


def bench_soak(quick: bool) -> SoakBench:
    from benchmarks.bench_soak import bench_soak as run

    return run(days=1 if quick else 30)


def bench_sunspec(quick: bool) -> SunspecBench:
    from benchmarks.bench_sunspec import bench_sunspec as run

    return run(50 if quick else 200)


def bench_dnp3(quick: bool) -> Dnp3Bench:
    from benchmarks.bench_dnp3 import bench_dnp3 as run

    return run(50 if quick else 200)


BENCHES: dict[str, Callable[[bool], Result]] = {
    "qsts": bench_qsts_all,
    "bridge": bench_bridge_all,
    "training": bench_training,
    "solver": bench_solver,
    "decision": bench_decision,
    "live": bench_live_all,
    "recording": bench_recording,
    "closedloop": bench_closedloop,
    "soak": bench_soak,
    "sunspec": bench_sunspec,
    "dnp3": bench_dnp3,
}

#: The type of each benchmark's result, by name (what ``read_results`` decodes).
RESULT_TYPES: dict[str, object] = {
    "qsts": dict[str, QstsBench],
    "bridge": dict[str, BridgeBench],
    "training": dict[str, TrainingBench],
    "solver": SolverRun,
    "decision": dict[str, DecisionBench],
    "live": dict[str, LiveDecisionBench],
    "recording": RecordingBench,
    "closedloop": ClosedLoopBench,
    "soak": SoakBench,
    "sunspec": SunspecBench,
    "dnp3": Dnp3Bench,
}


def read_results(path: str | Path) -> dict[str, Result | BenchError]:
    """Read a ``--json`` file back: each benchmark's figures decoded into its result type, or its ``BenchError``.

    Parameters
    ----------
    path : the file ``python -m benchmarks --json FILE`` wrote.

    Returns
    -------
    dict[str, Result | BenchError]
        By benchmark name, in the file's order.

    Raises
    ------
    msgspec.DecodeError, msgspec.ValidationError
        The file is not such JSON, or a benchmark's figures do not fit its type (the message says where).
    ValueError
        The file names a benchmark this suite does not have.
    """
    raw = msgspec.json.decode(Path(path).read_bytes(), type=dict[str, msgspec.Raw])
    out: dict[str, Result | BenchError] = {}
    for name, data in raw.items():
        if name not in RESULT_TYPES:
            raise ValueError(f"{path}: unknown benchmark {name!r} (known: {', '.join(RESULT_TYPES)})")
        try:
            out[name] = msgspec.json.decode(data, type=BenchError)
        except msgspec.ValidationError:  # not an error record: the benchmark's own figures
            out[name] = msgspec.json.decode(data, type=RESULT_TYPES[name])
    return out


def main(argv: list[str] | None = None) -> int:
    """Run the benchmarks ``argv`` selects (``make bench``: all) and print each one's figures as JSON.

    Returns 1 when a benchmark failed (the others still run), else 0.
    """
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", nargs="+", choices=sorted(BENCHES), help="run only these benchmarks")
    parser.add_argument("--quick", action="store_true", help="shorter windows (for a smoke run)")
    parser.add_argument("--json", metavar="FILE", help="also write every figure as JSON")
    args = parser.parse_args(argv)
    results: dict[str, Result | BenchError] = {}
    failed = []
    for name in args.only or list(BENCHES):
        print(f"== {name} ==", flush=True)
        t0 = time.perf_counter()
        try:
            results[name] = BENCHES[name](args.quick)
        except Exception as e:  # one broken benchmark must not hide the others' figures
            failed.append(name)
            results[name] = BenchError(error=f"{type(e).__name__}: {e}")
        print(to_json(results[name]), flush=True)
        print(f"({name}: {time.perf_counter() - t0:.1f} s)\n", flush=True)
    if args.json:
        Path(args.json).write_text(to_json(results))
    if failed:
        print(f"benchmarks that failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
