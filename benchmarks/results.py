"""The benchmarks' results: one frozen ``msgspec.Struct`` per benchmark, printed by ``python -m benchmarks``.

Every result is frozen, keyword-only and rejects unknown fields on decode. Attributes carry their unit
(docs/conventions.md). Where the printed JSON key predates these types and names no unit (``seconds``,
``exit``, ``n``) or puts it elsewhere (``agent_ms_p50``), the attribute follows the conventions and
``msgspec.field(name=...)`` keeps the key, so ``make bench`` prints the same lines as before. ``to_json`` is
what the suite prints; ``decode_result`` reads one benchmark's JSON back into its type.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Literal, TypeVar

import msgspec

__all__ = [
    "BenchError",
    "BridgeBench",
    "BurstBench",
    "ClosedLoopBench",
    "DecisionBench",
    "LiveDecisionBench",
    "MemoryKib",
    "OfflineRerun",
    "ProcessMemory",
    "QstsBench",
    "RecordingBench",
    "RoundTrip",
    "SoakBench",
    "SoakLosses",
    "SolverRun",
    "SunspecBench",
    "Dnp3Bench",
    "TrainingBench",
    "decode_result",
    "to_json",
]

Publisher = Literal["auto", "inline", "process"]  # ``BridgeConfig.publisher``


class BenchError(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A benchmark that raised: its exception's type and message (the others still run)."""

    error: str


class QstsBench(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """``bench_qsts``: QSTS steps/s against bare OpenDSS solves of the same steps (``ratio``: goal < 1.3)."""

    feeder: str
    n_nodes: int
    steps: int
    qsts_steps_per_s: float
    bare_steps_per_s: float
    ratio: float  # best QSTS time / best bare time
    tap_changes: int
    cap_switches: int
    qsts_s: list[float]  # every repeat's time [s]
    bare_s: list[float]
    compile_s: float
    profiles_s: float


class BridgeBench(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """``bench_bridge``: lockstep steps/s with a trivial responder against the bare QSTS (module doc)."""

    feeder: str
    n_nodes: int
    steps: int
    bare_steps_per_s: float
    lockstep_steps_per_s: float
    overhead: float  # median bare rate / median lockstep rate - 1
    overheads: list[float]
    overhead_cpu: float
    overhead_thread_cpu: float
    publisher_cpu_share: float
    decision_wait_share: float
    round_trip_p50_ms: float | None
    round_trip_p99_ms: float | None
    control_steps: int
    decisions: int
    lockstep_misses: int
    truth_every: int
    publisher: Publisher
    publisher_used: str  # what "auto" chose


class TrainingBench(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Training time of one feeder (the profiles cached beforehand, not timed)."""

    wall_s: float = msgspec.field(name="seconds")
    scenarios: int
    power_flows: int
    critical_nodes: int
    goal_s: int


class SolverRun(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """``bench_solver.main``: its exit code and wall time (its figures are printed by itself)."""

    exit_code: int = msgspec.field(name="exit")
    wall_s: float = msgspec.field(name="seconds")


class DecisionBench(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """``bench_decision``: the agent's per-decision time over a whole simulated day, beside the floor (OSQP's own solve
    of each decision's relaxation) and case A's per-interval cost on sampled states of the same day.

    The agent's figures are of one run (each decision timed once, as it happens live), the cold first decision
    apart; ``agent_best_of_n_*`` is the older figure (per step the fastest of ``best_of_n`` runs), labelled as such.
    """

    feeder: str
    critical_nodes: int
    nodes: int
    plants: int
    regulators: int
    control_steps: int
    agent_p50_ms: float = msgspec.field(name="agent_ms_p50")
    agent_p99_ms: float = msgspec.field(name="agent_ms_p99")
    agent_max_ms: float = msgspec.field(name="agent_ms_max")
    agent_cold_first_decision_ms: float
    agent_best_of_n_p50_ms: float = msgspec.field(name="agent_best_of_n_ms_p50")
    agent_best_of_n_p99_ms: float = msgspec.field(name="agent_best_of_n_ms_p99")
    best_of_n: int
    osqp_p50_ms: float = msgspec.field(name="osqp_ms_p50")  # OSQP set-up + solve of each decision's relaxation
    osqp_p99_ms: float = msgspec.field(name="osqp_ms_p99")
    ratio_agent_to_osqp_p50: float
    case_a_steps: int  # the sampled steps case A is timed on
    case_a_mean_ms: float = msgspec.field(name="case_a_ms_mean")
    case_a_oracle_mean_ms: float = msgspec.field(name="case_a_oracle_ms_mean")
    case_a_state_max_dv_pu: float  # the oracle engine's voltages against the simulation's
    ratio_case_a_to_agent_mean: float  # on the sampled steps: case A's mean over the agent's mean there
    load_average: float  # the machine's 1-minute load average when the agent's run started
    method: str
    goal: str


class LiveDecisionBench(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """``bench_live``: the agent's own time per decision in case D runs through the bus, a day of each season,
    read from the runs' recordings (``align_s + total_s``: the step's alignment and snapshot, then the decision).
    """

    feeder: str
    decisions: int  # over the four seasons' days
    days_per_season: float
    p50_ms: float
    p99_ms: float
    max_ms: float
    cpu_p50_ms: float  # the deciding thread's CPU time (``Timings.cpu_s``: the snapshot and the decision)
    cpu_p99_ms: float
    season_p99_ms: dict[str, float]
    first_decision_ms: dict[str, float]  # each run's first decision (cold: the agent's process just started)
    lockstep_misses: int  # steps the bridge went on without a decision (a starved machine: the figures are suspect)
    p99_goal_met: bool
    load_average: float  # the machine's 1-minute load average before the first run
    wall_s: float
    method: str
    goal: str


class OfflineRerun(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The offline re-run of one recorded synthetic day: its speed and the diff against the recording."""

    sim_minutes_per_wall_s: float
    frames: int
    decisions: int
    identical: int
    wall_s: float


class RecordingBench(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """``bench_recording``: messages/s through Zenoh into MCAP against the bare writer (``ratio``: goal > 0.5)."""

    messages: int = msgspec.field(name="n")
    bare_writer_msg_per_s: int
    zenoh_to_mcap_msg_per_s: int
    ratio: float
    recorded: int
    all_recorded: bool
    dropped: int
    bytes_per_message: float
    mean_payload_bytes: float
    offline_rerun: OfflineRerun | None  # None while ``agent.runtime.decide_offline`` is missing


class BurstBench(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """``bench_burst``: a decision's burst (11 commands then the decision) put express each vs batched.

    Per round and mode, medians over ``bursts``: ``*_put_cpu_us`` the publishing thread's CPU per burst [µs],
    ``*_latency_ms`` from the burst's first put to the subscriber (another process) receiving its decision [ms].
    ``batched``: the commands non-express, the decision express (it flushes them).
    """

    bursts: int
    rounds: int
    express_put_cpu_us: list[float]
    batched_put_cpu_us: list[float]
    express_latency_ms: list[float]
    batched_latency_ms: list[float]


class ClosedLoopBench(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """``bench_closedloop``: a recorded ``cvvc run`` (bridge, agent, recorder) against bare OpenDSS of the same steps.

    ``ratio`` = run wall time / bare time; ``loop_ratio`` the same with the
    bridge's stepping loop alone (no process start-up, no profile or model loading). ``bare_s`` steps the same loads,
    PV and the closed loop's own taps (read back from the recording's truth) with nothing else. ``truth_*``: the
    truth channel's payload per simulated week, as sent and after zstd in 1 MiB chunks (the recorder's chunking).
    """

    feeder: str
    case: str
    days: float
    steps: int
    run_wall_s: float  # RunSummary.wall_s: processes started to everything stopped [s]
    loop_wall_s: float  # the bridge's stepping loop [s]
    bare_s: float  # bare OpenDSS of the same steps, best of ``bare_repeats`` [s]
    bare_repeats: int
    ratio: float
    loop_ratio: float
    decision_wait_s: float  # the bridge's wait for the agent's decisions and commands [s]
    bridge_thread_cpu_s: float
    publisher_cpu_s: float
    round_trip_p50_s: float | None
    lockstep_misses: int
    recording_bytes_per_week: int
    truth_payload_bytes_per_week: int
    truth_zstd_bytes_per_week: int
    truth_frames: int  # in the recording (a step without one replays the previous step's taps in bare)
    truth_encoding: str  # the truth channel's MCAP message encoding


class MemoryKib(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True, omit_defaults=True):
    """``VmHWM`` and ``VmRSS`` of one process [KiB], as ``/proc/<pid>/status`` lists them (absent: gone)."""

    vm_hwm_kib: int | None = msgspec.field(default=None, name="VmHWM")
    vm_rss_kib: int | None = msgspec.field(default=None, name="VmRSS")


class ProcessMemory(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One process of the soak: memory at the first hour, at start and at the end, and the growths."""

    first_hour_kib: MemoryKib
    start_kib: MemoryKib
    end_kib: MemoryKib
    rss_growth: float | None  # end / start - 1
    hwm_growth: float | None


class SoakLosses(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Dropped or late frames of the soak (goal: 0 in lockstep) and the recorder's counts."""

    lockstep_misses: int
    lockstep_skipped: int
    bridge_frames_dropped: int
    control_steps: int
    decisions_seen: int
    control_steps_without_decision: int
    agent_queue_full: int
    agent_stale: int
    agent_rejected: dict[str, int]
    bridge_rejected: dict[str, int]
    recorder_dropped_queue_full: int  # -1: the recording has no recorder stats
    recorder_messages: int


class SoakBench(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """``bench_soak``: memory growth of every process and losses over simulated days in lockstep."""

    feeder: str
    days: float
    steps: int
    start: str
    wall_s: float
    steps_per_s: float
    exit_codes: dict[str, int]
    last_status_step: int | None
    memory: dict[str, ProcessMemory]  # bridge, agent, recorder, router
    losses: SoakLosses
    samples: int
    rss_by_day_kib: dict[str, list[int | None]]
    recording_complete: bool
    recording_bytes: int
    max_growth: float | None
    goal_growth: float
    growth_goal_met: bool
    lost_or_late: int
    loss_goal_met: bool
    out_dir: str | None


class RoundTrip(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Percentiles of round trips [ms]."""

    p50_ms: float
    p99_ms: float


class SunspecBench(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """``bench_sunspec``: command -> ack with and without the SunSpec hop, and the Modbus part alone."""

    commands: int
    bus_only: RoundTrip
    through_sunspec: RoundTrip
    modbus_write_read_back: RoundTrip
    extra_per_decision_p50_ms: float
    extra_per_decision_p99_ms: float


class Dnp3Bench(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """``bench_dnp3``: regulator command -> ack with and without the DNP3 hop, and the DNP3 part alone."""

    commands: int
    bus_only: RoundTrip
    through_dnp3: RoundTrip
    dnp3_operates_read_back: RoundTrip
    extra_per_decision_p50_ms: float
    extra_per_decision_p99_ms: float


R = TypeVar("R", bound=msgspec.Struct)
_Printable = msgspec.Struct | Mapping[str, msgspec.Struct | Mapping[str, msgspec.Struct]]


def to_json(result: _Printable) -> str:
    """The JSON ``python -m benchmarks`` prints: keys in field order, indented by 2, as ``json.dumps`` writes."""
    return json.dumps(msgspec.to_builtins(result), indent=2)


def decode_result(data: bytes | str, result_type: type[R]) -> R:
    """Decode one benchmark's JSON (``to_json``'s output) into its result type; ``msgspec.ValidationError`` if
    it does not fit.
    """
    return msgspec.json.decode(data, type=result_type)
