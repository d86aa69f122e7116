"""Closed-loop speed: a recorded ``cvvc run`` of case D against bare OpenDSS of the same steps, in one process.

``bench_closedloop`` runs ``cvvc.launch.run`` (bridge, agent and recorder as processes, lockstep, recording on),
then, in this process, bare OpenDSS (``FeederEngine.bare_steps_s``) over the same steps: the same loads and PV of the
same profile year, and the closed loop's own regulator taps and bank states replayed from the recording's truth
frames, so bare pays the same re-factorisations after tap moves. It prints both times and their ratio, the bridge's
loop alone, and the truth channel's bytes per simulated week.

Run: ``python -m benchmarks.bench_closedloop [DAYS [CACHE]]`` (default 7 days, the user's cache). ``make bench``
runs 2 days (1 with ``--quick``); the month is measured by hand with ``python -m benchmarks.bench_closedloop 30``
(docs/results.md).
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path
from typing import Literal

import msgspec
import numpy as np
import zstandard

from benchmarks.results import ClosedLoopBench, to_json

__all__ = ["bench_closedloop"]

_WEEK_STEPS = 7 * 1440
_CHUNK = 1 << 20  # the recorder's zstd chunk size [bytes]


def _truth_of(recording: Path, steps: int) -> tuple[np.ndarray, np.ndarray, int, int, str, int]:
    """(taps (steps, NR), bank states (steps, NC), payload bytes, zstd bytes, message encoding, frames) of the
    truth; a step whose frame the recording lacks keeps the previous step's positions (the frames are counted).
    """
    from mcap.reader import make_reader

    from schemas.truth import decode_truth

    taps, caps, times, payload, zstd_bytes, encoding = [], [], [], 0, 0, ""
    chunk = bytearray()
    compressor = zstandard.ZstdCompressor()
    with recording.open("rb") as f:
        for _, channel, msg in make_reader(f).iter_messages(log_time_order=True):
            if not channel.topic.endswith("/sim/truth"):
                continue
            encoding = channel.message_encoding
            tr = decode_truth(msg.data, encoding)
            taps.append(tr.taps)
            caps.append(tr.cap_states)
            times.append(tr.t_ns)
            payload += len(msg.data)
            chunk += msg.data
            if len(chunk) >= _CHUNK:
                zstd_bytes += len(compressor.compress(bytes(chunk)))
                chunk.clear()
    if chunk:
        zstd_bytes += len(compressor.compress(bytes(chunk)))
    if not times:
        raise RuntimeError(f"{recording}: no truth frames")
    step = ((np.array(times) - times[0]) // 60_000_000_000).astype(int)  # 1-minute steps from the first frame
    at = np.maximum.accumulate(np.where(np.isin(np.arange(steps), step), np.arange(steps), 0))
    row = np.searchsorted(step, at)  # the frame of each step, or of the last step before it that has one
    return np.array(taps)[row], np.array(caps)[row].reshape(steps, -1), payload, zstd_bytes, encoding, len(times)


def _bare_s(device_map: Path, cache: Path, start: str, year_seed: int, map_taps: np.ndarray,
            map_caps: np.ndarray, repeats: int) -> float:
    """Best of ``repeats`` bare OpenDSS runs of the steps, with the map's taps and banks as given per step."""
    from schemas.cache import profiles_dir
    from schemas.devicemap import load_device_map
    from simulator_bridge.bus.bridge import cached_profiles, start_step_of
    from simulator_bridge.opendss.engine import FeederEngine

    dm = load_device_map(device_map)
    engine = FeederEngine(dm)
    try:
        profiles = cached_profiles(dm, engine, seed=year_seed, cache_dir=profiles_dir(cache))
        first = start_step_of(start, profiles.start_t_ns, profiles.n_steps, profiles.step_s)
        n = len(map_taps)
        load_kw = np.asarray(profiles.load_kw(first, first + n), dtype=float)
        pv_kw = np.asarray(profiles.pv_kw(first, first + n), dtype=float)
        taps = np.tile(engine.control_taps(), (n, 1))  # the map's regulators first (control_taps' order)
        taps[:, :map_taps.shape[1]] = map_taps
        caps = np.tile(engine.control_cap_states(), (n, 1))
        caps[:, :map_caps.shape[1]] = map_caps
        return min(engine.bare_steps_s(load_kw, pv_kw, taps, caps) for _ in range(repeats))
    finally:
        engine.close()


def bench_closedloop(days: float = 7.0, *, case: Literal["A", "B", "C", "D", "none", "local"] = "D",
                     start: str = "2023-01-16", cache: str | None = None, bare_repeats: int = 2,
                     out: str | None = None, feeder: str | None = None, model: str | None = None) -> ClosedLoopBench:
    """A recorded ``cvvc run`` of ``days`` (rural feeder by default) against bare OpenDSS of the same steps.

    Parameters
    ----------
    days : simulated days. case : the paper's case (``D``: every control). start : first simulated day (local
    standard time). cache : cache root (None: the user's). bare_repeats : bare runs, the best kept (the machine is
    shared: the least disturbed). out : the run's folder (None: a temporary one, removed). feeder, model : another
    device map and its model (tests; None: the embedded rural feeder, its model trained once and cached).
    """
    from cvvc.launch import RunConfig, run
    from schemas.cache import cache_root
    from simulator_bridge.bus.bridge import BridgeSummary

    with tempfile.TemporaryDirectory(prefix="cvvc-bench-loop-") as tmp:
        folder = Path(out) if out else Path(tmp) / "run"
        config = RunConfig(days=days, case=case, start=start, cache=cache, out=str(folder), baseline=False,
                           progress=False, feeder=feeder, model=model)
        summary = run(config)
        bridge = msgspec.json.decode((folder / "bridge-summary.json").read_bytes(), type=BridgeSummary)
        if summary.recording is None:
            raise RuntimeError("the run wrote no recording")
        recording = Path(summary.recording)
        taps, caps, payload, zstd_bytes, encoding, frames = _truth_of(recording, summary.steps)
        bare = _bare_s(Path(summary.feeder), cache_root(cache), summary.start, config.year_seed, taps, caps,
                       bare_repeats)
        weeks = summary.steps / _WEEK_STEPS
        return ClosedLoopBench(
            feeder=summary.feeder_id, case=summary.case, days=days, steps=summary.steps,
            run_wall_s=summary.wall_s, loop_wall_s=round(bridge.wall_s, 3), bare_s=round(bare, 5),
            bare_repeats=bare_repeats, ratio=round(summary.wall_s / bare, 2), loop_ratio=round(bridge.wall_s / bare, 2),
            decision_wait_s=round(bridge.decision_wait_s, 2), bridge_thread_cpu_s=round(bridge.thread_cpu_s, 2),
            publisher_cpu_s=round(bridge.publisher_cpu_s, 2), round_trip_p50_s=bridge.round_trip_p50_s,
            lockstep_misses=summary.lockstep_misses,
            recording_bytes_per_week=round(recording.stat().st_size / weeks),
            truth_payload_bytes_per_week=round(payload / weeks), truth_zstd_bytes_per_week=round(zstd_bytes / weeks),
            truth_frames=frames, truth_encoding=encoding)


if __name__ == "__main__":  # python -m benchmarks.bench_closedloop [DAYS [CACHE_DIR [RUN_DIR]]]
    t0 = time.perf_counter()
    print(to_json(bench_closedloop(float(sys.argv[1]) if len(sys.argv) > 1 else 7.0,
                                   cache=sys.argv[2] if len(sys.argv) > 2 else None,
                                   out=sys.argv[3] if len(sys.argv) > 3 else None)))
    print(f"({time.perf_counter() - t0:.1f} s)", file=sys.stderr)
