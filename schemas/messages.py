"""Every message on the cvvc bus, as frozen msgspec Structs.

Conventions (docs/conventions.md): generator convention for device output (``q_kvar > 0`` injects
reactive power into the grid); the feeder-head meter reports power flowing *into* the feeder; voltages
``_v`` are line-to-neutral volts, ``_v120`` volts on the 120 V base, ``_pu`` per unit of the node's
nominal line-to-neutral voltage; time ``t_ns`` is integer nanoseconds since the Unix epoch (UTC), the
*measurement* time, never the wall clock of the receiver.

Every field with a number has bounds (``Meta``): msgspec checks them on decode, so out-of-range and
infinite values (JSON ``1e999``) are rejected at the door. So does every list, dict, string and byte string: a
length bound (``MAX_DEVICES``, ``MAX_NODES``, the six quality flags, ...), so an oversized list is refused as
``out_of_range`` before any code sees it (0.88 MB of quality flags used to decode). JSON cannot carry NaN;
senders refuse non-finite numbers (``schemas.bus.check_finite``). Schemas evolve append-only, with defaults.
"""

from __future__ import annotations

from typing import Annotated, ClassVar, Literal

import msgspec
import numpy as np
from msgspec import Meta

__all__ = [
    "MAX_DEVICES",
    "MAX_NODES",
    "MESSAGE_TYPES",
    "Ack",
    "AgentStatus",
    "BAND_RANGE_V120",
    "BridgeStatus",
    "CapCommand",
    "CapControlType",
    "CapFrame",
    "Command",
    "Decision",
    "DecisionCommand",
    "HeadFrame",
    "HeadPhase",
    "LinkStatus",
    "Message",
    "MeterFrame",
    "MetricsFrame",
    "NodeEstimate",
    "OracleReply",
    "OracleRequest",
    "Phase",
    "PvCommand",
    "PvFrame",
    "PvPhase",
    "QualityFlag",
    "RegCommand",
    "RegFrame",
    "RegPhase",
    "SETPOINT_RANGE_V120",
    "SetpointAction",
    "SolverStats",
    "StepEnd",
    "TapAction",
    "Timings",
    "TRUTH_LAYOUT",
    "TruthFrame",
    "TruthPack",
    "Wire",
    "pack_v_pu",
    "unpack_v_pu",
    "wire_of",
]

# ---------------------------------------------------------------------------------------------- scalars
TimeNs = Annotated[int, Meta(ge=0, le=2**63 - 1, description="integer ns since the Unix epoch (UTC)")]
Seq = Annotated[int, Meta(ge=0, le=2**63 - 1)]
Ident = Annotated[str, Meta(pattern=r"^[A-Za-z0-9_.\-]{1,64}$", max_length=64)]
Reason = Annotated[str, Meta(max_length=500)]
Phase = Literal["a", "b", "c"]
VoltsLN = Annotated[float, Meta(ge=0.0, le=1e6)]
Amps = Annotated[float, Meta(ge=0.0, le=1e6)]
AngleDeg = Annotated[float, Meta(ge=-360.0, le=360.0)]
Kw = Annotated[float, Meta(ge=-1e6, le=1e6)]
Kvar = Annotated[float, Meta(ge=-1e6, le=1e6)]
Kva = Annotated[float, Meta(ge=0.0, le=1e6)]
V120 = Annotated[float, Meta(ge=0.0, le=200.0)]
Band120 = Annotated[float, Meta(gt=0.0, le=12.0)]
Pu = Annotated[float, Meta(ge=0.0, le=3.0)]
Tap = Annotated[int, Meta(ge=-16, le=16)]
Cost = Annotated[float, Meta(ge=0.0, le=1e12)]
Count = Annotated[int, Meta(ge=0, le=2**53)]
Seconds = Annotated[float, Meta(ge=0.0, le=1e6)]
Sens = Annotated[float, Meta(ge=-1.0, le=1.0)]
CapSteps = Annotated[int, Meta(ge=0, le=64)]  # closed steps of a capacitor bank (OpenDSS allows up to 64 steps)
ControlValue = Annotated[float, Meta(ge=-1e9, le=1e9)]  # a CapControl's compared quantity, in its own unit
CapControlType = Literal["voltage", "kvar", "current", "pf", "time", "follow", "none"]

SETPOINT_RANGE_V120 = (108.0, 132.0)
"""Set points a regulator controller accepts [V on the 120 V base]: ±10 % of 120 V (the command contract)."""
BAND_RANGE_V120 = (1.0, 8.0)
"""Bandwidths a regulator controller accepts [V on the 120 V base] (the paper's case C uses 4 V)."""

QualityFlag = Literal["invalid", "questionable", "substituted", "old_data", "test", "noisy"]
Qualities = Annotated[list[QualityFlag], Meta(max_length=6)]  # each flag at most once

MAX_DEVICES = 4096
"""The most devices of one kind (PV plants, regulators, banks) a message lists: a bound, not a feeder's size."""
MAX_NODES = 300_000
"""The most nodes a message lists (IEEE 8500: about 8,500 phase nodes; epri-ckt24 about 10,000); above the 262,144
float32 voltages a 1 MiB truth frame can hold, so for the truth the payload limit binds first."""
NodeName = Annotated[str, Meta(max_length=256)]  # an OpenDSS node, bus.phase
CountKey = Annotated[str, Meta(max_length=200)]  # what a count is of: a kind of refusal, a device, a point
Counts = Annotated[dict[CountKey, Annotated[int, Meta(ge=0, le=2**53)]], Meta(max_length=MAX_DEVICES)]
NodeList = Annotated[list[NodeName], Meta(max_length=MAX_NODES)]
SensMatrix = Annotated[list[Annotated[list[Sens], Meta(max_length=MAX_DEVICES)]], Meta(max_length=MAX_NODES)]


class Message(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Common header: measurement time, per-source sequence number, and who sent it."""

    t_ns: TimeNs
    seq: Seq
    source: Ident


class Command(Message, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Header of every command: its id, the measurement seq it answers, and when it expires."""

    cmd_id: Annotated[str, Meta(pattern=r"^[A-Za-z0-9_.:\-]{1,96}$", max_length=96)]
    in_reply_to: Seq
    valid_until_t_ns: TimeNs


# ------------------------------------------------------------------------------------- measurements
class HeadPhase(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One phase of the feeder-head meter: voltage and current phasors, P and Q into the feeder."""

    phase: Phase
    v_mag_v: VoltsLN
    v_ang_deg: AngleDeg
    i_mag_a: Amps
    i_ang_deg: AngleDeg
    p_kw: Kw
    q_kvar: Kvar


class HeadFrame(Message, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Feeder-head meter (PMU-style): per-phase phasors and power into the feeder."""

    feeder_id: Ident
    phases: Annotated[list[HeadPhase], Meta(min_length=1, max_length=3)]
    p_kw: Kw
    q_kvar: Kvar
    quality: Qualities = []


class PvPhase(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One phase of a PV plant: P and Q (generator convention) and the terminal voltage."""

    phase: Phase
    p_kw: Kw
    q_kvar: Kvar
    v_mag_v: VoltsLN


class PvFrame(Message, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A PV plant inverter: output (generator convention), rating and its present reactive set point."""

    plant_id: Ident
    phases: Annotated[list[PvPhase], Meta(min_length=1, max_length=3)]
    p_kw: Kw
    q_kvar: Kvar
    s_rated_kva: Kva
    q_available_kvar: Kva  # headroom sqrt(S^2 - P^2) at this P
    q_setpoint_kvar: Kvar | None = None  # None: on its local default
    local_mode: Literal["unity_pf", "volt_var"] = "unity_pf"
    quality: Qualities = []


class RegPhase(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One phase of a regulator: its PT secondary voltage on the 120 V base."""

    phase: Phase
    v_120: V120  # raw secondary voltage on the 120 V base (PT secondary)


class RegFrame(Message, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A regulator controller (one tap changer): secondary voltage, tap and its present settings."""

    regulator_id: Ident
    phases: Annotated[list[RegPhase], Meta(min_length=1, max_length=3)]
    v_compared_120: V120  # what the controller compares with its band (line-drop compensation included)
    tap: Tap
    setpoint_v120: V120
    band_v120: Band120
    mode: Literal["local", "locked"]
    quality: Qualities = []


class CapFrame(Message, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A switched capacitor bank: its state, bus voltage, its local control's reading, and the settings in force.

    ``closed_steps`` of ``steps`` are closed (0: open). ``v_v`` is the bus line-to-neutral voltage [V] (the mean of
    the bank's phases). ``control_type`` is its ``CapControl``'s type (``none``: no local control, the bank holds);
    ``control_value`` is the quantity that control compares with its ON/OFF settings, in the control's own unit
    (V on its PT secondary, kvar, A, power factor, hour of day; ``None`` without a control). ``mode``:
    ``local`` (its control acts) or ``commanded`` (held at a commanded state; ``cmd_id`` and
    ``valid_until_t_ns`` say which command and until when).
    """

    capacitor_id: Ident
    closed_steps: CapSteps
    steps: Annotated[int, Meta(ge=1, le=64)]
    kvar_rated: Kva  # the bank's rating, all steps closed [kvar]
    v_v: VoltsLN
    control_type: CapControlType = "none"
    control_value: ControlValue | None = None
    mode: Literal["local", "commanded"] = "local"
    cmd_id: Annotated[str, Meta(max_length=96)] | None = None
    valid_until_t_ns: TimeNs | None = None
    quality: Qualities = []


class MeterFrame(Message, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """An AMI meter's voltage reading at a customer node (explicit option beyond the paper; ``MeterSpec``).

    ``node`` is the OpenDSS node (``bus.phase``) the meter reads; ``v_pu`` its voltage [pu of the node's base],
    read at ``t_ns`` (every ``interval_s`` of the meter, not every step).
    """

    meter_id: Ident
    node: Ident
    v_pu: Pu
    interval_s: Annotated[int, Meta(ge=60, le=86_400)] = 900


# ------------------------------------------------------------------------------------------ commands
class PvCommand(Command, frozen=True, kw_only=True, forbid_unknown_fields=True, tag="pv"):
    """Reactive power set point for one PV plant [kvar], generator convention."""

    plant_id: Ident
    q_kvar: Kvar


class TapAction(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True, tag="tap"):
    """Lock the tap changer at a position (cases A/B)."""

    tap: Tap


class SetpointAction(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True, tag="setpoint"):
    """Local control around a voltage set point and band on the 120 V base (cases C/D, paper eq. 8)."""

    setpoint_v120: Annotated[float, Meta(ge=100.0, le=140.0)]
    band_v120: Band120


class RegCommand(Command, frozen=True, kw_only=True, forbid_unknown_fields=True, tag="vr"):
    """A regulator command: a tap position or a voltage set point and band."""

    regulator_id: Ident
    action: TapAction | SetpointAction


class CapCommand(Command, frozen=True, kw_only=True, forbid_unknown_fields=True, tag="cap"):
    """Hold a capacitor bank at ``closed_steps`` closed steps until ``valid_until_t_ns``; ``None`` (JSON ``null``)
    releases it to its local control at once. Acked like every command; on expiry the bank returns to its local
    control (its ``CapControl``, or holding its state when it has none).
    """

    capacitor_id: Ident
    closed_steps: CapSteps | None


DecisionCommand = PvCommand | RegCommand | CapCommand


class Ack(Message, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A device's answer to one command. ``applied_value`` is kvar (PV), a tap, volts (set point), or a
    capacitor bank's closed steps (None when a bank was released to its local control).
    """

    cmd_id: Annotated[str, Meta(max_length=96)]
    device_id: Ident
    status: Literal["accepted", "clipped", "rejected", "expired"]
    applied_value: Annotated[float, Meta(ge=-1e6, le=1e6)] | None = None
    reason: Reason = ""


# ------------------------------------------------------------------------------------------ decisions
class NodeEstimate(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A critical node's estimated voltage, its calibrated bounds and the voltage predicted after the actions [pu]."""

    node: Annotated[str, Meta(max_length=128)]
    v_pu: Pu
    v_predicted_pu: Pu  # after the decided actions (linear model)
    bound_low_pu: Pu = 0.0  # calibrated bounds as applied: the true voltage is expected in [v - low, v + high]
    bound_high_pu: Pu = 0.0


class SolverStats(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The optimizer's status, iterations and eq. (9) objective of one decision."""

    status: Annotated[str, Meta(max_length=64)]
    iterations: Count = 0
    objective: Annotated[float, Meta(ge=-1e12, le=1e12)] = 0.0
    soft: bool = False


class Timings(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Wall time spent in each stage [s]. Not part of the decision's content (replay ignores it)."""

    align_s: Seconds = 0.0
    estimate_s: Seconds = 0.0
    solve_s: Seconds = 0.0
    round_s: Seconds = 0.0
    total_s: Seconds = 0.0
    # the deciding thread's CPU time from the step's snapshot to its message: the rest of ``total_s`` (which includes
    # ``align_s``) the step waited, for its frames' alignment or for a core
    cpu_s: Seconds = 0.0


class Decision(Message, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One per control step: what the agent decided, from what, and how long it took.

    ``status``: ``optimal`` (hard limits met), ``soft`` (soft form: some violation predicted), ``hold`` (no
    new commands; devices keep their last valid commands or local control; ``reason`` says why).
    """

    feeder_id: Ident
    step_t_ns: TimeNs  # t_ns of the frames this decision answers
    in_reply_to: Seq  # seq of the feeder-head frame it answers
    status: Literal["optimal", "soft", "hold"]
    reason: Reason = ""
    commands: Annotated[list[DecisionCommand], Meta(max_length=3 * MAX_DEVICES)] = []
    estimates: Annotated[list[NodeEstimate], Meta(max_length=MAX_NODES)] = []
    dv_dq_pu_per_kvar: SensMatrix = []  # [node][plant]
    dv_dtap_pu: SensMatrix = []  # [node][regulator]
    solver: SolverStats | None = None
    timings: Timings = Timings()
    corrected: bool = False
    missing: Annotated[list[Ident], Meta(max_length=3 * MAX_DEVICES + 1)] = []  # frames missing, stale or invalid
    out_of_envelope: bool = False  # the inputs left what training covered: bounds widened (``reason`` says which)
    # commands (their cmd_id) the agent sends once the next step's frames are in: set points mode, the band of a
    # regulator told to step re-centred on its new reading (agent.setpoints.recentred_setpoint); lockstep waits
    follow_ups: Annotated[list[Annotated[str, Meta(max_length=96)]], Meta(max_length=MAX_DEVICES)] = []


class AgentStatus(Message, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Agent health, published on a wall-clock period: staleness and rejected-input counts.

    ``degraded``: the agent refused most of the frames it received lately; ``reason`` says which and why.
    """

    feeder_id: Ident
    state: Literal["ok", "stale", "holding", "starting", "degraded"]
    last_frame_t_ns: TimeNs = 0
    seconds_since_frame: Seconds = 0.0
    decisions: Count = 0
    rejected: Counts = {}
    reason: Reason = ""
    log_suppressed: Counts = {}  # log lines not written by the rate limit so far, by kind


# ----------------------------------------------------------------------------------- simulation only
class TruthFrame(Message, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Every node's true voltage [pu] (simulation only). ``node_names`` is sent on the first frame."""

    feeder_id: Ident
    v_pu: Annotated[list[Pu], Meta(max_length=MAX_NODES)]
    v_min_pu: Pu
    v_max_pu: Pu
    node_names: NodeList | None = None
    taps: Annotated[list[Tap], Meta(max_length=MAX_DEVICES)] = []
    pv_q_kvar: Annotated[list[Kvar], Meta(max_length=MAX_DEVICES)] = []
    cap_states: Annotated[list[CapSteps], Meta(max_length=MAX_DEVICES)] = []  # each bank's closed steps (map order)


TRUTH_LAYOUT = "f32le-shuffle4"
"""``TruthPack.layout``: float32 little-endian, the 4 bytes of the values stored plane by plane (every value's
first byte, then every second byte, ...): the exponent bytes of voltages near 1 pu are nearly constant, so zstd
compresses the planes far better than interleaved floats (measured on the rural feeder's truth: 2.6 vs 3.6 kB a
frame after zstd, 10.4 kB as JSON text)."""


def pack_v_pu(v_pu: np.ndarray) -> bytes:
    """The bytes of ``TruthPack.v_pu_f32``: ``v_pu`` [pu] as float32 little-endian, byte planes (``TRUTH_LAYOUT``).

    float32 keeps 24 bits of mantissa: within 6e-8 pu of the float64 value between 0.5 and 2 pu.
    """
    f32 = np.asarray(v_pu, dtype="<f4")
    return np.ascontiguousarray(f32.reshape(-1).view(np.uint8).reshape(-1, 4).T).tobytes()


def unpack_v_pu(raw: bytes, n_nodes: int) -> np.ndarray:
    """``TruthPack.v_pu_f32`` back into a new float64 array of ``n_nodes`` voltages [pu] (inverse of
    ``pack_v_pu``); ValueError when ``raw`` does not hold exactly ``n_nodes`` values.
    """
    if len(raw) != 4 * n_nodes:
        raise ValueError(f"v_pu_f32 holds {len(raw)} bytes, expected 4 x n_nodes = {4 * n_nodes}")
    planes = np.frombuffer(raw, dtype=np.uint8).reshape(4, n_nodes)
    return np.ascontiguousarray(planes.T).view("<f4").reshape(n_nodes).astype(np.float64)


class TruthPack(Message, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Every node's true voltage, compact (simulation only): the ``sim/truth`` message, Protobuf ``cvvc.Truth`` on
    the bus and in recordings (``WIRE``; ``schemas.truth_proto``), so Foxglove decodes it. In Python ``v_pu_f32``
    holds ``n_nodes`` voltages [pu] as float32 (``pack_v_pu``; read them with ``unpack_v_pu`` or
    ``schemas.truth.truth_arrays``); the rest is ``TruthFrame``'s, whose JSON form ``schemas.truth.to_truth_frame``
    gives. Recordings of earlier versions hold it as MessagePack (``schemas.truth.decode_truth`` reads those).
    Decoding checks the byte count and that every voltage is within 0..3 pu (NaN is not).
    """

    WIRE: ClassVar[str] = "protobuf"
    feeder_id: Ident
    n_nodes: Annotated[int, Meta(ge=0, le=MAX_NODES)]
    v_pu_f32: Annotated[bytes, Meta(max_length=4 * MAX_NODES)]
    v_min_pu: Pu
    v_max_pu: Pu
    node_names: NodeList | None = None
    taps: Annotated[list[Tap], Meta(max_length=MAX_DEVICES)] = []
    pv_q_kvar: Annotated[list[Kvar], Meta(max_length=MAX_DEVICES)] = []
    cap_states: Annotated[list[CapSteps], Meta(max_length=MAX_DEVICES)] = []  # each bank's closed steps (map order)
    layout: Literal["f32le-shuffle4"] = "f32le-shuffle4"  # the version of v_pu_f32's layout (TRUTH_LAYOUT)

    def __post_init__(self) -> None:
        """Check ``v_pu_f32`` (runs on decode too: a bad frame is a ``msgspec.ValidationError``)."""
        v = unpack_v_pu(self.v_pu_f32, self.n_nodes)
        if not (bool((v >= 0.0).all()) and bool((v <= 3.0).all())):
            raise ValueError("v_pu_f32 holds a voltage outside 0..3 pu or not a number")
        if self.node_names is not None and len(self.node_names) != self.n_nodes:
            raise ValueError(f"node_names has {len(self.node_names)} names for {self.n_nodes} voltages")


Wire = Literal["json", "msgpack", "protobuf"]


def wire_of(msg_type: type) -> Wire:
    """How ``msg_type`` is encoded on the bus and in recordings: ``protobuf`` for ``TruthPack``, else ``json``
    (``msgpack``: the truth in recordings of earlier versions, read only).
    """
    wire = getattr(msg_type, "WIRE", "json")
    return "protobuf" if wire == "protobuf" else "msgpack" if wire == "msgpack" else "json"


class MetricsFrame(Message, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Paper IV.F metrics from the truth, since ``start_t_ns`` (cumulative). ``final`` on shutdown."""

    feeder_id: Ident
    start_t_ns: TimeNs
    steps: Count
    mvvm_pu: Annotated[float, Meta(ge=0.0, le=3.0)]
    nvv: Count
    minutes_in_violation: Count
    ntc: Count
    q_cost: Cost
    t_cost: Cost
    total_cost: Cost
    v_min_pu: Pu
    v_max_pu: Pu
    taps_changes: Counts = {}
    q_mvar_intervals: Annotated[dict[CountKey, Annotated[float, Meta(ge=0.0, le=1e12)]],
                                Meta(max_length=MAX_DEVICES)] = {}
    final: bool = False
    cap_switches: Count = 0  # capacitor switching operations (steps opened or closed), over every bank
    cap_cost: Cost = 0.0  # sum over banks of cost_per_switch x switchings (included in total_cost)
    cap_switches_per_bank: Counts = {}
    # every minute on its own (no average): judged nodes outside the optimization limits and ANSI C84.1 Range A
    node_minutes_outside_opt: Count = 0
    minutes_outside_opt: Count = 0
    node_minutes_outside_ansi: Count = 0
    minutes_outside_ansi: Count = 0
    # steps at which a regulator had moved faster than its RegControl's tapdelay allows (empty: not judged)
    steps_over_tap_rate: Counts = {}
    # the optimization limits the per-minute counts were judged against (None: not stated, older recordings)
    opt_limits_pu: tuple[Pu, Pu] | None = None


class BridgeStatus(Message, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Bridge health: where the simulation is, lockstep misses, and rejected-command counts."""

    feeder_id: Ident
    step: Count
    steps_total: Count
    clock: Literal["lockstep", "realtime"]
    lockstep_misses: Count = 0
    agent_alive: bool = False
    rejected: Counts = {}
    done: bool = False
    log_suppressed: Counts = {}  # log lines not written by the rate limit so far, by kind


class StepEnd(Message, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The end of one scan: which devices sent a frame for ``t_ns``, from whoever collects the frames (the bridge
    in simulation), after those frames.

    Lets a receiver decide on a step as soon as every frame that was sent has arrived, instead of waiting out a
    late-frame window for frames that were lost. A device of the feeder not
    listed sent nothing for this step.
    """

    feeder_id: Ident
    head: bool  # the feeder-head meter sent its frame
    pv: Annotated[list[Ident], Meta(max_length=4096)] = []  # PV plants that sent a frame
    vr: Annotated[list[Ident], Meta(max_length=4096)] = []  # regulator controllers that sent a frame
    cap: Annotated[list[Ident], Meta(max_length=4096)] = []  # capacitor banks that sent a frame


class LinkStatus(Message, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A field-protocol adapter's link to one device (a PV inverter behind SunSpec Modbus, a regulator control or
    capacitor bank controller behind DNP3).

    Published by the adapter when the link's state changes and on a period. ``state``: ``starting`` (not yet
    read), ``ok`` (the last scan read valid values), ``down`` (the device does not answer: no frames are sent,
    commands are acknowledged ``rejected``), ``refusing`` (the device answers with values refused as malformed
    or out of range: no frames are sent). ``refused`` counts refused register values by point (``701.W``);
    ``reason`` says what happened last, in words.
    """

    feeder_id: Ident
    device_id: Ident
    kind: Literal["pv", "vr", "cap"] = "pv"
    protocol: Literal["sunspec", "dnp3"] = "sunspec"
    endpoint: Annotated[str, Meta(max_length=200)] = ""
    state: Literal["starting", "ok", "down", "refusing"]
    scans: Count = 0
    scan_failures: Count = 0
    frames: Count = 0
    refused: Counts = {}
    commands: Count = 0
    commands_failed: Count = 0
    last_ok_t_ns: TimeNs = 0
    reason: Reason = ""
    foreign_writes: Count = 0  # scans that found a set point the adapter did not write (it wrote its own again)


class OracleRequest(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Case A: ask the bridge for true voltages and perturbation sensitivities at its present state."""

    t_ns: TimeNs
    include_sensitivities: bool = True


class OracleReply(Message, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Case A: true voltages of every node and perturbation sensitivities at one step, from the bridge."""

    feeder_id: Ident
    node_names: NodeList
    v_pu: Annotated[list[Pu], Meta(max_length=MAX_NODES)]
    dv_dq_pu_per_kvar: SensMatrix = []  # [node][plant]
    dv_dtap_pu: SensMatrix = []  # [node][regulator]
    taps: Annotated[list[Tap], Meta(max_length=MAX_DEVICES)] = []
    dv_dp_pu_per_kw: SensMatrix = []  # [node][plant], per kW of output (for the PV variability margin)


MESSAGE_TYPES: tuple[type[msgspec.Struct], ...] = (
    HeadFrame,
    PvFrame,
    RegFrame,
    PvCommand,
    RegCommand,
    Ack,
    Decision,
    AgentStatus,
    TruthFrame,
    MetricsFrame,
    BridgeStatus,
    OracleRequest,
    OracleReply,
    CapFrame,
    CapCommand,
    StepEnd,
    LinkStatus,
    TruthPack,
    MeterFrame,
)
