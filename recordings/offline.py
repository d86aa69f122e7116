"""Offline re-run: the agent's decision code on recorded frames (no bus), diffed against recorded decisions.

The agent side is one function of ``agent.runtime``::

    decide_offline(model, settings, frames: Iterable[Received]) -> Iterator[schemas.messages.Decision]

This module feeds it the recorded measurement frames (``cvvc/*/meas/**``) decoded with the same typed
codecs as the live inbox, in ``log_time`` order (ties in file order), each as a ``schemas.bus.Received``
(``key``, ``msg``, ``recv_wall_ns`` = the recorded receive time, ``raw`` = the recorded bytes). Frames that
fail to decode are skipped and counted, as the live inbox would.

Pairing and comparison (``diff_decisions``): a re-run decision answers the recorded one with the same
``(feeder_id, step_t_ns)``. Two decisions are *identical* when they are equal in every field except
``timings`` (wall-clock durations, never reproducible). A changed pair whose only differences are
counters (``seq``, ``in_reply_to``, command ``seq`` / ``cmd_id`` / ``in_reply_to``: a recording that
started after the agent) is counted as ``changed_identity_only``. For every changed pair the command values
are compared per device and quantity (``pv/<id>/q_kvar``, ``vr/<id>/tap``, ``vr/<id>/setpoint_v120``,
``vr/<id>/band_v120``, ``cap/<id>/closed_steps``) and the largest absolute change of each is reported with its step.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import msgspec

from recordings.errors import OfflineError
from recordings.info import recording_info
from recordings.recorder import METADATA_NAME
from recordings.replay import MEASUREMENT_KEYS, RecordedMessages
from schemas import messages as m
from schemas.bus import BadMessage, Received, codec_for
from schemas.keys import message_type_for_key

__all__ = [
    "DECISION_KEYS",
    "CommandChange",
    "Decider",
    "DiffReport",
    "OfflineResult",
    "agent_decider",
    "agent_inputs",
    "command_values",
    "diff_decisions",
    "recorded_decisions",
    "recorded_frames",
    "run_offline",
]

DECISION_KEYS: tuple[str, ...] = ("cvvc/*/agent/decision",)
Decider = Callable[[Iterable[Received]], Iterable[m.Decision]]
_MAX_LISTED_STEPS = 20


class CommandChange(msgspec.Struct, frozen=True, kw_only=True):
    """One command quantity at one step: recorded and re-run values and the absolute change."""

    quantity: str  # pv/<id>/q_kvar [kvar], vr/<id>/tap [steps], vr/<id>/setpoint_v120 [V], vr/<id>/band_v120 [V],
    # cap/<id>/closed_steps [steps]
    step_t_ns: int
    recorded: float
    rerun: float
    abs_change: float


class DiffReport(msgspec.Struct, frozen=True, kw_only=True):
    """Recorded vs re-run decisions.

    ``missing``: recorded decisions the re-run did not make; ``extra``: re-run decisions with no recorded
    counterpart. ``largest_change``: per command quantity, the pair where its value changed most;
    ``appeared_or_vanished``: per quantity, the changed pairs where only one side has that command.
    """

    recorded: int
    rerun: int
    identical: int
    changed: int
    changed_identity_only: int
    missing: int
    extra: int
    status_changed: int
    duplicate_recorded: int
    largest_change: dict[str, CommandChange]
    appeared_or_vanished: dict[str, int]
    changed_steps_ns: list[int]  # the first few, in step order
    missing_steps_ns: list[int]

    @property
    def all_identical(self) -> bool:
        """Every recorded decision re-made identically, none missing and none extra."""
        return self.identical == self.recorded and self.missing == 0 and self.extra == 0


class OfflineResult(msgspec.Struct, frozen=True, kw_only=True):
    """A re-run: frames fed, frames rejected at decode, simulated span [s], wall time [s], and the diff."""

    path: str
    model_path: str
    frames: int
    frames_rejected: int
    simulated_s: float
    wall_s: float
    sim_minutes_per_wall_s: float
    diff: DiffReport


# -------------------------------------------------------------------------------------------- read
def recorded_frames(path: str | Path, keys: tuple[str, ...] = MEASUREMENT_KEYS,
                    rejected: list[str] | None = None) -> Iterator[Received]:
    """The recorded frames on ``keys`` in log-time order, decoded with the live typed codecs.

    Undecodable frames (or keys outside the layout) are skipped; a line per frame is appended to
    ``rejected`` when given.
    """
    with RecordedMessages(path, keys) as recorded:
        yield from _decoded(recorded, rejected)


def _decoded(recorded: RecordedMessages, rejected: list[str] | None) -> Iterator[Received]:
    for rec in recorded:
        msg_type = message_type_for_key(rec.topic)
        if msg_type is None:
            if rejected is not None:
                rejected.append(f"{rec.topic}: key outside the cvvc layout")
            continue
        try:
            msg = codec_for(msg_type).decode(rec.data)
        except BadMessage as e:
            if rejected is not None:
                rejected.append(f"{rec.topic} at {rec.log_time_ns}: {e}")
            continue
        yield Received(rec.topic, msg, rec.publish_time_ns, rec.data)


def recorded_decisions(path: str | Path) -> list[m.Decision]:
    """Every decodable ``Decision`` recorded in ``path``, in log-time order."""
    return [r.msg for r in recorded_frames(path, DECISION_KEYS)]


# -------------------------------------------------------------------------------------------- diff
def command_values(decision: m.Decision) -> dict[str, float]:
    """The decided values by quantity name (see ``CommandChange.quantity``)."""
    out: dict[str, float] = {}
    for c in decision.commands:
        match c:
            case m.PvCommand():
                out[f"pv/{c.plant_id}/q_kvar"] = c.q_kvar
            case m.RegCommand(action=m.TapAction() as a):
                out[f"vr/{c.regulator_id}/tap"] = float(a.tap)
            case m.RegCommand(action=m.SetpointAction() as a):
                out[f"vr/{c.regulator_id}/setpoint_v120"] = a.setpoint_v120
                out[f"vr/{c.regulator_id}/band_v120"] = a.band_v120
            case m.CapCommand(closed_steps=int() as steps):  # a bank released to its own control has no value
                out[f"cap/{c.capacitor_id}/closed_steps"] = float(steps)
    return out


def _content(d: m.Decision) -> m.Decision:
    return msgspec.structs.replace(d, timings=m.Timings())


def _without_identity(d: m.Decision) -> m.Decision:
    commands = [msgspec.structs.replace(c, seq=0, cmd_id="x", in_reply_to=0) for c in d.commands]
    return msgspec.structs.replace(d, timings=m.Timings(), seq=0, in_reply_to=0, commands=commands)


def diff_decisions(recorded: Iterable[m.Decision], rerun: Iterable[m.Decision]) -> DiffReport:
    """Pair decisions by ``(feeder_id, step_t_ns)`` and compare them (module docstring)."""
    rec_by_step: dict[tuple[str, int], m.Decision] = {}
    duplicates = 0
    n_recorded = 0
    for d in recorded:
        n_recorded += 1
        key = (d.feeder_id, d.step_t_ns)
        if key in rec_by_step:
            duplicates += 1
            continue
        rec_by_step[key] = d
    identical = changed = identity_only = extra = status_changed = n_rerun = 0
    largest: dict[str, CommandChange] = {}
    presence: Counter[str] = Counter()
    changed_steps: list[int] = []
    seen: set[tuple[str, int]] = set()
    for new in rerun:
        n_rerun += 1
        key = (new.feeder_id, new.step_t_ns)
        old = rec_by_step.get(key)
        if old is None or key in seen:
            extra += 1
            continue
        seen.add(key)
        if _content(old) == _content(new):
            identical += 1
            continue
        changed += 1
        changed_steps.append(new.step_t_ns)
        if _without_identity(old) == _without_identity(new):
            identity_only += 1
        if old.status != new.status:
            status_changed += 1
        _track_largest(largest, presence, old, new)
    missing_steps = sorted(k[1] for k in rec_by_step if k not in seen)
    return DiffReport(recorded=n_recorded, rerun=n_rerun, identical=identical, changed=changed,
                      changed_identity_only=identity_only, missing=len(missing_steps), extra=extra,
                      status_changed=status_changed, duplicate_recorded=duplicates,
                      largest_change=dict(sorted(largest.items())),
                      appeared_or_vanished=dict(sorted(presence.items())),
                      changed_steps_ns=sorted(changed_steps)[:_MAX_LISTED_STEPS],
                      missing_steps_ns=missing_steps[:_MAX_LISTED_STEPS])


def _track_largest(largest: dict[str, CommandChange], presence: Counter[str], old: m.Decision,
                   new: m.Decision) -> None:
    a, b = command_values(old), command_values(new)
    for q in sorted(a.keys() | b.keys()):
        va, vb = a.get(q), b.get(q)
        if va is None or vb is None:
            presence[q] += 1
            continue
        delta = abs(vb - va)
        if delta == 0.0:
            continue
        best = largest.get(q)
        if best is None or delta > best.abs_change:
            largest[q] = CommandChange(quantity=q, step_t_ns=new.step_t_ns, recorded=va, rerun=vb, abs_change=delta)


# ------------------------------------------------------------------------------------------ re-run
def agent_inputs(model_path: str | Path, settings_json: str = "") -> tuple[Any, Any]:
    """``(model, settings)`` of an offline re-run: the model file and the recorded agent settings (JSON, may be empty)
    as ``agent.runtime`` reads them; a case A session (full visibility) is refused.
    """
    try:
        from agent import runtime
    except ImportError as e:
        raise OfflineError(f"the agent runtime cannot be imported ({e}); offline re-run needs "
                           "agent.runtime.decide_offline") from e
    from regression.model import read_model

    model = read_model(model_path)
    settings: Any = None
    settings_type = getattr(runtime, "AgentSettings", None)
    if settings_type is not None:
        try:
            settings = msgspec.json.decode(settings_json, type=settings_type) if settings_json else settings_type()
        except msgspec.DecodeError as e:
            raise OfflineError(f"the recorded agent settings do not decode as {settings_type.__name__}: {e}") from e
    if getattr(settings, "full_visibility", False):
        raise OfflineError("this session ran case A (full visibility): its decisions used the live bridge's "
                           "oracle and cannot be re-run offline")
    return model, settings


def agent_decider(model_path: str | Path, settings_json: str = "") -> Decider:
    """Bind ``agent.runtime.decide_offline`` to a model file and the agent settings (JSON, may be empty)."""
    model, settings = agent_inputs(model_path, settings_json)
    from agent import runtime

    decide = getattr(runtime, "decide_offline", None)
    if decide is None:
        raise OfflineError("agent.runtime has no decide_offline(model, settings, frames) yet")

    def run(frames: Iterable[Received]) -> Iterable[m.Decision]:
        return decide(model, settings, frames)

    return run


def run_offline(path: str | Path, *, model_path: str | Path | None = None, decide: Decider | None = None,
                settings_json: str | None = None) -> OfflineResult:
    """Re-run the agent on the frames of ``path`` and diff its decisions against the recorded ones.

    ``model_path`` defaults to the model named in the recording's metadata; ``decide`` defaults to
    ``agent_decider(model_path, settings)`` with the settings recorded in the metadata (``agent_settings``).
    """
    info = recording_info(path)
    meta = info.metadata.get(METADATA_NAME, {})
    model = str(model_path or recorded_model(path, meta.get("model_path", "")))
    recorded = recorded_decisions(path)
    if not recorded:
        raise OfflineError(f"{path} holds no decodable agent decisions (cvvc/*/agent/decision) to compare with")
    if decide is None:
        if not model:
            raise OfflineError(f"{path} names no model in its metadata: pass --model MODEL")
        if not Path(model).is_file():
            raise OfflineError(f"model file {model} not found: pass --model MODEL")
        decide = agent_decider(model, settings_json if settings_json is not None else meta.get("agent_settings", ""))
    rejected: list[str] = []
    counter = _Counting(recorded_frames(path, MEASUREMENT_KEYS, rejected))
    t0 = time.perf_counter()
    rerun = list(decide(counter))
    wall_s = time.perf_counter() - t0
    simulated_s = 0.0 if counter.first is None else (counter.last - counter.first) / 1e9
    return OfflineResult(path=str(path), model_path=model, frames=counter.n, frames_rejected=len(rejected),
                         simulated_s=simulated_s, wall_s=wall_s,
                         sim_minutes_per_wall_s=simulated_s / 60.0 / wall_s if wall_s > 0 else 0.0,
                         diff=diff_decisions(recorded, rerun))


def recorded_model(path: str | Path, model_path: str) -> str:
    """The model a recording names (``model_path`` of its metadata), found from any working directory: the path as
    recorded when it is a file, else the file of that name beside the recording (``cvvc run`` keeps its model as
    ``model.json`` beside ``session.mcap``; recordings of earlier versions named it relative to where the run
    started); ``""`` when the recording names none.
    """
    if not model_path or Path(model_path).is_file():
        return model_path
    beside = Path(path).resolve().parent / Path(model_path).name
    return str(beside) if beside.is_file() else model_path


class _Counting:
    """Passes frames through, counting them and noting the first and last ``t_ns``."""

    def __init__(self, frames: Iterator[Received]) -> None:
        self._frames = frames
        self.n = 0
        self.first: int | None = None
        self.last = 0

    def __iter__(self) -> Iterator[Received]:
        for r in self._frames:
            self.n += 1
            t = r.msg.t_ns
            self.first = t if self.first is None else min(self.first, t)
            self.last = max(self.last, t)
            yield r
