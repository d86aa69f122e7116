"""Whether a run was attacked or degraded, from the summaries its own processes wrote (``RunIntegrity``).

The agent counts what it refused (frames, readings, acks by reason) and which devices answered its commands
``rejected``; the bridge counts the control steps, the decisions it took, its lockstep misses and what it refused; each
field-protocol adapter (SunSpec, DNP3) counts the scans that found a command it had not written
(``LinkStatus.foreign_writes``), and the bridge's simulated inverters the Modbus writes they refused from another
master. None of it is read from the bus,
where any session could publish a figure.

The agent was **degraded** when, for more than one control period, it did not control the feeder: more than one
control step without its decision (or with a lockstep miss), or one device that refused more than one of its
commands, or one device whose command another master held for more than a control period (foreign writes times the
scan period), or more than one decision the bridge took that the agent did not make. ``cvvc run`` then exits
``EXIT_DEGRADED`` with one line saying why (docs/security.md).
"""

from __future__ import annotations

from collections.abc import Mapping

from agent.ami import REFUSED_KINDS
from agent.runtime import AgentSummary
from cvvc.run_summary import RunIntegrity
from schemas import messages as m
from simulator_bridge.bus.bridge import BridgeSummary

__all__ = ["EXIT_DEGRADED", "run_integrity"]

#: ``cvvc run``'s exit status when the agent was degraded for more than one control period (2 is an error).
EXIT_DEGRADED = 3


def run_integrity(agent: AgentSummary | None, bridge: BridgeSummary, links: Mapping[str, m.LinkStatus], *,
                  step_s: float, control_period_s: float) -> RunIntegrity:
    """The run's ``RunIntegrity`` from the agent's summary (None: a case without an agent), the bridge's and the
    field-protocol adapters' last ``LinkStatus`` by device; ``step_s`` [s] is the adapters' scan period (one per step),
    ``control_period_s`` [s] the feeder's.
    """
    foreign_writes = {pid: s.foreign_writes for pid, s in links.items() if s.foreign_writes}
    if agent is None:  # no agent, nothing it could lose
        return RunIntegrity(decisions_due=0, bridge_refused=dict(bridge.rejected), foreign_writes=foreign_writes,
                            foreign_master_writes=dict(bridge.sunspec_foreign_master_writes))
    due = bridge.control_steps
    missing = max(0, due - agent.decisions)
    meters = {k: n for k, n in agent.ami.items() if k in REFUSED_KINDS and n}
    foreign_decisions = max(0, bridge.decisions - agent.decisions)
    why: list[str] = []
    lost = max(missing, bridge.lockstep_misses)
    if lost > 1:
        why.append(f"{lost} of {due} control steps without a decision of the agent ({missing} missing, "
                   f"{bridge.lockstep_misses} lockstep misses)")
    for device, n in sorted(agent.commands_refused.items(), key=lambda kv: -kv[1]):
        if n > 1:
            why.append(f"{device} refused {n} of the agent's commands")
    for pid, n in sorted(foreign_writes.items(), key=lambda kv: -kv[1]):
        if n * step_s > control_period_s:
            why.append(f"{pid}'s set point was another master's at {n} scans (about {n * step_s:.0f} s)")
    if foreign_decisions > 1:
        why.append(f"the bridge took {foreign_decisions} decisions the agent did not make")
    return RunIntegrity(decisions_due=due, decisions_missing=missing, lockstep_misses=bridge.lockstep_misses,
                        inputs_refused=dict(agent.rejected), foreign_acks=agent.rejected.get("foreign_ack", 0),
                        meter_readings_refused=meters, commands_refused=dict(agent.commands_refused),
                        bridge_refused=dict(bridge.rejected), foreign_decisions=foreign_decisions,
                        foreign_writes=foreign_writes,
                        foreign_master_writes=dict(bridge.sunspec_foreign_master_writes), degraded="; ".join(why))
