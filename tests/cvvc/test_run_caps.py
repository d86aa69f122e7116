"""Capacitor decisions closed loop: ``cvvc run`` (case D) on IEEE 13 with its two banks in the device map.

Real processes, real Zenoh on loopback, real OpenDSS, real MCAP: the model is trained on the map with banks, the
agent sends a ``CapCommand`` for each bank every decision, and the bridge applies it (ack accepted, the bank's
next frame ``commanded`` under that command's id).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader

from tests.capmap import write_ieee13_caps_map

REPO = Path(__file__).resolve().parents[2]
FEEDER = "ieee13caps"
STEP_NS = 60_000_000_000


def _cap_map(folder: Path) -> Path:
    return write_ieee13_caps_map(folder)


@pytest.fixture(scope="module")
def caps_run(tmp_path_factory, profile_cache):
    from regression.model import write_model
    from schemas.settings import TrainingOptions
    from training.train import train

    work = tmp_path_factory.mktemp("caps-run")
    dm = _cap_map(work)
    result = train(dm, TrainingOptions(blocks=(3, 3)), cache_dir=profile_cache, progress=False)
    assert [c.id for c in result.model.capacitors] == ["cap1", "cap2"]
    model = work / "model.json"
    write_model(result.model, model)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-m", "cvvc", "run", "--feeder", str(dm), "--model", str(model),
                           "--days", str(1 / 96), "--start", "2023-07-10T11:00", "--out", str(work / "out"),
                           "--cache", str(work / "cache"), "--control-banks", "--json"],
                          cwd=work, env=env, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout)
    by_topic: dict[str, list[dict]] = {}
    with Path(summary["recording"]).open("rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
            if channel.message_encoding == "json":  # the truth is Protobuf (schemas.truth), not needed here
                by_topic.setdefault(channel.topic, []).append(json.loads(message.data))
    return result.model, by_topic


def test_the_bridge_applies_the_agents_bank_commands(caps_run):
    model, rec = caps_run
    decisions = rec[f"cvvc/{FEEDER}/agent/decision"]
    assert len(decisions) == 3  # 15 simulated minutes, one decision every 5
    assert all(d["status"] in ("optimal", "soft") for d in decisions), [d["reason"] for d in decisions]
    commands = [(d["step_t_ns"], c) for d in decisions for c in d["commands"] if c["type"] == "cap"]
    assert sorted({c["capacitor_id"] for _, c in commands}) == ["cap1", "cap2"]
    assert len(commands) == 2 * len(decisions)
    acks = {a["cmd_id"]: a for b in ("cap1", "cap2") for a in rec.get(f"cvvc/{FEEDER}/ack/cap/{b}", [])}
    frames = {(f["capacitor_id"], f["t_ns"]): f for b in ("cap1", "cap2") for f in rec[f"cvvc/{FEEDER}/meas/cap/{b}"]}
    checked = 0
    for step, c in commands:
        ack = acks[c["cmd_id"]]
        assert ack["status"] == "accepted", ack
        assert ack["applied_value"] == c["closed_steps"]
        nxt = frames.get((c["capacitor_id"], step + STEP_NS))
        if nxt is None:
            continue  # the last decision of the run
        assert nxt["mode"] == "commanded" and nxt["cmd_id"] == c["cmd_id"]
        assert nxt["closed_steps"] == c["closed_steps"]
        checked += 1
    assert checked >= 2 * (len(decisions) - 1)
