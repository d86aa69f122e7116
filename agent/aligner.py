"""Frame aligner: gathers the feeder-head, PV and regulator frames of one timestamp.

Driven by frame timestamps only (never a clock), so a live run and an offline replay of the same frames
produce the same aligned sets. The rule, documented in docs/agent.md:

- Frames are grouped by their ``t_ns``. A group is *complete* when the head meter, every PV plant and every
  regulator of the model have reported; a complete group is released at once.
- An incomplete group is released when a frame of a *newer* timestamp arrives, or when the runtime closes it
  after its late-frame window (``close_pending``); devices that did not report are listed as ``missing``.
- Rejected, never stored (and counted by reason): a frame for another feeder, from a device the model does
  not know, with a ``seq`` not above the last accepted one from that source (duplicate / out of order),
  older than the newest released group (stale), with the ``invalid`` quality flag, or with physically
  impossible values.
- Only groups on a control step (``t_ns`` a multiple of the control period) are released as decisions to
  make; the others only refresh the last-known state.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

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

    @property
    def complete(self) -> bool:
        return not self.missing


def plausibility_problem(frame: m.HeadFrame | m.PvFrame | m.RegFrame) -> str | None:
    """Why a schema-valid frame is physically impossible, or None.

    The schema bounds catch absurd numbers; these catch values that are representable but cannot be:
    phases repeated, a total that is not the sum of its phases, PV output above its rating.
    """
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


@dataclass
class _Group:
    t_ns: int
    head: m.HeadFrame | None = None
    pv: dict[str, m.PvFrame] = field(default_factory=dict)
    vr: dict[str, m.RegFrame] = field(default_factory=dict)


class FrameAligner:
    """Stateful grouping of frames by timestamp; see the module docstring for the rule."""

    def __init__(self, *, feeder_id: str, pv_ids: tuple[str, ...], regulator_ids: tuple[str, ...],
                 control_period_ns: int) -> None:
        self.feeder_id = feeder_id
        self.pv_ids = pv_ids
        self.regulator_ids = regulator_ids
        self.control_period_ns = control_period_ns
        self.rejected: Counter[str] = Counter()
        self.last_reject: dict[str, str] = {}
        self._last_seq: dict[str, int] = {}
        self._groups: dict[int, _Group] = {}
        self._released_t_ns = -1

    # ---------------------------------------------------------------------------------------- input
    def add(self, key: str, frame: m.HeadFrame | m.PvFrame | m.RegFrame) -> list[AlignedFrames]:
        """Add one decoded frame; returns the control-step groups this frame completes or closes."""
        why = self._check(key, frame)
        if why is not None:
            kind, detail = why
            self.rejected[kind] += 1
            self.last_reject[kind] = detail
            return []
        self._last_seq[frame.source] = frame.seq
        out = [self._release(t) for t in sorted(self._groups) if t < frame.t_ns]
        g = self._groups.setdefault(frame.t_ns, _Group(frame.t_ns))
        match frame:
            case m.HeadFrame():
                g.head = frame
            case m.PvFrame():
                g.pv[frame.plant_id] = frame
            case m.RegFrame():
                g.vr[frame.regulator_id] = frame
        if self._missing(g) == ():
            out.append(self._release(frame.t_ns))
        return [a for a in out if a.t_ns % self.control_period_ns == 0]

    def close_pending(self) -> list[AlignedFrames]:
        """Release every open group (late-frame window over, or end of input); control steps only."""
        out = [self._release(t) for t in sorted(self._groups)]
        return [a for a in out if a.t_ns % self.control_period_ns == 0]

    @property
    def pending(self) -> bool:
        return bool(self._groups)

    # ------------------------------------------------------------------------------------- internals
    def _check(self, key: str, frame: m.HeadFrame | m.PvFrame | m.RegFrame) -> tuple[str, str] | None:
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
        last = self._last_seq.get(frame.source)
        if last is not None and frame.seq <= last:
            return ("duplicate" if frame.seq == last else "out_of_order"), f"{frame.source} seq {frame.seq} <= {last}"
        if frame.t_ns <= self._released_t_ns:
            return "stale", f"{frame.source} t_ns {frame.t_ns} not after released {self._released_t_ns}"
        problem = plausibility_problem(frame)
        if problem is not None:
            return "implausible", f"{frame.source}: {problem}"
        return None

    def _missing(self, g: _Group) -> tuple[str, ...]:
        miss = [] if g.head is not None else ["head"]
        miss += [k for k in self.pv_ids if k not in g.pv]
        miss += [r for r in self.regulator_ids if r not in g.vr]
        return tuple(miss)

    def _release(self, t_ns: int) -> AlignedFrames:
        g = self._groups.pop(t_ns)
        self._released_t_ns = max(self._released_t_ns, t_ns)
        return AlignedFrames(t_ns=g.t_ns, head=g.head, pv=dict(g.pv), vr=dict(g.vr), missing=self._missing(g))
