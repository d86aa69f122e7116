"""What ``cvvc run`` reports (``summary.json``): the one result type of a run, read by the run's report, the
evaluation and the fleet.
"""

from __future__ import annotations

import msgspec

from recordings.info import RecorderGap
from schemas import messages as m
from schemas.settings import RunCase
from simulator_bridge.simulation.live_accuracy import LiveAccuracy

__all__ = ["RunIntegrity", "RunSummary"]


class RunIntegrity(msgspec.Struct, frozen=True, kw_only=True):
    """What a run refused, missed or found overwritten: the signs of an attack (or a fault), each taken from the
    summary a process of the run wrote itself (``cvvc.integrity``), never from the bus.

    ``degraded`` says why the agent did not control the feeder for more than one control period (the run then exits
    ``cvvc.integrity.EXIT_DEGRADED``); empty when it did.
    """

    decisions_due: int = 0  # control steps of the run (the bridge's)
    decisions_missing: int = 0  # control steps the agent made no decision for
    lockstep_misses: int = 0  # control steps the bridge went on without a complete decision
    inputs_refused: dict[str, int] = {}  # the agent's refused frames, readings and acks, by reason
    foreign_acks: int = 0  # acks that answered no command of the agent (or not first): refused
    meter_readings_refused: dict[str, int] = {}  # AMI readings refused, by kind (unknown meter, future, ...)
    commands_refused: dict[str, int] = {}  # by device: the agent's commands it answered 'rejected'
    bridge_refused: dict[str, int] = {}  # commands, decisions and payloads the bridge refused, by reason
    foreign_decisions: int = 0  # decisions the bridge took beyond those the agent made
    foreign_writes: dict[str, int] = {}  # SunSpec, by plant: scans that found a set point its adapter had not written
    foreign_master_writes: dict[str, int] = {}  # SunSpec, by plant: Modbus writes refused, not from its adapter
    degraded: str = ""  # why the agent was degraded for more than a control period; empty: it was not


class RunSummary(msgspec.Struct, frozen=True, kw_only=True):
    """What ``cvvc run`` reports (``summary.json``): the run, its final metrics and the baseline's."""

    feeder: str
    feeder_id: str
    case: str
    start: str
    days: float
    steps: int
    wall_s: float
    metrics: m.MetricsFrame  # the bridge's final metrics frame (paper IV.F)
    # the no-control baseline of the same days, in the same form as ``metrics`` (its plotted series: baseline_trace.npz)
    baseline: m.MetricsFrame | None
    lockstep_misses: int
    decisions: int
    out_dir: str
    recording: str | None
    model: str | None
    holds: int = 0  # decisions with status 'hold' (no command sent), as the agent counted them
    soft: int = 0  # soft decisions: the soft form (eq. 17) and those the tap deadband tolerated
    tolerated: int = 0  # of them, the tap deadband's (taps held, the limits widened by the deadband met)
    reasons: dict[str, int] = {}  # the reasons of soft and hold decisions, most frequent first
    decision_ms: dict[str, float] = {}  # the agent's wall time per decision [ms]: p50, p99, max
    decision_cpu_ms: dict[str, float] = {}  # of it, the deciding thread's CPU time [ms]: p50, p99, max
    recorder_restarts: int = 0  # the recorder died and was restarted this many times; control went on
    recording_gaps: list[RecorderGap] = []  # what the recording misses because of it (also in the MCAP file)
    recorder_gave_up: bool = False  # the recorder died more than recorder_restarts_max times: recording stopped
    pv_protocol: str = "bus"  # how the PV plants reached the bus (``RunConfig.pv_protocol``)
    sunspec_frame_misses: int = 0  # sunspec: steps some adapter's PV frame did not reach the bridge in time
    field_protocol: str = "bus"  # how the regulators and banks reached the bus (``RunConfig.field_protocol``)
    dnp3_frame_misses: int = 0  # dnp3: steps some adapter's regulator or bank frame did not reach the bridge in time
    live: LiveAccuracy | None = None  # the agent's estimates and bounds against the truth of their step (bridge)
    secure: bool = False  # the bus ran with mTLS and the access policy (False: ``--insecure``)
    case_file: str | None = None  # the case file the run was read from (``cvvc run case.toml``)
    settings: RunCase | None = None  # the resolved case: every setting of the run, file and flags applied
    integrity: RunIntegrity = RunIntegrity()  # what was refused, missed or overwritten; whether control was lost
    follow_ups: int = 0  # commands sent a step after their decision (re-centred bands, ``Decision.follow_ups``)
    follow_up_misses: int = 0  # lockstep: steps whose announced follow-ups did not all reach the devices in time
    bought: int = 0  # the agent's decisions that took a tap move once the Q standing in for it had cost as much
    measured_steps_v120: dict[str, float] = {}  # the agent's: each regulator's step on its compared reading [V]
