"""The simulator bridge: the QSTS feeder seen through Zenoh as a utility sees its field devices.

The only simulator module that knows Zenoh and clocks. Device logic (checks, watchdogs, acks, frames,
noise) is in ``devices.py``; physics in ``qsts.py`` / ``engine.py``. ``docs/bridge.md`` is the user's
guide; in short:

* Every device is its own entity with its own keys and liveliness token: the feeder-head meter
  (``meas/head``, token ``alive/head/head``), each PV inverter (``meas/pv/<id>``, ``cmd/pv/<id>``,
  ``ack/pv/<id>``, token ``alive/pv/<id>``), each regulator controller (``.../vr/<id>``), and the bridge
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
* **Publisher thread** (``BridgeConfig.publisher``; by default on feeders of 1000 nodes or more, never with
  ``latency_s``): a step's device frames, streaming metrics and truth frame are built, encoded and put by
  one publisher thread, in step order, while the stepping thread solves the next step (OpenDSS releases
  the GIL while it solves). In lockstep a step is handed over when the next step's first power flow starts
  (``Qsts.before_solve``): handed over earlier, the publisher takes the GIL at the stepping thread's first
  short OpenDSS call and keeps it while the stepping thread waits (slower than inline publishing, measured
  without Zenoh). The stepping thread waits until every step
  so far is published (:meth:`_Runtime.drain`) before it changes a device's command state (the frames show
  it), on a control step before it waits for the decision and publishes metrics and status, and at the
  end; so every message is the one inline publishing sends, and lockstep is unchanged.
"""

from __future__ import annotations

import dataclasses
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
from simulator_bridge import devices as dv
from simulator_bridge.engine import FieldReadings

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
_PIPE_DEPTH = 4  # simulated steps handed to the publisher thread and not yet published, at most
_PIPE_WAIT_S = 60.0  # longest the stepping thread waits for the publisher thread to take or publish steps [s]
# publisher="auto" uses the publisher thread from this many nodes on: measured faster on the rural feeder (1283
# nodes) and IEEE 8500 (8531), slower on IEEE 123 (278), whose power flow is too short to hide the publishing
# (docs/bridge.md, Speed)
_PIPE_MIN_NODES = 1000


class BridgeError(CvvcError):
    """The bridge cannot run as configured (bad dates, step counts, speeds, feeders)."""


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
    publisher : who builds, encodes and puts a step's frames, metrics update and truth: ``inline`` the
        stepping thread; ``thread`` a publisher thread, while the stepping thread solves the next step (not
        with ``latency_s``); ``auto`` (default) the thread on feeders of 1000 nodes or more without latency,
        inline otherwise. The messages are the same.
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
    cache_dir: str | None = ".cvvc-cache"
    publisher: Literal["auto", "inline", "thread"] = "auto"


class BridgeSummary(msgspec.Struct, frozen=True, kw_only=True):
    """What a bridge run did (printed as JSON by ``cvvc bridge --json``).

    Times in seconds: ``wall_s`` of the stepping loop; ``cpu_s`` CPU time of every thread of the process
    during the loop, Zenoh's included; ``thread_cpu_s`` of the stepping thread alone;
    ``publisher_thread_cpu_s`` of the publisher thread (0 when the frames are published inline);
    ``drain_wait_s`` the stepping thread's wall time waiting, on control steps, for the publisher thread to
    finish the steps so far, and ``decision_wait_s`` waiting for the agent's decisions (lockstep).
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
    publisher_thread_cpu_s: float = 0.0
    drain_wait_s: float = 0.0
    decision_wait_s: float = 0.0


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
    if c.publisher == "thread" and c.latency_s > 0.0:
        raise BridgeError("publisher='thread' cannot hold frames for --latency-s (the stepping thread flushes the "
                          "delay line); use publisher='auto' or 'inline' with latency")


_READING_FIELDS = tuple(f.name for f in dataclasses.fields(FieldReadings))


class _FramePublisher:
    """Publisher of the bridge's own messages, whose numbers are already known to be finite.

    ``TypedPublisher`` walks every field of every message for NaN (about 60 µs a frame, more than a power
    flow of IEEE 13). Frames and truth here come from arrays that :func:`_check_finite_step` checked in one
    vectorised pass; metrics from the accumulator, which refuses non-finite inputs and clips what it reports;
    the status holds no float. Same Zenoh settings and JSON as ``TypedPublisher``.
    """

    def __init__(self, session: zenoh.Session, key: str, *, reliable: bool = False) -> None:
        self.key = key
        self._enc = msgspec.json.Encoder()
        self._pub = session.declare_publisher(
            key, encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.REAL_TIME if reliable else zenoh.Priority.DATA, express=reliable)

    def put(self, msg: msgspec.Struct) -> None:
        self._pub.put(self._enc.encode(msg))

    def wait_matched(self, timeout_s: float) -> bool:
        """Wait until a subscriber exists (a put right after a remote declaration is often lost)."""
        return wait_for(lambda: bool(self._pub.matching_status.matching), timeout_s)


def _check_finite_step(res: Any) -> tuple[float, float]:
    """Raise ``BridgeError`` if a step's readings or truth hold NaN or inf (a power flow gone wrong); return
    the lowest and highest node voltage [pu].

    The node voltages are finite exactly when their extremes are (NaN propagates through min and max); the
    few readings are checked in one vectorised pass. A few µs.
    """
    v_lo, v_hi = float(res.v_pu.min()), float(res.v_pu.max())
    rd = res.readings
    small = np.concatenate([getattr(rd, name) for name in _READING_FIELDS] + [res.pv_q_kvar, res.pv_p_kw],
                           axis=None, dtype=float)
    if not (math.isfinite(v_lo) and math.isfinite(v_hi) and np.isfinite(small).all()):
        raise BridgeError(f"step at t_ns={res.t_ns}: the power flow produced non-finite values; the "
                          "feeder or its profiles are broken (check `cvvc feeder info`)")
    return v_lo, v_hi


class _StepPublisher:
    """One thread that publishes simulated steps in order: ``publish(*item)`` for every :meth:`submit`-ted item.

    The stepping thread hands over a step (its ``StepResult``, whose arrays the engine never reuses) and goes
    on to simulate the next one; OpenDSS releases the GIL while it solves, so the frames of step ``t`` are
    encoded and put while step ``t+1`` is solved. At most ``_PIPE_DEPTH`` steps wait. :meth:`drain` returns
    once every submitted step is published. An exception in the thread is kept and raised as
    ``BridgeError`` in the stepping thread by the next :meth:`submit` or :meth:`drain`; the thread publishes
    nothing after it. Every wait is bounded (``_PIPE_WAIT_S``).
    """

    def __init__(self, publish: Any) -> None:
        self._publish = publish
        self._queue: queue.Queue[tuple[Any, ...] | None] = queue.Queue(maxsize=_PIPE_DEPTH)
        self._cond = threading.Condition()
        self._submitted = self._published = 0
        self._draining = False  # the stepping thread waits in drain(): wake it after each step
        self._error: Exception | None = None
        self._abort = threading.Event()
        self._thread = threading.Thread(target=self._run, name="cvvc-bridge-publisher", daemon=True)
        self._thread.start()
        ident = self._thread.ident
        self._clock = (time.pthread_getcpuclockid(ident)
                       if ident is not None and hasattr(time, "pthread_getcpuclockid") else None)

    def _run(self) -> None:
        try:
            while True:
                item = self._queue.get()
                if item is None or self._abort.is_set():
                    return
                self._publish(*item)
                self._published += 1  # only this thread writes it
                if self._draining:
                    with self._cond:
                        self._cond.notify_all()
        except Exception as e:  # kept for the stepping thread, which raises it (see _raise_if_failed)
            with self._cond:
                self._error = e
                self._cond.notify_all()

    def cpu_s(self) -> float:
        """CPU time of the publisher thread so far [s] (0 where the platform cannot tell)."""
        return time.clock_gettime(self._clock) if self._clock is not None and self._thread.is_alive() else 0.0

    def _raise_if_failed(self) -> None:
        if self._error is not None:
            raise BridgeError(f"the publisher thread failed after publishing {self._published} steps: "
                              f"{self._error!r}; the run stops (later frames were not published)") from self._error
        if not self._thread.is_alive():
            raise BridgeError("the publisher thread is gone; the run stops")

    def submit(self, item: tuple[Any, ...]) -> None:
        """Hand one step over (waits while ``_PIPE_DEPTH`` steps are pending, at most ``_PIPE_WAIT_S``)."""
        deadline = time.monotonic() + _PIPE_WAIT_S
        while True:
            self._raise_if_failed()
            try:
                self._queue.put(item, timeout=_POLL_S)
                break
            except queue.Full:
                if time.monotonic() > deadline:
                    raise BridgeError(f"the publisher thread took no step for {_PIPE_WAIT_S:.0f} s (a put that "
                                      "blocks?); the run stops") from None
        self._submitted += 1

    def drain(self) -> None:
        """Return once every submitted step is published (at most ``_PIPE_WAIT_S``)."""
        deadline = time.monotonic() + _PIPE_WAIT_S
        with self._cond:
            self._draining = True
            try:
                while self._published < self._submitted:
                    self._raise_if_failed()
                    left = deadline - time.monotonic()
                    if left <= 0:
                        raise BridgeError(f"the publisher thread published {self._published} of "
                                          f"{self._submitted} steps in {_PIPE_WAIT_S:.0f} s; the run stops")
                    self._cond.wait(min(left, _POLL_S))
            finally:
                self._draining = False
        self._raise_if_failed()

    def close(self) -> None:
        """Stop the thread: after what is queued when the queue was drained, at once otherwise (bounded)."""
        if self._published < self._submitted:
            self._abort.set()  # an error path: what is still queued is not published
        try:
            self._queue.put(None, timeout=1.0)
        except queue.Full:
            self._abort.set()
        self._thread.join(5.0)
        if self._thread.is_alive():
            log.warning("the publisher thread did not stop within 5 s (a blocked put?); left as a daemon")


@dataclass(frozen=True)
class _SenderGone:
    """An agent's liveliness token was withdrawn: its devices forget its command sequence (stepping thread)."""

    source: str


@dataclass(frozen=True)
class _OracleQuery:
    query: zenoh.Query
    request: m.OracleRequest


def _percentile(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


# ------------------------------------------------------------------------------------------ runtime
class _Runtime:
    """The bridge's state between steps. Used only by the stepping thread (callbacks only enqueue)."""

    def __init__(self, config: BridgeConfig, session: zenoh.Session, dm: DeviceMap, engine: Any,
                 profiles: Any, qsts: Any, start_step: int) -> None:
        from simulator_bridge.metrics import MetricsAccumulator

        c = self.config = config
        self.session, self.dm, self.engine, self.profiles, self.qsts = session, dm, engine, profiles, qsts
        self.fid = c.feeder_id or dm.feeder.name
        self.step_s = int(profiles.step_s)
        self.control_every = max(1, dm.feeder.control_period_s // self.step_s)
        self.start_step = start_step
        self.now_t_ns = int(profiles.t_ns(start_step)) - self.step_s * _NS  # nothing simulated yet
        self.pv_p_kw = engine.pv_setpoints()[0]
        local: Literal["unity_pf", "volt_var"] = "volt_var" if c.pv_local == "volt_var" else "unity_pf"
        self.pvs = {pid: dv.PvInverter(pid, k, float(engine.pv_kva[k]), local) for k, pid in enumerate(engine.pv_ids)}
        self.regs = {rid: dv.RegulatorController(rid, r, int(engine.reg_tap_max[r]),
                                                 float(engine.reg_default_setpoint_v120[r]),
                                                 float(engine.reg_default_band_v120[r]))
                     for r, rid in enumerate(engine.regulator_ids)}
        self._devices: list[dv.PvInverter | dv.RegulatorController] = [*self.pvs.values(), *self.regs.values()]
        self.reg_phase = ["abc"[int(engine.node_names[n].split(".")[1]) - 1] for n in engine.reg_secondary_node]
        self.noise = (dv.MeasurementNoise(pmu_pct=c.noise_pmu_pct, scada_pct=c.noise_scada_pct, seed=c.noise_seed)
                      if c.noise_pmu_pct > 0 or c.noise_scada_pct > 0 else None)
        self.dropper = dv.FrameDropper(p=c.drop_prob, seed=c.noise_seed)
        self.delay = dv.DelayLine(c.latency_s)
        self.metrics = MetricsAccumulator.for_feeder(dm, engine, step_s=self.step_s)
        self._truth_v = np.empty(len(engine.node_names))  # the clipped truth voltages, rewritten every step
        # counters
        self.seqs: Counter[str] = Counter()  # stepping thread: acks, oracle, metrics, status
        self.frame_seqs: Counter[str] = Counter()  # frames and truth (the publisher thread when there is one)
        self.acks: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        self.steps = self.control_steps = self.misses = self.skipped = self.decisions = 0
        self.frames_published = self.frames_dropped = self.truth_frames = 0
        self.oracle_replies = self.oracle_rejected = self.late_steps = 0
        self.round_trips: list[float] = []
        self.drain_wait_s = self.decision_wait_s = 0.0  # stepping thread's waits on control steps [s]
        self._ctrl_pub_wall_ns: dict[int, int] = {}  # written by the publisher, read by the stepping thread
        self._ctrl_lock = threading.Lock()
        self._handled: set[str] = set()
        self._handled_order: deque[str] = deque()
        self._decision: m.Decision | None = None
        self._logged_no_agent = False
        self._declare()
        # the delay line is flushed by the stepping thread (serve): with latency, frames are published inline
        threaded = c.latency_s == 0.0 and (c.publisher == "thread" or (
            c.publisher == "auto" and len(engine.node_names) >= _PIPE_MIN_NODES))
        self.publisher = _StepPublisher(self._publish_step) if threaded else None
        # lockstep: the last step waits here until the next step's first power flow starts (see the module
        # docstring); real time hands a step over at once, its frames being due now
        self._pending: tuple[Any, ...] | None = None
        self._defer = self.publisher is not None and c.clock == "lockstep"
        if self._defer:
            qsts.before_solve = self._hand_over

    # ---------------------------------------------------------------- declarations
    def _declare(self) -> None:
        s, f = self.session, self.fid
        lv = s.liveliness()
        self.tokens = [lv.declare_token(keys.alive(f, "bridge", "bridge")),
                       lv.declare_token(keys.alive(f, "head", "head"))]
        self.tokens += [lv.declare_token(keys.alive(f, "pv", p)) for p in self.pvs]
        self.tokens += [lv.declare_token(keys.alive(f, "vr", r)) for r in self.regs]
        self.pub_head = _FramePublisher(s, keys.meas_head(f))
        self.pub_pv = {p: _FramePublisher(s, keys.meas_pv(f, p)) for p in self.pvs}
        self.pub_vr = {r: _FramePublisher(s, keys.meas_vr(f, r)) for r in self.regs}
        self.ack_pv = {p: TypedPublisher(s, keys.ack(f, "pv", p), m.Ack, reliable=True) for p in self.pvs}
        self.ack_vr = {r: TypedPublisher(s, keys.ack(f, "vr", r), m.Ack, reliable=True) for r in self.regs}
        self.pub_truth = _FramePublisher(s, keys.sim_truth(f), reliable=True)
        self.pub_metrics = _FramePublisher(s, keys.sim_metrics(f), reliable=True)
        self.pub_status = _FramePublisher(s, keys.sim_status(f), reliable=True)
        self.inbox = Inbox(maxsize=4096)
        self.inbox.subscribe(s, f"{keys.ROOT}/*/cmd/**")  # other feeders too: see _wrong_feeder
        self.inbox.subscribe(s, keys.agent_decision(f), m.Decision)
        self.agents = LivelinessWatcher(s, f"{keys.ROOT}/{f}/alive/agent/*", self._on_agent)
        self.bridges = LivelinessWatcher(s, f"{keys.ROOT}/*/alive/bridge/*")
        self.queryable = s.declare_queryable(keys.sim_oracle(f), self._on_query, complete=True)

    def close(self) -> None:
        """Withdraw every token and declaration (the session is closed by the caller's ``with``); oracle
        queries still queued are answered with an error, so their getters do not wait for their timeout.
        """
        if self.publisher is not None:
            self.publisher.close()
        if self._defer:
            self.qsts.before_solve = None
        for undeclare in [self.queryable.undeclare, self.inbox.undeclare, self.agents.undeclare,
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

    # ---------------------------------------------------------------- callbacks (Zenoh threads)
    def _on_agent(self, key: str, up: bool) -> None:
        if up:
            log.info("agent liveliness token up: %s", key)
        else:
            log.warning("agent liveliness lost: %s", key)
            # in order with its commands: a restarted agent's sequence starts again at 1 (see _forget_sender)
            try:
                self.inbox.queue.put_nowait(Received(key, _SenderGone(key.rsplit("/", 1)[-1]), time.time_ns(), b""))
            except queue.Full:
                log.warning("queue full: the devices keep the lost agent's command sequence")

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
            self._flush(now)
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
            nxt = self.delay.next_due_s()
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
            for device in [*self.pvs.values(), *self.regs.values()]:
                device.guard.forget_source(msg.source)
        elif isinstance(msg, m.Decision):
            self._on_decision(msg, item.recv_wall_ns)
        elif isinstance(msg, m.PvCommand | m.RegCommand):
            self._on_command(item.key, msg)

    def _on_decision(self, d: m.Decision, recv_wall_ns: int) -> None:
        if d.feeder_id != self.fid:
            self.rejected["decision_wrong_feeder"] += 1
            return
        self.decisions += 1
        with self._ctrl_lock:
            pub = self._ctrl_pub_wall_ns.pop(d.step_t_ns, None)
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
        if verdict.status == "rejected":
            self.rejected[verdict.reason_kind] += 1
            log.info("rejected command %s for %s: %s", cmd_id, device_id, verdict.reason)
        if isinstance(pub_or_key, TypedPublisher):
            pub_or_key.put(ack)
        else:
            self.session.put(pub_or_key, codec_for(m.Ack).encode(ack), encoding=zenoh.Encoding.APPLICATION_JSON,
                             congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.REAL_TIME)

    def _on_command(self, key: str, cmd: m.PvCommand | m.RegCommand) -> None:
        self._remember(cmd.cmd_id)
        parts = keys.parse_device_key(key)
        if parts is None:
            self.rejected["unknown_device"] += 1  # no device key to answer on
            return
        feeder, _, kind, device = parts
        if feeder != self.fid:
            self._wrong_feeder(feeder, kind, device, cmd)
            return
        ack_key = keys.ack(self.fid, "pv" if kind == "pv" else "vr", device)
        if kind == "pv" and device in self.pvs and isinstance(cmd, m.PvCommand):
            self._pv_command(self.pvs[device], cmd)
        elif kind == "vr" and device in self.regs and isinstance(cmd, m.RegCommand):
            self._reg_command(self.regs[device], cmd)
        else:
            self._ack(ack_key, device, "bridge", cmd.cmd_id, dv.reject(
                "unknown_device", f"feeder {self.fid!r} has no {kind} device {device!r}; devices: "
                f"{sorted(self.pvs) if kind == 'pv' else sorted(self.regs)}"))

    def _wrong_feeder(self, feeder: str, kind: str, device: str, cmd: m.Command) -> None:
        """A command addressed to another feeder: ignored when that feeder has a live bridge (it is its
        business), otherwise rejected and acked on that feeder's ack key, so the sender learns of it.
        """
        if any(k.startswith(f"{keys.ROOT}/{feeder}/alive/bridge/") for k in self.bridges.alive()):
            return
        try:
            ack_key = keys.ack(feeder, "pv" if kind == "pv" else "vr", device)
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
        self.drain()  # the frames of the steps simulated so far show the state before this command
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
        self.drain()  # the frames of the steps simulated so far show the state before this command
        match cmd.action:
            case m.TapAction(tap=tap):
                self.qsts.command_tap(reg.index, tap)
                self.qsts.command_setpoint(reg.index, None, None)
            case m.SetpointAction(setpoint_v120=sp, band_v120=bw):
                self.qsts.command_tap(reg.index, None)
                self.qsts.command_setpoint(reg.index, sp, bw)
        self._ack(self.ack_vr[reg.regulator_id], reg.regulator_id, reg.regulator_id, cmd.cmd_id, reg.apply(cmd))

    def run_watchdogs(self, t_ns: int) -> None:
        """Before simulating ``t_ns``: expire commands past their validity; devices go back to default."""
        if self.publisher is not None:
            for device in self._devices:  # the frames of earlier steps show the command (CommandGuard.expire's rule)
                active = device.guard.active
                if active is not None and active.valid_until_t_ns < t_ns:
                    self.drain()
                    break
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

    # ---------------------------------------------------------------- oracle
    def _answer_oracle(self, item: _OracleQuery) -> None:
        q = item.query
        try:
            # Only the feeder's own nodes (the head meter's side): the transmission side of the substation
            # is no control target, and constraining it made case A trade Q and taps for an unfixable node.
            feeder = np.flatnonzero(self.engine.node_in_feeder)
            v = self.engine.node_voltages_pu()[feeder]
            dq: list[list[float]] = []
            dtap: list[list[float]] = []
            dp: list[list[float]] = []
            if item.request.include_sensitivities:
                s = self.engine.perturbation_sensitivities()
                dq, dtap, dp = (np.clip(np.nan_to_num(a[feeder], nan=0.0), -1.0, 1.0).tolist()
                                for a in (s.dv_dq, s.dv_dtap, s.dv_dp))
            self.seqs["oracle"] += 1
            reply = m.OracleReply(t_ns=max(self.now_t_ns, 0), seq=self.seqs["oracle"], source="bridge",
                                  feeder_id=self.fid, node_names=[self.engine.node_names[i] for i in feeder],
                                  v_pu=np.clip(v, 0.0, 3.0).tolist(), dv_dq_pu_per_kvar=dq, dv_dtap_pu=dtap,
                                  taps=[int(t) for t in self.engine.taps()], dv_dp_pu_per_kw=dp)
            q.reply(q.key_expr, codec_for(m.OracleReply).encode(reply), encoding=zenoh.Encoding.APPLICATION_JSON)
            self.oracle_replies += 1
        except CvvcError as e:
            self.oracle_rejected += 1
            log.warning("oracle query failed: %s", e)
            q.reply_err(f"oracle failed: {e}".encode())
        finally:
            q.drop()

    # ---------------------------------------------------------------- frames
    def _flush(self, now_s: float) -> None:
        for pub, msg in self.delay.due(now_s):  # type: ignore[misc]
            self._publish(pub, msg)

    def _publish(self, pub: _FramePublisher, msg: msgspec.Struct) -> None:
        if pub is self.pub_head and self.is_control_step(self._step_of(msg.t_ns)):  # type: ignore[attr-defined]
            with self._ctrl_lock:
                self._ctrl_pub_wall_ns[msg.t_ns] = time.time_ns()  # before put: the answer may beat put's return
                while len(self._ctrl_pub_wall_ns) > 64:  # decisions that never came
                    self._ctrl_pub_wall_ns.pop(next(iter(self._ctrl_pub_wall_ns)))
        pub.put(msg)
        self.frames_published += 1

    def _step_of(self, t_ns: int) -> int:
        return (t_ns - int(self.profiles.start_t_ns)) // (self.step_s * _NS)

    def _send_now(self, pub: _FramePublisher, msg: msgspec.Struct, now_s: float) -> None:
        """:meth:`_send` without drops or latency configured."""
        self._publish(pub, msg)

    def _send(self, pub: _FramePublisher, msg: msgspec.Struct, now_s: float) -> None:
        if self.dropper.drop():
            self.frames_dropped += 1
        elif self.delay.latency_s > 0.0:
            self.delay.put((pub, msg), now_s)
        else:
            self._publish(pub, msg)

    def publish_frames(self, res: Any, now_s: float) -> None:
        """Schedule the frames of one step (noise, drops, latency applied).

        The readings are turned into Python numbers once per step (``tolist``), so the frame builders index
        lists rather than making a NumPy scalar of every value; the numbers, hence the frames, are the same.
        """
        rd, t, seqs, noise = res.readings, int(res.t_ns), self.frame_seqs, self.noise
        send = self._send if self.dropper.p > 0.0 or self.delay.latency_s > 0.0 else self._send_now
        head = (rd.head_v_mag_v, rd.head_v_ang_deg, rd.head_i_mag_a, rd.head_i_ang_deg, rd.head_p_kw,
                rd.head_q_kvar)
        if noise is not None:
            head = noise.head(*head)
        hv, ha, hi, hia, hp, hq = (x.tolist() for x in head)
        seqs["head"] += 1
        send(self.pub_head, dv.head_frame(feeder_id=self.fid, t_ns=t, seq=seqs["head"], v_mag_v=hv, v_ang_deg=ha,
                                          i_mag_a=hi, i_ang_deg=hia, p_kw=hp, q_kvar=hq), now_s)
        pv_p, pv_q, pv_v = rd.pv_p_kw, rd.pv_q_kvar, rd.pv_v_v
        if noise is None:
            pv_p, pv_q, pv_v = pv_p.tolist(), pv_q.tolist(), pv_v.tolist()
        available, q_at_night = np.asarray(res.pv_p_kw, dtype=float).tolist(), self.qsts.pv_q_at_night
        for pid, pv in self.pvs.items():
            k = pv.index
            p, q, v = pv_p[k], pv_q[k], pv_v[k]
            if noise is not None:
                p, q, v = (x.tolist() for x in noise.pv(p, q, v, pv.s_rated_kva))
            seqs[pid] += 1
            send(self.pub_pv[pid], dv.pv_frame(plant=pv, t_ns=t, seq=seqs[pid], p_kw=p, q_kvar=q, v_v=v,
                                               available_p_kw=available[k], q_at_night=q_at_night), now_s)
        v120s = np.asarray(rd.reg_v120, dtype=float).tolist()
        vcs = np.asarray(rd.reg_v120_compared, dtype=float).tolist()
        taps = np.asarray(res.taps).tolist()
        for rid, reg in self.regs.items():
            r = reg.index
            v120, vc = v120s[r], vcs[r]
            if noise is not None:
                v120, vc = noise.regulator(v120, vc)
            seqs[rid] += 1
            send(self.pub_vr[rid], dv.reg_frame(reg=reg, t_ns=t, seq=seqs[rid], phase=self.reg_phase[r],
                                                v120=min(v120, 200.0), v_compared_120=min(vc, 200.0),
                                                tap=int(taps[r])), now_s)
        if len(self.delay):
            self._flush(now_s)

    def publish_truth(self, res: Any, n_step: int, v_lo_pu: float, v_hi_pu: float) -> None:
        """The TruthFrame of the ``n_step``-th step of the run (from 1), if it has one; ``v_lo_pu``, ``v_hi_pu``:
        the extremes of ``res.v_pu``.

        The voltages are clipped to the schema's 0..3 pu into a buffer kept across steps; the extremes of the
        clipped voltages are the clipped extremes (clipping is monotonic).
        """
        c = self.config
        if c.truth_every == 0 or (n_step - 1) % c.truth_every != 0:
            return
        self.frame_seqs["truth"] += 1
        v = np.clip(res.v_pu, 0.0, 3.0, out=self._truth_v)
        self.pub_truth.put(m.TruthFrame(
            t_ns=int(res.t_ns), seq=self.frame_seqs["truth"], source="bridge", feeder_id=self.fid, v_pu=v.tolist(),
            v_min_pu=min(max(v_lo_pu, 0.0), 3.0), v_max_pu=min(max(v_hi_pu, 0.0), 3.0),
            node_names=list(self.engine.node_names) if self.truth_frames == 0 else None,
            taps=np.asarray(res.taps).tolist(), pv_q_kvar=np.asarray(res.pv_q_kvar, dtype=float).tolist()))
        self.truth_frames += 1

    def metrics_frame(self, *, final: bool) -> m.MetricsFrame:
        """Cumulative paper IV.F metrics since the first step (``simulator_bridge.metrics``)."""
        r = self.metrics.result()
        self.seqs["metrics"] += 1
        return m.MetricsFrame(
            t_ns=max(self.now_t_ns, 0), seq=self.seqs["metrics"], source="bridge", feeder_id=self.fid,
            start_t_ns=int(self.profiles.t_ns(self.start_step)), steps=r.n_steps,
            mvvm_pu=min(float(r.mvvm_pu), 3.0), nvv=int(r.nvv),
            minutes_in_violation=int(round(r.minutes_in_violation)), ntc=int(r.ntc), q_cost=float(r.q_cost),
            t_cost=float(r.t_cost), total_cost=float(r.total_cost),
            v_min_pu=min(max(r.v_min_pu if r.v_min_pu is not None else 0.0, 0.0), 3.0),
            v_max_pu=min(max(r.v_max_pu if r.v_max_pu is not None else 0.0, 0.0), 3.0),
            taps_changes=dict(zip(r.regulator_ids, r.tap_changes_per_regulator, strict=True)),
            q_mvar_intervals=dict(zip(r.pv_ids, r.q_mvar_intervals_per_plant, strict=True)),
            final=final)

    def status(self, *, done: bool) -> m.BridgeStatus:
        self.seqs["status"] += 1
        return m.BridgeStatus(t_ns=max(self.now_t_ns, 0), seq=self.seqs["status"], source="bridge",
                              feeder_id=self.fid, step=self.steps, steps_total=self.config.steps,
                              clock=self.config.clock, lockstep_misses=self.misses, agent_alive=self.agent_alive,
                              rejected=self.all_rejected(), done=done)

    def all_rejected(self) -> dict[str, int]:
        out = dict(self.rejected)
        for kind, n in self.inbox.rejects.by_kind().items():
            out[f"decode_{kind}"] = out.get(f"decode_{kind}", 0) + n
        return out

    # ---------------------------------------------------------------- one step
    def step(self) -> Any:
        """Watchdogs, one QSTS step, then its frames, metrics and truth (:meth:`_publish_step`, by the publisher
        thread when there is one: call :meth:`drain` before reading the metrics); returns the StepResult.
        """
        t_next = int(self.profiles.t_ns(self.qsts.next_step))
        self.run_watchdogs(t_next)
        res = self.qsts.step()
        v_lo, v_hi = _check_finite_step(res)
        self.now_t_ns = int(res.t_ns)
        self.pv_p_kw = np.asarray(res.pv_p_kw, float)
        self.steps += 1
        if self.publisher is None:
            self._publish_step(res, self.steps, v_lo, v_hi)
        elif self._defer:
            self._pending = (res, self.steps, v_lo, v_hi)
        else:
            self.publisher.submit((res, self.steps, v_lo, v_hi))
        return res

    def _hand_over(self) -> None:
        if self._pending is not None:
            item, self._pending = self._pending, None
            self.publisher.submit(item)  # type: ignore[union-attr]

    def _publish_step(self, res: Any, n_step: int, v_lo_pu: float, v_hi_pu: float) -> None:
        """Frames, metrics update and truth of the ``n_step``-th step. The device frames go out first, so that
        on a control step the agent works while the bridge updates the metrics and publishes the truth.
        """
        self.publish_frames(res, time.monotonic())
        self.metrics.update(res.v_pu, res.tap_changes, res.pv_q_kvar)
        self.publish_truth(res, n_step, v_lo_pu, v_hi_pu)

    def drain(self) -> None:
        """Return once every simulated step is published (frames, truth) and in the metrics."""
        if self.publisher is not None:
            self._hand_over()
            self.publisher.drain()

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
            rt = _Runtime(config, session, dm, engine, profiles, qsts, start)
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
    pub_cpu0 = rt.publisher.cpu_s() if rt.publisher is not None else 0.0
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
        else:
            rt.serve(0.0, stop)  # handle what is queued, without waiting
        res = rt.step()
        if rt.is_control_step(res.step):
            t_drain = time.monotonic()
            rt.drain()  # the step's frames are out and in the metrics before the wait and the metrics frame
            t_wait = time.monotonic()
            rt.drain_wait_s += t_wait - t_drain
            rt.control_steps += 1
            if c.clock == "lockstep":
                _await_decision(rt, int(res.t_ns), stop)
                rt.decision_wait_s += time.monotonic() - t_wait
            rt.pub_metrics.put(rt.metrics_frame(final=False))
            rt.pub_status.put(rt.status(done=False))
    rt.drain()
    wall_s, cpu_s, thread_cpu_s = time.monotonic() - t0, time.process_time() - cpu0, time.thread_time() - thread0
    pub_cpu_s = rt.publisher.cpu_s() - pub_cpu0 if rt.publisher is not None else 0.0
    rt.serve(time.monotonic() + c.latency_s, stop if stop.is_set() else threading.Event(),
             lambda: len(rt.delay) == 0)  # frames still in the delay line go out
    final = rt.metrics_frame(final=True)
    rt.pub_metrics.put(final)
    rt.pub_status.put(rt.status(done=True))
    return BridgeSummary(
        feeder_id=rt.fid, clock=c.clock, start_t_ns=int(rt.profiles.t_ns(rt.start_step)), end_t_ns=max(rt.now_t_ns, 0),
        steps=rt.steps, steps_total=c.steps, control_steps=rt.control_steps, wall_s=wall_s, cpu_s=cpu_s,
        thread_cpu_s=thread_cpu_s,
        steps_per_s=rt.steps / wall_s if wall_s > 0 else 0.0, lockstep_misses=rt.misses,
        lockstep_skipped=rt.skipped, decisions=rt.decisions, acks=dict(rt.acks), rejected=rt.all_rejected(),
        frames_published=rt.frames_published, frames_dropped=rt.frames_dropped, truth_frames=rt.truth_frames,
        oracle_replies=rt.oracle_replies, oracle_rejected=rt.oracle_rejected, realtime_late_steps=rt.late_steps,
        round_trip_p50_s=_percentile(rt.round_trips, 50), round_trip_p99_s=_percentile(rt.round_trips, 99),
        agent_alive=rt.agent_alive, stopped_early=rt.steps < c.steps, metrics=final,
        publisher_thread_cpu_s=pub_cpu_s, drain_wait_s=rt.drain_wait_s, decision_wait_s=rt.decision_wait_s)


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
        rt.pub_head.wait_matched(max(deadline - time.monotonic(), _STARTUP_PROBE_S))


def _await_decision(rt: _Runtime, t_ns: int, stop: threading.Event) -> None:
    """Lockstep: wait (serving the queue) for the decision of step ``t_ns`` and its commands."""
    # frames held by the latency line must be out before the agent can answer them
    rt.serve(time.monotonic() + rt.config.latency_s + 1.0, stop, lambda: len(rt.delay) == 0)
    if not rt.agent_alive:
        rt.skipped += 1
        if not rt._logged_no_agent:
            log.warning("lockstep: no agent liveliness token on %s/alive/agent/*; stepping without waiting "
                        "until one appears", rt.fid)
            rt._logged_no_agent = True
        return
    rt._logged_no_agent = False
    if not rt.serve(time.monotonic() + rt.config.timeout_s, stop, lambda: rt._decided(t_ns)):
        if stop.is_set():
            return
        rt.misses += 1
        d = rt._decision
        why = ("no decision" if d is None or d.step_t_ns != t_ns
               else "decision arrived but not all of its commands")
        log.warning("lockstep miss at t_ns=%d: %s within %.3f s; going on under local control "
                    "(%d misses so far)", t_ns, why, rt.config.timeout_s, rt.misses)
