"""The simulator bridge: the QSTS feeder seen through Zenoh as a utility sees its field devices.

The only simulator module that knows Zenoh and clocks. Device logic (checks, watchdogs, acks, frames,
noise) is in ``devices.py``; physics in ``qsts.py`` / ``engine.py``. ``docs/bridge.md`` is the user's
guide; in short:

* Every device is its own entity with its own keys and liveliness token: the feeder-head meter
  (``meas/head``, token ``alive/head/head``), each PV inverter (``meas/pv/<id>``, ``cmd/pv/<id>``,
  ``ack/pv/<id>``, token ``alive/pv/<id>``), each regulator controller (``.../vr/<id>``), each capacitor bank
  of the device map (``.../cap/<id>``), and the bridge
  itself (``alive/bridge/bridge``; ``sim/truth``, ``sim/metrics``, ``sim/status``, queryable ``sim/oracle``).
* One stepping thread (the caller of :func:`run_bridge`) does everything that touches the simulation.
  Zenoh callbacks only decode and enqueue (``schemas.bus.Inbox``); oracle queries are enqueued on the
  same queue and answered by the stepping thread between steps, so a power flow never runs in a Zenoh
  thread and never concurrently with a step.
* **Lockstep**: on a control step, after the step's frames are out, the bridge serves its queue until
  the agent's :class:`Decision` for that step has arrived *and* every command it lists (by ``cmd_id``)
  has been handled by its device, or until ``timeout_s`` of wall time (a *miss*: counted, logged,
  published in ``BridgeStatus``; the run goes on with what the devices have). With no agent liveliness
  token alive, the bridge does not wait (counted as ``lockstep_skipped``).
* **Real time**: step ``i`` is simulated at ``t0 + i · step_s / speed`` of wall time; the bridge never
  waits for anyone, it serves commands and oracle queries while it waits for the next tick.
* **Publishing** (``simulator_bridge.publishing``): a step's device frames, metrics update and truth frame,
  and the metrics frames, come from a ``StepFramer``: called inline by the stepping thread, or, by default
  on feeders of 200 nodes or more, in a publisher process with its own Zenoh session, fed through shared
  memory with each step's results and the device settings in force, so its Python work runs beside the next
  power flow instead of under this process's GIL. The messages are the same either way.
"""

from __future__ import annotations

import datetime as dt
import logging
import math
import queue
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import msgspec
import numpy as np
import zenoh

from schemas import keys
from schemas import messages as m
from schemas.bus import (
    BusConfig,
    Inbox,
    LivelinessWatcher,
    Received,
    TypedPublisher,
    codec_for,
    open_session,
    wait_for,
)
from schemas.devicemap import DeviceMap, load_device_map
from schemas.errors import CvvcError
from schemas.logs import RateLimitedLog
from schemas.security import COMMAND_ROLE
from simulator_bridge import devices as dv
from simulator_bridge.errors import SimulatorError
from simulator_bridge.publisher_process import PublisherProcess, StepPacker, child_bus
from simulator_bridge.publishing import (
    FINITE_READING_FIELDS,
    DeviceSettings,
    FramePublisher,
    FramerSpec,
    StepFramer,
)

__all__ = [
    "BridgeConfig",
    "BridgeError",
    "BridgeSummary",
    "cached_profiles",
    "run_bridge",
    "start_step_of",
]

log = logging.getLogger(__name__)

_NS = 1_000_000_000
_LOCAL_TZ = dt.timezone(dt.timedelta(hours=-5))  # the profiles' fixed local standard time (UTC-5)
_POLL_S = 0.05  # longest a wait goes without checking the stop event [s]
_HANDLED_MEMORY = 10_000  # cmd_ids remembered for matching decisions
_STARTUP_PROBE_S = 1.0  # bounded look for an agent already alive, and for its subscription, at startup [s]
_DRAIN_MAX = 1000  # queued items handled in one go before the clock and the stop event are looked at again
# publisher="auto" uses the publisher process from this many nodes on: measured faster than inline on IEEE 123 (278
# nodes), the rural feeder (1283) and IEEE 8500 (8531); no faster on IEEE 13 (41), where a child process would only
# add its start, about a second (docs/bridge.md, Speed)
_PROCESS_MIN_NODES = 200


class BridgeError(SimulatorError):
    """The bridge cannot run as configured (bad dates, step counts, speeds, feeders)."""


ORACLE_REPLIES_PER_STEP = 2
"""Case-A oracle replies the bridge gives per simulated step (the agent asks once per control step; one retry)."""


class BridgeConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Everything a bridge run needs (built by the ``cvvc bridge`` handler, or by tests and launchers).

    Attributes
    ----------
    device_map_path : the feeder's device map TOML.
    feeder_id : id in the key space (default: the map's ``feeder.name``).
    start : first simulated instant, ``YYYY-MM-DD`` or ``YYYY-MM-DDTHH:MM`` local standard time (UTC-5),
        within the profile year. steps : number of steps to simulate.
    clock : ``lockstep`` or ``realtime``. timeout_s : lockstep wall-clock wait per control step [s].
    speed : real-time speed factor (simulated seconds per wall second).
    wait_agent_s : before the first step, wait up to this long for an agent liveliness token [s].
    year_seed : profile seed. pv_local : PV local default (``unity`` or ``volt_var``).
    truth_every : publish a TruthFrame every N steps (0: never).
    noise_pmu_pct, noise_scada_pct : measurement noise per class [%]; drop_prob : frame drop probability;
    latency_s : fixed frame latency [s of wall time]; noise_seed : seed of noise and drops.
    cache_dir : where profiles are cached as ``.npz`` (None: no cache).
    publisher : who builds, encodes and puts a step's frames, metrics update, truth and metrics frames:
        ``inline`` the stepping thread; ``process`` a publisher process with its own Zenoh session, while the
        stepping thread solves the next step (not with ``latency_s``; the bus must have connect or listen
        endpoints and no config file); ``auto`` (default) the process on feeders of 200 nodes or more when it
        can, inline otherwise. The messages are the same.
    oracle : serve the case-A oracle (``sim/oracle``: every node's true voltage and perturbation sensitivities).
        Off by default: it exists only when case A asks for it (``cvvc run --case A`` sets it), and then answers
        at most ``ORACLE_REPLIES_PER_STEP`` queries per simulated step; the rest are refused and counted
        (``oracle_rate``): each reply costs the stepping thread K + R + 2 power flows.
    """

    device_map_path: str
    feeder_id: str | None = None
    start: str = "2023-07-01"
    steps: int = 1440
    clock: Literal["lockstep", "realtime"] = "lockstep"
    timeout_s: float = 5.0
    speed: float = 1.0
    wait_agent_s: float = 0.0
    year_seed: int = 1
    pv_local: Literal["unity", "volt_var"] = "unity"
    truth_every: int = 1
    noise_pmu_pct: float = 0.0
    noise_scada_pct: float = 0.0
    drop_prob: float = 0.0
    latency_s: float = 0.0
    noise_seed: int = 0
    cache_dir: str | None = None  # year-profile cache folder; None: no cache (the CLI passes its --cache's)
    publisher: Literal["auto", "inline", "process"] = "auto"
    oracle: bool = False


class BridgeSummary(msgspec.Struct, frozen=True, kw_only=True):
    """What a bridge run did (printed as JSON by ``cvvc bridge --json``).

    Times in seconds: ``wall_s`` of the stepping loop; ``cpu_s`` CPU time of every thread of the process
    during the loop, Zenoh's included; ``thread_cpu_s`` of the stepping thread alone; ``publisher_cpu_s`` of the
    publisher process from its first step on (0 when the frames are published inline); ``decision_wait_s`` the
    stepping thread's wall time waiting for the agent's decisions (lockstep). ``publisher``: who published the
    frames (``BridgeConfig.publisher`` resolved).
    ``round_trip_*_s`` is from the publication of a control step's head frame to the reception of the agent's
    decision for it; ``rejected`` counts rejected commands per reason (device reasons, and ``decode_<kind>``
    for payloads that did not decode).
    """

    feeder_id: str
    clock: str
    start_t_ns: int
    end_t_ns: int
    steps: int
    steps_total: int
    control_steps: int
    wall_s: float
    steps_per_s: float
    cpu_s: float
    thread_cpu_s: float
    lockstep_misses: int
    lockstep_skipped: int
    decisions: int
    acks: dict[str, int]
    rejected: dict[str, int]
    frames_published: int
    frames_dropped: int
    truth_frames: int
    oracle_replies: int
    oracle_rejected: int
    realtime_late_steps: int
    round_trip_p50_s: float | None
    round_trip_p99_s: float | None
    agent_alive: bool
    stopped_early: bool
    metrics: m.MetricsFrame | None
    publisher_cpu_s: float = 0.0
    decision_wait_s: float = 0.0
    publisher: Literal["inline", "process"] = "inline"
    log_suppressed: dict[str, int] = {}  # log lines not written by the rate limit, by kind (rejected_<kind>: bus)


# ------------------------------------------------------------------------------------------ helpers
def start_step_of(start: str, profile_start_t_ns: int, n_steps: int, step_s: int) -> int:
    """Profile step of a ``YYYY-MM-DD[THH:MM]`` local standard time (UTC-5) within the profile year."""
    try:
        when = dt.datetime.fromisoformat(start)
    except ValueError as e:
        raise BridgeError(f"--start {start!r}: use YYYY-MM-DD or YYYY-MM-DDTHH:MM (local standard time)") from e
    if when.tzinfo is None:
        when = when.replace(tzinfo=_LOCAL_TZ)
    t_ns = int(when.timestamp()) * _NS
    step = (t_ns - profile_start_t_ns) // (step_s * _NS)
    if not 0 <= step < n_steps:
        year = dt.datetime.fromtimestamp(profile_start_t_ns // _NS, tz=_LOCAL_TZ).year
        raise BridgeError(f"--start {start!r} is outside the profile year {year}; pick a date in {year}")
    return int(step)


def cached_profiles(device_map: DeviceMap, engine: Any, *, seed: int, cache_dir: str | Path | None) -> Any:
    """The feeder's year profiles for ``seed`` (see ``simulator_bridge.profiles.feeder_profiles``)."""
    from simulator_bridge.profiles import feeder_profiles

    return feeder_profiles(device_map, engine, seed=seed, cache_dir=cache_dir)


def _check_config(c: BridgeConfig) -> None:
    if c.steps < 1:
        raise BridgeError(f"steps must be >= 1, got {c.steps}")
    if not (math.isfinite(c.timeout_s) and 0.0 < c.timeout_s <= 3600.0):
        raise BridgeError(f"--timeout-s must be within (0, 3600] s, got {c.timeout_s}")
    if not (math.isfinite(c.speed) and 0.0 < c.speed <= 1e6):
        raise BridgeError(f"--speed must be within (0, 1e6], got {c.speed}")
    if c.truth_every < 0:
        raise BridgeError(f"--truth-every must be >= 0 (0: no truth frames), got {c.truth_every}")
    if not (math.isfinite(c.wait_agent_s) and 0.0 <= c.wait_agent_s <= 3600.0):
        raise BridgeError(f"--wait-agent-s must be within 0..3600 s, got {c.wait_agent_s}")
    if c.publisher == "process" and c.latency_s > 0.0:
        raise BridgeError("publisher='process' cannot hold frames for --latency-s (the stepping thread flushes "
                          "the delay line); use publisher='auto' or 'inline' with latency")


def _check_finite_step(res: Any) -> tuple[float, float]:
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
        raise _non_finite(res)
    return v_lo, v_hi


def _non_finite(res: Any) -> BridgeError:
    return BridgeError(f"step at t_ns={res.t_ns}: the power flow produced non-finite values; the feeder or its "
                       "profiles are broken (check `cvvc feeder info`)")


def _publisher_bus(c: BridgeConfig, bus: BusConfig, n_nodes: int) -> BusConfig | None:
    """The publisher process's bus, or None to publish inline (``BridgeConfig.publisher``)."""
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


@dataclass(frozen=True)
class _OracleQuery:
    query: zenoh.Query
    request: m.OracleRequest


def _ack_kind(kind: str) -> keys.DeviceKind:
    """The ack key kind of a command key's kind (``vr`` for kinds this bridge does not know)."""
    return "pv" if kind == "pv" else "cap" if kind == "cap" else "vr"


def _percentile(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


# ------------------------------------------------------------------------------------------ runtime
class _Runtime:
    """The bridge's state between steps. Used only by the stepping thread (callbacks only enqueue)."""

    def __init__(self, config: BridgeConfig, bus: BusConfig, session: zenoh.Session, dm: DeviceMap, engine: Any,
                 profiles: Any, qsts: Any, start_step: int) -> None:
        from simulator_bridge.metrics_stream import MetricsAccumulator
        from simulator_bridge.oracle import Oracle

        c = self.config = config
        self.session, self.dm, self.engine, self.profiles, self.qsts = session, dm, engine, profiles, qsts
        self.oracle = Oracle(engine) if c.oracle else None  # compiles its twin engine now, not at the first query
        self.fid = c.feeder_id or dm.feeder.name
        self.step_s = int(profiles.step_s)
        self.control_every = max(1, dm.feeder.control_period_s // self.step_s)
        self.start_step = start_step
        self.now_t_ns = int(profiles.t_ns(start_step)) - self.step_s * _NS  # nothing simulated yet
        self.pv_p_kw = engine.pv_setpoints()[0]
        local: Literal["unity_pf", "volt_var"] = "volt_var" if c.pv_local == "volt_var" else "unity_pf"
        period_ns = int(dm.feeder.control_period_s) * _NS  # the unit of the commands' time windows
        # secure: only the command role's certificate can put commands, so replay protection is keyed on it
        sender = COMMAND_ROLE if bus.tls_dir is not None else None
        self.pvs = {pid: dv.PvInverter(pid, k, float(engine.pv_kva[k]), local, period_ns=period_ns,
                                       sender_identity=sender)
                    for k, pid in enumerate(engine.pv_ids)}
        self.regs = {rid: dv.RegulatorController(rid, r, int(engine.reg_tap_max[r]),
                                                 float(engine.reg_default_setpoint_v120[r]),
                                                 float(engine.reg_default_band_v120[r]), period_ns=period_ns,
                                                 sender_identity=sender)
                     for r, rid in enumerate(engine.regulator_ids)}
        self.caps = {cid: dv.CapBankController(cid, c, int(engine.cap_steps[c]), float(engine.cap_kvar[c]),
                                               engine.cap_control_type[c], period_ns=period_ns,
                                               sender_identity=sender)
                     for c, cid in enumerate(engine.capacitor_ids)}
        self.reg_phase = ["abc"[int(engine.node_names[n].split(".")[1]) - 1] for n in engine.reg_secondary_node]
        self.spec = FramerSpec(
            feeder_id=self.fid, step_s=self.step_s, control_every=self.control_every,
            profile_start_t_ns=int(profiles.start_t_ns), run_start_t_ns=int(profiles.t_ns(start_step)),
            truth_every=c.truth_every, node_names=tuple(engine.node_names),
            pvs=tuple((pv.plant_id, pv.index, pv.s_rated_kva, pv.local_mode) for pv in self.pvs.values()),
            regs=tuple((r.regulator_id, r.index, r.tap_max, r.default_setpoint_v120, r.default_band_v120)
                       for r in self.regs.values()),
            reg_phase=tuple(self.reg_phase), q_at_night=bool(qsts.pv_q_at_night), noise_pmu_pct=c.noise_pmu_pct,
            noise_scada_pct=c.noise_scada_pct, drop_prob=c.drop_prob, latency_s=c.latency_s,
            noise_seed=c.noise_seed, metrics=MetricsAccumulator.for_feeder(dm, engine, step_s=self.step_s),
            caps=tuple((k.capacitor_id, k.index, k.steps, k.kvar_rated, k.control_type) for k in self.caps.values()))
        # counters
        self.rlog = RateLimitedLog(log)  # every line a peer can provoke (issue "Robust by default" (f))
        self.seqs: Counter[str] = Counter()  # acks, oracle, status
        self.acks: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        self.steps = self.control_steps = self.misses = self.skipped = self.decisions = 0
        self.oracle_replies = self.oracle_rejected = self.late_steps = 0
        self.round_trips: list[float] = []
        self.decision_wait_s = 0.0  # stepping thread's waits for decisions on control steps [s]
        self._ctrl_pub_wall_ns: dict[int, int] = {}  # inline: when a control step's head frame was put
        self._handled: set[str] = set()
        self._handled_order: deque[str] = deque()
        self._decision: m.Decision | None = None
        self._logged_no_agent = False
        self._settings: DeviceSettings | None = None  # the devices' settings, until the next change
        self._declare()
        self.child: PublisherProcess | None = None
        self.framer: StepFramer | None = None
        child = _publisher_bus(c, bus, len(engine.node_names))
        if child is None:
            self.framer = StepFramer(self.spec, session, self._on_control_head)
        else:
            packer = StepPacker(len(engine.node_names), len(self.pvs), len(self.regs), len(engine.capacitor_ids))
            self.child = PublisherProcess(self.spec, packer, child)

    # ---------------------------------------------------------------- declarations
    def _declare(self) -> None:
        s, f = self.session, self.fid
        lv = s.liveliness()
        self.tokens = [lv.declare_token(keys.alive(f, "bridge", "bridge")),
                       lv.declare_token(keys.alive(f, "head", "head"))]
        self.tokens += [lv.declare_token(keys.alive(f, "pv", p)) for p in self.pvs]
        self.tokens += [lv.declare_token(keys.alive(f, "vr", r)) for r in self.regs]
        self.tokens += [lv.declare_token(keys.alive(f, "cap", k)) for k in self.caps]
        self.ack_pv = {p: TypedPublisher(s, keys.ack(f, "pv", p), m.Ack, reliable=True) for p in self.pvs}
        self.ack_vr = {r: TypedPublisher(s, keys.ack(f, "vr", r), m.Ack, reliable=True) for r in self.regs}
        self.ack_cap = {k: TypedPublisher(s, keys.ack(f, "cap", k), m.Ack, reliable=True) for k in self.caps}
        self.pub_status = FramePublisher(s, keys.sim_status(f), reliable=True)
        self.inbox = Inbox(maxsize=4096)
        self.inbox.subscribe(s, f"{keys.ROOT}/*/cmd/**")  # other feeders too: see _wrong_feeder
        self.inbox.subscribe(s, keys.agent_decision(f), m.Decision)
        self.agents = LivelinessWatcher(s, f"{keys.ROOT}/{f}/alive/agent/*", self._on_agent)
        self.bridges = LivelinessWatcher(s, f"{keys.ROOT}/*/alive/bridge/*")
        self.queryable = (s.declare_queryable(keys.sim_oracle(f), self._on_query, complete=True)
                          if self.oracle is not None else None)
        self._oracle_step_t_ns, self._oracle_step_replies = -1, 0

    def close(self) -> None:
        """Withdraw every token and declaration (the session is closed by the caller's ``with``); oracle
        queries still queued are answered with an error, so their getters do not wait for their timeout.
        """
        if self.child is not None:
            self.child.close(None)  # nothing more when the run closed it already
        declared = [self.queryable] if self.queryable is not None else []
        for undeclare in [*(q.undeclare for q in declared), self.inbox.undeclare, self.agents.undeclare,
                          self.bridges.undeclare, *(t.undeclare for t in self.tokens)]:
            try:
                undeclare()
            except Exception as e:  # zenoh raises plain exceptions; shutdown goes on regardless
                log.warning("undeclare failed during shutdown: %s", e)
        for item in self.inbox.drain():
            if isinstance(item.msg, _OracleQuery):
                try:
                    item.msg.query.reply_err(b"bridge shutting down")
                    item.msg.query.drop()
                except Exception as e:  # the getter may be gone already
                    log.info("could not answer an oracle query at shutdown: %s", e)
        if self.oracle is not None:
            self.oracle.close()

    # ---------------------------------------------------------------- callbacks (Zenoh threads)
    def _on_agent(self, key: str, up: bool) -> None:
        if up:
            log.info("agent liveliness token up: %s", key)
        else:
            self.rlog.warning("agent_lost", "agent liveliness lost: %s", key)
            # in order with its commands: a restarted agent's sequence starts again at 1 (see _forget_sender)
            try:
                self.inbox.queue.put_nowait(Received(key, _SenderGone(key.rsplit("/", 1)[-1]), time.time_ns(), b""))
            except queue.Full:
                self.rlog.warning("queue_full", "queue full: the devices keep the lost agent's command sequence")

    def _on_query(self, query: zenoh.Query) -> None:
        """Decode the request and enqueue it for the stepping thread; never compute here."""
        try:
            raw = query.payload.to_bytes() if query.payload is not None else b""
            request = (codec_for(m.OracleRequest).decode(raw) if raw
                       else m.OracleRequest(t_ns=0))
        except CvvcError as e:
            self.inbox.rejects.reject(keys.sim_oracle(self.fid), "oracle_bad_request", str(e))
            query.reply_err(f"bad OracleRequest: {e}".encode())
            query.drop()
            return
        try:
            self.inbox.queue.put_nowait(Received(str(query.key_expr), _OracleQuery(query, request),
                                                 time.time_ns(), raw))
        except Exception:  # queue.Full
            self.inbox.rejects.reject(keys.sim_oracle(self.fid), "oracle_busy", "queue full")
            query.reply_err(b"bridge busy: oracle queue full; retry after the next step")
            query.drop()

    # ---------------------------------------------------------------- serving the queue
    @property
    def agent_alive(self) -> bool:
        return bool(self.agents.alive())

    def serve(self, deadline_s: float, stop: threading.Event, done: Any = None) -> bool:
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
            item = self.inbox.get(timeout_s=max(wait, 0.0))
            if item is not None:
                self._handle(item)

    def _handle(self, item: Received) -> None:
        msg = item.msg
        if isinstance(msg, _OracleQuery):
            self._answer_oracle(msg)
        elif isinstance(msg, _SenderGone):
            for device in [*self.pvs.values(), *self.regs.values(), *self.caps.values()]:
                device.guard.forget_source(msg.source)
        elif isinstance(msg, m.Decision):
            self._on_decision(msg, item.recv_wall_ns)
        elif isinstance(msg, m.PvCommand | m.RegCommand | m.CapCommand):
            self._on_command(item.key, msg)

    def _on_decision(self, d: m.Decision, recv_wall_ns: int) -> None:
        if d.feeder_id != self.fid:
            self.rejected["decision_wrong_feeder"] += 1
            return
        self.decisions += 1
        pub = (self._ctrl_pub_wall_ns.pop(d.step_t_ns, None) if self.child is None
               else self.child.control_head_wall_ns(d.step_t_ns))
        if pub is not None:
            self.round_trips.append((recv_wall_ns - pub) / _NS)
        self._decision = d

    def _remember(self, cmd_id: str) -> None:
        if cmd_id in self._handled:
            return
        self._handled.add(cmd_id)
        self._handled_order.append(cmd_id)
        if len(self._handled_order) > _HANDLED_MEMORY:
            self._handled.discard(self._handled_order.popleft())

    def _decided(self, t_ns: int) -> bool:
        d = self._decision
        return d is not None and d.step_t_ns == t_ns and all(c.cmd_id in self._handled for c in d.commands)

    # ---------------------------------------------------------------- commands
    def _ack(self, pub_or_key: TypedPublisher | str, device_id: str, source: str, cmd_id: str,
             verdict: dv.Verdict) -> None:
        self.seqs[f"ack:{source}"] += 1
        ack = dv.make_ack(device_id=device_id, source=source, cmd_id=cmd_id, verdict=verdict,
                          t_ns=max(self.now_t_ns, 0), seq=self.seqs[f"ack:{source}"])
        self.acks[verdict.status] += 1
        if verdict.status != "rejected":
            self._settings = None  # accepted, clipped or expired: a device's settings changed
        if verdict.status == "rejected":
            self.rejected[verdict.reason_kind] += 1
            self.rlog.info("command_rejected", "rejected command %s for %s: %s", cmd_id, device_id, verdict.reason)
        if isinstance(pub_or_key, TypedPublisher):
            pub_or_key.put(ack)
        else:
            self.session.put(pub_or_key, codec_for(m.Ack).encode(ack), encoding=zenoh.Encoding.APPLICATION_JSON,
                             congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.REAL_TIME)

    def _on_command(self, key: str, cmd: m.PvCommand | m.RegCommand | m.CapCommand) -> None:
        self._remember(cmd.cmd_id)
        parts = keys.parse_device_key(key)
        if parts is None:
            self.rejected["unknown_device"] += 1  # no device key to answer on
            return
        feeder, _, kind, device = parts
        if feeder != self.fid:
            self._wrong_feeder(feeder, kind, device, cmd)
            return
        ack_key = keys.ack(self.fid, _ack_kind(kind), device)
        if kind == "pv" and device in self.pvs and isinstance(cmd, m.PvCommand):
            self._pv_command(self.pvs[device], cmd)
        elif kind == "vr" and device in self.regs and isinstance(cmd, m.RegCommand):
            self._reg_command(self.regs[device], cmd)
        elif kind == "cap" and device in self.caps and isinstance(cmd, m.CapCommand):
            self._cap_command(self.caps[device], cmd)
        else:
            known = {"pv": self.pvs, "cap": self.caps}.get(kind, self.regs)
            self._ack(ack_key, device, "bridge", cmd.cmd_id, dv.reject(
                "unknown_device", f"feeder {self.fid!r} has no {kind} device {device!r}; devices: {sorted(known)}"))

    def _wrong_feeder(self, feeder: str, kind: str, device: str, cmd: m.Command) -> None:
        """A command addressed to another feeder: ignored when that feeder has a live bridge (it is its
        business), otherwise rejected and acked on that feeder's ack key, so the sender learns of it.
        """
        if any(k.startswith(f"{keys.ROOT}/{feeder}/alive/bridge/") for k in self.bridges.alive()):
            return
        try:
            ack_key = keys.ack(feeder, _ack_kind(kind), device)
        except CvvcError:
            self.rejected["wrong_feeder"] += 1
            return
        self._ack(ack_key, device, "bridge", cmd.cmd_id, dv.reject(
            "wrong_feeder", f"no bridge runs feeder {feeder!r}; this bridge runs {self.fid!r}"))

    def _pv_command(self, pv: dv.PvInverter, cmd: m.PvCommand) -> None:
        bad = pv.check(cmd, now_t_ns=self.now_t_ns)
        if bad is not None:
            self._ack(self.ack_pv[pv.plant_id], pv.plant_id, pv.plant_id, cmd.cmd_id, bad)
            return
        applied = self.qsts.command_pv_q(pv.index, cmd.q_kvar)
        p = float(self.pv_p_kw[pv.index])
        headroom = math.sqrt(max(pv.s_rated_kva**2 - p**2, 0.0)) if p > 0 or self.qsts.pv_q_at_night else 0.0
        pv.guard.apply(cmd, cmd.q_kvar)
        self._ack(self.ack_pv[pv.plant_id], pv.plant_id, pv.plant_id, cmd.cmd_id,
                  dv.pv_verdict(cmd.q_kvar, applied, headroom))

    def _reg_command(self, reg: dv.RegulatorController, cmd: m.RegCommand) -> None:
        bad = reg.check(cmd, now_t_ns=self.now_t_ns)
        if bad is not None:
            self._ack(self.ack_vr[reg.regulator_id], reg.regulator_id, reg.regulator_id, cmd.cmd_id, bad)
            return
        match cmd.action:
            case m.TapAction(tap=tap):
                self.qsts.command_tap(reg.index, tap)
                self.qsts.command_setpoint(reg.index, None, None)
            case m.SetpointAction(setpoint_v120=sp, band_v120=bw):
                self.qsts.command_tap(reg.index, None)
                self.qsts.command_setpoint(reg.index, sp, bw)
        self._ack(self.ack_vr[reg.regulator_id], reg.regulator_id, reg.regulator_id, cmd.cmd_id, reg.apply(cmd))

    def _cap_command(self, cap: dv.CapBankController, cmd: m.CapCommand) -> None:
        bad = cap.check(cmd, now_t_ns=self.now_t_ns)
        if bad is not None:
            self._ack(self.ack_cap[cap.capacitor_id], cap.capacitor_id, cap.capacitor_id, cmd.cmd_id, bad)
            return
        applied = self.qsts.command_cap(cap.index, cmd.closed_steps)
        self._ack(self.ack_cap[cap.capacitor_id], cap.capacitor_id, cap.capacitor_id, cmd.cmd_id,
                  cap.apply(cmd, None if cmd.closed_steps is None else applied))

    def run_watchdogs(self, t_ns: int) -> None:
        """Before simulating ``t_ns``: expire commands past their validity; devices go back to default."""
        for pv in self.pvs.values():
            gone = pv.guard.expire(t_ns)
            if gone is not None:
                self.qsts.command_pv_q(pv.index, None)
                self._ack(self.ack_pv[pv.plant_id], pv.plant_id, pv.plant_id, gone.cmd_id, dv.Verdict(
                    status="expired", reason=f"valid until {gone.valid_until_t_ns}; back to local "
                                             f"{pv.local_mode}"))
        for reg in self.regs.values():
            gone = reg.expire(t_ns)
            if gone is not None:
                self.qsts.command_tap(reg.index, None)
                self.qsts.command_setpoint(reg.index, None, None)
                self._ack(self.ack_vr[reg.regulator_id], reg.regulator_id, reg.regulator_id, gone.cmd_id,
                          dv.Verdict(status="expired", applied_value=reg.default_setpoint_v120,
                                     reason=f"valid until {gone.valid_until_t_ns}; back to local control at "
                                            f"{reg.default_setpoint_v120:.2f} V, band {reg.default_band_v120:.2f} V"))
        for cap in self.caps.values():
            gone = cap.expire(t_ns)
            if gone is not None:
                self.qsts.command_cap(cap.index, None)
                self._ack(self.ack_cap[cap.capacitor_id], cap.capacitor_id, cap.capacitor_id, gone.cmd_id,
                          dv.Verdict(status="expired", reason=f"valid until {gone.valid_until_t_ns}; back to local "
                                                              f"control ({cap.control_type})"))

    # ---------------------------------------------------------------- oracle
    def _answer_oracle(self, item: _OracleQuery) -> None:
        q = item.query
        if self._oracle_step_t_ns != self.now_t_ns:
            self._oracle_step_t_ns, self._oracle_step_replies = self.now_t_ns, 0
        if self._oracle_step_replies >= ORACLE_REPLIES_PER_STEP:
            self.rejected["oracle_rate"] += 1
            q.reply_err(f"rate limited: at most {ORACLE_REPLIES_PER_STEP} oracle replies per simulated step; "
                        "ask again after the next step".encode())
            q.drop()
            return
        self._oracle_step_replies += 1
        try:
            self.qsts.unstage_loads()  # the oracle's flows are of the present state
            assert self.oracle is not None  # queries are only taken with an oracle
            self.seqs["oracle"] += 1
            reply = self.oracle.reply(t_ns=self.now_t_ns, seq=self.seqs["oracle"], feeder_id=self.fid,
                                      include_sensitivities=item.request.include_sensitivities)
            q.reply(q.key_expr, codec_for(m.OracleReply).encode(reply), encoding=zenoh.Encoding.APPLICATION_JSON)
            self.oracle_replies += 1
        except CvvcError as e:
            self.oracle_rejected += 1
            self.rlog.warning("oracle_failed", "oracle query failed: %s", e)
            q.reply_err(f"oracle failed: {e}".encode())
        finally:
            q.drop()

    # ---------------------------------------------------------------- frames
    def _on_control_head(self, t_ns: int, wall_ns: int) -> None:
        """Inline publishing: a control step's head frame is about to be put (the round trip starts)."""
        self._ctrl_pub_wall_ns[t_ns] = wall_ns
        while len(self._ctrl_pub_wall_ns) > 64:  # decisions that never came
            self._ctrl_pub_wall_ns.pop(next(iter(self._ctrl_pub_wall_ns)))

    def settings(self) -> DeviceSettings:
        """The devices' command state now, as the frames of the step just simulated show it (kept until a
        command is applied or expires: every such change is acked, see :meth:`_ack`).
        """
        if self._settings is None:
            self._settings = self._read_settings()
        return self._settings

    def _read_settings(self) -> DeviceSettings:
        regs = self.regs.values()
        return DeviceSettings(pv_q_setpoint_kvar=tuple(pv.q_setpoint_kvar for pv in self.pvs.values()),
                              reg_setpoint_v120=tuple(r.setpoint_v120 for r in regs),
                              reg_band_v120=tuple(r.band_v120 for r in regs), reg_mode=tuple(r.mode for r in regs),
                              cap_command=tuple(None if k.guard.active is None else
                                                (k.guard.active.cmd_id, k.guard.active.valid_until_t_ns)
                                                for k in self.caps.values()))

    def status(self, *, done: bool) -> m.BridgeStatus:
        self.seqs["status"] += 1
        return m.BridgeStatus(t_ns=max(self.now_t_ns, 0), seq=self.seqs["status"], source="bridge",
                              feeder_id=self.fid, step=self.steps, steps_total=self.config.steps,
                              clock=self.config.clock, lockstep_misses=self.misses, agent_alive=self.agent_alive,
                              rejected=self.all_rejected(), done=done, log_suppressed=self.log_suppressed())

    def log_suppressed(self) -> dict[str, int]:
        """Log lines not written by the rate limits, by kind (``rejected_<kind>``: the bus's rejections)."""
        return dict(self.rlog.suppressed) | {f"rejected_{k}": n for k, n in self.inbox.rejects.log_suppressed().items()}

    def all_rejected(self) -> dict[str, int]:
        out = dict(self.rejected)
        for kind, n in self.inbox.rejects.by_kind().items():
            out[f"decode_{kind}"] = out.get(f"decode_{kind}", 0) + n
        return out

    # ---------------------------------------------------------------- one step
    def step(self) -> Any:
        """Watchdogs, one QSTS step, then its frames, metrics update and truth (inline, or handed to the publisher
        process with a metrics frame after it on a control step); returns the StepResult.
        """
        t_next = int(self.profiles.t_ns(self.qsts.next_step))
        self.run_watchdogs(t_next)
        res = self.qsts.step()
        self.now_t_ns = int(res.t_ns)
        self.pv_p_kw = res.pv_p_kw
        self.steps += 1
        if self.child is not None:
            if not self.child.submit(res, self.steps, self.settings(), metrics_after=self.is_control_step(res.step)):
                raise _non_finite(res)
        else:
            v_lo, v_hi = _check_finite_step(res)
            self.framer.publish_step(res, self.steps, v_lo, v_hi, self.settings(), time.monotonic())  # type: ignore[union-attr]
        return res

    def flush(self, now_s: float) -> None:
        """Frames held by the latency line (inline publishing only) that are due go out."""
        if self.framer is not None and len(self.framer.delay):
            self.framer.flush(now_s)

    def held(self) -> int:
        """Frames the latency line still holds."""
        return len(self.framer.delay) if self.framer is not None else 0

    def is_control_step(self, step_index: int) -> bool:
        return step_index % self.control_every == 0


# ------------------------------------------------------------------------------------------ the loop
def run_bridge(config: BridgeConfig, bus: BusConfig, *, stop: threading.Event | None = None,
               on_ready: Any = None) -> BridgeSummary:
    """Run the bridge until ``config.steps`` steps are simulated or ``stop`` is set; returns its summary.

    Parameters
    ----------
    config : what to simulate and how (see :class:`BridgeConfig`).
    bus : how to join the bus (``schemas.bus.BusConfig``).
    stop : set it (e.g. from a signal handler) to end the run cleanly after the present step.
    on_ready : called with no argument once every device is declared, before the first step (tests).

    Raises
    ------
    BridgeError, DeviceMapError, EngineError, BusError
        Bad configuration, a feeder that does not compile or solve, a bus that cannot be opened.
    """
    from simulator_bridge.engine import FeederEngine
    from simulator_bridge.qsts import Qsts

    _check_config(config)
    stop = stop or threading.Event()
    dm = load_device_map(config.device_map_path)
    engine = FeederEngine(dm)
    try:
        profiles = cached_profiles(dm, engine, seed=config.year_seed, cache_dir=config.cache_dir)
        start = start_step_of(config.start, profiles.start_t_ns, profiles.n_steps, profiles.step_s)
        if start + config.steps > profiles.n_steps:
            raise BridgeError(f"{config.steps} steps from {config.start} run past the end of the profile year "
                              f"({profiles.n_steps - start} steps left); start earlier or run fewer steps")
        qsts = Qsts(engine, profiles, start_step=start, pv_local=config.pv_local)
        with open_session(bus) as session:
            rt = _Runtime(config, bus, session, dm, engine, profiles, qsts, start)
            try:
                return _loop(rt, stop, on_ready)
            finally:
                rt.close()
    finally:
        engine.close()


def _loop(rt: _Runtime, stop: threading.Event, on_ready: Any) -> BridgeSummary:
    c = rt.config
    _startup(rt, stop)
    if on_ready is not None:
        on_ready()
    rt.pub_status.put(rt.status(done=False))
    t0, cpu0, thread0 = time.monotonic(), time.process_time(), time.thread_time()
    period_s = rt.step_s / c.speed
    for i in range(c.steps):
        if stop.is_set():
            break
        if c.clock == "realtime":
            due = t0 + i * period_s
            if time.monotonic() > due + period_s:
                rt.late_steps += 1
            rt.serve(due, stop)
            if stop.is_set():
                break
        elif rt.inbox.queue.qsize() or rt.held():
            rt.serve(0.0, stop)  # handle what is queued, without waiting
        res = rt.step()
        if rt.is_control_step(res.step):
            rt.control_steps += 1
            if c.clock == "lockstep":
                t_wait = time.monotonic()
                _await_decision(rt, int(res.t_ns), stop)
                rt.decision_wait_s += time.monotonic() - t_wait
            if rt.framer is not None:  # the publisher process publishes it after the step's frames
                rt.framer.publish_metrics(rt.now_t_ns, final=False)
            rt.pub_status.put(rt.status(done=False))
    if rt.child is not None:
        rt.child.drain()
    wall_s, cpu_s, thread_cpu_s = time.monotonic() - t0, time.process_time() - cpu0, time.thread_time() - thread0
    rt.serve(time.monotonic() + c.latency_s, stop if stop.is_set() else threading.Event(),
             lambda: rt.held() == 0)  # frames still in the delay line go out
    if rt.child is not None:
        r = rt.child.close(rt.now_t_ns)
        if r is None:
            raise BridgeError("the publisher process gave no report at the end of the run (see the log)")
        final, published, dropped, truth, pub_cpu_s = (r.final_metrics, r.frames_published, r.frames_dropped,
                                                       r.truth_frames, r.cpu_s)
    else:
        f = rt.framer
        assert f is not None
        final = f.publish_metrics(rt.now_t_ns, final=True)
        published, dropped, truth, pub_cpu_s = f.frames_published, f.frames_dropped, f.truth_frames, 0.0
    rt.pub_status.put(rt.status(done=True))
    return BridgeSummary(
        feeder_id=rt.fid, clock=c.clock, start_t_ns=int(rt.profiles.t_ns(rt.start_step)), end_t_ns=max(rt.now_t_ns, 0),
        steps=rt.steps, steps_total=c.steps, control_steps=rt.control_steps, wall_s=wall_s, cpu_s=cpu_s,
        thread_cpu_s=thread_cpu_s,
        steps_per_s=rt.steps / wall_s if wall_s > 0 else 0.0, lockstep_misses=rt.misses,
        lockstep_skipped=rt.skipped, decisions=rt.decisions, acks=dict(rt.acks), rejected=rt.all_rejected(),
        frames_published=published, frames_dropped=dropped, truth_frames=truth,
        oracle_replies=rt.oracle_replies, oracle_rejected=rt.oracle_rejected, realtime_late_steps=rt.late_steps,
        round_trip_p50_s=_percentile(rt.round_trips, 50), round_trip_p99_s=_percentile(rt.round_trips, 99),
        agent_alive=rt.agent_alive, stopped_early=rt.steps < c.steps, metrics=final,
        publisher_cpu_s=pub_cpu_s, decision_wait_s=rt.decision_wait_s,
        publisher="inline" if rt.child is None else "process",
        log_suppressed=rt.log_suppressed())


def _startup(rt: _Runtime, stop: threading.Event) -> None:
    """Before the first step: learn whether an agent is alive (waiting up to ``wait_agent_s`` for one), and
    if so let its subscription of the head frames reach this session (bounded), so step 0 is not lost.
    """
    c = rt.config
    deadline = time.monotonic() + c.wait_agent_s
    if c.wait_agent_s > 0:
        rt.serve(deadline, stop, lambda: rt.agent_alive)
    if not rt.agent_alive:  # the watcher's history may still be on its way: ask once, bounded
        key = f"{keys.ROOT}/{rt.fid}/alive/agent/*"
        if any(r.ok is not None for r in rt.session.liveliness().get(key, timeout=_STARTUP_PROBE_S)):
            wait_for(lambda: rt.agent_alive, _STARTUP_PROBE_S)
    if rt.agent_alive:
        timeout_s = max(deadline - time.monotonic(), _STARTUP_PROBE_S)
        if rt.child is not None:
            rt.child.wait_matched(timeout_s)
        else:
            rt.framer.pub_head.wait_matched(timeout_s)  # type: ignore[union-attr]


def _await_decision(rt: _Runtime, t_ns: int, stop: threading.Event) -> None:
    """Lockstep: wait (serving the queue) for the decision of step ``t_ns`` and its commands."""
    # frames held by the latency line must be out before the agent can answer them
    rt.serve(time.monotonic() + rt.config.latency_s + 1.0, stop, lambda: rt.held() == 0)
    if not rt.agent_alive:
        rt.skipped += 1
        if not rt._logged_no_agent:
            log.warning("lockstep: no agent liveliness token on %s/alive/agent/*; stepping without waiting "
                        "until one appears", rt.fid)
            rt._logged_no_agent = True
        return
    rt._logged_no_agent = False
    rt.qsts.stage_loads()  # the next step's loads do not depend on the decision: set them while it comes
    if not rt.serve(time.monotonic() + rt.config.timeout_s, stop, lambda: rt._decided(t_ns)):
        if stop.is_set():
            return
        rt.misses += 1
        d = rt._decision
        why = ("no decision" if d is None or d.step_t_ns != t_ns
               else "decision arrived but not all of its commands")
        rt.rlog.warning("lockstep_miss", "lockstep miss at t_ns=%d: %s within %.3f s; going on under local control "
                    "(%d misses so far)", t_ns, why, rt.config.timeout_s, rt.misses)
