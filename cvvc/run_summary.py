"""What ``cvvc run`` reports (``summary.json``): the one result type of a run, read by the run's report, the
evaluation and the fleet.
"""

from __future__ import annotations

import msgspec

from recordings.info import RecorderGap
from schemas import messages as m
from simulator_bridge.simulation.live_accuracy import LiveAccuracy

__all__ = ["RunSummary"]


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
    soft: int = 0  # decisions on the soft form (eq. 17)
    reasons: dict[str, int] = {}  # the reasons of soft and hold decisions, most frequent first
    decision_ms: dict[str, float] = {}  # the agent's wall time per decision [ms]: p50, p99, max
    recorder_restarts: int = 0  # the recorder died and was restarted this many times; control went on
    recording_gaps: list[RecorderGap] = []  # what the recording misses because of it (also in the MCAP file)
    recorder_gave_up: bool = False  # the recorder died more than recorder_restarts_max times: recording stopped
    pv_protocol: str = "bus"  # how the PV plants reached the bus (``RunConfig.pv_protocol``)
    sunspec_frame_misses: int = 0  # sunspec: steps some adapter's PV frame did not reach the bridge in time
    live: LiveAccuracy | None = None  # the agent's estimates and bounds against the truth of their step (bridge)
    secure: bool = False  # the bus ran with mTLS and the access policy (False: ``--insecure``)
