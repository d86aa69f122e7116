"""Soak benchmark: a simulated month in lockstep, as ``cvvc run`` runs it, watching memory and losses.

``bench_soak(days=30, feeder=None)`` prepares the feeder and model as ``cvvc run`` does
(``cvvc.launch.prepare_feeder_and_model``; the embedded rural feeder by default), opens a router in this
process and starts the recorder, the case D agent and the lockstep bridge as ``python -m cvvc`` processes. It
samples ``VmRSS`` and ``VmHWM`` of every process (the three children and this router process) from
``/proc/<pid>/status`` once per simulated hour, and reports:

- memory at *start* (the first sample after one simulated day, or half the run when it is shorter than two
  days, when caches, Zenoh buffers and the profiles are loaded; the sample at the first hour is reported
  too) and at the *end* (the last sample before the bridge finished), with the growth ``end / start - 1``
  of ``VmRSS`` and of ``VmHWM`` (goal: < 10 %);
- dropped or late frames (goal: 0 in lockstep): the bridge's lockstep misses and skips and dropped frames,
  control steps without a decision, the agent's ``queue_full`` and ``stale`` rejections (and every other
  rejection kind), the recorder's ``dropped_queue_full``.

Run it with ``make bench`` (``python -m benchmarks --only soak``) or ``python -m benchmarks.bench_soak [DAYS]``.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import msgspec

from benchmarks.results import MemoryKib, ProcessMemory, SoakBench, SoakLosses, to_json
from schemas.cache import profiles_dir
from schemas.errors import CvvcError

__all__ = ["SoakError", "bench_soak", "proc_memory_kib", "run_folder", "stop_process"]

_NS = 1_000_000_000
_GOAL_GROWTH = 0.10


class SoakError(CvvcError):
    """The soak run could not start or one of its processes died; the message names it and its log."""


class _Sample(msgspec.Struct, frozen=True, kw_only=True):
    """Memory of every process at one simulated step (``kib``: by process name)."""

    step: int
    wall_s: float
    kib: dict[str, MemoryKib]


def proc_memory_kib(pid: int) -> MemoryKib:
    """``VmHWM`` and ``VmRSS`` of process ``pid`` from ``/proc/<pid>/status`` [KiB] (both None if it is gone)."""
    found: dict[str, int] = {}
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return MemoryKib()
    for line in text.splitlines():
        key = line.split(":", 1)[0]
        if key in ("VmRSS", "VmHWM"):
            found[key] = int(line.split()[1])
    return MemoryKib(vm_hwm_kib=found.get("VmHWM"), vm_rss_kib=found.get("VmRSS"))


def _spawn(name: str, args: list[str], log_dir: Path) -> subprocess.Popen[bytes]:
    with open(log_dir / f"{name}.log", "wb") as log:
        return subprocess.Popen([sys.executable, "-m", "cvvc", *args], stdout=log, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, env={**os.environ, "PYTHONUNBUFFERED": "1"})


def run_folder(out_dir: str | Path | None, prefix: str) -> tuple[Path, tempfile.TemporaryDirectory[str] | None]:
    """The folder a live benchmark writes to: ``out_dir`` (made if absent), else a temporary folder named from
    ``prefix``, returned too so that the caller cleans it up.
    """
    tmp = None if out_dir else tempfile.TemporaryDirectory(prefix=prefix)
    out = Path(tmp.name) if tmp is not None else Path(str(out_dir))
    out.mkdir(parents=True, exist_ok=True)
    return out, tmp


def stop_process(proc: subprocess.Popen[bytes], timeout_s: float = 30.0) -> int:
    """SIGINT ``proc`` (every cvvc process ends cleanly on it), kill it after ``timeout_s``; its exit code."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)
    return int(proc.returncode)


def _growth(start: int | None, end: int | None) -> float | None:
    """``end / start - 1`` rounded to 1e-4, None when either is unknown (or ``start`` is 0)."""
    if not start or end is None:
        return None
    return round(end / start - 1.0, 4)


def bench_soak(days: float = 30.0, feeder: str | None = None, *, start: str = "2023-06-01",
               cache: str | None = None, out_dir: str | None = None, lockstep_timeout_s: float = 10.0,
               truth_every: int = 60, year_seed: int = 2) -> SoakBench:
    """Run ``days`` simulated days in lockstep (case D) and return the memory and loss figures (module doc).

    Parameters
    ----------
    days : simulated days (1-minute steps). feeder : device map (None: the embedded rural feeder).
    start : first simulated day (local standard time). cache : the ``cvvc run`` cache (model, profiles).
    out_dir : where the logs and the recording go (None: a temporary directory, removed afterwards).
    lockstep_timeout_s : the bridge's wait per control step [s]. truth_every : truth frame every N steps
        (hourly by default: a month of every-step truth frames would be gigabytes of recording).
    year_seed : profile seed of the simulated year (2: not the training year, as ``cvvc run``).
    """
    from cvvc.launch import RunConfig, agent_settings_args, case_agent_settings, prepare_feeder_and_model
    from recordings.info import recording_info
    from schemas import keys
    from schemas import messages as m
    from schemas.bus import BusConfig, Inbox, free_port, has_subscribers, open_session, wait_for
    from schemas.devicemap import load_device_map
    from simulator_bridge.bus.bridge import BridgeSummary

    dm_path, model_path = prepare_feeder_and_model(RunConfig(feeder=feeder, cache=cache, progress=False))
    dm = load_device_map(dm_path)
    fid = dm.feeder.name
    steps = int(round(days * 1440))
    per_hour = 60 * 60 // dm.feeder.step_s
    warm_step = min(24 * per_hour, max(steps // 2, 1))
    out, tmp = run_folder(out_dir, "cvvc-soak-")
    mcap = out / "soak.mcap"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs: dict[str, subprocess.Popen[bytes]] = {}
    samples: list[_Sample] = []
    last_agent: m.AgentStatus | None = None
    last_bridge: m.BridgeStatus | None = None
    decisions = 0
    t0 = time.monotonic()
    try:
        with open_session(BusConfig(mode="router", listen=(endpoint,))) as session:
            inbox = Inbox(maxsize=100_000)
            inbox.subscribe(session, keys.sim_status(fid), m.BridgeStatus)
            inbox.subscribe(session, keys.agent_status(fid), m.AgentStatus)
            inbox.subscribe(session, keys.agent_decision(fid), m.Decision)
            procs["recorder"] = _spawn("recorder", ["record", "--out", str(mcap), "--keys", f"cvvc/{fid}/**",
                                                    "--connect", endpoint, "--insecure"], out)
            probe = session.declare_publisher(keys.sim_status(fid))
            if not wait_for(lambda: has_subscribers(probe), 60.0):
                raise SoakError(f"the recorder did not subscribe within 60 s; see {out / 'recorder.log'}")
            probe.undeclare()
            case_d = case_agent_settings("D", fid)
            if case_d is None:
                raise SoakError("case D runs no agent: the case table is broken")
            procs["agent"] = _spawn("agent", ["agent", "--model", str(model_path), *agent_settings_args(case_d),
                                              "--connect", endpoint, "--insecure"], out)
            procs["bridge"] = _spawn("bridge", [
                "bridge", "--feeder", str(dm_path), "--feeder-id", fid, "--start", start, "--steps", str(steps),
                "--year-seed", str(year_seed), "--lockstep", "--timeout-s", str(lockstep_timeout_s),
                "--wait-agent-s", "120", "--truth-every", str(truth_every),
                "--cache-dir", str(profiles_dir(cache)), "--json", "--connect", endpoint, "--insecure"], out)
            next_sample_step = per_hour
            while procs["bridge"].poll() is None:
                for name in ("recorder", "agent"):
                    if procs[name].poll() is not None:
                        raise SoakError(f"the {name} exited with {procs[name].returncode}; see {out / name}.log")
                item = inbox.get(timeout_s=0.5)
                while item is not None:
                    match item.msg:
                        case m.BridgeStatus() as st:
                            last_bridge = st
                            if st.step >= next_sample_step and not st.done:
                                kib = {n: proc_memory_kib(p.pid) for n, p in procs.items()}
                                samples.append(_Sample(step=st.step, wall_s=round(time.monotonic() - t0, 1),
                                                       kib=kib | {"router": proc_memory_kib(os.getpid())}))
                                next_sample_step = st.step + per_hour
                        case m.AgentStatus() as st:
                            last_agent = st
                        case m.Decision():
                            decisions += 1
                    item = inbox.get(timeout_s=0.0)
            wait_for(lambda: not inbox.queue.empty(), 2.0)
            for item in inbox.drain():
                if isinstance(item.msg, m.Decision):
                    decisions += 1
                elif isinstance(item.msg, m.AgentStatus):
                    last_agent = item.msg
                elif isinstance(item.msg, m.BridgeStatus):
                    last_bridge = item.msg
            wall_s = time.monotonic() - t0
            codes = {n: stop_process(p) for n, p in procs.items()}
    finally:
        for p in procs.values():
            stop_process(p)
    log = (out / "bridge.log").read_text(errors="replace")
    try:
        summary = msgspec.json.decode(log[log.rindex("\n{\n") + 1:] if not log.startswith("{") else log,
                                      type=BridgeSummary)
    except (ValueError, msgspec.DecodeError, msgspec.ValidationError) as e:
        raise SoakError(f"the bridge printed no summary (exit {codes.get('bridge')}); see {out / 'bridge.log'}") from e
    info = recording_info(mcap)
    rec_stats = info.metadata.get("cvvc.recorder_stats", {})
    start_sample = next((x for x in samples if x.step >= warm_step), samples[0] if samples else None)
    end_sample = samples[-1] if samples else None
    memory: dict[str, ProcessMemory] = {}
    for name in ("bridge", "agent", "recorder", "router"):
        s0 = start_sample.kib.get(name, MemoryKib()) if start_sample else MemoryKib()
        s1 = end_sample.kib.get(name, MemoryKib()) if end_sample else MemoryKib()
        memory[name] = ProcessMemory(first_hour_kib=samples[0].kib.get(name, MemoryKib()) if samples else MemoryKib(),
                                     start_kib=s0, end_kib=s1, rss_growth=_growth(s0.vm_rss_kib, s1.vm_rss_kib),
                                     hwm_growth=_growth(s0.vm_hwm_kib, s1.vm_hwm_kib))
    rejected = dict(last_agent.rejected) if last_agent else {}
    losses = SoakLosses(
        lockstep_misses=summary.lockstep_misses,
        lockstep_skipped=summary.lockstep_skipped,
        bridge_frames_dropped=summary.frames_dropped,
        control_steps=summary.control_steps,
        decisions_seen=decisions,
        control_steps_without_decision=max(0, summary.control_steps - summary.decisions),
        agent_queue_full=rejected.get("queue_full", 0),
        agent_stale=rejected.get("stale", 0),
        agent_rejected=rejected,
        bridge_rejected=summary.rejected,
        recorder_dropped_queue_full=int(rec_stats.get("dropped_queue_full", -1)),
        recorder_messages=int(rec_stats.get("messages", info.messages)),
    )
    per_day = [x for x in samples if x.step % (24 * per_hour) < per_hour]  # the first sample of every day
    rss_by_day = {name: [x.kib.get(name, MemoryKib()).vm_rss_kib for x in per_day] for name in memory}
    growths = [g for v in memory.values() for g in (v.rss_growth, v.hwm_growth) if g is not None]
    lost = (losses.lockstep_misses + losses.lockstep_skipped + losses.bridge_frames_dropped
            + losses.control_steps_without_decision + losses.agent_queue_full + losses.agent_stale)
    lost += max(losses.recorder_dropped_queue_full, 0)
    result = SoakBench(
        feeder=fid, days=days, steps=summary.steps, start=start, wall_s=round(wall_s, 1),
        steps_per_s=summary.steps_per_s, exit_codes=codes,
        last_status_step=last_bridge.step if last_bridge else None, memory=memory, losses=losses,
        samples=len(samples), rss_by_day_kib=rss_by_day, recording_complete=info.complete,
        recording_bytes=info.size_bytes,
        max_growth=max(growths) if growths else None, goal_growth=_GOAL_GROWTH,
        growth_goal_met=bool(growths) and max(growths) < _GOAL_GROWTH, lost_or_late=lost,
        loss_goal_met=lost == 0, out_dir=str(out) if out_dir else None,
    )
    if tmp is not None:
        tmp.cleanup()
    return result


if __name__ == "__main__":
    days_arg = float(sys.argv[1]) if len(sys.argv) > 1 else 30.0
    out_arg = sys.argv[2] if len(sys.argv) > 2 else None
    print(to_json(bench_soak(days_arg, out_dir=out_arg)))
