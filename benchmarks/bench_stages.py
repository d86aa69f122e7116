"""Where a recorded day's decision time goes, stage by stage: ``python -m benchmarks.bench_stages RECORDING``.

The agent's decision code re-runs on the recording's frames offline (as ``cvvc replay --offline``: same
decisions bit for bit, checked against the recorded ones), each decision timed once, and every solve the controller
makes within it is split into its stages (``CvvcSolution.seconds``: problem build, relaxation, rounding and the MILP
fallback within it) and by why it was made: ``main`` (the decision), ``unlocked`` (again without the tap reversal
locks, when the first is not optimal), ``deadband`` (taps held, ``tap_deadband_pu``) and ``tolerated`` (their Q,
the limits widened by the deadband): each controller decision lists its solves (``agent.decision.Decision.solves``).
"""

from __future__ import annotations

import argparse
import os
import typing
from pathlib import Path

import msgspec
import numpy as np

from agent.decision import SolveRole

__all__ = ["StageFigures", "StagesBench", "bench_stages", "main"]


class StageFigures(msgspec.Struct, frozen=True, kw_only=True):
    """One stage's time per decision [ms] (0 where the stage did not run) and the decisions where it ran."""

    ran: int
    p50_ms: float
    p99_ms: float
    max_ms: float
    sum_ms: float


class StagesBench(msgspec.Struct, frozen=True, kw_only=True):
    """Per-stage figures of one offline re-run of a recording."""

    recording: str
    decisions: int
    identical_to_recorded: int
    load_average: float
    stages: dict[str, StageFigures]
    milp_decisions: int
    milp_solves: int
    lattice_tried: int
    solves_by_role: dict[str, int]


def _figures(values_s: list[float]) -> StageFigures:
    v = np.array(values_s) * 1e3
    return StageFigures(ran=int(np.count_nonzero(v)), p50_ms=float(np.percentile(v, 50)),
                        p99_ms=float(np.percentile(v, 99)), max_ms=float(v.max()), sum_ms=float(v.sum()))


def bench_stages(recording: str | Path) -> StagesBench:
    """Re-run the agent on ``recording``'s frames and time every decision and its solves' stages."""
    from agent.runtime import decide_offline_in_detail
    from recordings.info import recording_info
    from recordings.offline import agent_inputs, diff_decisions, recorded_decisions, recorded_frames, recorded_model
    from recordings.recorder import METADATA_NAME
    from recordings.replay import MEASUREMENT_KEYS

    meta = recording_info(recording).metadata.get(METADATA_NAME, {})
    model, settings = agent_inputs(recorded_model(recording, meta.get("model_path", "")),
                                   meta.get("agent_settings", ""))
    frames = list(recorded_frames(recording, MEASUREMENT_KEYS))
    pairs = list(decide_offline_in_detail(model, settings, frames))
    rerun, per_decision = [message for message, _ in pairs], [decision for _, decision in pairs]
    diff = diff_decisions(recorded_decisions(recording), rerun)

    def stage(pick) -> StageFigures:  # noqa: ANN001
        return _figures([sum(pick(role, s) for role, s in d.solves) for d in per_decision])

    stages = {
        "decision": _figures([d.timings.total_s for d in per_decision]),
        "build": stage(lambda r, s: s.seconds.build_s),
        "relaxation": stage(lambda r, s: s.seconds.relaxed_s),
        "rounding without the MILP": stage(lambda r, s: s.seconds.rounding_s - s.seconds.milp_s),
        "MILP": stage(lambda r, s: s.seconds.milp_s),
        "outside the solves": _figures([d.timings.total_s - sum(s.seconds.total_s for _, s in d.solves)
                                        for d in per_decision]),
    }
    for role in typing.get_args(SolveRole):
        stages[f"solves: {role}"] = stage(lambda r, s, role=role: s.seconds.total_s if r == role else 0.0)
    calls = [(r, s) for d in per_decision for r, s in d.solves]
    return StagesBench(
        recording=str(recording), decisions=len(per_decision), identical_to_recorded=diff.identical,
        load_average=os.getloadavg()[0], stages=stages,
        milp_decisions=sum(1 for d in per_decision if any(s.milp_solves for _, s in d.solves)),
        milp_solves=sum(s.milp_solves for _, s in calls), lattice_tried=sum(s.lattice_tried for _, s in calls),
        solves_by_role={role: sum(1 for r, _ in calls if r == role) for role in typing.get_args(SolveRole)},
    )


def main(argv: list[str] | None = None) -> int:
    """Print the per-stage table of a recording (and its JSON with ``--json FILE``)."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_stages", description=__doc__.split("\n\n")[0])
    parser.add_argument("recording", help="an MCAP recording of a run (cvvc run ... --out DIR: DIR/session.mcap)")
    parser.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    args = parser.parse_args(argv)
    result = bench_stages(args.recording)
    print(f"{result.decisions} decisions, {result.identical_to_recorded} identical to the recorded ones, "
          f"load average {result.load_average:.1f}")
    print(f"{'stage':28s} {'ran':>5s} {'p50 ms':>9s} {'p99 ms':>9s} {'max ms':>9s} {'sum ms':>10s}")
    for name, f in result.stages.items():
        print(f"{name:28s} {f.ran:5d} {f.p50_ms:9.2f} {f.p99_ms:9.1f} {f.max_ms:9.1f} {f.sum_ms:10.0f}")
    print(f"MILP in {result.milp_decisions} decisions ({result.milp_solves} solves); lattice points re-solved "
          f"{result.lattice_tried}; solves by role {result.solves_by_role}")
    if args.json:
        Path(args.json).write_bytes(msgspec.json.format(msgspec.json.encode(result)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
