"""A flood of bad input writes a bounded number of log lines, and the rest is counted.

Real agent and bridge processes on IEEE 13, real Zenoh on loopback: a plain session puts undecodable payloads
on thousands of made-up device keys, measurement keys for the agent and command keys for the bridge. Before,
each new key wrote one warning line ("the first of each kind per topic"): one line per junk key.
"""

from __future__ import annotations

import json
from pathlib import Path

import zenoh
from relutil import FEEDER, Procs, Watcher, plain_session

from schemas import messages as m

N = 2000  # junk keys of each process
MAX_LINES = 3  # one line per kind per 10 s; the flood is one kind and takes seconds


def _rejected(statuses: list, prefix: str = "") -> int:
    return sum(n for k, n in statuses[-1].rejected.items() if k.startswith(prefix)) if statuses else 0


def _suppressed_rejections(summary: dict) -> int:
    return sum(n for k, n in summary["log_suppressed"].items() if k.startswith("rejected_"))


def test_a_flood_of_bad_input_writes_few_lines_and_counts_the_rest(procs: Procs, watcher: Watcher,
                                                                  router_endpoint: str, tmp_path: Path) -> None:
    agent_out, bridge_out = tmp_path / "agent-summary.json", tmp_path / "bridge-summary.json"
    agent = procs.agent("--summary-out", str(agent_out), stale_after_s=60.0)
    watcher.wait(lambda: watcher.is_alive(f"cvvc/{FEEDER}/alive/agent/agent"), 30, "the agent's liveliness token")
    bridge = procs.bridge("--realtime", "--speed", "300", "--steps", "100000", "--summary-out", str(bridge_out))
    watcher.first(m.AgentStatus, lambda s: s.state == "ok", 60, "an agent status 'ok'")
    watcher.first(m.BridgeStatus, lambda s: s.step > 0, 60, "a bridge status")
    watcher.skip = ("/junk",)
    with plain_session(router_endpoint, mode="client") as attacker:
        block = zenoh.CongestionControl.BLOCK
        for i in range(N):
            attacker.put(f"cvvc/{FEEDER}/meas/pv/junk{i}", b"{not json", congestion_control=block)
            attacker.put(f"cvvc/{FEEDER}/cmd/pv/junk{i}", b"{not json", congestion_control=block)
        watcher.wait(lambda: _rejected(watcher.messages(m.AgentStatus)) >= N, 60, f"the agent counting {N} rejections")
        watcher.wait(lambda: _rejected(watcher.messages(m.BridgeStatus), "decode_") >= N, 60,
                     f"the bridge counting {N} rejections")
        # the statuses say it live too
        for status_type in (m.AgentStatus, m.BridgeStatus):
            watcher.first(status_type, lambda s: sum(s.log_suppressed.values()) >= N - MAX_LINES, 60,
                          f"a {status_type.__name__} counting the suppressed lines")
    assert bridge.stop() == 0, bridge.log()[-2000:]
    assert agent.stop() == 0, agent.log()[-2000:]

    for proc, out in ((agent, agent_out), (bridge, bridge_out)):
        lines = [ln for ln in proc.log().splitlines() if "rejected message on" in ln]
        assert 1 <= len(lines) <= MAX_LINES, lines[:10]
        summary = json.loads(out.read_text())
        assert _suppressed_rejections(summary) >= N - MAX_LINES, summary["log_suppressed"]
