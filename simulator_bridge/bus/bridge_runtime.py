"""The bridge's state between steps: its declarations, its queue, the lockstep's decision tracking, one step.

:class:`BridgeRuntime` is used only by the stepping thread (``bridge.py``'s run loop); Zenoh callbacks only decode
and enqueue (``schemas.bus.Inbox``). Its parts: the :class:`~simulator_bridge.bus.device_bank.DeviceBank` (the devices
and their commands), the :class:`~simulator_bridge.bus.oracle_serving.OracleServer` (case A only), and the publishing of
a step's frames, inline (:class:`~simulator_bridge.bus.publishing.StepFramer`) or by a
:class:`~simulator_bridge.bus.publisher_process.PublisherProcess`.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import msgspec
import numpy as np
import zenoh

from schemas import keys
from schemas import messages as m
from schemas.bus import BusConfig, Inbox, LivelinessWatcher, Received
from schemas.devicemap import DeviceMap
from schemas.logs import RateLimitedLog
from schemas.security import COMMAND_ROLE
from simulator_bridge.bus.adapter_frames import AdapterFrames, Protocol
from simulator_bridge.bus.bridge_config import BridgeConfig
from simulator_bridge.bus.device_bank import BridgeCounters, DeviceBank
from simulator_bridge.bus.dnp3_fleet import Dnp3Fleet, regulator_phases
from simulator_bridge.bus.oracle_serving import OracleQuery, OracleServer
from simulator_bridge.bus.publisher_process import PublisherProcess, StepPacker, child_bus
from simulator_bridge.bus.publishing import FINITE_READING_FIELDS, FramePublisher, FramerSpec, StepFramer
from simulator_bridge.bus.sunspec_fleet import SunSpecFleet, plant_phases
from simulator_bridge.errors import BridgeError
from simulator_bridge.simulation.live_accuracy import LiveAccuracyAccumulator
from simulator_bridge.simulation.metrics_stream import MetricsAccumulator, zone_phase_nodes

if TYPE_CHECKING:
    from simulator_bridge.opendss.engine import FeederEngine
    from simulator_bridge.simulation.profiles import YearProfiles
    from simulator_bridge.simulation.qsts import Qsts, StepResult

__all__ = ["BridgeRuntime", "dnp3_fleet", "publisher_bus", "sunspec_fleet"]

log = logging.getLogger("simulator_bridge.bus.bridge")  # the bridge's log lines, under the bridge's name

_NS = 1_000_000_000
_POLL_S = 0.05  # longest a wait goes without checking the stop event [s]
_TRUTH_KEPT = 16  # control steps whose truth waits for their decision (real time: decisions may come late)
_DRAIN_MAX = 1000  # queued items handled in one go before the clock and the stop event are looked at again
# publisher="auto" uses the publisher process from this many nodes on: measured faster than inline on IEEE 123 (278
# nodes), the rural feeder (1283) and IEEE 8500 (8531); no faster on IEEE 13 (41), where a child process would only
# add its start, about a second (docs/bridge.md, Speed)
_PROCESS_MIN_NODES = 200


def check_finite_step(res: StepResult) -> tuple[float, float]:
    """Raise ``BridgeError`` if a step's readings or truth hold NaN or inf (a power flow gone wrong); return
    the lowest and highest node voltage [pu].

    The node voltages are finite exactly when their extremes are (NaN propagates through min and max); the
    few readings are checked in one vectorised pass. A few µs.
    """
    v_lo, v_hi = float(res.v_pu.min()), float(res.v_pu.max())
    rd = res.readings
    small = np.concatenate([getattr(rd, name) for name in FINITE_READING_FIELDS] + [res.pv_q_kvar, res.pv_p_kw],
                           axis=None, dtype=float)
    if not (math.isfinite(v_lo) and math.isfinite(v_hi) and np.isfinite(small).all()):
        raise non_finite(res)
    return v_lo, v_hi


def non_finite(res: StepResult) -> BridgeError:
    """The error of a step whose power flow produced NaN or inf."""
    return BridgeError(f"step at t_ns={res.t_ns}: the power flow produced non-finite values; the feeder or its "
                       "profiles are broken (check `cvvc feeder info`)")


def sunspec_fleet(c: BridgeConfig, dm: DeviceMap, engine: FeederEngine, qsts: Qsts) -> SunSpecFleet | None:
    """The simulated SunSpec inverters of ``c.pv_sunspec`` (not serving yet), or None without any.

    Raises
    ------
    BridgeError
        A plant the feeder does not have, an endpoint that is not ``tcp/127.0.0.1:PORT``.
    """
    if not c.pv_sunspec:
        return None
    return SunSpecFleet(c.pv_sunspec, dm, tuple(engine.pv_ids),
                        plant_phases(tuple(engine.node_names), engine.pv_node_index),
                        q_at_night=tuple(qsts.pv_q_at_night.tolist()), volt_var=c.pv_local == "volt_var")


def dnp3_fleet(c: BridgeConfig, engine: FeederEngine) -> Dnp3Fleet | None:
    """The simulated DNP3 outstations of ``c.field_dnp3`` (not serving yet), or None without any.

    Raises
    ------
    BridgeError
        A device the feeder does not have, an endpoint that is not ``tcp/127.0.0.1:PORT``, a bank of several steps.
    """
    return Dnp3Fleet(c.field_dnp3, engine) if c.field_dnp3 else None


def publisher_bus(c: BridgeConfig, bus: BusConfig, n_nodes: int) -> BusConfig | None:
    """The publisher process's bus, or None to publish inline (``BridgeConfig.publisher``).

    Raises
    ------
    BridgeError
        ``publisher='process'`` with a bus the publisher process cannot join.
    """
    if c.publisher == "inline" or c.latency_s > 0.0 or (c.publisher == "auto" and n_nodes < _PROCESS_MIN_NODES):
        return None
    child = child_bus(bus)
    if child is None and c.publisher == "process":
        raise BridgeError("publisher='process' needs a bus the publisher process can join: connect or listen "
                          "endpoints (not :0) and no Zenoh config file; use publisher='inline'")
    return child


@dataclass(frozen=True)
class _SenderGone:
    """An agent's liveliness token was withdrawn: its devices forget its command sequence (stepping thread)."""

    source: str


class BridgeRuntime:
    """The bridge's state between steps. Used only by the stepping thread (callbacks only enqueue).

    Parameters
    ----------
    config : the run. bus : the bridge's bus settings. session : its open Zenoh session. dm : the device map.
    engine, profiles, qsts : the feeder, its year profiles and the simulation. start_step : the profile step of the
    run's first step. fleet : the simulated inverters of the plants behind SunSpec (:func:`sunspec_fleet`), not
    started yet (started here, stopped by :meth:`close`), or None. dnp3 : the simulated outstations of the
    regulators and banks behind DNP3 (:func:`dnp3_fleet`), the same way, or None.
    """

    def __init__(self, config: BridgeConfig, bus: BusConfig, session: zenoh.Session, dm: DeviceMap,
                 engine: FeederEngine, profiles: YearProfiles, qsts: Qsts, start_step: int,
                 fleet: SunSpecFleet | None = None, dnp3: Dnp3Fleet | None = None) -> None:
        c = self.config = config
        self.session, self.dm, self.engine, self.profiles, self.qsts = session, dm, engine, profiles, qsts
        self.counters = BridgeCounters(rlog=RateLimitedLog(log))  # every line a peer can provoke
        self.fid = c.feeder_id or dm.feeder.name
        self.step_s = int(profiles.step_s)
        self.control_every = max(1, dm.feeder.control_period_s // self.step_s)
        self.start_step = start_step
        local: Literal["unity_pf", "volt_var"] = "volt_var" if c.pv_local == "volt_var" else "unity_pf"
        self.fleet = fleet  # the plants behind SunSpec (``sunspec_fleet``), if any
        self.dnp3 = dnp3  # the regulators and banks behind DNP3 (``dnp3_fleet``), if any
        external = frozenset(self.fleet.plant_ids) if self.fleet is not None else frozenset()
        external_vr = frozenset(dnp3.regulator_ids) if dnp3 is not None else frozenset()
        external_cap = frozenset(dnp3.capacitor_ids) if dnp3 is not None else frozenset()
        behind: dict[tuple[str, str], Protocol] = {("pv", p): "sunspec" for p in external}
        dnp3_behind: dict[tuple[str, str], Protocol] = {("vr", r): "dnp3" for r in external_vr}
        behind |= dnp3_behind | {("cap", k): "dnp3" for k in external_cap}
        self.frames = AdapterFrames(behind) if behind else None  # the adapters' frames each step waits for
        # secure: only the command role's certificate can put commands, so replay protection is keyed on it
        self.bank = DeviceBank(session, self.fid, engine, qsts, local=local,
                               period_ns=int(dm.feeder.control_period_s) * _NS,  # the commands' time window unit
                               sender=COMMAND_ROLE if bus.tls_dir is not None else None, counters=self.counters,
                               external_pv=external, external_vr=external_vr, external_cap=external_cap)
        self.bank.now_t_ns = int(profiles.t_ns(start_step)) - self.step_s * _NS  # nothing simulated yet
        bank = self.bank
        self.reg_phase = list(regulator_phases(engine))
        self.spec = FramerSpec(
            feeder_id=self.fid, step_s=self.step_s, control_every=self.control_every,
            profile_start_t_ns=int(profiles.start_t_ns), run_start_t_ns=int(profiles.t_ns(start_step)),
            truth_every=c.truth_every, node_names=tuple(engine.node_names),
            pvs=tuple((pv.plant_id, pv.index, pv.s_rated_kva, pv.local_mode) for pv in bank.pvs.values()),
            regs=tuple((r.regulator_id, r.index, r.tap_max, r.default_setpoint_v120, r.default_band_v120)
                       for r in bank.regs.values()),
            reg_phase=tuple(self.reg_phase), q_at_night=tuple(qsts.pv_q_at_night.tolist()),
            noise_pmu_pct=c.noise_pmu_pct, noise_scada_pct=c.noise_scada_pct, drop_prob=c.drop_prob,
            latency_s=c.latency_s, noise_seed=c.noise_seed,
            metrics=MetricsAccumulator.for_feeder(dm, engine, step_s=self.step_s),
            drop_burst_s=60.0 * c.drop_burst_min, clock_skew_s=c.clock_skew_s,
            caps=tuple((k.capacitor_id, k.index, k.steps, k.kvar_rated, k.control_type) for k in bank.caps.values()),
            pv_external=tuple(sorted(external)), meters=_meters(dm, engine.node_names),
            vr_external=tuple(sorted(external_vr)), cap_external=tuple(sorted(external_cap)))
        self.steps = self.control_steps = self.misses = self.skipped = self.decisions = 0
        self.late_steps = 0
        self.round_trips: list[float] = []
        self.decision_wait_s = 0.0  # stepping thread's waits for decisions on control steps [s]
        self.logged_no_agent = False  # the lockstep said once that it steps without an agent
        self.decision: m.Decision | None = None  # the last decision received
        # the follow-up commands (cmd_id) the last decision announced for the step after its own; lockstep waits for
        # them once that step's frames are out
        self.follow_ups: tuple[int, tuple[str, ...]] = (0, ())
        self.follow_up_misses = 0
        # the agent's estimates judged against the truth of their step (control steps' voltages kept until then)
        self.live = LiveAccuracyAccumulator(engine.node_names, zone_phase_nodes(engine))
        self._control_truth: dict[int, np.ndarray] = {}
        self._ctrl_pub_wall_ns: dict[int, int] = {}  # inline: when a control step's head frame was put
        self.oracle: OracleServer | None = None
        try:
            for served in (self.fleet, self.dnp3):
                if served is not None:
                    served.start()  # before the adapters' first scan; stopped by close()
            self._declare()
            self.child: PublisherProcess | None = None
            self.framer: StepFramer | None = None
            child = publisher_bus(c, bus, len(engine.node_names))
            if child is None:
                self.framer = StepFramer(self.spec, session, self._on_control_head)
            else:
                packer = StepPacker(len(engine.node_names), len(bank.pvs), len(bank.regs),
                                    len(engine.capacitor_ids))
                self.child = PublisherProcess(self.spec, packer, child)
        except BaseException:
            for served in (self.fleet, self.dnp3):  # no close() follows a failed construction: they stop here
                if served is not None:
                    served.close()
            raise

    @property
    def now_t_ns(self) -> int:
        """The simulation time of the step just simulated [ns] (one step before the first before it)."""
        return self.bank.now_t_ns

    # ---------------------------------------------------------------- declarations
    def _declare(self) -> None:
        s, f = self.session, self.fid
        lv = s.liveliness()
        self.tokens = [lv.declare_token(keys.alive(f, "bridge", "bridge")),
                       lv.declare_token(keys.alive(f, "head", "head"))]
        self.tokens += self.bank.declare()
        self.pub_status = FramePublisher(s, keys.sim_status(f), reliable=True)
        self.inbox = Inbox(maxsize=4096)
        # other feeders too (see DeviceBank._wrong_feeder), unless own_commands_only (many feeders on one bus)
        self.inbox.subscribe(s, f"{keys.ROOT}/{f if self.config.own_commands_only else '*'}/cmd/**")
        self.inbox.subscribe(s, keys.agent_decision(f), m.Decision)
        self.agents = LivelinessWatcher(s, f"{keys.ROOT}/{f}/alive/agent/*", self._on_agent)
        self.adapter_tokens: list[LivelinessWatcher] = []
        frames: dict[str, tuple[str, type[msgspec.Struct]]] = {
            "pv": (keys.meas_pv(f), m.PvFrame), "vr": (keys.meas_vr(f), m.RegFrame),
            "cap": (keys.meas_cap(f), m.CapFrame)}
        for kind, (key, frame_type) in frames.items():  # the adapters' frames (the step's wait), acks (lockstep)
            if self.frames is not None and any(self.frames.devices(kind)):
                self.inbox.subscribe(s, key, frame_type)
                self.inbox.subscribe(s, keys.ack(f, kind), m.Ack)  # type: ignore[arg-type]
                self.adapter_tokens.append(LivelinessWatcher(s, f"{keys.ROOT}/{f}/alive/{kind}/*"))
        if self.config.oracle:  # compiles its twin engine now, not at the first query
            self.oracle = OracleServer(s, f, self.engine, self.qsts, self.inbox, self.counters)

    def close(self) -> None:
        """Withdraw every token and declaration (the session is closed by the caller's ``with``); oracle
        queries still queued are answered with an error, so their getters do not wait for their timeout.
        """
        if self.child is not None:
            self.child.close(None)  # nothing more when the run closed it already
        for served in (self.fleet, self.dnp3):
            if served is not None:
                served.close()
        declared = [self.oracle.undeclare] if self.oracle is not None else []
        declared += [w.undeclare for w in self.adapter_tokens]
        for undeclare in [*declared, self.inbox.undeclare, self.agents.undeclare,
                          self.bank.bridges.undeclare, *(t.undeclare for t in self.tokens)]:
            try:
                undeclare()
            except Exception as e:  # zenoh raises plain exceptions; shutdown goes on regardless
                log.warning("undeclare failed during shutdown: %s", e)
        for item in self.inbox.drain():
            if isinstance(item.msg, OracleQuery):
                OracleServer.refuse_at_shutdown(item.msg)
        if self.oracle is not None:
            self.oracle.close()

    # ---------------------------------------------------------------- callbacks (Zenoh threads)
    def _on_agent(self, key: str, up: bool) -> None:
        if up:
            log.info("agent liveliness token up: %s", key)
        else:
            self.counters.rlog.warning("agent_lost", "agent liveliness lost: %s", key)
            # in order with its commands: a restarted agent's sequence starts again at 1 (see _forget_sender)
            try:
                self.inbox.queue.put_nowait(Received(key, _SenderGone(key.rsplit("/", 1)[-1]), time.time_ns(), b""))
            except queue.Full:
                self.counters.rlog.warning("queue_full",
                                           "queue full: the devices keep the lost agent's command sequence")

    # ---------------------------------------------------------------- serving the queue
    @property
    def agent_alive(self) -> bool:
        """Whether an agent's liveliness token of this feeder is alive."""
        return bool(self.agents.alive())

    def serve(self, deadline_s: float, stop: threading.Event, done: Callable[[], bool] | None = None) -> bool:
        """Handle queued items and due frames until ``done()`` is true (returns True) or ``deadline_s``
        of ``time.monotonic()`` passes or ``stop`` is set (returns False). What is already queued is
        always handled, even with a deadline in the past.
        """
        while True:
            now = time.monotonic()
            self.flush(now)
            for _ in range(_DRAIN_MAX):
                try:
                    item = self.inbox.queue.get_nowait()
                except queue.Empty:
                    break
                self._handle(item)
            if done is not None and done():
                return True
            if now >= deadline_s or stop.is_set():
                return False
            wait = min(deadline_s - now, _POLL_S)
            nxt = self.framer.delay.next_due_s() if self.framer is not None else None
            if nxt is not None:
                wait = min(wait, max(nxt - now, 0.0))
            waited = self.inbox.get(timeout_s=max(wait, 0.0))
            if waited is not None:
                self._handle(waited)

    def _handle(self, item: Received) -> None:
        msg = item.msg
        if isinstance(msg, OracleQuery):
            if self.oracle is not None:  # queries are only taken with an oracle
                self.oracle.answer(msg, self.now_t_ns)
        elif isinstance(msg, _SenderGone):
            self.bank.forget_source(msg.source)
        elif isinstance(msg, m.Decision):
            self._on_decision(msg, item.recv_wall_ns)
        elif isinstance(msg, m.PvCommand | m.RegCommand | m.CapCommand):
            self.bank.on_command(item.key, msg)
        elif isinstance(msg, m.PvFrame | m.RegFrame | m.CapFrame) and self.frames is not None:
            kind, device = _frame_device(msg)
            self.frames.on_frame(kind, device, msg.t_ns)
        elif isinstance(msg, m.Ack) and self.frames is not None:
            parts = keys.parse_device_key(item.key)
            if parts is not None and (parts[2], parts[3]) in self.frames.protocol:
                self.bank.remember(msg.cmd_id)  # the adapter handled it: the lockstep's decision may be complete

    def _on_decision(self, d: m.Decision, recv_wall_ns: int) -> None:
        if d.feeder_id != self.fid:
            self.counters.rejected["decision_wrong_feeder"] += 1
            return
        self.decisions += 1
        pub = (self._ctrl_pub_wall_ns.pop(d.step_t_ns, None) if self.child is None
               else self.child.control_head_wall_ns(d.step_t_ns))
        if pub is not None:
            self.round_trips.append((recv_wall_ns - pub) / _NS)
        self.decision = d
        self.follow_ups = (d.step_t_ns, tuple(d.follow_ups))
        truth = self._control_truth.pop(d.step_t_ns, None)
        if truth is not None and d.estimates:
            est = d.estimates
            self.live.add([e.node for e in est], np.array([e.v_pu for e in est]),
                          np.array([e.bound_low_pu for e in est]), np.array([e.bound_high_pu for e in est]), truth)

    def follow_ups_due(self, t_ns: int) -> tuple[str, ...]:
        """The follow-ups to wait for after step ``t_ns`` (the first step after their decision's), and forget them."""
        after, ids = self.follow_ups
        if not ids or t_ns <= after:
            return ()
        self.follow_ups = (0, ())
        return ids

    def decided(self, t_ns: int) -> bool:
        """Whether the decision of step ``t_ns`` arrived and every command it lists was handled."""
        d = self.decision
        return d is not None and d.step_t_ns == t_ns and all(self.bank.handled(c.cmd_id) for c in d.commands)

    # ---------------------------------------------------------------- frames and status
    def _on_control_head(self, t_ns: int, wall_ns: int) -> None:
        """Inline publishing: a control step's head frame is about to be put (the round trip starts)."""
        self._ctrl_pub_wall_ns[t_ns] = wall_ns
        while len(self._ctrl_pub_wall_ns) > 64:  # decisions that never came
            self._ctrl_pub_wall_ns.pop(next(iter(self._ctrl_pub_wall_ns)))

    def status(self, *, done: bool) -> m.BridgeStatus:
        """The bridge's status message now (its ``seq`` is the next)."""
        self.counters.seqs["status"] += 1
        # before the first step (now_t_ns one step before it) the status is stamped at the first simulated instant,
        # so that a recording of the session starts there, not a step earlier
        t_ns = max(self.now_t_ns, self.spec.run_start_t_ns)
        return m.BridgeStatus(t_ns=t_ns, seq=self.counters.seqs["status"], source="bridge",
                              feeder_id=self.fid, step=self.steps, steps_total=self.config.steps,
                              clock=self.config.clock, lockstep_misses=self.misses, agent_alive=self.agent_alive,
                              rejected=self.all_rejected(), done=done, log_suppressed=self.log_suppressed())

    def log_suppressed(self) -> dict[str, int]:
        """Log lines not written by the rate limits, by kind (``rejected_<kind>``: the bus's rejections)."""
        return dict(self.counters.rlog.suppressed) | {
            f"rejected_{k}": n for k, n in self.inbox.rejects.log_suppressed().items()}

    def all_rejected(self) -> dict[str, int]:
        """Rejected commands and queries by reason, and payloads that did not decode (``decode_<kind>``)."""
        out = dict(self.counters.rejected)
        for kind, n in self.inbox.rejects.by_kind().items():
            out[f"decode_{kind}"] = out.get(f"decode_{kind}", 0) + n
        return out

    # ---------------------------------------------------------------- one step
    def step(self) -> StepResult:
        """Watchdogs, one QSTS step, then its frames, metrics update and truth (inline, or handed to the publisher
        process with a metrics frame after it on a control step); returns the StepResult.
        """
        t_next = int(self.profiles.t_ns(self.qsts.next_step))
        self.bank.run_watchdogs(t_next)
        if self.fleet is not None:  # the inverters' local modes (705) and set points (704, timers on the step's time)
            for k, volt_var in self.fleet.local_modes().items():
                self.qsts.set_pv_local(k, volt_var)
            for k, q_kvar in self.fleet.commands(t_next).items():
                self.qsts.command_pv_q(k, q_kvar)
        if self.dnp3 is not None:  # what the outstations hold in force (hold timers on the step's time), if changed
            reg_changes, cap_changes = self.dnp3.commands(t_next)
            for r, held in reg_changes.items():
                self.qsts.command_setpoint(r, *(held or (None, None)))
            for c, closed_steps in cap_changes.items():
                self.qsts.command_cap(c, closed_steps)
        res = self.qsts.step()
        self.bank.now_t_ns = int(res.t_ns)
        if self.is_control_step(res.step):  # the truth the decision of this step is judged against
            self._control_truth[int(res.t_ns)] = np.array(res.v_pu, dtype=float)
            while len(self._control_truth) > _TRUTH_KEPT:
                self._control_truth.pop(next(iter(self._control_truth)))
        self.bank.pv_p_kw = res.pv_p_kw
        self.steps += 1
        if self.frames is not None:  # before the head frame is put: the adapters scan when it arrives
            check_finite_step(res)
            rd = res.readings
            if self.fleet is not None:
                self.fleet.measure(int(res.t_ns), rd.pv_p_kw, rd.pv_q_kvar, rd.pv_v_v)
            if self.dnp3 is not None:
                self.dnp3.measure(int(res.t_ns), v_compared_120=rd.reg_v120_compared, v_120=rd.reg_v120,
                                  taps=res.taps, cap_states=rd.cap_states, cap_v_v=rd.cap_v_v,
                                  cap_control_value=rd.cap_control_value)
        if self.child is not None:
            if not self.child.submit(res, self.steps, self.bank.settings(),
                                     metrics_after=self.is_control_step(res.step)):
                raise non_finite(res)
        elif self.framer is not None:
            v_lo, v_hi = check_finite_step(res)
            self.framer.publish_step(res, self.steps, v_lo, v_hi, self.bank.settings(), time.monotonic())
        return res

    def adapters_alive(self) -> bool:
        """Whether every field-protocol adapter's liveliness token (``alive/<kind>/<id>``) is up and every DNP3
        outstation has its master connected (True without any).
        """
        if self.frames is None:
            return True
        if self.dnp3 is not None and not self.dnp3.masters_connected():
            return False
        alive = set().union(*(w.alive() for w in self.adapter_tokens))
        return all(keys.alive(self.fid, kind, d) in alive for kind, d in self.frames.protocol)  # type: ignore[arg-type]

    def await_adapter_frames(self, t_ns: int, stop: threading.Event) -> None:
        """Serve the queue until every field-protocol adapter's frame of the step at ``t_ns`` [ns] arrived, at most
        ``timeout_s``; a step whose frames did not all come is counted (``AdapterFrames.misses``, by protocol), and
        the devices that missed it are not waited for again until their next frame (``AdapterFrames.missed``).
        """
        frames = self.frames
        if frames is None or self.serve(time.monotonic() + self.config.timeout_s, stop,
                                        lambda: frames.frames_in(t_ns)) or stop.is_set():
            return
        late = frames.missed(t_ns)
        self.counters.rlog.warning("adapter_frame_miss", "no frame of %s at t_ns=%d within %.3f s (%s steps so far); "
                                   "not waiting for them until their next frame", late, t_ns, self.config.timeout_s,
                                   dict(frames.misses))

    def flush(self, now_s: float) -> None:
        """Frames held by the latency line (inline publishing only) that are due go out."""
        if self.framer is not None and len(self.framer.delay):
            self.framer.flush(now_s)

    def held(self) -> int:
        """Frames the latency line still holds."""
        return len(self.framer.delay) if self.framer is not None else 0

    def is_control_step(self, step_index: int) -> bool:
        """Whether profile step ``step_index`` is a control step."""
        return step_index % self.control_every == 0


def _frame_device(frame: m.PvFrame | m.RegFrame | m.CapFrame) -> tuple[str, str]:
    """A device frame's ``(kind, device id)``."""
    match frame:
        case m.PvFrame(plant_id=d):
            return "pv", d
        case m.RegFrame(regulator_id=d):
            return "vr", d
        case m.CapFrame(capacitor_id=d):
            return "cap", d
    raise TypeError(f"not a device frame: {type(frame).__name__}")


def _meters(dm: DeviceMap, node_names: list[str] | tuple[str, ...]) -> tuple[tuple[str, int, int], ...]:
    """The device map's AMI meters as ``(meter_id, node index, interval_s)``; a node the circuit lacks is an error."""
    index = {n.lower(): i for i, n in enumerate(node_names)}
    out = []
    for meter in dm.meter:
        i = index.get(meter.node.lower())
        if i is None:
            raise BridgeError(f"meter {meter.id}: node {meter.node!r} is not a node of the circuit (bus.phase)")
        out.append((meter.id, i, meter.interval_s))
    return tuple(out)
