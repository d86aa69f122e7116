"""Lost frames in lockstep: a step with a lost frame is decided at once, with what arrived.

Real agent and bridge processes on IEEE 13, real Zenoh on loopback, real OpenDSS; the bridge drops 20 % of the
device frames (seeded) and ends each step with a scan-end marker listing what it sent. Before the marker, each
control step with a lost frame waited out the agent's 2 s late-frame window while the bridge waited for its
decision. The assertions are on counts, never on wall time.
"""

from __future__ import annotations

import json
from pathlib import Path

from relutil import FEEDER, Procs, Watcher

STEPS = 120  # 24 control steps of 5 minutes
DROP = 0.2  # a control step loses at least one of its 7 frames with probability 1 - 0.8**7 = 0.79


def test_lockstep_steps_with_lost_frames_are_decided_at_once(procs: Procs, watcher: Watcher, tmp_path: Path) -> None:
    agent_summary, bridge_summary = tmp_path / "agent-summary.json", tmp_path / "bridge-summary.json"
    agent = procs.agent("--summary-out", str(agent_summary))
    watcher.wait(lambda: watcher.is_alive(f"cvvc/{FEEDER}/alive/agent/agent"), 30, "the agent's liveliness token")
    bridge = procs.bridge("--lockstep", "--steps", str(STEPS), "--drop-prob", str(DROP), "--noise-seed", "7",
                          "--wait-agent-s", "30", "--summary-out", str(bridge_summary))
    watcher.wait(lambda: not bridge.alive(), 240, "the end of the bridge's run")
    assert bridge.stop() == 0, bridge.log()[-2000:]
    assert agent.stop() == 0, agent.log()[-2000:]
    b = json.loads(bridge_summary.read_text())
    a = json.loads(agent_summary.read_text())

    assert b["steps"] == STEPS and b["frames_dropped"] > 0
    assert b["decisions"] == b["control_steps"] == STEPS // 5 == a["decisions"]
    assert b["lockstep_misses"] == 0
    # every control step that lost a frame was decided on the marker, none after the late-frame window
    assert a["released_by_step_end"] >= 10  # about 0.79 x 24 control steps, and the other steps' groups
    assert a["decided_after_late_window"] == 0
