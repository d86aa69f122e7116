"""Secure mode: the devices' replay protection is keyed on the authenticated identity.

A real bridge process on IEEE 13 joins a router that enforces the access policy with mTLS (real certificates,
real Zenoh on loopback); a client with the agent's certificate, the only one the policy lets command, sends
commands naming different ``source`` strings. Before, each ``source`` had its own sequence, so a command
replayed under another name was applied again.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import msgspec
import pytest
import zenoh
from relutil import FEEDER, FEEDER_MAP, NOON, Procs

from schemas import messages as m
from schemas.bus import BusConfig, free_port, open_session, wait_for, zenoh_config
from schemas.security import COMMAND_ROLE, init_ca, init_security_dir
from tests.busprobe import Seen

pytestmark = [pytest.mark.bus, pytest.mark.process]  # a secure router and ``cvvc`` programs

PLANT = "pv675"
MIN_NS = 60 * 10**9


@pytest.fixture
def secure(tmp_path: Path) -> Iterator[tuple[str, Path]]:
    """A router with the access policy on a free port, and the security directory of its certificates."""
    d, ca = tmp_path / "security", tmp_path / "ca"
    init_ca(ca)
    init_security_dir(d, ca_dir=ca)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with open_session(BusConfig(mode="router", listen=(endpoint,), tls_dir=str(d), role="router")):
        yield endpoint, d


def test_in_secure_mode_a_command_under_another_source_name_is_still_a_replay(secure, tmp_path: Path,
                                                                              rel_cache: Path) -> None:
    endpoint, d = secure
    procs = Procs(tmp_path, endpoint, None, rel_cache)
    seen = Seen()
    try:
        with zenoh.open(zenoh_config(BusConfig(connect=(endpoint,), tls_dir=str(d), role=COMMAND_ROLE))) as agent:
            subs = [agent.declare_subscriber(f"cvvc/{FEEDER}/meas/head", seen.on_head),
                    agent.declare_subscriber(f"cvvc/{FEEDER}/ack/pv/{PLANT}", seen.on_ack)]
            pub = agent.declare_publisher(f"cvvc/{FEEDER}/cmd/pv/{PLANT}",
                                          congestion_control=zenoh.CongestionControl.BLOCK)
            bridge = procs.start("bridge", ["bridge", "--feeder", str(FEEDER_MAP), "--cache-dir", str(rel_cache),
                                            "--start", NOON, "--truth-every", "0", "--realtime", "--speed", "60",
                                            "--steps", "100000", "--wait-agent-s", "0", "--secure-dir", str(d)])
            assert wait_for(lambda: bool(seen.head_t_ns) and bool(pub.matching_status.matching), 60.0), \
                bridge.log()[-2000:]

            def send(name: str, source: str, seq: int) -> m.Ack:
                with seen.lock:
                    t = seen.head_t_ns[-1]
                cmd = m.PvCommand(t_ns=t, seq=seq, source=source, cmd_id=name, in_reply_to=0,
                                  valid_until_t_ns=t + 10 * MIN_NS, plant_id=PLANT, q_kvar=50.0)
                pub.put(msgspec.json.encode(cmd))
                assert wait_for(lambda: name in seen.acks, 30.0), (name, bridge.log()[-2000:])
                return seen.acks[name]

            assert send("first", "agent", 5).status in ("accepted", "clipped")
            renamed = send("renamed", "agent2", 5)  # the same seq under another name: a replay all the same
            assert renamed.status == "rejected" and "replay" in renamed.reason, renamed
            assert send("older", "someone", 4).status == "rejected"
            assert send("next", "agent2", 6).status in ("accepted", "clipped")  # the sequence goes on
            for sub in subs:
                sub.undeclare()
    finally:
        procs.close()


def test_in_secure_mode_commands_count_only_from_the_agent_role(secure, tmp_path: Path, rel_cache: Path) -> None:
    """Commands from a ``devices`` or a ``recorder`` certificate (a compromised gateway or recorder host) reach no
    device: the bridge neither applies nor acks them, while the agent's certificate, sent after them, is acked."""
    endpoint, d = secure
    procs = Procs(tmp_path, endpoint, None, rel_cache)
    seen = Seen()
    key = f"cvvc/{FEEDER}/cmd/pv/{PLANT}"
    try:
        with zenoh.open(zenoh_config(BusConfig(connect=(endpoint,), tls_dir=str(d), role=COMMAND_ROLE))) as agent, \
                zenoh.open(zenoh_config(BusConfig(connect=(endpoint,), tls_dir=str(d), role="devices"))) as gateway, \
                zenoh.open(zenoh_config(BusConfig(connect=(endpoint,), tls_dir=str(d), role="recorder"))) as rec:
            subs = [agent.declare_subscriber(f"cvvc/{FEEDER}/meas/head", seen.on_head),
                    agent.declare_subscriber(f"cvvc/{FEEDER}/ack/pv/{PLANT}", seen.on_ack)]
            pubs = {who: s.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
                    for who, s in (("agent", agent), ("devices", gateway), ("recorder", rec))}
            bridge = procs.start("bridge", ["bridge", "--feeder", str(FEEDER_MAP), "--cache-dir", str(rel_cache),
                                            "--start", NOON, "--truth-every", "0", "--realtime", "--speed", "60",
                                            "--steps", "100000", "--wait-agent-s", "0", "--secure-dir", str(d)])
            assert wait_for(lambda: bool(seen.head_t_ns) and bool(pubs["agent"].matching_status.matching), 60.0), \
                bridge.log()[-2000:]
            with seen.lock:
                t = seen.head_t_ns[-1]
            for seq, who in enumerate(("devices", "recorder", "agent"), start=1):
                cmd = m.PvCommand(t_ns=t, seq=seq, source="agent", cmd_id=f"from-{who}", in_reply_to=0,
                                  valid_until_t_ns=t + 10 * MIN_NS, plant_id=PLANT, q_kvar=50.0 * seq)
                pubs[who].put(msgspec.json.encode(cmd))
            assert wait_for(lambda: "from-agent" in seen.acks, 30.0), bridge.log()[-2000:]
            assert seen.acks["from-agent"].status in ("accepted", "clipped")
            assert "from-devices" not in seen.acks and "from-recorder" not in seen.acks
            for sub in subs:
                sub.undeclare()
    finally:
        procs.close()
