"""Field clocks off the agent's, late frames in real time, and frames lost in outages.

Real agent and bridge processes on IEEE 13, real Zenoh on loopback, real OpenDSS. The bridge stamps its frames
2 s off its own clock (``--clock-skew-s``), holds every frame 30 simulated seconds (``--latency-s`` in wall
seconds at ``--speed``), or loses each device's frames in 10-minute outages (``--drop-burst-min``). Before the
agent took a frame stamped within ``clock_tolerance_s`` of a control step as that step's, a 2 s skew left every
control step undecided (no frame fell on one). The assertions are on counts, never on wall time.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from relutil import FEEDER, Procs, Watcher

STEPS = 60  # 12 control steps of 5 minutes


def _run(procs: Procs, watcher: Watcher, tmp_path: Path, *bridge_args: str) -> tuple[dict, dict]:
    agent_summary, bridge_summary = tmp_path / "agent-summary.json", tmp_path / "bridge-summary.json"
    agent = procs.agent("--summary-out", str(agent_summary), stale_after_s=10.0)
    watcher.wait(lambda: watcher.is_alive(f"cvvc/{FEEDER}/alive/agent/agent"), 30, "the agent's liveliness token")
    bridge = procs.bridge("--wait-agent-s", "30", "--summary-out", str(bridge_summary), *bridge_args)
    watcher.wait(lambda: not bridge.alive(), 240, "the end of the bridge's run")
    assert bridge.stop() == 0, bridge.log()[-2000:]
    assert agent.stop() == 0, agent.log()[-2000:]
    return json.loads(agent_summary.read_text()), json.loads(bridge_summary.read_text())


@pytest.mark.parametrize("skew_s", ["2", "-2"])
def test_with_field_clocks_2s_off_every_control_step_is_decided_and_obeyed(
        procs: Procs, watcher: Watcher, tmp_path: Path, skew_s: str) -> None:
    a, b = _run(procs, watcher, tmp_path, "--lockstep", "--steps", str(STEPS), "--clock-skew-s", skew_s)
    assert b["decisions"] == b["control_steps"] == STEPS // 5 == a["decisions"]
    assert b["lockstep_misses"] == 0 and a["holds"] == 0
    assert a["clock_snapped"] == 8 * (STEPS // 5)  # head, 3 plants, 3 regulators and the scan-end marker per step
    assert b["acks"].get("accepted", 0) + b["acks"].get("clipped", 0) == a["commands"] > 0
    assert b["rejected"] == {}  # no command refused as out of its window


def test_frames_30s_late_in_real_time_still_command_every_control_step(
        procs: Procs, watcher: Watcher, tmp_path: Path) -> None:
    speed = 300.0  # 60 steps in 12 s of wall time; 30 simulated seconds are 0.1 s
    a, b = _run(procs, watcher, tmp_path, "--realtime", "--speed", str(speed), "--steps", str(STEPS),
                "--latency-s", str(30.0 / speed))
    assert b["steps"] == STEPS and b["decisions"] == a["decisions"] == STEPS // 5
    assert a["holds"] == 0 and a["rejected"].get("stale", 0) == 0
    assert b["acks"].get("accepted", 0) + b["acks"].get("clipped", 0) == a["commands"] > 0
    assert b["acks"].get("expired", 0) == 0 and b["rejected"] == {}


def test_frames_lost_in_10_minute_outages_stall_no_step(procs: Procs, watcher: Watcher, tmp_path: Path) -> None:
    steps = 240  # 48 control steps
    a, b = _run(procs, watcher, tmp_path, "--lockstep", "--steps", str(steps), "--drop-prob", "0.2",
                "--drop-burst-min", "10", "--noise-seed", "5")
    assert 0.1 < b["frames_dropped"] / (b["frames_dropped"] + b["frames_published"]) < 0.3
    assert b["decisions"] == b["control_steps"] == steps // 5 == a["decisions"]
    assert b["lockstep_misses"] == 0
    assert a["released_by_step_end"] > 0 and a["decided_after_late_window"] == 0
