"""The agent process: the only agent module that knows Zenoh and clocks.

Layers (STYLE.md): ``aligner`` groups frames by timestamp, ``snapshot`` turns them into the controller's arrays,
``controller`` decides, and this module turns decisions into bus messages (``DecisionMaker``, no I/O), then runs
that on the bus (``run_agent``) or on recorded frames (``decide_offline``). The same ``DecisionMaker`` serves both,
so a replay of the recorded frames reproduces the live decisions exactly.

Live loop: a Zenoh callback decodes and enqueues (``schemas.bus.Inbox``); this thread takes frames from the
queue, feeds the aligner, and on each control step publishes the commands (reliable, high priority) and
then the ``Decision`` that lists them; once the next step's frames are in, the follow-ups the decision announced
(``DecisionMaker.take_follow_ups``). An incomplete step is decided after a short wall-clock window for
late frames. A wall-clock watchdog publishes ``AgentStatus`` every second and says ``stale`` when no frame
has come for ``stale_after_s``; the agent never sends commands without fresh frames.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Iterable, Iterator
from typing import Any, Literal

import msgspec
import numpy as np

from agent.aligner import AlignedFrames, FrameAligner
from agent.ami import REFUSED_KINDS
from agent.controller import CvvcController
from agent.controller import Decision as ControllerDecision
from agent.decision import decision_time_ms, reason_kind
from agent.errors import AgentInputError
from agent.setpoints import recentred_setpoint
from agent.snapshot import snapshot_from
from agent.state import OracleSource
from regression.model import CvvcModel
from schemas import keys
from schemas import messages as m
from schemas.logs import RateLimitedLog
from schemas.settings import AgentSettings

__all__ = ["AgentSettings", "AgentSummary", "DecisionMaker", "decide_offline", "decide_offline_in_detail", "run_agent"]

log = logging.getLogger(__name__)
#: The window over which the status judges the share of refused frames [s], and the least refused to say so.
DEGRADED_WINDOW_S = 10.0
DEGRADED_MIN_REFUSED = 3
#: Decisions whose wall time the summary's percentiles cover (the latest; a week of 1-minute steps is 10,080).
DECISION_TIMES_KEPT = 100_000
#: Commands whose ids an ack may answer (the latest sent; a day of decisions on a feeder of ~40 devices).
SENT_COMMANDS_KEPT = 16_384


class AgentSummary(msgspec.Struct, frozen=True, kw_only=True):
    """Counts of one agent run, printed at exit with ``--json``: decisions, commands, acks by status, refused
    inputs by reason.

    ``clamped``: eq. (8) set points or bands brought into the regulators' accepted range before sending;
    ``log_suppressed``: warning lines not written by the rate limit, by kind.
    """

    decisions: int
    holds: int
    commands: int
    acks: dict[str, int]
    rejected: dict[str, int]
    clamped: int = 0
    log_suppressed: dict[str, int] = {}
    soft: int = 0
    # of the soft decisions, those of the tap deadband: taps held for a predicted violation within it, the limits
    # widened by it met (``Decision.tolerated``); the others are the soft form, eq. (17)
    tolerated: int = 0
    reasons: dict[str, int] = {}  # why decisions were soft or held, by kind of reason (``reason_kind``)
    decision_ms: dict[str, float] = {}  # the agent's wall time per decision (``decision_time_ms``): p50, p99, max
    decision_cpu_ms: dict[str, float] = {}  # the deciding thread's CPU time per decision (``Timings.cpu_s``)
    ami: dict[str, int] = {}  # AMI meter readings taken, used and ignored by kind (``agent.ami``; none without meters)
    step_ends: int = 0  # scan-end markers taken (``StepEnd``)
    released_by_step_end: int = 0  # steps with lost frames decided at once, on a marker, not after the late window
    decided_after_late_window: int = 0  # live: control steps decided only once the late-frame window was over
    clock_snapped: int = 0  # frames stamped off a control step within ``clock_tolerance_s``, taken as on it
    commands_refused: dict[str, int] = {}  # by device: its 'rejected' acks to this agent's commands (taken acks only)
    follow_ups: int = 0  # commands sent after a decision, at the next step (set points re-centred; in ``commands``)
    # each regulator's tap step as its compared reading measured it at its own moves [V on 120 V base], those measured
    # (``agent.setpoints.MeasuredSteps``: eq. 8 lands one-step moves with it)
    measured_steps_v120: dict[str, float] = {}
    bought: int = 0  # decisions that took a tap move once the Q standing in for it had cost as much (rent or buy)


class _Recentre(msgspec.Struct, frozen=True):
    """A regulator told to step by eq. (8) by the latest decision: what its follow-up needs."""

    cmd_id: str
    tap_before: int
    tap_target: int
    action: m.SetpointAction
    valid_until_t_ns: int


def _round(x: float, digits: int = 9) -> float:
    return float(round(float(x), digits))


def _within(x: float, lo: float, hi: float, digits: int = 9) -> float:
    """``_round`` clipped to a schema range: a diagnostic out of its bounds (an estimate of a broken model or of
    extreme frames) must not make the whole decision undecodable for its receivers.
    """
    return min(max(_round(x, digits), lo), hi)


def _within_array(x: np.ndarray, lo: float, hi: float, digits: int) -> list:
    """``_within`` of every element of an array, as (nested) Python lists (vectorised: a decision carries
    hundreds of sensitivities, and element-wise Python rounding was 40 % of its decision time).
    """
    return np.clip(np.round(np.asarray(x, float), digits), lo, hi).tolist()


class DecisionMaker:
    """Frames in, decision messages out: aligner + controller + message construction. No I/O, no clock.

    Command ids are ``<agent>:<step t_ns>:<device>`` (a follow-up's ``<agent>:<step t_ns>:<device>:recentre``, the
    step being its decision's), the ``seq`` of every message of one decision or one batch of follow-ups is the
    count of both so far, and commands expire ``valid_intervals`` control periods after their decision's step.
    """

    def __init__(self, model: CvvcModel, settings: AgentSettings) -> None:
        self.model = model
        self.settings = settings
        self.period_ns = int(model.control_period_s) * 1_000_000_000
        self.aligner = FrameAligner(feeder_id=settings.feeder_id, pv_ids=tuple(p.id for p in model.pv),
                                    regulator_ids=tuple(r.id for r in model.regulators),
                                    control_period_ns=self.period_ns,
                                    capacitor_ids=tuple(c.id for c in model.capacitors),
                                    clock_tolerance_ns=int(settings.clock_tolerance_s * 1e9))
        self.controller = CvvcController(model, settings, mode=settings.mode, correction=settings.correction,
                                         meters=settings.meters)
        self.oracle: OracleSource | None = None  # case A: set by the live runtime once its session is open
        self.seq = 0  # decisions and batches of follow-ups sent
        self.decisions = 0
        self.follow_ups = 0
        self._recentre: dict[str, _Recentre] = {}  # regulator -> its follow-up, announced by the latest decision
        self._decided_t_ns = -1  # the latest decision's step: follow-ups go with the first step after it
        self.holds = 0
        self.commands_sent = 0
        self.clamped = 0  # set points / bands brought into the regulators' accepted range
        self.soft = 0
        self.tolerated = 0  # of the soft ones: taps held by the tap deadband, the limits widened by it met
        self.reasons: Counter[str] = Counter()  # of soft and hold decisions
        self.decision_s: deque[float] = deque(maxlen=DECISION_TIMES_KEPT)  # wall time of each decision [s]
        self.decision_cpu_s: deque[float] = deque(maxlen=DECISION_TIMES_KEPT)  # its thread's CPU time [s]
        # cmd_id -> (device, answered) of the latest commands sent: one answer (accepted, clipped, rejected) and one
        # 'expired' count per command, so the device's ack to a replay of it by someone else does not
        self._sent: OrderedDict[str, tuple[str, bool]] = OrderedDict()
        self._dv_dtap = _within_array(np.asarray(model.dv_dtap_pu, float), -1.0, 1.0, 12)  # a model constant

    def on_frame(self, key: str, msg: Any) -> list[tuple[AlignedFrames, ControllerDecision]]:
        """Add a received frame; the decisions of the steps it completes (none for an AMI meter's reading)."""
        if isinstance(msg, m.MeterFrame):
            if key.rsplit("/", 1)[-1] != msg.meter_id:
                self.aligner.reject("unknown_device", f"{key[:200]}: a reading of meter {msg.meter_id[:64]!r}")
                return []
            ignored = self.controller.ami.add(msg, self.aligner.newest_t_ns)
            if ignored is not None and ignored[0] in REFUSED_KINDS:
                self.aligner.reject(REFUSED_KINDS[ignored[0]], ignored[1])
            return []
        return [(a, self._decide(a)) for a in self.aligner.add(key, msg)]

    def ack_problem(self, key: str, ack: m.Ack) -> str | None:
        """Why an ack does not count, or None (then it is taken): it must answer a command this agent sent (its
        ``cmd_id``, kept for the latest ``SENT_COMMANDS_KEPT``) to the device it names, on that device's ack key, and
        be that command's first answer (or its one ``expired``): the device's answer to someone's replay of the
        command ('rejected', replay) does not count.
        """
        if key.rsplit("/", 1)[-1] != ack.device_id:
            return f"{key[:200]}: an ack of device {ack.device_id[:64]!r}"
        sent = self._sent.get(ack.cmd_id)
        if sent is None or sent[0] != ack.device_id:
            return f"ack of {ack.device_id[:64]!r} for {ack.cmd_id[:96]!r}: not a command this agent sent to it"
        if ack.status == "expired":
            del self._sent[ack.cmd_id]
        elif sent[1]:
            return f"ack of {ack.device_id[:64]!r} for {ack.cmd_id[:96]!r}: that command was answered already"
        else:
            self._sent[ack.cmd_id] = (sent[0], True)
        return None

    def close_pending(self) -> list[tuple[AlignedFrames, ControllerDecision]]:
        """Decide the steps still waiting for frames with what arrived (the late window passed)."""
        return [(a, self._decide(a)) for a in self.aligner.close_pending()]

    def _decide(self, aligned: AlignedFrames) -> ControllerDecision:
        cpu_started = time.thread_time()  # the step's CPU time counts the snapshot too (``Timings.cpu_s``)
        snap = snapshot_from(aligned, self.model, reading_window_s=self.settings.reading_window_s,
                             last_good_s=self.settings.last_good_s, reading_fit_s=self.settings.reading_fit_s)
        return self.controller.decide(snap, oracle=self.oracle, cpu_started=cpu_started)

    def to_message(self, aligned: AlignedFrames, d: ControllerDecision, *, align_s: float = 0.0) -> m.Decision:
        """The bus message of one controller decision, with the commands it sends."""
        s = self.settings
        self.seq += 1
        self.decisions += 1
        self._recentre.clear()  # a new decision: the last one's follow-ups are due no more
        seq = self.seq
        t = self._decided_t_ns = aligned.t_ns
        valid_until = t + int(s.valid_intervals * self.period_ns)
        in_reply_to = aligned.head.seq if aligned.head is not None else 0

        def header(device: str) -> dict[str, Any]:
            return {"t_ns": t, "seq": seq, "source": s.agent_id, "in_reply_to": in_reply_to,
                    "valid_until_t_ns": valid_until, "cmd_id": f"{s.agent_id}:{t}:{device}"}

        commands: list[m.DecisionCommand] = []
        if d.status != "hold":
            for k, plant in enumerate(self.model.pv):
                if d.pv_command[k] and d.pv_q_kvar is not None:
                    commands.append(m.PvCommand(plant_id=plant.id, q_kvar=_round(d.pv_q_kvar[k], 3),
                                                **header(plant.id)))
            for r, reg in enumerate(self.model.regulators):
                if not d.reg_command[r]:
                    continue
                action: m.TapAction | m.SetpointAction
                if s.mode == "setpoints" and d.reg_setpoint_v120 is not None and d.reg_band_v120 is not None:
                    action = m.SetpointAction(setpoint_v120=self._clamp(d.reg_setpoint_v120[r], m.SETPOINT_RANGE_V120),
                                              band_v120=self._clamp(d.reg_band_v120[r], m.BAND_RANGE_V120))
                elif d.reg_tap is not None:
                    action = m.TapAction(tap=int(d.reg_tap[r]))
                else:
                    continue
                commands.append(m.RegCommand(regulator_id=reg.id, action=action, **header(reg.id)))
                self._announce(aligned, d, r, action, valid_until)
            if d.cap_steps is not None:
                for c, bank in enumerate(self.model.capacitors):
                    if d.cap_command[c]:
                        commands.append(m.CapCommand(capacitor_id=bank.id, closed_steps=int(d.cap_steps[c]),
                                                     **header(bank.id)))
        else:
            self.holds += 1
        if d.status in ("soft", "hold"):
            self.soft += d.status == "soft"
            self.tolerated += d.tolerated  # a soft decision by construction
            self.reasons[reason_kind(d.reason)] += 1
        self.commands_sent += len(commands)
        for cmd in commands:
            self._sent[cmd.cmd_id] = (_command_device(cmd), False)
        while len(self._sent) > SENT_COMMANDS_KEPT:
            self._sent.popitem(last=False)
        estimates = []
        if d.v_pu is not None:
            pred = d.v_pred_pu if d.v_pred_pu is not None else d.v_pu
            n = len(self.model.critical_nodes)
            lows = [0.0] * n if d.v_bound_low_pu is None else _within_array(d.v_bound_low_pu, 0.0, 3.0, 6)
            highs = [0.0] * n if d.v_bound_high_pu is None else _within_array(d.v_bound_high_pu, 0.0, 3.0, 6)
            estimates = [m.NodeEstimate(node=c.name, v_pu=v, v_predicted_pu=p, bound_low_pu=lo, bound_high_pu=hi)
                         for c, v, p, lo, hi in zip(self.model.critical_nodes, _within_array(d.v_pu, 0.0, 3.0, 9),
                                                    _within_array(pred, 0.0, 3.0, 9), lows, highs, strict=True)]
        dv_dq = [] if d.dv_dq_pu_per_kvar is None else _within_array(d.dv_dq_pu_per_kvar, -1.0, 1.0, 12)
        tm = d.timings
        self.decision_s.append(tm.total_s + align_s)
        self.decision_cpu_s.append(tm.cpu_s)
        return m.Decision(
            t_ns=t, seq=seq, source=s.agent_id, feeder_id=s.feeder_id, step_t_ns=t, in_reply_to=in_reply_to,
            status=d.status, reason=d.reason[:500], commands=commands, estimates=estimates,
            dv_dq_pu_per_kvar=dv_dq,
            dv_dtap_pu=self._dv_dtap,
            solver=m.SolverStats(status=d.solver_status, iterations=d.iterations,
                                 objective=_within(d.objective, -1e12, 1e12),
                                 soft=d.status == "soft"),
            timings=msgspec.structs.replace(tm, align_s=align_s, total_s=tm.total_s + align_s),
            corrected=d.corrected, missing=list(aligned.missing) + [x for x in d.missing if x not in aligned.missing],
            out_of_envelope=bool(d.out_of_envelope),
            follow_ups=[f.cmd_id for f in self._recentre.values()],
        )

    def _announce(self, aligned: AlignedFrames, d: ControllerDecision, r: int,
                  action: m.TapAction | m.SetpointAction, valid_until: int) -> None:
        """Note regulator ``r``'s follow-up if ``d`` tells it to step by eq. (8) (``setpoint_recentre``) and the
        frames come between control steps (there is a next step before the next decision).
        """
        reg_id = self.model.regulators[r].id
        recent = aligned.vr.get(reg_id) or (aligned.vr_recent.get(reg_id) or (None,))[-1]
        if (not self.settings.setpoint_recentre or not isinstance(action, m.SetpointAction) or d.reg_tap is None
                or recent is None or int(d.reg_tap[r]) == recent.tap or not self.aligner.between_seen):
            return
        self._recentre[reg_id] = _Recentre(
            cmd_id=f"{self.settings.agent_id}:{aligned.t_ns}:{reg_id}:recentre",
            tap_before=recent.tap, tap_target=int(d.reg_tap[r]), action=action, valid_until_t_ns=valid_until)

    def take_follow_ups(self) -> list[m.RegCommand]:
        """The follow-ups due: once a step after the latest decision's is in, one command for each regulator
        that decision told to step (``agent.setpoints.recentred_setpoint``: the band centred on the reading once
        the regulator has stepped, else eq. (8)'s set point again), all with one new ``seq``. Call after
        publishing the decisions of each frame taken (the live loop and ``decide_offline`` both do).
        """
        due = [a for a in self.aligner.take_between() if a.t_ns > self._decided_t_ns]
        if not due or not self._recentre:
            return []
        a, s = due[0], self.settings
        self.seq += 1
        out = []
        for reg_id, f in self._recentre.items():
            frame = a.vr.get(reg_id)
            setpoint = f.action.setpoint_v120
            if frame is not None:
                try:
                    setpoint = self._clamp(recentred_setpoint(f.tap_before, f.tap_target, frame.tap,
                                                              frame.v_compared_120, setpoint), m.SETPOINT_RANGE_V120)
                except AgentInputError:
                    pass  # eq. (8)'s again
            cmd = m.RegCommand(t_ns=a.t_ns, seq=self.seq, source=s.agent_id,
                               in_reply_to=a.head.seq if a.head is not None else 0,
                               valid_until_t_ns=f.valid_until_t_ns, cmd_id=f.cmd_id, regulator_id=reg_id,
                               action=m.SetpointAction(setpoint_v120=setpoint, band_v120=f.action.band_v120))
            self._sent[cmd.cmd_id] = (reg_id, False)
            out.append(cmd)
        self._recentre.clear()
        self.commands_sent += len(out)
        self.follow_ups += len(out)
        while len(self._sent) > SENT_COMMANDS_KEPT:
            self._sent.popitem(last=False)
        return out


    def _clamp(self, value: float, accepted: tuple[float, float]) -> float:
        """``value`` rounded and brought into a regulator's ``accepted`` range; counts clamps.

        Eq. (8) can ask for a set point outside what a controller accepts (a large tap change from an extreme
        reading); the nearest accepted value moves the regulator the same way instead of being refused.
        """
        v = _round(value, 4)
        c = min(max(v, accepted[0]), accepted[1])
        self.clamped += c != v
        return c


_FRAME_TYPES = (m.HeadFrame, m.PvFrame, m.RegFrame, m.CapFrame, m.StepEnd, m.MeterFrame)  # frames, markers, meters


def decide_offline(model: CvvcModel, settings: AgentSettings | None,
                   frames: Iterable[Any]) -> Iterator[m.Decision]:
    """Re-run the agent's decision code on recorded frames (no bus, no clock), in the order given.

    ``frames`` yields objects with ``key`` and ``msg`` (``schemas.bus.Received`` or the recordings
    reader's items) or ``(key, msg)`` pairs. Steps still open at the end are decided as the live agent
    decides them after its late-frame window.
    """
    for message, _ in decide_offline_in_detail(model, settings, frames):
        yield message


def decide_offline_in_detail(model: CvvcModel, settings: AgentSettings | None, frames: Iterable[Any], *,
                             maker: DecisionMaker | None = None) -> Iterator[tuple[m.Decision, ControllerDecision]]:
    """``decide_offline`` with each message's controller decision (its solves, ``Decision.solves``). ``maker``: the
    decision maker to use (made from ``model`` and ``settings`` when None), for a caller that reads its controller
    between decisions (``cvvc.explain``).
    """
    settings = settings or AgentSettings()
    if settings.full_visibility:
        raise ValueError("case A (full visibility) needs the live bridge's oracle; it cannot be re-run offline")
    maker = maker or DecisionMaker(model, settings)
    for item in frames:
        key, msg = (item.key, item.msg) if hasattr(item, "key") else item
        if isinstance(msg, _FRAME_TYPES):
            for aligned, d in maker.on_frame(key, msg):
                yield maker.to_message(aligned, d), d
            maker.take_follow_ups()  # as the live loop does (their seq counts)
    for aligned, d in maker.close_pending():
        yield maker.to_message(aligned, d), d


# ------------------------------------------------------------------------------------------- live
def run_agent(model: CvvcModel, settings: AgentSettings, bus, *, stop: threading.Event | None = None,
              install_signals: bool = True) -> AgentSummary:
    """Run the agent on the bus until ``stop`` is set (or SIGINT/SIGTERM when ``install_signals``)."""
    from schemas.bus import Inbox, LivelinessWatcher, TypedPublisher, open_session

    stop = stop or threading.Event()
    if install_signals and threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
    maker = DecisionMaker(model, settings)
    f = settings.feeder_id
    acks: Counter[str] = Counter()
    refused_by: Counter[str] = Counter()  # device -> our commands it answered 'rejected'
    rlog = RateLimitedLog(log)
    health = _FrameHealth(maker.aligner)
    with open_session(bus) as session:
        devices = LivelinessWatcher(session, keys.alive_all(f),
                                    on_change=lambda k, up: log.info("device %s %s", k, "up" if up else "down"))
        inbox = Inbox(maxsize=8192)
        # one subscription for every frame: Zenoh runs the callbacks of separate subscribers concurrently, so
        # frames of consecutive steps on three subscriptions were enqueued out of order (seen in lockstep: a
        # step released early and its last frames rejected as stale); one callback keeps the arrival order
        inbox.subscribe(session, f"{keys.ROOT}/{f}/meas/**", validate=_frame_key_problem)
        inbox.subscribe(session, f"cvvc/{f}/ack/**", m.Ack)
        decision_pub = TypedPublisher(session, keys.agent_decision(f), m.Decision, reliable=True)
        status_pub = TypedPublisher(session, keys.agent_status(f), m.AgentStatus, reliable=True)
        # a decision's commands are batched by Zenoh and flushed by the decision (express, same priority) after them
        cmd_pubs: dict[str, TypedPublisher[Any]] = {}
        batched = {"reliable": True, "express": False}
        for p in model.pv:
            cmd_pubs[p.id] = TypedPublisher(session, keys.cmd(f, "pv", p.id), m.PvCommand, **batched)
        for r in model.regulators:
            cmd_pubs[r.id] = TypedPublisher(session, keys.cmd(f, "vr", r.id), m.RegCommand, **batched)
        for c in model.capacitors:
            cmd_pubs[c.id] = TypedPublisher(session, keys.cmd(f, "cap", c.id), m.CapCommand, **batched)
        # follow-ups have no decision after them to flush a batch: sent at once
        follow_pubs = {r.id: TypedPublisher(session, keys.cmd(f, "vr", r.id), m.RegCommand, reliable=True)
                       for r in model.regulators} if settings.mode == "setpoints" else {}
        if settings.full_visibility:
            maker.oracle = _Oracle(session, f, settings.oracle_timeout_s, rlog).reply
        # alive once listening: a device or a watcher that sees the token may count on the next step being heard
        token = session.liveliness().declare_token(keys.alive(f, "agent", settings.agent_id))

        last_frame_wall = time.monotonic()
        last_frame_t_ns = 0
        pending_since: float | None = None
        late_decided = 0
        next_status = time.monotonic()
        status_seq = 0

        def publish(pairs: list[tuple[AlignedFrames, ControllerDecision]], t_recv: float) -> None:
            for aligned, d in pairs:
                msg = maker.to_message(aligned, d, align_s=max(0.0, time.monotonic() - t_recv - d.timings.total_s))
                for c in msg.commands:
                    cmd_pubs[_command_device(c)].put(c)
                decision_pub.put(msg)
            for c in maker.take_follow_ups():
                follow_pubs[c.regulator_id].put(c)

        try:
            while not stop.is_set():
                item = inbox.get(timeout_s=0.02)
                now = time.monotonic()
                if item is not None:
                    msg = item.msg
                    if isinstance(msg, m.Ack) and (why := maker.ack_problem(item.key, msg)) is not None:
                        maker.aligner.reject("foreign_ack", why)  # a forged 'rejected' would hold a bank
                    elif isinstance(msg, m.Ack):
                        acks[msg.status] += 1
                        if msg.status == "rejected":
                            refused_by[msg.device_id] += 1
                            rlog.warning("command_rejected", "command %s rejected by %s: %s", msg.cmd_id,
                                         msg.device_id, msg.reason)
                            maker.controller.refuse_bank(msg.device_id, msg.t_ns)  # a bank is then held
                    else:
                        if not isinstance(msg, m.StepEnd):  # a marker alone does not make the inputs fresh
                            last_frame_wall, last_frame_t_ns = now, msg.t_ns
                        publish(maker.on_frame(item.key, msg), now)
                        pending_since = (pending_since or now) if maker.aligner.pending else None
                # frames already received are not late: close only once the queue is drained (under a burst,
                # closing earlier would decide an incomplete step and reject its queued frames as stale)
                if pending_since is not None and now - pending_since > settings.late_window_s and inbox.queue.empty():
                    late = maker.close_pending()
                    late_decided += len(late)
                    publish(late, now)
                    pending_since = None
                if now >= next_status:
                    next_status = now + 1.0
                    status_seq += 1
                    since = now - last_frame_wall
                    degraded = health.refusing(now)
                    state: Literal["ok", "stale", "starting", "degraded"] = (
                        "stale" if since > settings.stale_after_s else "degraded" if degraded
                        else ("starting" if not last_frame_t_ns else "ok"))
                    rejected = dict(inbox.rejects.by_kind())
                    for k, n in maker.aligner.rejected.items():
                        rejected[k] = rejected.get(k, 0) + n
                    status_pub.put(m.AgentStatus(
                        t_ns=last_frame_t_ns, seq=status_seq, source=settings.agent_id, feeder_id=f, state=state,
                        last_frame_t_ns=last_frame_t_ns, seconds_since_frame=min(since, 1e6),
                        decisions=maker.decisions, rejected=rejected, reason=(degraded or "")[:500],
                        log_suppressed=_suppressed(rlog, inbox.rejects.log_suppressed())))
                    if state == "stale":
                        rlog.warning("stale", "no frames for %.0f s: inputs stale, sending nothing", since)
                    elif degraded:
                        rlog.warning("degraded", "degraded: %s", degraded)
        finally:
            devices.undeclare()
            inbox.undeclare()
            token.undeclare()
    rejected = dict(inbox.rejects.by_kind())
    for k, n in maker.aligner.rejected.items():
        rejected[k] = rejected.get(k, 0) + n
    return AgentSummary(decisions=maker.decisions, holds=maker.holds, commands=maker.commands_sent, acks=dict(acks),
                        rejected=rejected, clamped=maker.clamped,
                        log_suppressed=_suppressed(rlog, inbox.rejects.log_suppressed()),
                        soft=maker.soft, tolerated=maker.tolerated, reasons=dict(maker.reasons.most_common(20)),
                        decision_ms=decision_time_ms(maker.decision_s),
                        decision_cpu_ms=decision_time_ms(maker.decision_cpu_s),
                        ami=dict(maker.controller.ami.counts),
                        step_ends=maker.aligner.step_ends, released_by_step_end=maker.aligner.released_by_step_end,
                        decided_after_late_window=late_decided, clock_snapped=maker.aligner.snapped,
                        commands_refused=dict(refused_by), follow_ups=maker.follow_ups,
                        measured_steps_v120=maker.controller.measured_steps_v120(),
                        bought=maker.controller.tap_moves.bought)


def _suppressed(rlog: RateLimitedLog, rejects: dict[str, int]) -> dict[str, int]:
    """Log lines not written, by kind: the process's own and the bus's rejections (``rejected_<kind>``)."""
    return dict(rlog.suppressed) | {f"rejected_{k}": n for k, n in rejects.items()}


class _FrameHealth:
    """Whether the agent refused most of the frames it got in the last ``DEGRADED_WINDOW_S`` (wall clock)."""

    def __init__(self, aligner: FrameAligner) -> None:
        self._aligner = aligner
        self._samples: list[tuple[float, int, Counter[str]]] = []  # (wall time, accepted, refused by kind) so far

    def refusing(self, now: float) -> str | None:
        """The reason the agent is degraded now, or None (call once per status period)."""
        a = self._aligner
        self._samples.append((now, a.accepted, Counter(a.rejected)))
        while len(self._samples) > 1 and now - self._samples[0][0] > DEGRADED_WINDOW_S:
            self._samples.pop(0)
        _, acc0, ref0 = self._samples[0]
        by_kind = a.rejected - ref0
        accepted, refused = a.accepted - acc0, sum(by_kind.values())
        if refused < DEGRADED_MIN_REFUSED or refused <= accepted:
            return None
        kind = max(by_kind, key=lambda k: by_kind[k])
        return (f"refused {refused} of {refused + accepted} frames in the last {DEGRADED_WINDOW_S:g} s, "
                f"mostly {kind!r}: {a.last_reject.get(kind, '')}")


def _command_device(c: m.DecisionCommand) -> str:
    """The id of the device a command is for."""
    match c:
        case m.PvCommand():
            return c.plant_id
        case m.RegCommand():
            return c.regulator_id
        case m.CapCommand():
            return c.capacitor_id
    raise TypeError(f"not a device command: {type(c).__name__}")


def _frame_key_problem(key: str, msg: Any) -> str | None:
    """Why a decoded sample under ``meas/**`` is not a device frame key of its type, or None."""
    depth = 4 if isinstance(msg, m.HeadFrame | m.StepEnd) else 5
    return None if key.count("/") + 1 == depth else f"{key}: not a {type(msg).__name__} key"


class _Oracle:
    """Case A: true voltages of every node and perturbation sensitivities, asked of the bridge."""

    def __init__(self, session, feeder_id: str, timeout_s: float, rlog: RateLimitedLog) -> None:
        self._session = session
        self._key = keys.sim_oracle(feeder_id)
        self._timeout_s = timeout_s
        self._rlog = rlog

    def reply(self, t_ns: int) -> m.OracleReply | None:
        """The oracle's reply for step ``t_ns`` [ns], or None when the bridge did not answer in time."""
        from schemas.bus import BadMessage, codec_for

        request = codec_for(m.OracleRequest).encode(m.OracleRequest(t_ns=t_ns))
        reply = None
        for r in self._session.get(self._key, payload=request, timeout=self._timeout_s):
            if r.ok is not None:
                try:
                    reply = codec_for(m.OracleReply).decode(r.ok.payload.to_bytes())
                except BadMessage as e:
                    self._rlog.warning("bad_oracle_reply", "bad oracle reply: %s", e)
        return reply
