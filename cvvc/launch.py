"""``cvvc run``: the main job. Feeder, model, one router, then bridge, agent and recorder as processes.

What it does, in order:

1. the feeder: the embedded rural feeder (generated once into the cache) or ``--feeder``;
2. the model: ``--model``, or the cached model of that feeder and training seed (trained once);
3. a router-mode Zenoh session in this process on a free ``tcp/127.0.0.1`` port;
4. the recorder, the agent (not for the ``none`` / ``local`` baselines) and the bridge as separate
   processes (``subprocess``: a fresh interpreter each, never a fork), connected to the router;
5. progress from the bridge's status frames; the final metrics frame when the bridge finishes;
6. stop the agent and recorder (SIGINT, then SIGKILL after a deadline), every one by its pid;
7. the no-control baseline of the same days, simulated in this process (no bus, the same physics);
8. a summary (printed, ``summary.json``, ``report.md``) with where the MCAP and the model are.

A bridge or agent that dies early stops everything: the others are stopped, the recording finished, exit 1.
The recorder is off the control path: when it dies, the crash is logged, a
new recorder writes the next part of the recording (at most ``recorder_restarts_max`` times), control goes on,
and at the end the parts are joined into one file where each span the recording missed is a ``RecorderGap``
(``recordings.join``); the summary says how many restarts there were.
"""

from __future__ import annotations

import datetime as dt
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Literal, TypeVar

import msgspec

from agent.runtime import AgentSummary
from cvvc.errors import CommandError
from cvvc.integrity import run_integrity
from cvvc.parent_watch import PARENT_ENV
from cvvc.progress import progress_bar
from cvvc.run_report import render_summary, top_reasons
from cvvc.run_summary import RunSummary
from cvvc.run_trace import BASELINE_TRACE, TruthSeries, write_series
from recordings.info import RecorderGap
from schemas import messages as m
from schemas.cache import cache_root, profiles_dir
from schemas.settings import CASES, SECTIONS, AgentOptions, AgentSettings, Case, FieldProtocol, PvProtocol, RunCase
from simulator_bridge.bus.bridge import BridgeSummary

if TYPE_CHECKING:
    from schemas.devicemap import DeviceMap

__all__ = ["CASES", "CASE_AGENT", "CaseAgent", "LaunchError", "RunConfig", "RunSummary", "agent_settings_args",
           "bridge_args", "cached_model_path", "case_agent_settings", "check_mostly_held", "run", "train_model"]

_DEFAULT = RunCase()  # the tree's defaults: RunConfig's
_RENAMED = {("feeder", "map"): "feeder"}  # a case file's (section, key) -> RunConfig's field, where they differ
_AGENT_UP_S = 60.0  # the longest the agent may take to come up; the bridge waits that long for it [s]


class LaunchError(CommandError):
    """A run that cannot start or whose processes failed; the message says which and why."""


class RunConfig(msgspec.Struct, frozen=True, kw_only=True):
    """Everything ``cvvc run`` needs: the case (``schemas.settings.RunCase``, flattened: ``of_case`` and
    ``settings`` convert; every default is the tree's) and what only the launcher sets (progress, checks).
    """

    feeder: str | None = _DEFAULT.feeder.map  # device map TOML or folder; None: embedded rural feeder
    model: str | None = _DEFAULT.feeder.model
    days: float = _DEFAULT.window.days
    start: str = _DEFAULT.window.start  # YYYY-MM-DD[THH:MM] local standard time (UTC-5)
    case: Case = _DEFAULT.case
    realtime: bool = _DEFAULT.bridge.realtime
    speed: float = _DEFAULT.bridge.speed
    out: str | None = _DEFAULT.output.out
    train_seed: int = _DEFAULT.feeder.train_seed
    year_seed: int = _DEFAULT.window.year_seed
    agent: AgentOptions = msgspec.field(default_factory=AgentOptions)  # the agent's options (cases A-D)
    lockstep_timeout_s: float = _DEFAULT.bridge.lockstep_timeout_s
    cache: str | None = _DEFAULT.cache  # cache root; None: schemas.cache.default_cache_root()
    record: bool = _DEFAULT.output.record
    baseline: bool = _DEFAULT.output.baseline
    progress: bool = True
    noise_pmu_pct: float = _DEFAULT.bridge.noise_pmu_pct
    noise_scada_pct: float = _DEFAULT.bridge.noise_scada_pct
    drop_prob: float = _DEFAULT.bridge.drop_prob
    drop_burst_min: float = _DEFAULT.bridge.drop_burst_min
    meas_delay_s: float = _DEFAULT.bridge.meas_delay_s
    clock_skew_s: float = _DEFAULT.bridge.clock_skew_s
    truth_every: int = _DEFAULT.bridge.truth_every
    secure: bool = _DEFAULT.security.secure  # False: --insecure
    ca_dir: str | None = _DEFAULT.security.ca_dir
    progress_label: str = "simulated"  # the progress bar's label (``cvvc evaluate`` names the run)
    # False only for the model-error study (``cvvc evaluate --robustness``): the simulated feeder is deliberately
    # not the one the model was trained on, so its fingerprint differs from the model's.
    check_model_fingerprint: bool = True
    recorder_restarts_max: int = _DEFAULT.output.recorder_restarts_max
    pv_protocol: PvProtocol = _DEFAULT.bridge.pv_protocol
    field_protocol: FieldProtocol = _DEFAULT.bridge.field_protocol
    case_file: str | None = None  # the case file the run was read from (recorded in the summary and report)

    @classmethod
    def of_case(cls, case: RunCase, **launcher: object) -> RunConfig:
        """The run of ``case``; ``launcher``: the fields only the launcher sets (``progress``, ``case_file``...)."""
        flat: dict[str, object] = {"case": case.case, "cache": case.cache, "agent": case.agent}
        for section in SECTIONS:
            if section != "agent":
                for name, value in msgspec.structs.asdict(getattr(case, section)).items():
                    flat[_RENAMED.get((section, name), name)] = value
        return cls(**flat, **launcher)  # type: ignore[arg-type]

    def settings(self) -> RunCase:
        """The case this run runs (what ``of_case`` was given, with the launcher's fields left out)."""
        sections: dict[str, object] = {}
        for section in SECTIONS:
            kind = type(getattr(_DEFAULT, section))
            if section == "agent":
                sections[section] = self.agent
                continue
            sections[section] = kind(**{name: getattr(self, _RENAMED.get((section, name), name))
                                        for name in kind.__struct_fields__})
        return RunCase(case=self.case, cache=self.cache, **sections)  # type: ignore[arg-type]


class CaseAgent(msgspec.Struct, frozen=True, kw_only=True):
    """What a paper case (Table I) sets in the agent; the rest of ``AgentSettings`` is the run's or the default."""

    mode: Literal["taps", "setpoints"]
    correction: bool
    full_visibility: bool = False
    setpoints: bool = False  # the run's regulator band and set-point hold apply (cases C/D)


#: The one table of cases -> agent settings (paper Table I); ``none`` and ``local`` run no agent.
CASE_AGENT: Mapping[Case, CaseAgent | None] = MappingProxyType({
    "A": CaseAgent(mode="taps", correction=False, full_visibility=True),
    "B": CaseAgent(mode="taps", correction=False),
    "C": CaseAgent(mode="setpoints", correction=False, setpoints=True),
    "D": CaseAgent(mode="setpoints", correction=True, setpoints=True),
    "none": None,
    "local": None,
})


def case_agent_settings(case: Case, feeder_id: str, options: AgentOptions | None = None) -> AgentSettings | None:
    """The agent's settings of a case (``CASE_AGENT``) with the run's ``options`` (None: the defaults), or None when
    the case runs no agent.

    What the case fixes wins: the band and the set-point hold apply to cases C/D only (A and B keep the defaults),
    and case A never switches banks (the oracle has no bank terms). The agent process and the recording get these
    settings encoded (``agent_settings_args``).
    """
    row = CASE_AGENT[case]
    if row is None:
        return None
    options = options or AgentOptions()
    fixed: dict[str, object] = {}
    if not row.setpoints:
        fixed.update(bandwidth_v120=_DEFAULT.agent.bandwidth_v120, setpoint_hold=_DEFAULT.agent.setpoint_hold)
    if row.full_visibility:
        fixed.update(control_banks=False)
    settings = AgentSettings(**{**msgspec.structs.asdict(options), **fixed}, feeder_id=feeder_id, mode=row.mode,
                             correction=row.correction, full_visibility=row.full_visibility)
    return msgspec.convert(msgspec.to_builtins(settings), AgentSettings)  # checks the settings' constraints


def agent_settings_args(settings: AgentSettings) -> list[str]:
    """The ``cvvc agent`` flags that hand ``settings`` over to the agent process, encoded."""
    return ["--feeder-id", settings.feeder_id, "--settings", msgspec.json.encode(settings).decode()]


def bridge_args(config: RunConfig, dm_path: Path, feeder_id: str, start_text: str, steps: int,
                agent_settings: AgentSettings | None, summary_path: Path, extra: list[str]) -> list[str]:
    """The ``cvvc bridge`` arguments of a run's feeder (clock, realism, oracle, ``extra``), without the bus flags."""
    clock = (["--realtime", "--speed", str(config.speed)] if config.realtime
             else ["--lockstep", "--timeout-s", str(config.lockstep_timeout_s)])
    realism = []
    if config.noise_pmu_pct:
        realism += ["--noise-pmu-pct", str(config.noise_pmu_pct)]
    if config.noise_scada_pct:
        realism += ["--noise-scada-pct", str(config.noise_scada_pct)]
    if config.drop_prob:
        realism += ["--drop-prob", str(config.drop_prob), "--drop-burst-min", str(config.drop_burst_min)]
    if config.meas_delay_s:
        realism += ["--latency-s", str(config.meas_delay_s / config.speed)]  # wall s at --speed
    if config.clock_skew_s:
        realism += ["--clock-skew-s", str(config.clock_skew_s)]
    realism += [*extra, "--truth-every", str(config.truth_every), "--cache-dir", str(profiles_dir(config.cache))]
    return ["bridge", "--feeder", str(dm_path), "--feeder-id", feeder_id, "--start", start_text,
            "--steps", str(steps), "--year-seed", str(config.year_seed),
            "--pv-local", "volt_var" if config.case == "local" else "unity",
            *(["--oracle"] if agent_settings is not None and agent_settings.full_visibility else []),
            "--summary-out", str(summary_path), *clock, *realism]


def _log(msg: str) -> None:
    print(f"[cvvc run] {msg}", file=sys.stderr, flush=True)


def prepare_feeder_and_model(config: RunConfig) -> tuple[Path, Path]:
    """Resolve (generating or training once, cached) the device map and the model.

    A case that runs no agent (``none``, ``local``) trains nothing: the model path is then where the cached
    model would be, and may not exist.
    """
    from schemas.devicemap import load_device_map, resolve_device_map_path
    from simulator_bridge.rural.default_feeder import ensure_default_feeder

    cache = cache_root(config.cache)
    dm_path = resolve_device_map_path(config.feeder) if config.feeder else ensure_default_feeder(cache)
    if config.model:
        return dm_path, Path(config.model)
    model_path = cached_model_path(load_device_map(dm_path), config.train_seed, cache)
    if not model_path.is_file() and CASE_AGENT[config.case] is not None:  # cases without an agent need none
        train_model(dm_path, model_path, train_seed=config.train_seed, cache=cache, progress=config.progress)
    return dm_path, model_path


def cached_model_path(dm: DeviceMap, train_seed: int, cache: Path) -> Path:
    """Where ``cvvc run`` keeps the model of a feeder (its name and fingerprint), a training year and the training
    revision in the cache root ``cache``.
    """
    from training.train import TRAINING_REVISION

    return cache / "models" / f"{dm.feeder.name}-{dm.fingerprint()}-y{train_seed}-r{TRAINING_REVISION}.json"


def train_model(dm_path: Path, model_path: Path, *, train_seed: int, cache: Path, progress: bool) -> Path:
    """Train the model ``cvvc run`` uses for the feeder of ``dm_path`` (guided selection, the feeder's default
    feature set) on the profile year ``train_seed`` and write it to ``model_path`` (whole or not at all).
    """
    from regression.model import write_model
    from schemas.devicemap import load_device_map
    from schemas.settings import TrainingOptions
    from training.extended import default_feature_options
    from training.train import train

    dm = load_device_map(dm_path)
    _log(f"training a model for {dm.feeder.name} (year seed {train_seed}) into {model_path}")
    t0 = time.monotonic()
    options = TrainingOptions(year_seed=train_seed, features=default_feature_options(dm))
    result = train(dm_path, options, cache_dir=cache / "profiles", progress=progress)
    model_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = model_path.with_name(model_path.name + ".tmp")
    write_model(result.model, tmp)
    os.replace(tmp, model_path)
    _log(f"model trained in {time.monotonic() - t0:.1f} s: {model_path}")
    return model_path


@dataclass
class _Child:
    name: str
    proc: subprocess.Popen[bytes]
    essential: bool


def _spawn(name: str, args: list[str], log_dir: Path, *, essential: bool = True) -> _Child:
    log = open(log_dir / f"{name}.log", "wb")  # noqa: SIM115  (closed with the process)
    proc = subprocess.Popen([sys.executable, "-m", "cvvc", *args], stdout=log, stderr=subprocess.STDOUT,
                            stdin=subprocess.DEVNULL, env=dict(os.environ, **{PARENT_ENV: str(os.getpid())}))
    log.close()
    return _Child(name, proc, essential)


def _stop(child: _Child, timeout_s: float = 15.0, *, signalled: bool = False) -> int:
    """Stop one child by its pid: SIGINT (unless ``signalled``: sent already), then SIGKILL after ``timeout_s``.
    Returns its exit status.
    """
    if child.proc.poll() is None and not signalled:
        try:
            child.proc.send_signal(signal.SIGINT)
        except ProcessLookupError:
            pass
    if child.proc.poll() is None:
        try:
            child.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            _log(f"{child.name} (pid {child.proc.pid}) did not stop in {timeout_s:.0f} s: killing it")
            child.proc.kill()
            child.proc.wait(timeout=10)
    return int(child.proc.returncode)


def _stop_all(children: list[_Child]) -> None:
    """Stop every child: SIGINT to all first, so they finish (a recorder its file) side by side, then ``_stop``."""
    signalled = set()
    for child in children:
        if child.proc.poll() is None:
            try:
                child.proc.send_signal(signal.SIGINT)
                signalled.add(child.proc.pid)
            except ProcessLookupError:
                pass
    for child in children:
        _stop(child, signalled=child.proc.pid in signalled)


class _RecorderSupervisor:
    """The run's recorder, restarted when it dies: each recorder writes its own part of the recording.

    ``check`` (called by the launcher's loop) notices a dead recorder, logs why and starts the next one, at most
    ``max_restarts`` times; ``finish`` joins the parts into the first part's path, with the gaps between them.
    """

    def __init__(self, args_for: Callable[[Path], list[str]], path: Path, log_dir: Path, max_restarts: int) -> None:
        self._args_for, self._log_dir, self._max = args_for, log_dir, max_restarts
        self.path = path
        self.parts: list[Path] = [path]
        self.reasons: list[str] = []
        self.gave_up = False
        self.child = _spawn("recorder", args_for(path), log_dir, essential=False)

    @property
    def restarts(self) -> int:
        return len(self.parts) - 1

    def check(self) -> _Child | None:
        """Restart the recorder if it died; returns the new child (to be stopped with the others), or None."""
        code = self.child.proc.poll()
        if code is None or self.gave_up:
            return None
        how = f"killed by signal {-code}" if code < 0 else f"exited with {code}"
        last = _tail(self._log_dir / f"{self.child.name}.log", 1)
        reason = f"the recorder (pid {self.child.proc.pid}) {how}" + (f": {last}" if last else "")
        if self.restarts >= self._max:
            self.gave_up = True
            _log(f"{reason}; it died {self.restarts + 1} times: recording stops here, control goes on")
            return None
        n = len(self.parts)
        part = self.path.with_name(f"{self.path.stem}.r{n}{self.path.suffix}")
        _log(f"{reason}; restarting it ({n} of at most {self._max}) into {part.name}; control goes on")
        self.parts.append(part)
        self.reasons.append(reason)
        self.child = _spawn(f"recorder.r{n}", self._args_for(part), self._log_dir, essential=False)
        return self.child

    def finish(self) -> list[RecorderGap]:
        """After every recorder stopped: join the parts into ``path`` (the parts are removed), so the recording
        is one finished file even when the last recorder died; the gaps. Nothing to do when none died.
        """
        if not self.reasons and not self.gave_up:
            return []
        from recordings.join import join_parts

        joined = self.path.with_name(f"{self.path.stem}.joined{self.path.suffix}")
        result = join_parts(self.parts, self.reasons, joined)
        for part in self.parts:
            part.unlink(missing_ok=True)
        os.replace(joined, self.path)
        _log(f"recording joined from {len(self.parts)} parts: {result.messages} messages, "
             f"{len(result.gaps)} gap(s) recorded on {len(result.gaps) and 'cvvc.recorder_gap'}")
        return result.gaps


def _tail(path: Path, n: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return ""


def run(config: RunConfig) -> RunSummary:
    """Run one case end to end; see the module docstring."""
    from schemas import keys
    from schemas.bus import BusConfig, Inbox, LivelinessWatcher, free_port, has_subscribers, open_session, wait_for
    from schemas.devicemap import load_device_map

    if config.case not in CASES:
        raise LaunchError(f"unknown case {config.case!r}; choose one of {', '.join(CASES)}")
    try:
        start = dt.datetime.fromisoformat(config.start)
        start_text = start.isoformat(timespec="minutes")
    except ValueError as e:
        raise LaunchError(f"--start {config.start!r} is not a date (YYYY-MM-DD or YYYY-MM-DDTHH:MM)") from e
    if not 0 < config.days <= 366:
        raise LaunchError(f"--days {config.days} must be in (0, 366]")
    if config.meas_delay_s and not config.realtime:
        raise LaunchError("--meas-delay-s needs --realtime (in lockstep the bridge waits for each decision)")
    from cvvc import field_protocol as fdp
    from cvvc import pv_protocol as pvp

    try:
        pvp.check_pv_protocol(config.pv_protocol, noise_scada_pct=config.noise_scada_pct, drop_prob=config.drop_prob,
                              meas_delay_s=config.meas_delay_s, clock_skew_s=config.clock_skew_s,
                              secure=config.secure)
        fdp.check_field_protocol(config.field_protocol, case=config.case, noise_scada_pct=config.noise_scada_pct,
                                 drop_prob=config.drop_prob, meas_delay_s=config.meas_delay_s,
                                 clock_skew_s=config.clock_skew_s)
    except CommandError as e:
        raise LaunchError(str(e)) from e

    t_wall0 = time.monotonic()
    dm_path, model_path = prepare_feeder_and_model(config)
    dm = load_device_map(dm_path)
    feeder_id = dm.feeder.name
    fingerprint = dm.fingerprint()
    try:  # the feeder's regulators and banks, as their DNP3 adapters describe them (a bank of several steps refused)
        dnp3_devices = fdp.dnp3_devices(dm_path) if config.field_protocol == "dnp3" else ()
    except CommandError as e:
        raise LaunchError(str(e)) from e
    agent_settings = case_agent_settings(config.case, feeder_id, config.agent)
    if agent_settings is not None and dm.meter:  # the only meters whose readings the agent takes
        agent_settings = msgspec.structs.replace(agent_settings, meters=tuple(dm.meter))
    if agent_settings is not None and config.check_model_fingerprint:
        from regression.model import read_model

        read_model(model_path, expect_fingerprint=fingerprint)  # refuse a model of another feeder early

    stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    out = Path(config.out) if config.out else Path("runs") / f"{feeder_id}-{config.case}-{stamp}"
    out.mkdir(parents=True, exist_ok=True)
    kept_model = out / "model.json"
    if agent_settings is not None:
        shutil.copyfile(model_path, kept_model)
    mcap_path = out / "session.mcap"
    steps = int(round(config.days * 1440))

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    connect = ["--connect", endpoint]
    security_dir = _security_dir(config)
    connect += ["--secure-dir", security_dir] if security_dir else ["--insecure"]
    children: list[_Child] = []
    endpoints: dict[str, str] = {}  # sunspec: plant -> its inverter's Modbus endpoint
    dnp3_endpoints: dict[str, str] = {}  # dnp3: regulator or bank -> its outstation's endpoint
    # The run's figures come from the processes the launcher started, never from the bus, where any session
    # could publish a metrics frame or a decision: each writes its own summary.
    agent_summary_path, bridge_summary_path = out / "agent-summary.json", out / "bridge-summary.json"
    agent_summary: AgentSummary | None = None
    recorder: _RecorderSupervisor | None = None
    try:
        with open_session(BusConfig(mode="router", listen=(endpoint,), tls_dir=security_dir,
                                    role="router" if security_dir else None)) as session:
            inbox = Inbox(maxsize=100_000)
            inbox.subscribe(session, keys.sim_status(feeder_id), m.BridgeStatus)  # progress only
            if config.record:
                recorder_args = ["--keys", f"cvvc/{feeder_id}/**", "--feeder-fingerprint", fingerprint,
                                 *_recorder_agent_args(agent_settings, kept_model), *connect]
                recorder = _RecorderSupervisor(lambda path: ["record", "--out", str(path), *recorder_args],
                                               mcap_path, out, config.recorder_restarts_max)
                children.append(recorder.child)
                probe = session.declare_publisher(keys.sim_status(feeder_id))
                if not wait_for(lambda: has_subscribers(probe), 30.0):
                    raise LaunchError(f"the recorder did not subscribe within 30 s:\n{_tail(out / 'recorder.log')}")
                probe.undeclare()
            if agent_settings is not None:
                children.append(_spawn("agent", [
                    "agent", "--model", str(kept_model), *agent_settings_args(agent_settings),
                    "--summary-out", str(agent_summary_path), *connect], out))
            endpoints = pvp.sunspec_endpoints(dm, free_port) if config.pv_protocol == "sunspec" else {}
            dnp3_endpoints = fdp.dnp3_endpoints(dnp3_devices, free_port)
            if set(endpoints) & set(dnp3_endpoints):
                raise LaunchError(f"{sorted(set(endpoints) & set(dnp3_endpoints))} name both a PV plant and a "
                                  "regulator or bank; each adapter is named by its device's id: rename one in the "
                                  "device map")
            adapted = {keys.alive(feeder_id, "pv", pid): pid for pid in endpoints}  # token -> the adapter's name
            for pid, ep in endpoints.items():  # up before the bridge: it waits for their tokens, then steps
                children.append(_spawn(f"adapter.{pid}", pvp.adapter_args(
                    dm, feeder_id, pid, ep, volt_var=config.case == "local", connect=connect,
                    summary_out=str(out / f"adapter.{pid}-summary.json")), out))
            for device in dnp3_devices:
                did = device.device_id
                adapted[keys.alive(feeder_id, device.kind, did)] = did
                children.append(_spawn(f"adapter.{did}", fdp.adapter_args(
                    dm, feeder_id, device, dnp3_endpoints[did], connect=connect,
                    summary_out=str(out / f"adapter.{did}-summary.json")), out))
            watch = LivelinessWatcher(session, f"{keys.ROOT}/{feeder_id}/alive/**") if adapted else None
            if watch is not None and not wait_for(lambda: all(watch.is_alive(k) for k in adapted), 60.0):
                down = [name for k, name in adapted.items() if not watch.is_alive(k)]
                raise LaunchError(f"the field-protocol adapters {down} did not come up within 60 s:\n"
                                  f"{_tail(out / f'adapter.{down[0]}.log')}")
            bridge = _spawn("bridge", [*bridge_args(config, dm_path, feeder_id, start_text, steps, agent_settings,
                                                    bridge_summary_path, [*pvp.bridge_args(endpoints),
                                                                          *fdp.bridge_args(dnp3_endpoints)]),
                                       *connect,
                                       *(["--wait-agent-s", str(_AGENT_UP_S)] if agent_settings is not None else [])],
                            out)
            children.append(bridge)
            if agent_settings is not None:  # the bridge compiles and loads while the agent starts, and waits for it
                agent_key = keys.alive(feeder_id, "agent", "agent")
                agents = LivelinessWatcher(session, agent_key)
                if not wait_for(lambda: agents.is_alive(agent_key) or bridge.proc.poll() is not None, _AGENT_UP_S):
                    raise LaunchError(f"the agent did not come up within {_AGENT_UP_S:.0f} s:\n"
                                      f"{_tail(out / 'agent.log')}")

            bar = progress_bar(steps, enabled=config.progress, desc=config.progress_label, unit="min")
            while True:
                restarted = recorder.check() if recorder is not None else None
                if restarted is not None:
                    children.append(restarted)
                for child in children:
                    code = child.proc.poll()
                    if code is not None and child is not bridge and child.essential:
                        raise LaunchError(f"{child.name} (pid {child.proc.pid}) exited with {code}:\n"
                                          f"{_tail(out / f'{child.name}.log')}")
                item = inbox.get(timeout_s=0.2)
                while item is not None:
                    if isinstance(item.msg, m.BridgeStatus):
                        bar.n = item.msg.step
                        bar.refresh()
                    item = inbox.get(timeout_s=0.0)
                if bridge.proc.poll() is not None:
                    break
            bar.close()
            if bridge.proc.returncode != 0:
                raise LaunchError(f"the bridge exited with {bridge.proc.returncode}:\n{_tail(out / 'bridge.log')}")
            _stop_all([child for child in children if child is not bridge])
    finally:
        _stop_all(children)
    wall_s = time.monotonic() - t_wall0
    bridge_summary = _read_summary(bridge_summary_path, BridgeSummary, "bridge")
    final = bridge_summary.metrics
    if final is None:
        raise LaunchError(f"the bridge finished without final metrics:\n{_tail(out / 'bridge.log')}")
    if agent_settings is not None:
        agent_summary = _read_summary(agent_summary_path, AgentSummary, "agent")
    gaps = recorder.finish() if recorder is not None else []
    links = {did: _read_summary(out / f"adapter.{did}-summary.json", m.LinkStatus, f"adapter.{did}")
             for did in [*endpoints, *dnp3_endpoints]}
    integrity = run_integrity(agent_summary, bridge_summary, links, step_s=dm.feeder.step_s,
                              control_period_s=dm.feeder.control_period_s)

    baseline = None
    if config.baseline and config.case != "none":
        _log("simulating the no-control baseline of the same days")
        baseline = no_control_baseline(dm_path, start, steps, config.year_seed, cache_root(config.cache),
                                       trace_path=out / BASELINE_TRACE, progress=config.progress)
    live = bridge_summary.live_accuracy
    if live is not None and agent_settings is not None:
        live = msgspec.structs.replace(live, promised_miss_rate=promised_miss_rate(kept_model))
    summary = RunSummary(
        feeder=str(dm_path), feeder_id=feeder_id, case=config.case, start=start_text, days=config.days,
        steps=steps, wall_s=round(wall_s, 2), metrics=final, baseline=baseline,
        lockstep_misses=bridge_summary.lockstep_misses, follow_up_misses=bridge_summary.follow_up_misses,
        follow_ups=agent_summary.follow_ups if agent_summary else 0,
        measured_steps_v120=dict(agent_summary.measured_steps_v120) if agent_summary else {},
        bought=agent_summary.bought if agent_summary else 0,
        decisions=agent_summary.decisions if agent_summary else 0, out_dir=str(out),
        recording=str(mcap_path) if config.record else None,
        model=str(kept_model) if agent_settings is not None else None,
        holds=agent_summary.holds if agent_summary else 0, soft=agent_summary.soft if agent_summary else 0,
        tolerated=agent_summary.tolerated if agent_summary else 0,
        reasons=dict(agent_summary.reasons) if agent_summary else {},
        decision_ms=dict(agent_summary.decision_ms) if agent_summary else {},
        decision_cpu_ms=dict(agent_summary.decision_cpu_ms) if agent_summary else {},
        recorder_restarts=recorder.restarts if recorder is not None else 0, recording_gaps=gaps,
        recorder_gave_up=recorder.gave_up if recorder is not None else False, pv_protocol=config.pv_protocol,
        sunspec_frame_misses=bridge_summary.sunspec_frame_misses, field_protocol=config.field_protocol,
        dnp3_frame_misses=bridge_summary.dnp3_frame_misses, live=live, secure=config.secure,
        case_file=config.case_file, settings=config.settings(), integrity=integrity)
    (out / "summary.json").write_bytes(msgspec.json.format(msgspec.json.encode(summary), indent=2))
    (out / "report.md").write_text(render_summary(summary, dm))
    check_mostly_held(summary)
    return summary


def promised_miss_rate(model_path: Path) -> float | None:
    """The miscoverage a model's calibrated bounds promise (``bounds.alpha``); None without bounds."""
    from regression.model import read_model

    bounds = read_model(model_path).bounds
    return None if bounds is None else float(bounds.alpha)


def _security_dir(config: RunConfig) -> str | None:
    """The role certificates every child presents (the router enforces the policy), issued on first use from the CA
    of ``config.ca_dir`` (default ``<cache>/ca``, created without a question); None with ``--insecure`` (warned).
    """
    from schemas.cache import ca_dir, security_dir
    from schemas.security import INSECURE_WARNING, ensure_local_security

    if not config.secure:
        _log(f"WARNING {INSECURE_WARNING}")
        return None
    path = security_dir(config.cache)
    written = ensure_local_security(path, ca_dir=config.ca_dir or ca_dir(config.cache))
    if written:
        _log(f"certificates issued into {path} (the CA in {config.ca_dir or ca_dir(config.cache)})")
    return str(path)


def check_mostly_held(summary: RunSummary) -> None:
    """Raise ``LaunchError`` when most of a run's decisions were ``hold``: such a run did not control the feeder,
    and its metrics must not read as a result.
    """
    if summary.decisions and 2 * summary.holds > summary.decisions:
        raise LaunchError(f"{summary.holds} of {summary.decisions} decisions were 'hold' (no command sent): the run "
                          f"did not control the feeder; most frequent reasons: {top_reasons(summary.reasons)} "
                          f"(the whole summary: {Path(summary.out_dir) / 'summary.json'})")


_S = TypeVar("_S", AgentSummary, BridgeSummary, m.LinkStatus)


def _read_summary(path: Path, kind: type[_S], who: str) -> _S:
    """The JSON summary a child process wrote at exit, decoded, or a clear error."""
    try:
        return msgspec.json.decode(path.read_bytes(), type=kind)
    except (OSError, msgspec.DecodeError, msgspec.ValidationError) as e:
        raise LaunchError(f"the {who} left no readable summary ({path}: {e}):\n"
                          f"{_tail(path.parent / f'{who}.log')}") from e


def _recorder_agent_args(settings: AgentSettings | None, model: Path) -> list[str]:
    if settings is None:
        return []
    return ["--model", str(model), "--agent-settings", msgspec.json.encode(settings).decode()]


def no_control_baseline(dm_path: Path, start: dt.datetime, steps: int, year_seed: int, cache: Path, *,
                        trace_path: Path | None = None, progress: bool = False) -> m.MetricsFrame:
    """The same days with no central control (regulators local, PV unity PF), simulated in-process: its metrics in
    the run's own form (the bridge's final ``MetricsFrame``), and its plotted series in ``trace_path`` (``.npz``,
    ``cvvc.run_trace``) when given.
    """
    from schemas.devicemap import load_device_map
    from simulator_bridge.bus.publishing import metrics_frame
    from simulator_bridge.opendss.engine import FeederEngine
    from simulator_bridge.simulation.metrics_stream import MetricsAccumulator, zone_phase_nodes
    from simulator_bridge.simulation.qsts import Qsts
    from training.train import load_profiles

    dm = load_device_map(dm_path)
    engine = FeederEngine(dm)
    profiles = load_profiles(dm, engine, seed=year_seed, cache_dir=cache / "profiles")
    first = int((start - dt.datetime(start.year, 1, 1)).total_seconds()) // dm.feeder.step_s
    sim = Qsts(engine, profiles, start_step=first, pv_local="unity")
    acc = MetricsAccumulator.for_feeder(dm, engine)
    series = TruthSeries()
    judged = zone_phase_nodes(engine)  # the envelope over the voltages judged, as the metrics (no neutral)
    bar = progress_bar(steps, enabled=progress, desc="no control", unit="min")
    for _ in range(steps):
        r = sim.step()
        acc.update(r.v_pu, r.tap_changes, r.pv_q_kvar, r.cap_switches)
        series.add(r.t_ns, r.v_pu if judged is None else r.v_pu[judged], r.taps, r.pv_q_kvar, r.cap_states)
        bar.update(1)
    bar.close()
    result = acc.result()
    if trace_path is not None:
        lo, hi = dm.feeder.judged_limits_pu
        write_series(trace_path, series.trace(regulator_ids=tuple(engine.regulator_ids), pv_ids=tuple(engine.pv_ids),
                                              limits_pu=(float(lo), float(hi)),
                                              capacitor_ids=tuple(result.capacitor_ids)))
    return metrics_frame(result, t_ns=profiles.t_ns(first + steps), seq=1, feeder_id=dm.feeder.name,
                         start_t_ns=profiles.t_ns(first), final=True)
