"""``cvvc fleet``'s results: per-feeder rows, the recording's cross-feeder check and decision times, the table.

Pure over files the run left behind (the one recording, the processes' summaries); no bus, no processes.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import msgspec
import numpy as np

from cvvc.run_summary import RunIntegrity

__all__ = ["CrossFeederProbe", "FeederRow", "FleetSummary", "RecordingCheck", "check_recording", "render_fleet"]


class FeederRow(msgspec.Struct, frozen=True, kw_only=True):
    """One feeder of a fleet run: what its agent and bridge reported, and its decision times from the recording.

    Times in milliseconds; ``None`` when not measured (no recording, or no decision).
    """

    feeder_id: str
    feeder: str  # the device map
    case: str
    year_seed: int
    steps: int
    decisions: int
    holds: int
    soft: int
    decision_p50_ms: float | None
    decision_p99_ms: float | None
    round_trip_p50_ms: float | None
    round_trip_p99_ms: float | None
    lockstep_misses: int
    nvv: int
    mvvm_pu: float
    ntc: int
    agent_refused: int  # inputs the agent refused (any reason), from its summary
    bridge_rejected: int  # commands the bridge's devices rejected (any reason), from its summary
    bridge_wall_s: float
    out_dir: str
    integrity: RunIntegrity = RunIntegrity()  # what was refused, missed or overwritten; whether control was lost


class CrossFeederProbe(msgspec.Struct, frozen=True, kw_only=True):
    """Secure mode: a command put with feeder ``sender``'s agent certificate on feeder ``target``'s ``key``.

    ``reached``: the router forwarded it (the launcher's own subscription, inside the router, saw it on
    ``key``) or the target's device acknowledged it; the access policy must make both false.
    ``target_acks_after``: acks of the target's own agent's commands seen after the probe was put, so the
    target was live and commanded while the probe was refused.
    """

    sender: str
    target: str
    key: str
    reached: bool
    acked: bool
    target_acks_after: int


class RecordingCheck(msgspec.Struct, frozen=True, kw_only=True):
    """What the one recording of a fleet shows about feeders keeping to their key spaces.

    ``crossing``: recorded messages on ``cvvc/<F>/...`` whose ``feeder_id`` is not ``F``; ``foreign_topics``:
    recorded topics whose feeder segment is no feeder of the fleet; ``checked``: messages that carry a
    ``feeder_id``. ``wrong_feeder_acks``: acks (they carry no feeder id) that another feeder's bridge put on
    ``F``'s ack keys, refusing a command of ``F`` it received on its ``cvvc/*/cmd/**`` subscription (reason
    ``wrong_feeder``), by ``F``.
    """

    messages: int
    checked: int
    crossing: int
    foreign_topics: list[str]
    decision_s: dict[str, list[float]]  # per feeder: each recorded decision's ``timings.total_s`` [s]
    wrong_feeder_acks: dict[str, int] = {}


class FleetSummary(msgspec.Struct, frozen=True, kw_only=True):
    """What ``cvvc fleet`` reports (``fleet-summary.json``)."""

    feeders: list[FeederRow]
    days: float
    start: str
    wall_s: float  # from the router's start to the last process stopped [s]
    secure: bool
    out_dir: str
    recording: str | None
    recorded_messages: int = 0
    messages_checked: int = 0
    crossing_messages: int = 0
    foreign_topics: list[str] = []
    probe: CrossFeederProbe | None = None
    wrong_feeder_acks: dict[str, int] = {}  # ``RecordingCheck.wrong_feeder_acks``
    prepare_s: float = 0.0  # feeders generated, models trained or read, certificates issued, before the router [s]


class _FeederId(msgspec.Struct, frozen=True):
    feeder_id: str | None = None


class _Timings(msgspec.Struct, frozen=True):
    total_s: float = 0.0


class _DecisionTimes(msgspec.Struct, frozen=True):
    timings: _Timings = _Timings()


class _AckReason(msgspec.Struct, frozen=True):
    reason: str = ""


_decode_id = msgspec.json.Decoder(_FeederId).decode
_decode_times = msgspec.json.Decoder(_DecisionTimes).decode
_decode_reason = msgspec.json.Decoder(_AckReason).decode


def check_recording(path: str | Path, feeder_ids: list[str]) -> RecordingCheck:
    """Read the fleet's recording once: messages whose ``feeder_id`` is not their key's feeder, topics of no
    feeder of the fleet, and every decision's time per feeder.
    """
    from recordings.replay import RecordedMessages
    from schemas.keys import message_type_for_key
    from schemas.messages import wire_of
    from schemas.truth_proto import truth_feeder_id

    known = set(feeder_ids)
    messages = checked = crossing = 0
    foreign: set[str] = set()
    decision_s: dict[str, list[float]] = defaultdict(list)
    wrong_feeder: dict[str, int] = defaultdict(int)
    with RecordedMessages(path, ("cvvc/**",)) as rec:
        for msg in rec:
            messages += 1
            parts = msg.topic.split("/")
            feeder = parts[1] if len(parts) > 1 else ""
            if feeder not in known:
                foreign.add(msg.topic)
            msg_type = message_type_for_key(msg.topic)
            # the truth is Protobuf (RecordedMessages gives an earlier recording's MessagePack truth as Protobuf too):
            # its feeder id read alone, not the whole frame
            truth = msg_type is not None and wire_of(msg_type) == "protobuf"
            try:
                fid = truth_feeder_id(msg.data) if truth else _decode_id(msg.data).feeder_id
            except (msgspec.DecodeError, msgspec.ValidationError):
                fid = None  # not a message of ours: counted as a message, not as checked
            if fid is not None:
                checked += 1
                crossing += fid != feeder
            if len(parts) > 2 and parts[2] == "ack":
                try:
                    wrong_feeder[feeder] += _decode_reason(msg.data).reason.startswith("wrong_feeder:")
                except (msgspec.DecodeError, msgspec.ValidationError):
                    pass
            if parts[2:] == ["agent", "decision"]:
                try:
                    decision_s[feeder].append(_decode_times(msg.data).timings.total_s)
                except (msgspec.DecodeError, msgspec.ValidationError):
                    pass
    return RecordingCheck(messages=messages, checked=checked, crossing=crossing, foreign_topics=sorted(foreign),
                          decision_s=dict(decision_s), wrong_feeder_acks={k: v for k, v in wrong_feeder.items() if v})


def percentile_ms(values_s: list[float] | None, q: float) -> float | None:
    """The ``q``-th percentile of ``values_s`` [s] in milliseconds, rounded to 0.01 ms; None when empty."""
    if not values_s:
        return None
    return round(float(np.percentile(np.asarray(values_s), q)) * 1e3, 2)


def _ms(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f}"


def render_fleet(s: FleetSummary) -> str:
    """The fleet's summary as Markdown: one row per feeder, then the cross-feeder checks."""
    lines = [f"# cvvc fleet: {len(s.feeders)} feeders, {s.start}, {s.days:g} day(s) each"
             f"{', secure' if s.secure else ''}", "",
             "| feeder | case | decisions | hold | soft | decision p50 / p99 [ms] | round trip p50 / p99 [ms] "
             "| lockstep misses | NVV | MVVM [pu] | NTC | refused (agent / devices) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in s.feeders:
        lines.append(f"| {r.feeder_id} | {r.case} | {r.decisions} | {r.holds} | {r.soft} "
                     f"| {_ms(r.decision_p50_ms)} / {_ms(r.decision_p99_ms)} "
                     f"| {_ms(r.round_trip_p50_ms)} / {_ms(r.round_trip_p99_ms)} | {r.lockstep_misses} | {r.nvv} "
                     f"| {r.mvvm_pu:.4f} | {r.ntc} | {r.agent_refused} / {r.bridge_rejected} |")
    lines += [""] + [f"- **{r.feeder_id} degraded for more than one control period**: {r.integrity.degraded}"
                     for r in s.feeders if r.integrity.degraded]
    lines += [f"- wall time {s.wall_s:.1f} s for the whole fleet (one router, one recorder; preparing feeders "
              f"and models before it: {s.prepare_s:.1f} s)"]
    if s.recording:
        lines.append(f"- recording `{s.recording}`: {s.recorded_messages} messages, {s.messages_checked} carry a "
                     f"feeder id, {s.crossing_messages} of them on another feeder's keys; topics of no feeder "
                     f"of the fleet: {len(s.foreign_topics)}; acks put by another feeder's bridge on a feeder's ack "
                     f"keys (`wrong_feeder`): {sum(s.wrong_feeder_acks.values())}"
                     + "".join(f", {n} on {f}'s" for f, n in sorted(s.wrong_feeder_acks.items())))
    if s.probe is not None:
        p = s.probe
        lines.append(f"- probe: a command with {p.sender}'s agent certificate on `{p.key}`: "
                     f"{'REACHED the router' if p.reached else 'refused by the router'}"
                     f"{', ACKED by the device' if p.acked else ''}; {p.target} acked {p.target_acks_after} "
                     f"command(s) of its own agent meanwhile")
    return "\n".join(lines) + "\n"
