"""``cvvc fleet``: several feeders at once on one bus: one bridge and one agent per feeder, one recorder, one router.

The machinery is ``cvvc run``'s (``cvvc.launch``): each feeder is prepared as a run of its own
(``prepare_feeder_and_model``: the generated rural feeder of a seed or a device map, the cached model), its agent
gets the case's settings (``case_agent_settings``) and its bridge the run's flags (``bridge_args``, lockstep per
feeder); the processes are started, watched and stopped by pid the same way. What the fleet adds:

- feeder ids: each feeder's key space is ``cvvc/<id>/...``; the id is the map's feeder name or the entry's ``id``
  (two entries of one map need distinct ids), and two feeders of one id are refused;
- secure mode: one certificate per feeder's agent and per feeder's devices (common names ``agent.<id>``,
  ``devices.<id>``, ``schemas.security.feeder_common_name``) in ``<cache>/security/feeders/<id>``, and the
  router's policy (``access_control_policy(feeders)``) allows each only on its own feeder's keys;
  ``probe_cross_feeder`` then puts one command with the first feeder's agent certificate on the second
  feeder's command key and reports whether it got through (``CrossFeederProbe``);
- after the run, the one recording is read once (``fleet_report.check_recording``): messages on one feeder's keys
  that carry another feeder's id, and every decision's time, per feeder.

No no-control baseline is simulated (``cvvc run`` per feeder gives it).
"""

from __future__ import annotations

import datetime as dt
import shutil
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

import msgspec

from agent.runtime import AgentSummary
from cvvc.fleet_report import CrossFeederProbe, FeederRow, FleetSummary, check_recording, percentile_ms
from cvvc.integrity import run_integrity
from cvvc.launch import (
    Case,
    LaunchError,
    RunConfig,
    _Child,
    _read_summary,
    _RecorderSupervisor,
    _spawn,
    _stop,
    _tail,
    agent_settings_args,
    bridge_args,
    case_agent_settings,
    prepare_feeder_and_model,
)
from schemas import messages as m
from schemas.settings import AgentOptions, RunCase
from simulator_bridge.bus.bridge import BridgeSummary

if TYPE_CHECKING:
    from schemas.devicemap import DeviceMap

__all__ = ["FleetConfig", "FleetFeeder", "FleetFile", "load_fleet_file", "run_fleet"]


class FleetFeeder(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One feeder of a fleet (a ``[[feeder]]`` table of a fleet file): a device map or a rural seed, and options.

    Exactly one of ``map`` (device map TOML or folder) and ``rural_seed`` (the embedded rural feeder generated
    with that seed, feeder id ``rural-s<seed>``). ``id``: its key space ``cvvc/<id>/...`` (default: the map's
    feeder name). ``case`` None: the fleet's case.
    """

    map: str | None = None
    rural_seed: int | None = None
    id: str | None = None
    model: str | None = None
    year_seed: int = RunCase().window.year_seed
    train_seed: int = RunCase().feeder.train_seed
    case: Case | None = None


class FleetFile(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A fleet file (TOML): defaults for every feeder and the ``[[feeder]]`` list; ``map`` paths are relative to
    the file's folder.
    """

    days: float | None = None
    start: str | None = None
    case: Case | None = None
    agent: AgentOptions | None = None  # [agent]: every feeder's agent options (a case file's [agent] section)
    feeder: list[FleetFeeder] = []


class FleetConfig(msgspec.Struct, frozen=True, kw_only=True):
    """Everything ``cvvc fleet`` needs; built from the command line (and a fleet file)."""

    feeders: list[FleetFeeder]
    days: float = 0.25
    start: str = RunCase().window.start
    case: Case = RunCase().case
    out: str | None = None
    cache: str | None = None
    record: bool = RunCase().output.record
    truth_every: int = RunCase().bridge.truth_every
    lockstep_timeout_s: float = 30.0  # 2 cores shared by every feeder's processes: a step may wait its turn
    secure: bool = True  # mTLS + the access policy; False: --insecure
    ca_dir: str | None = None  # None: <cache>/ca, created on the first run
    probe_cross_feeder: bool = True  # secure mode: the cross-feeder command probe (``CrossFeederProbe``)
    progress: bool = True
    recorder_restarts_max: int = 3
    agent: AgentOptions = msgspec.field(default_factory=AgentOptions)  # every feeder's agent options (cases A-D)


def load_fleet_file(path: str | Path) -> FleetFile:
    """Decode a fleet file; relative ``map`` paths are made relative to its folder. ``LaunchError`` when bad."""
    p = Path(path)
    try:
        fleet = msgspec.toml.decode(p.read_bytes(), type=FleetFile)
    except (OSError, msgspec.DecodeError, msgspec.ValidationError) as e:
        raise LaunchError(f"fleet file {p}: {e}") from e
    feeders = [f if f.map is None or Path(f.map).is_absolute()
               else msgspec.structs.replace(f, map=str(p.parent / f.map)) for f in fleet.feeder]
    return msgspec.structs.replace(fleet, feeder=feeders)


class _Member(msgspec.Struct, kw_only=True):
    """One prepared feeder: its run config, paths, settings and processes."""

    entry: FleetFeeder
    run: RunConfig
    feeder_id: str
    dm_path: Path
    dm: DeviceMap  # read once, in ``_prepare``
    model: Path
    out: Path
    pv_ids: list[str]
    agent: _Child | None = None
    bridge: _Child | None = None
    connect: list[str] = []


def _log(msg: str) -> None:
    import sys

    print(f"[cvvc fleet] {msg}", file=sys.stderr, flush=True)


def _prepare(config: FleetConfig, entry: FleetFeeder, out: Path) -> _Member:
    from schemas.cache import cache_root
    from schemas.devicemap import load_device_map
    from simulator_bridge.rural.default_feeder import ensure_default_feeder

    if (entry.map is None) == (entry.rural_seed is None):
        raise LaunchError(f"fleet feeder {entry}: give exactly one of map and rural_seed")
    feeder = entry.map or str(ensure_default_feeder(cache_root(config.cache), int(entry.rural_seed or 0)))
    run = RunConfig(feeder=feeder, model=entry.model, days=config.days, start=config.start,
                    case=entry.case or config.case, year_seed=entry.year_seed, train_seed=entry.train_seed,
                    cache=config.cache, record=config.record, progress=config.progress,
                    lockstep_timeout_s=config.lockstep_timeout_s, truth_every=config.truth_every,
                    secure=config.secure, ca_dir=config.ca_dir, agent=config.agent)
    dm_path, model = prepare_feeder_and_model(run)
    dm = load_device_map(dm_path)
    fid = entry.id or dm.feeder.name
    from schemas.keys import KeyExprError, feeder_all

    try:
        feeder_all(fid)
    except KeyExprError as e:
        raise LaunchError(f"fleet feeder id: {e}") from e
    return _Member(entry=entry, run=run, feeder_id=fid, dm_path=dm_path, dm=dm, model=model, out=out / fid,
                   pv_ids=[p.id for p in dm.pv])


def _security(config: FleetConfig, members: list[_Member]) -> str | None:
    """Issue the router's and recorder's certificates and each feeder's own; returns the router's folder."""
    from schemas.cache import ca_dir, security_dir
    from schemas.security import INSECURE_WARNING, ensure_local_security, init_security_dir

    if not config.secure:
        _log(f"WARNING {INSECURE_WARNING}")
        for mb in members:
            mb.connect = ["--insecure"]
        return None
    root = security_dir(config.cache)
    ca = config.ca_dir or ca_dir(config.cache)
    ensure_local_security(root, ca_dir=ca)
    for mb in members:
        d = root / "feeders" / mb.feeder_id
        init_security_dir(d, ca_dir=ca, feeder=mb.feeder_id)
        mb.connect = ["--secure-dir", str(d)]
    return str(root)


def _open_router(endpoint: str, security_dir: str | None, feeder_ids: list[str]):
    """The fleet's router session; in secure mode its policy has every feeder's own subjects."""
    import zenoh

    from schemas.bus import BusConfig, zenoh_config
    from schemas.security import zenoh_security_settings

    conf = zenoh_config(BusConfig(mode="router", listen=(endpoint,), tls_dir=security_dir,
                                  role="router" if security_dir else None))
    if security_dir is not None:
        policy = zenoh_security_settings(security_dir, "router", tuple(feeder_ids))["access_control"]
        conf.insert_json5("access_control", msgspec.json.encode(policy).decode())
    try:
        return zenoh.open(conf)
    except Exception as e:  # zenoh raises ZError, a plain Exception subclass
        raise LaunchError(f"cannot open the fleet's router on {endpoint}: {e}") from e


def run_fleet(config: FleetConfig) -> FleetSummary:
    """Run every feeder of ``config`` at once on one router; see the module docstring."""
    from schemas import keys
    from schemas.bus import LivelinessWatcher, free_port, has_subscribers, wait_for

    if not config.feeders:
        raise LaunchError("a fleet needs at least one feeder (--feeders, --rural-seeds or --fleet)")
    if not 0 < config.days <= 366:
        raise LaunchError(f"--days {config.days} must be in (0, 366]")
    try:
        start_text = dt.datetime.fromisoformat(config.start).isoformat(timespec="minutes")
    except ValueError as e:
        raise LaunchError(f"--start {config.start!r} is not a date (YYYY-MM-DD or YYYY-MM-DDTHH:MM)") from e
    t_wall0 = time.monotonic()
    stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    out = Path(config.out) if config.out else Path("runs") / f"fleet-{len(config.feeders)}-{stamp}"
    members = [_prepare(config, entry, out) for entry in config.feeders]
    ids = [mb.feeder_id for mb in members]
    dupes = sorted({i for i in ids if ids.count(i) > 1})
    if dupes:
        raise LaunchError(f"feeder id(s) {', '.join(dupes)} appear more than once: give each entry its own id")
    settings = {}
    for mb in members:
        mb.out.mkdir(parents=True, exist_ok=True)
        s = case_agent_settings(mb.run.case, mb.feeder_id, mb.run.agent)
        if s is not None:
            from regression.model import read_model

            if mb.dm.meter:  # the only meters whose readings the agent takes
                s = msgspec.structs.replace(s, meters=tuple(mb.dm.meter))
            read_model(mb.model, expect_fingerprint=mb.dm.fingerprint())
            shutil.copyfile(mb.model, mb.out / "model.json")
        settings[mb.feeder_id] = s
    security_dir = _security(config, members)
    steps = int(round(config.days * 1440))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    children: list[_Child] = []
    recorder: _RecorderSupervisor | None = None
    mcap_path = out / "session.mcap"
    probe: CrossFeederProbe | None = None
    prober: _Prober | None = None
    t_run0 = time.monotonic()
    try:
        with _open_router(endpoint, security_dir, ids) as session:
            if config.record:
                rec_args = ["--keys", f"{keys.ROOT}/**", "--connect", endpoint,
                            *(["--secure-dir", security_dir] if security_dir else ["--insecure"])]
                recorder = _RecorderSupervisor(lambda path: ["record", "--out", str(path), *rec_args], mcap_path,
                                               out, config.recorder_restarts_max)
                children.append(recorder.child)
                probe_pub = session.declare_publisher(keys.sim_status(ids[0]))
                if not wait_for(lambda: has_subscribers(probe_pub), 30.0):
                    raise LaunchError(f"the recorder did not subscribe within 30 s:\n{_tail(out / 'recorder.log')}")
                probe_pub.undeclare()
            agents = LivelinessWatcher(session, f"{keys.ROOT}/*/alive/agent/*")
            for mb in members:
                s = settings[mb.feeder_id]
                if s is not None:
                    mb.agent = _spawn("agent", ["agent", "--model", str(mb.out / "model.json"),
                                                *agent_settings_args(s), "--summary-out",
                                                str(mb.out / "agent-summary.json"), "--connect", endpoint,
                                                *mb.connect], mb.out)
                    children.append(mb.agent)
            expected = [keys.alive(mb.feeder_id, "agent", "agent") for mb in members if mb.agent is not None]
            if not wait_for(lambda: all(agents.is_alive(k) for k in expected), 60.0 + 10.0 * len(expected)):
                late = [k for k in expected if not agents.is_alive(k)]
                raise LaunchError(f"agents not up in time: {', '.join(late)}")
            for mb in members:
                args = bridge_args(mb.run, mb.dm_path, mb.feeder_id, start_text, steps, settings[mb.feeder_id],
                                   mb.out / "bridge-summary.json", [])
                mb.bridge = _spawn("bridge", [*args, "--own-commands-only", "--connect", endpoint, *mb.connect],
                                   mb.out)
                children.append(mb.bridge)
            _log(f"{len(members)} feeders on {endpoint}: {', '.join(ids)}")
            prober = (_Prober.create(session, members, endpoint) if security_dir and config.probe_cross_feeder
                      else None)
            done: set[str] = set()
            while len(done) < len(members):
                restarted = recorder.check() if recorder is not None else None
                if restarted is not None:
                    children.append(restarted)
                for mb in members:
                    for child in (mb.agent, mb.bridge):
                        code = None if child is None else child.proc.poll()
                        if child is None or code is None or (child is mb.bridge and code == 0):
                            continue
                        if child is mb.agent and mb.feeder_id in done:
                            continue
                        raise LaunchError(f"{mb.feeder_id}: {child.name} (pid {child.proc.pid}) exited with "
                                          f"{code}:\n{_tail(mb.out / f'{child.name}.log')}")
                    if mb.bridge is not None and mb.bridge.proc.poll() == 0 and mb.feeder_id not in done:
                        done.add(mb.feeder_id)
                        _log(f"{mb.feeder_id} finished ({len(done)}/{len(members)}, "
                             f"{time.monotonic() - t_run0:.0f} s)")
                if prober is not None:
                    prober.step()
                time.sleep(0.2)
            if prober is not None:
                probe = prober.result()
            for child in children:
                _stop(child)
    finally:
        if prober is not None:
            prober.close()
        for child in children:
            _stop(child)
    wall_s = time.monotonic() - t_run0
    if recorder is not None:
        recorder.finish()
    check = check_recording(mcap_path, ids) if config.record else None
    rows = [_row(mb, settings[mb.feeder_id] is not None, check.decision_s.get(mb.feeder_id) if check else None)
            for mb in members]
    summary = FleetSummary(feeders=rows, days=config.days, start=start_text, wall_s=round(wall_s, 2),
                           secure=config.secure, out_dir=str(out),
                           prepare_s=round(t_run0 - t_wall0, 2),
                           recording=str(mcap_path) if config.record else None,
                           recorded_messages=check.messages if check else 0,
                           messages_checked=check.checked if check else 0,
                           crossing_messages=check.crossing if check else 0,
                           foreign_topics=check.foreign_topics if check else [], probe=probe,
                           wrong_feeder_acks=check.wrong_feeder_acks if check else {})
    (out / "fleet-summary.json").write_bytes(msgspec.json.format(msgspec.json.encode(summary), indent=2))
    from cvvc.fleet_report import render_fleet

    (out / "fleet.md").write_text(render_fleet(summary))
    return summary


def _row(mb: _Member, has_agent: bool, decision_s: list[float] | None) -> FeederRow:
    bridge = _read_summary(mb.out / "bridge-summary.json", BridgeSummary, "bridge")
    agent = _read_summary(mb.out / "agent-summary.json", AgentSummary, "agent") if has_agent else None
    final = bridge.metrics
    if final is None:
        raise LaunchError(f"{mb.feeder_id}: the bridge finished without final metrics:\n"
                          f"{_tail(mb.out / 'bridge.log')}")

    def ms(v: float | None) -> float | None:
        return None if v is None else round(v * 1e3, 2)

    return FeederRow(
        feeder_id=mb.feeder_id, feeder=str(mb.dm_path), case=mb.run.case, year_seed=mb.run.year_seed,
        steps=bridge.steps, decisions=agent.decisions if agent else 0, holds=agent.holds if agent else 0,
        soft=agent.soft if agent else 0, decision_p50_ms=percentile_ms(decision_s, 50),
        decision_p99_ms=percentile_ms(decision_s, 99), round_trip_p50_ms=ms(bridge.round_trip_p50_s),
        round_trip_p99_ms=ms(bridge.round_trip_p99_s), lockstep_misses=bridge.lockstep_misses, nvv=final.nvv,
        mvvm_pu=final.mvvm_pu, ntc=final.ntc, agent_refused=sum(agent.rejected.values()) if agent else 0,
        bridge_rejected=sum(bridge.rejected.values()), bridge_wall_s=bridge.wall_s, out_dir=str(mb.out),
        integrity=run_integrity(agent, bridge, {}, step_s=mb.dm.feeder.step_s,
                                control_period_s=mb.dm.feeder.control_period_s))


class _Prober:
    """Secure mode: as soon as the target feeder's devices publish, put one command on its command key with the
    sender feeder's agent certificate, then watch (inside the router, where the policy does not apply) whether it
    was forwarded or acked, until the target acked three more commands of its own agent (or the fleet ended).

    ``create`` picks the sender (the first feeder with an agent) and the target (the next feeder with an agent
    and a PV plant) and opens the sender's session, or returns None when there are no such two. The probe sets
    0 kvar (unity power factor, the plants' own default) with ``seq`` 0: one that got through changes nothing.
    """

    _CMD_ID = "cross-feeder-probe"

    @classmethod
    def create(cls, session, members: list[_Member], endpoint: str) -> _Prober | None:
        """A prober of ``members`` on the router ``session``, or None (logged) when the fleet has no pair."""
        with_agent = [mb for mb in members if mb.agent is not None]
        targets = [mb for mb in with_agent[1:] if mb.pv_ids]
        if not with_agent or not targets:
            _log("probe skipped: it needs two feeders with agents, the second with a PV plant")
            return None
        return cls(session, with_agent[0], targets[0], endpoint)

    def __init__(self, session, sender: _Member, target: _Member, endpoint: str) -> None:
        import zenoh

        from schemas import keys
        from schemas.bus import BusConfig, zenoh_config

        self._sender, self._target = sender, target
        self._lock = threading.Lock()
        self._acks_after: int | None = None  # None until the probe was put
        self._seen_cmd = self._acked = 0
        self._head_t_ns = 0
        self._t_put = 0.0
        self._done: CrossFeederProbe | None = None
        self._key = keys.cmd(target.feeder_id, "pv", target.pv_ids[0])
        fid = target.feeder_id
        self._subs = [session.declare_subscriber(keys.cmd(fid, "pv", "*"), self._on_cmd),
                      session.declare_subscriber(f"{keys.ROOT}/{fid}/ack/**", self._on_ack),
                      session.declare_subscriber(keys.meas_head(fid), self._on_head)]
        bus = BusConfig(connect=(endpoint,), tls_dir=sender.connect[1], role="agent")  # the sender's certificate
        self._client: zenoh.Session | None = None
        try:
            self._client = zenoh.open(zenoh_config(bus))
        except Exception as e:  # zenoh raises ZError, a plain Exception subclass
            raise LaunchError(f"probe: cannot open a session with {sender.feeder_id}'s agent certificate: {e}") from e
        self._pub = self._client.declare_publisher(self._key, congestion_control=zenoh.CongestionControl.BLOCK)

    def _on_cmd(self, sample) -> None:
        if self._CMD_ID.encode() in sample.payload.to_bytes():
            with self._lock:
                self._seen_cmd += 1

    def _on_head(self, sample) -> None:
        try:
            t = msgspec.json.decode(sample.payload.to_bytes(), type=m.HeadFrame).t_ns
        except (msgspec.DecodeError, msgspec.ValidationError):
            return
        with self._lock:
            self._head_t_ns = self._head_t_ns or t

    def _on_ack(self, sample) -> None:
        try:
            ack = msgspec.json.decode(sample.payload.to_bytes(), type=m.Ack)
        except (msgspec.DecodeError, msgspec.ValidationError):
            return
        with self._lock:
            if ack.cmd_id == self._CMD_ID:
                self._acked += 1
            elif self._acks_after is not None:
                self._acks_after += 1

    def step(self) -> None:
        """Put the probe at the target's first head frame; finish after 3 more own acks and 2 s (or 60 s)."""
        if self._done is not None:
            return
        with self._lock:
            t_ns, after = self._head_t_ns, self._acks_after
        if after is None and t_ns > 0:
            cmd = m.PvCommand(t_ns=t_ns, seq=0, source="probe", cmd_id=self._CMD_ID, in_reply_to=0,
                              valid_until_t_ns=t_ns + 600 * 10**9, plant_id=self._target.pv_ids[0], q_kvar=0.0)
            with self._lock:
                self._acks_after = 0
            self._pub.put(msgspec.json.encode(cmd))
            self._t_put = time.monotonic()
            _log(f"probe: a command with {self._sender.feeder_id}'s agent certificate put on {self._key}")
        elif after is not None and ((after >= 3 and time.monotonic() - self._t_put > 2.0)
                                    or time.monotonic() - self._t_put > 60.0):
            self._finish()

    def _finish(self) -> None:
        with self._lock:
            self._done = CrossFeederProbe(sender=self._sender.feeder_id, target=self._target.feeder_id,
                                          key=self._key, reached=self._seen_cmd > 0 or self._acked > 0,
                                          acked=self._acked > 0, target_acks_after=self._acks_after or 0)
        self.close()

    def close(self) -> None:
        """Undeclare the router's subscriptions and close the sender's session (idempotent)."""
        for sub in self._subs:
            sub.undeclare()
        self._subs = []
        if self._client is not None:
            self._client.close()
            self._client = None

    def result(self) -> CrossFeederProbe | None:
        """The probe's outcome (finished now if the fleet ended first), or None if it was never put."""
        if self._done is None and self._acks_after is not None:
            self._finish()
        self.close()
        return self._done
