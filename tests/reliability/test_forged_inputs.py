"""Identity from the certificate and the device map, never from the payload: forged inputs on the real bus.

A router with the access policy on loopback, the agent and a lockstep bridge as processes with their certificates,
and an attacker holding a ``devices`` certificate (a compromised field gateway: the policy lets it put frames and
acks). Before the bridge starts, the attacker puts a forged AMI reading at 0.80 pu for every critical node of a map
without meters (each claiming a day-long interval), two head frames dated 2100 from made-up sources, and 'rejected'
acks for commands the agent never sent. The agent must take none of them, count each as refused, and decide every
control step of the run.
"""

from __future__ import annotations

import datetime as dt
import json
from collections.abc import Iterator
from pathlib import Path

import msgspec
import pytest
import zenoh
from relutil import FEEDER, FEEDER_MAP, NOON, Procs

from regression.model import read_model
from schemas import keys
from schemas import messages as m
from schemas.bus import BusConfig, codec_for, free_port, open_session, wait_for, zenoh_config
from schemas.examples import example
from schemas.security import init_ca, init_security_dir

NS = 10**9
STEPS = 30  # six control steps of 5 minutes
T_2100 = 4_102_444_800 * NS
PLANT = "pv675"


@pytest.fixture(scope="module")
def attacked_run(tmp_path_factory, model13: Path, rel_cache: Path) -> Iterator[dict]:
    tmp = tmp_path_factory.mktemp("forged")
    sec, ca = tmp / "security", tmp / "ca"
    init_ca(ca)
    init_security_dir(sec, ca_dir=ca)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    model = read_model(model13)
    t0 = int(dt.datetime(2023, 7, 1, 17, tzinfo=dt.UTC).timestamp()) * NS  # NOON, local standard time (UTC-5)
    procs = Procs(tmp, endpoint, model13, rel_cache)
    secure = ["--secure-dir", str(sec)]
    try:
        with open_session(BusConfig(mode="router", listen=(endpoint,), tls_dir=str(sec), role="router")), \
                zenoh.open(zenoh_config(BusConfig(connect=(endpoint,), tls_dir=str(sec), role="devices"))) as forger:
            agent = procs.start("agent", ["agent", "--model", str(model13), "--feeder-id", FEEDER,
                                          "--feeder", str(FEEDER_MAP), "--summary-out", str(tmp / "agent.json"),
                                          *secure])
            meter_pub = forger.declare_publisher(keys.meas_ami(FEEDER, "m0"),
                                                 congestion_control=zenoh.CongestionControl.BLOCK)
            assert wait_for(lambda: bool(meter_pub.matching_status.matching), 60.0), agent.log()[-2000:]
            sent = {"meters": 0, "heads": 0, "acks": 0}
            for i, node in enumerate(model.critical_nodes):
                pub = forger.declare_publisher(keys.meas_ami(FEEDER, f"m{i}"),
                                               congestion_control=zenoh.CongestionControl.BLOCK)
                assert wait_for(lambda p=pub: bool(p.matching_status.matching), 10.0)
                pub.put(codec_for(m.MeterFrame).encode(m.MeterFrame(
                    t_ns=t0, seq=10**9, source=f"m{i}", meter_id=f"m{i}", node=node.name, v_pu=0.80,
                    interval_s=86_400)))
                sent["meters"] += 1
            head_pub = forger.declare_publisher(keys.meas_head(FEEDER),
                                                congestion_control=zenoh.CongestionControl.BLOCK)
            head = example(m.HeadFrame)
            for source in ("x1", "x2"):
                head_pub.put(codec_for(m.HeadFrame).encode(msgspec.structs.replace(
                    head, t_ns=T_2100, seq=10**12, source=source, feeder_id=FEEDER)))
                sent["heads"] += 1
            ack_pub = forger.declare_publisher(keys.ack(FEEDER, "pv", PLANT),
                                               congestion_control=zenoh.CongestionControl.BLOCK)
            for i in range(5):
                ack_pub.put(codec_for(m.Ack).encode(m.Ack(
                    t_ns=t0, seq=i + 1, source=PLANT, cmd_id=f"agent:{t0}:{PLANT}:{i}", device_id=PLANT,
                    status="rejected", applied_value=None, reason="forged")))
                sent["acks"] += 1
            bridge = procs.start("bridge", ["bridge", "--feeder", str(FEEDER_MAP), "--cache-dir", str(rel_cache),
                                            "--start", NOON, "--truth-every", "0", "--lockstep", "--timeout-s", "5",
                                            "--steps", str(STEPS), "--wait-agent-s", "60",
                                            "--summary-out", str(tmp / "bridge.json"), *secure])
            assert wait_for(lambda: not bridge.alive(), 240.0), bridge.log()[-2000:]
            assert bridge.proc.returncode == 0, bridge.log()[-2000:]
            assert agent.stop() == 0, agent.log()[-2000:]
        yield {"agent": json.loads((tmp / "agent.json").read_text()),
               "bridge": json.loads((tmp / "bridge.json").read_text()), "sent": sent,
               "critical_nodes": len(model.critical_nodes)}
    finally:
        procs.close()


@pytest.mark.bus
def test_forged_meter_readings_on_a_map_without_meters_change_nothing_and_are_counted(attacked_run):
    agent, sent = attacked_run["agent"], attacked_run["sent"]
    assert sent["meters"] == attacked_run["critical_nodes"] > 0
    assert agent["ami"].get("ami_readings", 0) == 0 and agent["ami"].get("ami_used", 0) == 0
    assert agent["ami"]["ami_unknown_meter"] == sent["meters"]
    assert agent["rejected"]["unknown_device"] >= sent["meters"]


def test_head_frames_of_made_up_sources_dated_2100_do_not_blind_the_agent(attacked_run):
    agent, bridge = attacked_run["agent"], attacked_run["bridge"]
    assert bridge["lockstep_misses"] == 0
    assert agent["decisions"] == STEPS // 5 == bridge["decisions"]
    assert agent["rejected"].get("stale", 0) == 0


def test_rejected_acks_for_commands_the_agent_never_sent_are_refused_and_counted(attacked_run):
    agent, sent = attacked_run["agent"], attacked_run["sent"]
    assert agent["rejected"]["foreign_ack"] == sent["acks"]
    assert agent["acks"].get("rejected", 0) == 0
    assert agent["acks"].get("accepted", 0) + agent["acks"].get("clipped", 0) == agent["commands"] > 0
