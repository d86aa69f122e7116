"""Frame aligner: gathers the feeder-head, PV, regulator and capacitor-bank frames of one timestamp.

Driven by frame timestamps only (never a clock), so a live run and an offline replay of the same frames
produce the same aligned sets. The rule, documented in docs/agent.md:

- Frames are grouped by their ``t_ns``. A group is *complete* when the head meter, every PV plant, every
  regulator and every capacitor bank of the model have reported; a complete group is released at once. A
  model without banks ignores ``CapFrame`` s (counted in ``ignored``).
- An incomplete group is released when a frame of a *newer* timestamp arrives, or when the runtime closes it
  after its late-frame window (``close_pending``); devices that did not report are listed as ``missing``.
- Rejected, never stored (and counted by reason): a frame for another feeder, from a device the model does
  not know, with a ``seq`` not above the last accepted one from that source (duplicate / out of order),
  older than the newest released group (stale), with the ``invalid`` quality flag, or with physically
  impossible values.
- A frame's identity is the device of the model its key and its device id name (``head``, ``pv/<id>``,
  ``vr/<id>``, ``cap/<id>``), never the ``source`` the payload declares: sequences are kept, and the clock rule
  below counts, per device of the map, so made-up sources count for nothing.
- No single frame moves the clock: a frame more than ``max_jump_ns`` (one control
  period) ahead of the newest accepted frame, or any frame before the first accepted one, is *held* until
  frames of at least two devices (one if the model has a single device) agree on the new time within
  ``max_jump_ns``; then the held frames are taken in arrival order. Lost-frame bursts and the start of a run
  pass at once (every device reports the same step); a lone forged timestamp stays held, and is counted as
  ``time_jump`` when it is pushed out of the bounded hold.
- A device's sequence stands while the device reports: a frame that breaks it (a ``seq`` not above the device's
  last, or more than ``SEQ_JUMP_MAX`` above it) is refused (``duplicate``, ``out_of_order``, ``seq_jump``) until
  the other devices of the map have reported a control period past that device's last accepted frame (its
  sequence silent that long); then the new sequence is taken and counted (``seq_resets`` for one that went back,
  ``seq_jumps`` for one that jumped). The clock for that is the newest time the *other* devices' frames carry, so
  frames on the device's own key, forged or not, never move it. A device that restarts its counter loses at most
  a control period of frames; a forged frame with a high or low ``seq`` (e.g. stamped a few seconds after a step,
  which the clock tolerance would snap onto it) never replaces the frame of a device that is still reporting,
  whatever it and its followers claim. On a map of a single device, the frame's own time is the only clock.
- A scan's end marker (``StepEnd``, sent after a step's frames by whoever collects them) names the devices that
  sent a frame for its time: once those have arrived, the group is released at once, the rest listed as
  ``missing``, instead of waiting for the late-frame window. A marker never moves the clock, never releases a group that
  has no frame, and never makes a group wait longer; at most ``_EXPECT_MAX`` are kept ahead of their frames, so
  a forged marker can at worst have one step decided early on the frames that had arrived.
- A device's first frame of a time stays: another frame of the same device for a time already received (e.g. one
  stamped a few seconds off the step and snapped onto it) is refused as ``duplicate``, so it never replaces it.
- Only groups on a control step (``t_ns`` a multiple of the control period) are released as decisions to
  make; the others only refresh the last-known state (and are handed to the runtime's follow-ups,
  ``take_between``).
- Field clocks off by a little:
  a frame or scan-end marker stamped within ``clock_tolerance_ns`` of a control step is taken as that step's
  (its ``t_ns`` is set to the step's, counted in ``snapped``); before, a frame stamped 2 s off never fell on a
  control step and nothing was decided. Frames between control steps keep their stamps.
"""

from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass, field

import msgspec

from agent.errors import AgentInputError
from schemas import messages as m

__all__ = ["AlignedFrames", "FrameAligner", "plausibility_problem"]


@dataclass(frozen=True)
class AlignedFrames:
    """The frames of one timestamp. Missing devices are absent from the dicts and named in ``missing``."""

    t_ns: int
    head: m.HeadFrame | None
    pv: dict[str, m.PvFrame]
    vr: dict[str, m.RegFrame]
    missing: tuple[str, ...]
    cap: dict[str, m.CapFrame] = field(default_factory=dict)
    vr_recent: dict[str, tuple[m.RegFrame, ...]] = field(default_factory=dict)  # recent frames, oldest first
    head_recent: m.HeadFrame | None = None  # the latest head frame released up to this step (this one's, if any)
    pv_recent: dict[str, m.PvFrame] = field(default_factory=dict)  # each plant's latest frame up to this step
    head_history: tuple[m.HeadFrame, ...] = ()  # the head frames released lately up to this step, oldest first

    @property
    def complete(self) -> bool:
        """Whether every frame of the step arrived."""
        return not self.missing


def plausibility_problem(frame: m.HeadFrame | m.PvFrame | m.RegFrame | m.CapFrame) -> str | None:
    """Why a schema-valid frame is physically impossible, or None.

    The schema bounds catch absurd numbers; these catch values that are representable but cannot be:
    phases repeated, a total that is not the sum of its phases, PV output above its rating.
    """
    if isinstance(frame, m.CapFrame):
        if "invalid" in frame.quality:
            return "quality flag 'invalid'"
        if frame.closed_steps > frame.steps:
            return f"capacitor bank {frame.closed_steps} closed steps of {frame.steps}"
        return None
    phases = [p.phase for p in frame.phases]
    if len(set(phases)) != len(phases):
        return f"phase listed twice: {phases}"
    if "invalid" in frame.quality:
        return "quality flag 'invalid'"
    match frame:
        case m.HeadFrame():
            if abs(sum(p.p_kw for p in frame.phases) - frame.p_kw) > 1e-3 * max(1.0, abs(frame.p_kw)) + 1.0:
                return f"head p_kw {frame.p_kw} is not the sum of its phases"
            if abs(sum(p.q_kvar for p in frame.phases) - frame.q_kvar) > 1e-3 * max(1.0, abs(frame.q_kvar)) + 1.0:
                return f"head q_kvar {frame.q_kvar} is not the sum of its phases"
            if any(p.v_mag_v <= 0.0 for p in frame.phases):
                return "head voltage is zero on a phase"
        case m.PvFrame():
            s_kva = (frame.p_kw**2 + frame.q_kvar**2) ** 0.5
            if s_kva > 1.2 * frame.s_rated_kva + 1.0:
                return f"PV output {s_kva:.1f} kVA above 1.2 x rating {frame.s_rated_kva} kVA"
            if frame.p_kw < -0.05 * frame.s_rated_kva - 1.0:
                return f"PV p_kw {frame.p_kw} strongly negative"
        case m.RegFrame():
            if not 90.0 <= frame.v_compared_120 <= 150.0 or any(not 90.0 <= p.v_120 <= 150.0 for p in frame.phases):
                return "regulator voltage outside 90-150 V on the 120 V base"
    return None


_Frame = m.HeadFrame | m.PvFrame | m.RegFrame | m.CapFrame
_FRAME_TYPES = (m.HeadFrame, m.PvFrame, m.RegFrame, m.CapFrame)
_EXPECT_MAX = 64  # scan-end markers kept ahead of their frames (the oldest goes first)
SEQ_JUMP_MAX = 1440
"""The largest ``seq`` step a device's frame may take while the device reports: a day of one-minute frames lost."""
_VR_HISTORY = 64  # frames kept per regulator for the averaged readings (one per minute: an hour)


def _device(frame: _Frame) -> str:
    """The device a frame is of, as the map names it (its key was checked against it), never its ``source``."""
    match frame:
        case m.HeadFrame():
            return "head"
        case m.PvFrame():
            return f"pv/{frame.plant_id}"
        case m.RegFrame():
            return f"vr/{frame.regulator_id}"
        case m.CapFrame():
            return f"cap/{frame.capacitor_id}"
    raise TypeError(f"not a device frame: {type(frame).__name__}")


def _in_group(g: _Group, frame: _Frame) -> bool:
    """Whether ``g`` holds a frame of ``frame``'s device already."""
    match frame:
        case m.HeadFrame():
            return g.head is not None
        case m.PvFrame():
            return frame.plant_id in g.pv
        case m.RegFrame():
            return frame.regulator_id in g.vr
        case m.CapFrame():
            return frame.capacitor_id in g.cap
    return False


@dataclass
class _Group:
    t_ns: int
    head: m.HeadFrame | None = None
    pv: dict[str, m.PvFrame] = field(default_factory=dict)
    vr: dict[str, m.RegFrame] = field(default_factory=dict)
    cap: dict[str, m.CapFrame] = field(default_factory=dict)


class FrameAligner:
    """Stateful grouping of frames by timestamp; see the module docstring for the rule."""

    def __init__(self, *, feeder_id: str, pv_ids: tuple[str, ...], regulator_ids: tuple[str, ...],
                 control_period_ns: int, max_jump_ns: int | None = None,
                 capacitor_ids: tuple[str, ...] = (), clock_tolerance_ns: int = 0) -> None:
        if not 0 <= clock_tolerance_ns < control_period_ns // 2:
            raise AgentInputError(f"clock tolerance {clock_tolerance_ns} ns must be within 0 and half the control "
                             f"period ({control_period_ns} ns)")
        self.feeder_id = feeder_id
        self.clock_tolerance_ns = int(clock_tolerance_ns)
        self.snapped = 0  # frames and markers stamped off a control step within the tolerance, taken as on it
        self.pv_ids = pv_ids
        self.regulator_ids = regulator_ids
        self.capacitor_ids = capacitor_ids
        self.control_period_ns = control_period_ns
        self.max_jump_ns = control_period_ns if max_jump_ns is None else int(max_jump_ns)
        self.rejected: Counter[str] = Counter()
        self.last_reject: dict[str, str] = {}
        self.accepted = 0
        self.ignored = 0  # device frames of a kind the agent does not use
        self.seq_resets = 0  # device sequences that went back, taken after a control period of silence
        self.seq_jumps = 0  # device sequences that jumped, taken after a control period of silence
        self.step_ends = 0  # scan-end markers taken
        self.released_by_step_end = 0  # incomplete groups released at once because a marker said all had come
        self._expected: dict[int, frozenset[str]] = {}  # t_ns -> the devices a marker says sent a frame
        self._last_seq: dict[str, int] = {}
        self._last_t_ns: dict[str, int] = {}
        self._seen_t_ns: dict[str, int] = {}  # device -> the newest time its frames carried, taken or not
        self._groups: dict[int, _Group] = {}
        self._released_t_ns = -1
        # every regulator's frames released lately (control steps or not): the readings of a control period
        self._vr_history: dict[str, deque[m.RegFrame]] = {r: deque(maxlen=_VR_HISTORY) for r in regulator_ids}
        self._head_latest: m.HeadFrame | None = None
        self._head_history: deque[m.HeadFrame] = deque(maxlen=_VR_HISTORY)
        self._pv_latest: dict[str, m.PvFrame] = {}
        self._newest_t_ns: int | None = None  # newest accepted frame time; None before the first
        # groups between control steps released since take_between (bounded: an aligner nobody drains)
        self._between: deque[AlignedFrames] = deque(maxlen=_VR_HISTORY)
        self.between_seen = False  # whether any group between control steps was released (frames every minute)
        self._held: list[tuple[str, _Frame]] = []  # frames ahead of the clock, awaiting a second device
        n_sources = 1 + len(pv_ids) + len(regulator_ids) + len(capacitor_ids)
        self._sources_needed = min(2, n_sources)
        self._hold_max = 4 * n_sources

    # ---------------------------------------------------------------------------------------- input
    @property
    def newest_t_ns(self) -> int | None:
        """The newest accepted frame's time [ns], None before the first."""
        return self._newest_t_ns

    def add(self, key: str, frame: _Frame | m.StepEnd) -> list[AlignedFrames]:
        """Add one decoded frame or scan-end marker; returns the control-step groups this frame completes or closes.

        A device frame the agent does not use (a ``CapFrame`` when the model has no bank) is counted in ``ignored``.
        """
        frame = self._on_control_grid(frame)
        if isinstance(frame, m.StepEnd):
            return self._step_end(key, frame)
        if not isinstance(frame, _FRAME_TYPES) or (isinstance(frame, m.CapFrame) and not self.capacitor_ids):
            self.ignored += 1
            return []
        why = self._check_static(key, frame)
        if why is not None:
            self._reject(*why)
            return []
        if self._newest_t_ns is None or frame.t_ns > self._newest_t_ns + self.max_jump_ns:
            return self._hold(key, frame)
        return self._take(key, frame)

    def _on_control_grid(self, frame: _Frame | m.StepEnd) -> _Frame | m.StepEnd:
        """``frame`` restamped on the nearest control step if it is off it by at most the clock tolerance."""
        tol, period = self.clock_tolerance_ns, self.control_period_ns
        t_ns = getattr(frame, "t_ns", None)
        if tol <= 0 or not isinstance(t_ns, int):
            return frame
        off = t_ns % period
        if off == 0 or tol < off < period - tol:
            return frame
        self.snapped += 1
        return msgspec.structs.replace(frame, t_ns=t_ns - off + (period if off > tol else 0))

    def take_between(self) -> list[AlignedFrames]:
        """The groups between control steps released since the last call, oldest first (no decision is made on
        them; the runtime's follow-ups read them).
        """
        out = list(self._between)
        self._between.clear()
        return out

    def reject(self, kind: str, detail: str) -> None:
        """Count one refused input of ``kind`` (also the runtime's, e.g. an AMI reading of an unknown meter)."""
        self.rejected[kind] += 1
        self.last_reject[kind] = detail

    _reject = reject

    def _hold(self, key: str, frame: _Frame) -> list[AlignedFrames]:
        """Keep a frame that would move the clock until another source agrees (see the module docstring)."""
        self._held.append((key, frame))
        if len(self._held) > self._hold_max:
            _, gone = self._held.pop(0)
            self._reject("time_jump", f"{_device(gone)} t_ns {gone.t_ns}: ahead of the feeder's clock "
                         f"({self._newest_t_ns}) and never confirmed by another device")
        times = sorted({f.t_ns for _, f in self._held})
        for t in times:
            devices = {_device(f) for _, f in self._held if t <= f.t_ns <= t + self.max_jump_ns}
            if len(devices) >= self._sources_needed:
                held, self._held = self._held, []
                self._newest_t_ns = t if self._newest_t_ns is None else max(self._newest_t_ns, t)
                out: list[AlignedFrames] = []
                for k, f in held:
                    out += self.add(k, f)
                return out
        return []

    def _take(self, key: str, frame: _Frame) -> list[AlignedFrames]:
        why = self._check_order(frame)
        if why is not None:
            self._reject(*why)
            return []
        self.accepted += 1
        self._newest_t_ns = frame.t_ns if self._newest_t_ns is None else max(self._newest_t_ns, frame.t_ns)
        self._last_seq[_device(frame)] = frame.seq
        self._last_t_ns[_device(frame)] = frame.t_ns
        out = [self._release(t) for t in sorted(self._groups) if t < frame.t_ns]
        g = self._groups.setdefault(frame.t_ns, _Group(frame.t_ns))
        match frame:
            case m.HeadFrame():
                g.head = frame
            case m.PvFrame():
                g.pv[frame.plant_id] = frame
            case m.RegFrame():
                g.vr[frame.regulator_id] = frame
            case m.CapFrame():
                g.cap[frame.capacitor_id] = frame
        if self._all_sent_arrived(g):
            out.append(self._release(frame.t_ns))
        return [a for a in out if a.t_ns % self.control_period_ns == 0]

    def _step_end(self, key: str, end: m.StepEnd) -> list[AlignedFrames]:
        """Note which devices sent a frame for ``end.t_ns``; release that group if they all arrived."""
        parts = key.split("/")
        if len(parts) != 4 or parts[1] != self.feeder_id or end.feeder_id != self.feeder_id:
            self._reject("wrong_feeder", f"{key}: scan end for feeder {end.feeder_id!r}, not {self.feeder_id!r}")
            return []
        if end.t_ns <= self._released_t_ns:
            return []  # that step was decided already (every frame had come)
        self.step_ends += 1
        sent = [*(["head"] if end.head else []), *end.pv, *end.vr, *end.cap]
        self._expected[end.t_ns] = frozenset(sent)
        while len(self._expected) > _EXPECT_MAX:
            del self._expected[min(self._expected)]
        g = self._groups.get(end.t_ns)
        if g is None or not self._all_sent_arrived(g):
            return []
        out = [self._release(t) for t in sorted(self._groups) if t <= end.t_ns]
        return [a for a in out if a.t_ns % self.control_period_ns == 0]

    def _all_sent_arrived(self, g: _Group) -> bool:
        """Every device reported, or every device a scan-end marker says sent a frame did (counted)."""
        missing = self._missing(g)
        if not missing:
            return True
        expected = self._expected.get(g.t_ns)
        if expected is None or any(x in expected for x in missing):
            return False
        self.released_by_step_end += 1
        return True

    def close_pending(self) -> list[AlignedFrames]:
        """Release every open group (late-frame window over, or end of input); control steps only."""
        out = [self._release(t) for t in sorted(self._groups)]
        return [a for a in out if a.t_ns % self.control_period_ns == 0]

    @property
    def pending(self) -> bool:
        """Whether a step is waiting for frames."""
        return bool(self._groups)

    # ------------------------------------------------------------------------------------- internals
    def _check_static(self, key: str, frame: _Frame) -> tuple[str, str] | None:
        """Why a frame is not this feeder's, not a known device's, or physically impossible; or None."""
        parts = key.split("/")
        if len(parts) < 4 or parts[1] != self.feeder_id:
            return "wrong_feeder", f"{key}: not feeder {self.feeder_id!r}"
        match frame:
            case m.HeadFrame():
                if frame.feeder_id != self.feeder_id:
                    return "wrong_feeder", f"head frame for feeder {frame.feeder_id!r}"
            case m.PvFrame():
                if frame.plant_id not in self.pv_ids or parts[-1] != frame.plant_id:
                    return "unknown_device", f"PV plant {frame.plant_id!r} on {key}"
            case m.RegFrame():
                if frame.regulator_id not in self.regulator_ids or parts[-1] != frame.regulator_id:
                    return "unknown_device", f"regulator {frame.regulator_id!r} on {key}"
            case m.CapFrame():
                if frame.capacitor_id not in self.capacitor_ids or parts[-1] != frame.capacitor_id:
                    return "unknown_device", f"capacitor bank {frame.capacitor_id!r} on {key}"
        problem = plausibility_problem(frame)
        if problem is not None:
            return "implausible", f"{_device(frame)}: {problem}"
        return None

    def _check_order(self, frame: _Frame) -> tuple[str, str] | None:
        """Why a frame is a duplicate, out of order, a sequence jump or stale, or None (may count a new sequence)."""
        device = _device(frame)
        last = self._last_seq.get(device)
        self._seen_t_ns[device] = max(self._seen_t_ns.get(device, frame.t_ns), frame.t_ns)
        if last is not None and not last < frame.seq <= last + SEQ_JUMP_MAX:
            silent_ns = self._other_devices_clock(device, frame) - self._last_t_ns[device]
            if silent_ns < self.control_period_ns:
                kind = "duplicate" if frame.seq == last else "out_of_order" if frame.seq < last else "seq_jump"
                return kind, (f"{device} seq {frame.seq} (t_ns {frame.t_ns}) after {last}: the device reported "
                              f"{silent_ns / 1e9:.0f} s ago, less than a control period")
            if frame.seq > last:
                self.seq_jumps += 1
            else:
                self.seq_resets += 1
        if frame.t_ns <= self._released_t_ns:
            return "stale", f"{device} t_ns {frame.t_ns} not after released {self._released_t_ns}"
        g = self._groups.get(frame.t_ns)
        if g is not None and _in_group(g, frame):
            return "duplicate", f"{device}: a second frame for t_ns {frame.t_ns}; the first one stays"
        return None

    def _other_devices_clock(self, device: str, frame: _Frame) -> int:
        """The newest time the frames of the map's other devices carried (a frame's own on a one-device map)."""
        if self._sources_needed < 2:
            return frame.t_ns
        return max((t for d, t in self._seen_t_ns.items() if d != device), default=-1)

    def _missing(self, g: _Group) -> tuple[str, ...]:
        miss = [] if g.head is not None else ["head"]
        miss += [k for k in self.pv_ids if k not in g.pv]
        miss += [r for r in self.regulator_ids if r not in g.vr]
        miss += [c for c in self.capacitor_ids if c not in g.cap]
        return tuple(miss)

    def _release(self, t_ns: int) -> AlignedFrames:
        g = self._groups.pop(t_ns)
        self._released_t_ns = max(self._released_t_ns, t_ns)
        for t in [t for t in self._expected if t <= self._released_t_ns]:
            del self._expected[t]
        for reg_id, frame in g.vr.items():
            self._vr_history[reg_id].append(frame)
        if g.head is not None:
            self._head_latest = g.head
            self._head_history.append(g.head)
        self._pv_latest.update(g.pv)
        if t_ns % self.control_period_ns:  # a minute between control steps: nobody decides on it
            between = AlignedFrames(t_ns=g.t_ns, head=g.head, pv=g.pv, vr=g.vr, missing=(), cap=g.cap)
            self._between.append(between)
            self.between_seen = True
            return between
        recent = {r: tuple(f for f in h if f.t_ns <= t_ns) for r, h in self._vr_history.items() if h}
        return AlignedFrames(t_ns=g.t_ns, head=g.head, pv=dict(g.pv), vr=dict(g.vr), missing=self._missing(g),
                             cap=dict(g.cap), vr_recent=recent, head_recent=self._head_latest,
                             pv_recent=dict(self._pv_latest),
                             head_history=tuple(f for f in self._head_history if f.t_ns <= t_ns))
