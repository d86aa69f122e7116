"""``cvvc run --field-protocol dnp3`` against the plain run: real processes, real Zenoh, real DNP3 over TCP, real
OpenDSS.

Half a simulated hour of case D on IEEE 13 (three regulators, PV producing), lockstep, twice: every regulator's frames
from the bridge (``bus``), and every regulator behind a simulated DNP3 regulator control and its own
``cvvc adapter dnp3`` (``dnp3``), started together. The DNP3 values travel as doubles (g30v6, g40v4, g41v4), so the
agent sees exactly the bridge's numbers and its set points reach the regulator exactly: everything must be the same,
without tolerance: the regulators' frames, every decision's commands and the metrics.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.closed_loop import run_side_by_side
from tests.recorded import messages_by_topic

REGULATORS = ("reg1", "reg2", "reg3")
STEPS = 30


@pytest.fixture(scope="module")
def dnp3_runs(tmp_path_factory, ieee13_model) -> dict[str, tuple[Path, dict]]:
    return run_side_by_side(tmp_path_factory.mktemp("dnp3loop"), ieee13_model,
                            {p: ["--field-protocol", p] for p in ("bus", "dnp3")}, days=STEPS / 1440,
                            start="2023-07-10T11:00")


def _commands(rec: dict[str, list[dict]]) -> dict[int, list[dict]]:
    """Each decision's commands by its step, without their ids."""
    return {d["step_t_ns"]: [{k: v for k, v in c.items() if k != "cmd_id"} for c in d["commands"]]
            for d in rec["cvvc/ieee13/agent/decision"]}


def test_the_same_decisions_frames_and_metrics(dnp3_runs):
    (_, bus), (_, dn) = dnp3_runs["bus"], dnp3_runs["dnp3"]
    assert (bus["field_protocol"], dn["field_protocol"]) == ("bus", "dnp3")
    assert dn["decisions"] == bus["decisions"] == STEPS // 5  # every 5 simulated minutes
    assert dn["holds"] == bus["holds"] == 0
    assert dn["lockstep_misses"] == bus["lockstep_misses"] == 0 and dn["dnp3_frame_misses"] == 0
    assert dn["metrics"] == bus["metrics"]
    assert bus["metrics"]["ntc"] > 0  # the regulators did move
    rec_a, rec_b = messages_by_topic(bus["recording"]), messages_by_topic(dn["recording"])
    assert _commands(rec_b) == _commands(rec_a)
    assert sum("setpoint_v120" in str(c) for cs in _commands(rec_a).values() for c in cs) > 0  # set points sent
    for reg in REGULATORS:  # the adapter's frames are the bridge's, field by field
        assert rec_b[f"cvvc/ieee13/meas/vr/{reg}"] == rec_a[f"cvvc/ieee13/meas/vr/{reg}"]
        assert len(rec_b[f"cvvc/ieee13/meas/vr/{reg}"]) == STEPS


def test_the_regulators_frames_and_acks_come_from_the_adapters(dnp3_runs):
    out, dn = dnp3_runs["dnp3"]
    rec = messages_by_topic(dn["recording"])
    commands = {c["cmd_id"]: c for d in rec["cvvc/ieee13/agent/decision"] for c in d["commands"]
                if "regulator_id" in c}
    follow_ups = {f for d in rec["cvvc/ieee13/agent/decision"] for f in d["follow_ups"]}
    commands |= {c["cmd_id"]: c for reg in REGULATORS for c in rec[f"cvvc/ieee13/cmd/vr/{reg}"]
                 if c["cmd_id"] in follow_ups}  # the re-centred bands, sent a step after their decision
    assert commands and dn["follow_up_misses"] == 0
    assert dn["integrity"]["foreign_writes"] == {} and dn["integrity"]["degraded"] == ""
    for reg in REGULATORS:
        link = json.loads((out / f"adapter.{reg}-summary.json").read_text())
        assert (link["protocol"], link["kind"], link["state"], link["foreign_writes"]) == ("dnp3", "vr", "ok", 0)
        assert link["frames"] == STEPS and link["refused"] == {}
        status = rec[f"cvvc/ieee13/link/vr/{reg}"]
        assert status and all(s["state"] in ("starting", "ok") for s in status)
        acks = [a for a in rec[f"cvvc/ieee13/ack/vr/{reg}"] if a["status"] != "expired"]
        assert len(acks) == sum(c["regulator_id"] == reg for c in commands.values()) == link["commands"]
        assert all(a["status"] == "accepted" and a["source"] == reg for a in acks), acks
