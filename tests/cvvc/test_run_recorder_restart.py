"""``cvvc run`` with the recorder killed mid-run: control goes on, the gap is recorded.

Real processes on IEEE 13 in lockstep, real Zenoh on loopback, real OpenDSS, real MCAP; the recorder is killed
with SIGKILL by its pid once the recording holds head frames.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader

from recordings.info import recording_info

pytestmark = pytest.mark.process  # a ``cvvc run`` whose recorder is killed

REPO = Path(__file__).resolve().parents[2]
DAYS = 2  # 2880 lockstep steps: several seconds of stepping, so the kill lands mid-run and a restart records


def _recorder_pid(out_path: Path) -> int | None:
    """The pid of the recorder writing ``out_path`` (from /proc: the launcher's children are not ours)."""
    want = f"record --out {out_path} "
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:
                continue
            if want in cmd and "-m cvvc" in cmd:
                return int(d.name)
    return None


def _head_frames_recorded(path: Path) -> int:
    if not path.is_file():
        return 0
    try:
        info = recording_info(path)
    except Exception:  # the header is not on disk yet
        return 0
    return sum(ch.messages for ch in info.channels if ch.topic.endswith("/meas/head"))


def _wait(pred, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = pred()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"no {what} within {timeout_s} s")


def test_a_killed_recorder_is_restarted_control_goes_on_and_the_gap_is_recorded(tmp_path, ieee13_model,
                                                                                sharing_profiles):
    out = tmp_path / "out"
    mcap = out / "session.mcap"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    run = subprocess.Popen(
        [sys.executable, "-m", "cvvc", "run", "--feeder", str(REPO / "feeders" / "ieee13.toml"),
         "--model", str(ieee13_model), "--days", str(DAYS), "--start", "2023-07-10", "--out", str(out),
         "--cache", str(sharing_profiles(tmp_path / "cache")), "--no-baseline", "--json"],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait(lambda: _head_frames_recorded(mcap), 120, "head frame flushed into the recording")
        pid = _wait(lambda: _recorder_pid(mcap), 10, "recorder process")
        os.kill(pid, signal.SIGKILL)
        stdout, stderr = run.communicate(timeout=300)
    finally:
        if run.poll() is None:
            run.kill()
            run.communicate(timeout=30)
    assert run.returncode == 0, stderr[-3000:]
    assert f"the recorder (pid {pid}) killed by signal 9; restarting it" in stderr
    summary = json.loads(stdout)

    # control went on: every control step decided, no lockstep miss
    assert summary["decisions"] == DAYS * 1440 // 5
    assert summary["lockstep_misses"] == 0
    assert summary["recorder_restarts"] == 1 and not summary["recorder_gave_up"]
    [gap] = summary["recording_gaps"]
    assert gap["restart"] == 1 and f"pid {pid}" in gap["reason"]
    assert 0 < gap["from_t_ns"] < gap["to_t_ns"]

    # one finished file: head frames before and after the gap, none inside it, the gap on its channel
    assert sorted(p.name for p in out.glob("session*")) == ["session.mcap"]
    heads: list[int] = []
    recorded_gaps = []
    with mcap.open("rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
            if channel.topic == "cvvc/ieee13/meas/head":
                heads.append(message.log_time)
            elif channel.topic == "cvvc.recorder_gap":
                recorded_gaps.append(json.loads(message.data))
    assert recorded_gaps == [gap]
    before = [t for t in heads if t <= gap["from_t_ns"]]
    after = [t for t in heads if t >= gap["to_t_ns"]]
    assert before and after and len(before) + len(after) == len(heads)
    assert len(heads) == len(set(heads)) < DAYS * 1440

    info = subprocess.run([sys.executable, "-m", "cvvc", "recordings", "info", str(mcap)], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120, check=False)
    assert info.returncode == 0, info.stderr
    assert "gap: recorder restart 1: nothing recorded from" in info.stdout
    assert "restarted 1 time(s)" in (out / "report.md").read_text()
