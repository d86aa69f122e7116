"""The simulator bridge: the QSTS feeder seen through Zenoh as a utility sees its field devices.

This module is the run loop (:func:`run_bridge`: clocks, lockstep, startup, the summary); the state it steps is
``bridge_runtime.py``'s, with the devices on the bus and their commands in ``device_bank.py`` and the case-A oracle's
serving in ``oracle_serving.py``. Device logic (checks, watchdogs, acks, frames, noise) is in ``devices.py``; physics
in ``qsts.py`` / ``engine.py``. ``docs/bridge.md`` is the user's guide; in short:

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
  token alive, the bridge does not wait (counted as ``lockstep_skipped``). A decision may announce follow-up
  commands (``Decision.follow_ups``, by ``cmd_id``) for the step after its own: once that step's frames are out,
  the bridge waits for them the same way (a miss counted in ``follow_up_misses``), so a run in lockstep applies
  them at the same step every time.
* **Real time**: step ``i`` is simulated at ``t0 + i · step_s / speed`` of wall time; the bridge never
  waits for anyone, it serves commands and oracle queries while it waits for the next tick.
* **Publishing** (``simulator_bridge.bus.publishing``): a step's device frames, metrics update and truth frame,
  and the metrics frames, come from a ``StepFramer``: called inline by the stepping thread, or, by default
  on feeders of 200 nodes or more, in a publisher process with its own Zenoh session, fed through shared
  memory with each step's results and the device settings in force, so its Python work runs beside the next
  power flow instead of under this process's GIL. The messages are the same either way.
"""

from __future__ import annotations

import datetime as dt
import logging
import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import msgspec
import numpy as np

from schemas import keys
from schemas import messages as m
from schemas.bus import BusConfig, open_session, wait_for
from schemas.devicemap import DeviceMap, load_device_map
from simulator_bridge.bus.bridge_config import BridgeConfig
from simulator_bridge.bus.bridge_runtime import BridgeRuntime, dnp3_fleet, sunspec_fleet
from simulator_bridge.errors import BridgeError
from simulator_bridge.simulation.live_accuracy import LiveAccuracy

if TYPE_CHECKING:
    from simulator_bridge.opendss.engine import FeederEngine
    from simulator_bridge.simulation.profiles import YearProfiles

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
_ADAPTER_WAIT_S = 30.0  # before the first step, the longest wait for the field-protocol adapters' tokens [s]
_STARTUP_PROBE_S = 1.0  # bounded look for an agent already alive, and for its subscription, at startup [s]


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
    sunspec_frame_misses: int = 0  # steps some SunSpec adapter's frame did not come within the time-out
    sunspec_foreign_master_writes: dict[str, int] = {}  # Modbus writes an inverter refused: not its adapter's, by plant
    dnp3_frame_misses: int = 0  # steps some DNP3 adapter's frame did not come within the time-out
    follow_up_misses: int = 0  # lockstep: steps whose announced follow-up commands did not all come in the time-out
    live_accuracy: LiveAccuracy | None = None  # the agent's estimates against the truth of their step


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


def cached_profiles(device_map: DeviceMap, engine: FeederEngine, *, seed: int,
                    cache_dir: str | Path | None) -> YearProfiles:
    """The feeder's year profiles for ``seed`` (see ``simulator_bridge.simulation.profiles.feeder_profiles``)."""
    from simulator_bridge.simulation.profiles import feeder_profiles

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
    if not (math.isfinite(c.drop_burst_min) and 0.0 <= c.drop_burst_min <= 1440.0):
        raise BridgeError(f"--drop-burst-min must be within 0..1440 min, got {c.drop_burst_min}")
    if not (math.isfinite(c.clock_skew_s) and abs(c.clock_skew_s) <= 600.0):
        raise BridgeError(f"--clock-skew-s must be within -600..600 s, got {c.clock_skew_s}")
    if (c.pv_sunspec or c.field_dnp3) and (c.noise_scada_pct or c.drop_prob or c.latency_s or c.clock_skew_s):
        raise BridgeError("devices behind SunSpec or DNP3 (--pv-sunspec, --field-dnp3) take no SCADA noise, drops, "
                          "latency or clock skew yet: the adapters publish their frames; run without those options")
    if c.publisher == "process" and c.latency_s > 0.0:
        raise BridgeError("publisher='process' cannot hold frames for --latency-s (the stepping thread flushes "
                          "the delay line); use publisher='auto' or 'inline' with latency")


def _percentile(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


# ------------------------------------------------------------------------------------------ the loop
def run_bridge(config: BridgeConfig, bus: BusConfig, *, stop: threading.Event | None = None,
               on_ready: Callable[[], None] | None = None) -> BridgeSummary:
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
    from simulator_bridge.opendss.engine import FeederEngine
    from simulator_bridge.simulation.qsts import Qsts

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
        fleet = sunspec_fleet(config, dm, engine, qsts)
        dnp3 = dnp3_fleet(config, engine)
        with open_session(bus) as session:
            rt = BridgeRuntime(config, bus, session, dm, engine, profiles, qsts, start, fleet, dnp3)
            try:
                return _loop(rt, stop, on_ready)
            finally:
                rt.close()
    finally:
        engine.close()


def _loop(rt: BridgeRuntime, stop: threading.Event, on_ready: Callable[[], None] | None) -> BridgeSummary:
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
        if rt.frames is not None:
            rt.await_adapter_frames(int(res.t_ns), stop)
        if c.clock == "lockstep" and (follow_ups := rt.follow_ups_due(int(res.t_ns))):
            t_wait = time.monotonic()
            _await_follow_ups(rt, int(res.t_ns), follow_ups, stop)
            rt.decision_wait_s += time.monotonic() - t_wait
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
        lockstep_skipped=rt.skipped, decisions=rt.decisions, acks=dict(rt.counters.acks), rejected=rt.all_rejected(),
        frames_published=published, frames_dropped=dropped, truth_frames=truth,
        oracle_replies=rt.oracle.replies if rt.oracle is not None else 0,
        oracle_rejected=rt.oracle.rejected if rt.oracle is not None else 0, realtime_late_steps=rt.late_steps,
        round_trip_p50_s=_percentile(rt.round_trips, 50), round_trip_p99_s=_percentile(rt.round_trips, 99),
        agent_alive=rt.agent_alive, stopped_early=rt.steps < c.steps, metrics=final,
        publisher_cpu_s=pub_cpu_s, decision_wait_s=rt.decision_wait_s,
        publisher="inline" if rt.child is None else "process",
        log_suppressed=rt.log_suppressed(),
        sunspec_frame_misses=rt.frames.misses["sunspec"] if rt.frames is not None else 0,
        sunspec_foreign_master_writes=rt.fleet.foreign_master_writes() if rt.fleet is not None else {},
        dnp3_frame_misses=rt.frames.misses["dnp3"] if rt.frames is not None else 0,
        follow_up_misses=rt.follow_up_misses,
        live_accuracy=rt.live.result() if rt.decisions else None)


def _startup(rt: BridgeRuntime, stop: threading.Event) -> None:
    """Before the first step: learn whether an agent is alive (waiting up to ``wait_agent_s`` for one), and
    if so let its subscription of the head frames reach this session (bounded), so step 0 is not lost.
    """
    c = rt.config
    deadline = time.monotonic() + c.wait_agent_s
    if rt.frames is not None and not rt.serve(time.monotonic() + max(c.wait_agent_s, _ADAPTER_WAIT_S), stop,
                                              rt.adapters_alive):
        log.warning("not every field-protocol adapter is on the bus (%s): their devices' frames will be missing",
                    ", ".join(f"{k}/{d}" for k, d in rt.frames.protocol))
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
        elif rt.framer is not None:
            rt.framer.pub_head.wait_matched(timeout_s)


def _frames_out(rt: BridgeRuntime, stop: threading.Event) -> None:
    """Lockstep: serve the queue until the latency line's frames are out (the agent answers only frames it has)."""
    rt.serve(time.monotonic() + rt.config.latency_s + 1.0, stop, lambda: rt.held() == 0)


def _answered(rt: BridgeRuntime, stop: threading.Event, done: Callable[[], bool]) -> bool:
    """Lockstep: serve the queue until ``done()`` or the time-out; False only on a time-out (not when stopped)."""
    return rt.serve(time.monotonic() + rt.config.timeout_s, stop, done) or stop.is_set()


def _await_follow_ups(rt: BridgeRuntime, t_ns: int, cmd_ids: tuple[str, ...], stop: threading.Event) -> None:
    """Lockstep: wait (serving the queue) for the follow-up commands the last decision announced, sent once the
    frames of step ``t_ns`` (the next) are in; a miss is counted (``follow_up_misses``) and the run goes on.
    """
    _frames_out(rt, stop)
    if rt.agent_alive and not _answered(rt, stop, lambda: all(rt.bank.handled(c) for c in cmd_ids)):
        rt.follow_up_misses += 1
        rt.counters.rlog.warning("follow_up_miss", "lockstep: follow-ups announced for t_ns=%d not all in within "
                                 "%.3f s (%d misses so far)", t_ns, rt.config.timeout_s, rt.follow_up_misses)


def _await_decision(rt: BridgeRuntime, t_ns: int, stop: threading.Event) -> None:
    """Lockstep: wait (serving the queue) for the decision of step ``t_ns`` and its commands."""
    _frames_out(rt, stop)
    if not rt.agent_alive:
        rt.skipped += 1
        if not rt.logged_no_agent:
            log.warning("lockstep: no agent liveliness token on %s/alive/agent/*; stepping without waiting "
                        "until one appears", rt.fid)
            rt.logged_no_agent = True
        return
    rt.logged_no_agent = False
    rt.qsts.stage_loads()  # the next step's loads do not depend on the decision: set them while it comes
    if not _answered(rt, stop, lambda: rt.decided(t_ns)):
        rt.misses += 1
        d = rt.decision
        why = ("no decision" if d is None or d.step_t_ns != t_ns
               else "decision arrived but not all of its commands")
        rt.counters.rlog.warning("lockstep_miss", "lockstep miss at t_ns=%d: %s within %.3f s; going on under local "
                                 "control (%d misses so far)", t_ns, why, rt.config.timeout_s, rt.misses)
