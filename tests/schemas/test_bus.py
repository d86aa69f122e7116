"""Two real Zenoh sessions in two processes on loopback, through the bus layer."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import msgspec
import pytest
import zenoh

from schemas import messages as m
from schemas.bus import (
    BusConfig,
    Inbox,
    NonFiniteError,
    TypedPublisher,
    free_port,
    open_session,
    zenoh_config,
)
from schemas.examples import example

PEER = Path(__file__).with_name("echo_peer.py")


def _peer_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[2]) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def test_config_disables_multicast_and_stays_on_loopback():
    conf = zenoh_config(BusConfig(mode="peer"))
    assert conf.get_json("scouting/multicast/enabled") == "false"
    assert conf.get_json("listen/endpoints") == '["tcp/127.0.0.1:0"]'
    conf = zenoh_config(BusConfig(mode="client", connect=("tcp/127.0.0.1:7999",)))
    assert conf.get_json("connect/endpoints") == '["tcp/127.0.0.1:7999"]'
    assert conf.get_json("listen/endpoints") == "[]"
    conf = zenoh_config(BusConfig(mode="peer", connect=("tcp/127.0.0.1:7999",)))
    assert conf.get_json("listen/endpoints") == '["tcp/127.0.0.1:0"]'  # peers listen, on loopback only


def test_config_file_is_read_and_multicast_still_forced_off(tmp_path):
    f = tmp_path / "z.json5"
    f.write_text('{ mode: "peer", scouting: { multicast: { enabled: true } } }')
    conf = zenoh_config(BusConfig(config_file=str(f), listen=("tcp/127.0.0.1:7998",)))
    assert conf.get_json("scouting/multicast/enabled") == "false"


@pytest.mark.process
def test_two_processes_exchange_typed_messages_and_count_a_bad_one(router_endpoint):
    good = example(m.PvCommand)
    peer = subprocess.Popen([sys.executable, str(PEER), router_endpoint, "2"], env=_peer_env())
    try:
        with open_session(BusConfig(mode="peer", connect=(router_endpoint,))) as session:
            inbox = Inbox()
            inbox.subscribe(session, "test/out", m.PvCommand)
            inbox.subscribe(session, "test/report", m.AgentStatus)
            inbox.subscribe(session, "test/ready", m.AgentStatus)
            out = TypedPublisher(session, "test/in", m.PvCommand, reliable=True)
            # the same priority and express flag as ``out``: one queue, so the bad payload arrives between the two
            # good ones (at DATA priority it could arrive after the second and be counted after the report)
            raw = session.declare_publisher("test/in", congestion_control=zenoh.CongestionControl.BLOCK,
                                            priority=zenoh.Priority.REAL_TIME, express=True)
            # wait for the peer's ready signal: it has subscribed and sees our subscriber
            first = inbox.get(timeout_s=20.0)
            assert first is not None and first.key == "test/ready"
            out.put(good)
            raw.put(b'{"t_ns": "not a number"}')  # bad payload: counted by the peer, delivery goes on
            second = msgspec.structs.replace(good, seq=2, q_kvar=55.5)
            out.put(second)
            echoed, report = [], None
            # callbacks of different subscribers run concurrently: the report may overtake the last echo
            while report is None or len(echoed) < 2:
                item = inbox.get(timeout_s=20.0)
                assert item is not None, "peer went silent"
                if item.key == "test/out":
                    echoed.append(item.msg)
                elif item.key == "test/report":
                    report = item.msg
            assert echoed == [good, second]
            assert report.rejected == {"wrong_type": 1}
        assert peer.wait(timeout=20.0) == 0  # exits cleanly: no hang at exit
    finally:
        if peer.poll() is None:
            peer.kill()
            peer.wait(timeout=10)


def test_publisher_refuses_nan_and_sends_nothing(router_endpoint):
    with open_session(BusConfig(mode="peer", connect=(router_endpoint,))) as session:
        inbox = Inbox()
        inbox.subscribe(session, "test/nan", m.PvCommand)
        pub = TypedPublisher(session, "test/nan", m.PvCommand, reliable=True)
        assert pub.wait_matched(5.0)
        with pytest.raises(NonFiniteError):
            pub.put(msgspec.structs.replace(example(m.PvCommand), q_kvar=float("nan")))
        pub.put(example(m.PvCommand))
        item = inbox.get(timeout_s=5.0)
        assert item is not None and item.msg == example(m.PvCommand)
        assert inbox.get(timeout_s=0.2) is None


def test_inbox_drops_oldest_when_full_and_counts(router_endpoint):
    with open_session(BusConfig(mode="peer", connect=(router_endpoint,))) as session:
        inbox = Inbox(maxsize=4)
        inbox.subscribe(session, "test/burst", m.PvCommand)
        pub = TypedPublisher(session, "test/burst", m.PvCommand, reliable=True)
        assert pub.wait_matched(5.0)
        for i in range(10):
            pub.put(msgspec.structs.replace(example(m.PvCommand), seq=i))
        from schemas.bus import wait_for
        assert wait_for(lambda: inbox.accepted == 10, 5.0)
        kept = [r.msg.seq for r in inbox.drain()]
        assert kept == [6, 7, 8, 9]
        assert inbox.rejects.by_kind() == {"queue_full": 6}


def test_unknown_key_type_is_counted(router_endpoint):
    with open_session(BusConfig(mode="peer", connect=(router_endpoint,))) as session:
        inbox = Inbox()
        inbox.subscribe(session, "cvvc/rural/**")  # type from the key
        pub = session.declare_publisher("cvvc/rural/nonsense/x",
                                        congestion_control=zenoh.CongestionControl.BLOCK)
        from schemas.bus import wait_for
        assert wait_for(lambda: bool(pub.matching_status.matching), 5.0)
        pub.put(b"{}")
        assert wait_for(lambda: inbox.rejects.total() == 1, 5.0)
        assert inbox.rejects.by_kind() == {"unknown_key": 1}


def test_an_oversized_list_is_refused_and_counted_then_the_next_frame_taken(router_endpoint):
    """A head frame with 100,000 quality flags (0.9 MB, under the payload limit) through the real bus: refused as
    ``out_of_range`` by its list bound, counted, nothing enqueued; the valid frame after it is taken."""
    from schemas.bus import wait_for

    with open_session(BusConfig(mode="peer", connect=(router_endpoint,))) as session:
        inbox = Inbox()
        inbox.subscribe(session, "cvvc/ieee13/meas/**")  # the agent's subscription: the type from the key
        pub = session.declare_publisher("cvvc/ieee13/meas/head", congestion_control=zenoh.CongestionControl.BLOCK)
        assert wait_for(lambda: bool(pub.matching_status.matching), 5.0)
        head = msgspec.structs.replace(example(m.HeadFrame), feeder_id="ieee13")
        pub.put(msgspec.json.encode(msgspec.structs.replace(head, quality=["noisy"] * 100_000)))
        pub.put(msgspec.json.encode(head))
        assert wait_for(lambda: inbox.accepted == 1, 5.0)
        assert inbox.rejects.by_kind() == {"out_of_range": 1}
        assert [r.msg for r in inbox.drain()] == [head]


@pytest.mark.bus
def test_free_port_is_bindable():
    port = free_port()
    assert 1024 <= port <= 65535
    ep = f"tcp/127.0.0.1:{port}"
    with open_session(BusConfig(mode="router", listen=(ep,))):
        pass
