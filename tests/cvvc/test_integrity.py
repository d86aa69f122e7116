"""Whether a run was degraded for more than one control period (``cvvc.integrity``), from its processes' summaries."""

from __future__ import annotations

import msgspec
import pytest

from agent.runtime import AgentSummary
from cvvc.integrity import EXIT_DEGRADED, run_integrity
from schemas import messages as m
from schemas.examples import example
from simulator_bridge.bus.bridge import BridgeSummary

STEP_S, PERIOD_S = 60, 300


def _bridge(**kw) -> BridgeSummary:
    base = dict(feeder_id="f", clock="lockstep", start_t_ns=0, end_t_ns=0, steps=60, steps_total=60, control_steps=12,
                wall_s=1.0, steps_per_s=60.0, cpu_s=1.0, thread_cpu_s=1.0, lockstep_misses=0, lockstep_skipped=0,
                decisions=12, acks={"accepted": 72}, rejected={}, frames_published=600, frames_dropped=0,
                truth_frames=0, oracle_replies=0, oracle_rejected=0, realtime_late_steps=0, round_trip_p50_s=None,
                round_trip_p99_s=None, agent_alive=True, stopped_early=False, metrics=None)
    return BridgeSummary(**(base | kw))


def _agent(**kw) -> AgentSummary:
    return AgentSummary(**(dict(decisions=12, holds=0, commands=72, acks={"accepted": 72}, rejected={}) | kw))


def _link(foreign_writes: int) -> m.LinkStatus:
    return msgspec.structs.replace(example(m.LinkStatus), foreign_writes=foreign_writes)


def _verdict(agent=None, bridge=None, links=None):
    return run_integrity(agent or _agent(), bridge or _bridge(), links or {}, step_s=STEP_S, control_period_s=PERIOD_S)


def test_a_clean_run_is_not_degraded_and_counts_nothing():
    g = _verdict()
    assert (g.decisions_due, g.decisions_missing, g.foreign_acks, g.foreign_decisions, g.degraded) == (12, 0, 0, 0, "")
    assert EXIT_DEGRADED == 3


@pytest.mark.parametrize(("agent", "bridge", "links", "degraded"), [
    # one control period lost is within what a run may lose (one late decision); two are more than a period
    (_agent(decisions=11), None, None, ""),
    (_agent(decisions=10), None, None, "2 of 12 control steps without a decision of the agent"),
    (None, _bridge(lockstep_misses=2), None, "2 of 12 control steps without a decision of the agent (0 missing, 2 "
                                             "lockstep misses)"),
    # a device that refused one command went a period without ours; two, more than a period
    (_agent(commands_refused={"cap1": 1}), None, None, ""),
    (_agent(commands_refused={"cap1": 2, "pv1": 1}), None, None, "cap1 refused 2 of the agent's commands"),
    # another master's set point, found at a scan a minute: 5 scans are a control period, 6 more
    (None, None, {"pv1": _link(5)}, ""),
    (None, None, {"pv1": _link(6)}, "pv1's set point was another master's at 6 scans (about 360 s)"),
    # decisions the bridge took that the agent never made
    (None, _bridge(decisions=14), None, "the bridge took 2 decisions the agent did not make"),
])
def test_degraded_for_more_than_one_control_period(agent, bridge, links, degraded):
    g = _verdict(agent, bridge, links)
    assert (degraded in g.degraded) if degraded else g.degraded == ""
    assert bool(g.degraded) == bool(degraded)


def test_what_was_refused_is_reported_by_kind():
    agent = _agent(rejected={"foreign_ack": 5, "unknown_device": 20, "future": 1},
                   ami={"ami_unknown_meter": 20, "ami_future": 1, "ami_readings": 3, "ami_not_critical": 2})
    g = _verdict(agent, _bridge(rejected={"decode_malformed": 2}, sunspec_foreign_master_writes={"pv1": 4}),
                 {"pv1": _link(1), "pv2": _link(0)})
    assert g.foreign_acks == 5 and g.inputs_refused == agent.rejected
    assert g.meter_readings_refused == {"ami_unknown_meter": 20, "ami_future": 1}  # refusals, not readings taken
    assert g.bridge_refused == {"decode_malformed": 2}
    assert g.foreign_writes == {"pv1": 1} and g.foreign_master_writes == {"pv1": 4}
    assert g.degraded == ""
