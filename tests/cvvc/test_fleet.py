"""``cvvc fleet``: several feeders on one router, kept apart (real processes, real Zenoh on loopback, real mTLS).

(a) a secure fleet of two IEEE 13 feeders under their own ids: every feeder decides, no recorded message of one
feeder's keys carries the other's id, and the launcher's probe command across feeders is refused;
(b) the router's per-feeder policy on its own: a real bridge of feeder B; a session with feeder A's agent
certificate commands it and reads its frames in vain, while B's own agent certificate is acked; the bridge, started
with ``--own-commands-only`` as ``cvvc fleet`` starts it, subscribes to no other feeder's commands;
(c) an agent process subscribes to its own feeder's frames and acks only (what keeps a plain fleet's agents apart).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import msgspec
import pytest
import zenoh
from mcap.writer import Writer

from cvvc.fleet import _open_router
from cvvc.fleet_report import check_recording
from recordings.replay import RecordedMessages
from schemas import messages as m
from schemas.bus import BusConfig, free_port, has_subscribers, wait_for, zenoh_config
from schemas.security import init_ca, init_security_dir
from tests.busprobe import Seen
from tests.yearcache import cache_year_profiles

REPO = Path(__file__).resolve().parents[2]
IEEE13 = REPO / "feeders" / "ieee13.toml"
MIN_NS = 60 * 10**9


def _cvvc(*args: str, cwd: Path, timeout_s: float) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", "cvvc", *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout_s, check=False)


@pytest.mark.process
def test_a_secure_fleet_decides_on_every_feeder_and_keeps_them_apart(tmp_path, ieee13_model, profile_cache) -> None:
    cache = tmp_path / "cache"
    shutil.copytree(cache_year_profiles(IEEE13, profile_cache), cache / "profiles")
    ca = tmp_path / "ca"
    init_ca(ca)
    fleet = tmp_path / "fleet.toml"
    fleet.write_text(f'days = 0.05\nstart = "2023-07-10T11:00"\n'
                     f'[[feeder]]\nmap = "{IEEE13}"\nid = "ieee13-a"\nmodel = "{ieee13_model}"\nyear_seed = 1\n'
                     f'[[feeder]]\nmap = "{IEEE13}"\nid = "ieee13-b"\nmodel = "{ieee13_model}"\nyear_seed = 1\n')
    out = tmp_path / "out"
    proc = _cvvc("fleet", "--fleet", str(fleet), "--cache", str(cache), "--out", str(out), "--secure",
                 "--ca-dir", str(ca), "--truth-every", "0", "--json", cwd=tmp_path, timeout_s=240.0)
    assert proc.returncode == 0, proc.stderr[-3000:]
    s = json.loads(proc.stdout)
    rows = {r["feeder_id"]: r for r in s["feeders"]}
    assert sorted(rows) == ["ieee13-a", "ieee13-b"]
    for fid, r in rows.items():  # 72 minutes, a decision every 5: each feeder decided, in lockstep, unrefused
        assert r["decisions"] >= 14 and r["lockstep_misses"] == 0, (fid, r)
        assert r["agent_refused"] == 0 and r["bridge_rejected"] == 0, (fid, r)
        assert r["decision_p50_ms"] is not None and r["round_trip_p50_ms"] is not None
        g = r["integrity"]  # the run's integrity per feeder: every decision due made, nothing refused, not degraded
        assert g["decisions_due"] == r["decisions"] and g["degraded"] == "" and g["foreign_decisions"] == 0, (fid, g)
    probe = s["probe"]
    assert probe["sender"] == "ieee13-a" and probe["target"] == "ieee13-b", probe
    assert not probe["reached"] and not probe["acked"] and probe["target_acks_after"] > 0, probe

    # the recording read here, apart from the launcher's check: every message on one feeder's keys names it
    ids_by_feeder: dict[str, set[str]] = {"ieee13-a": set(), "ieee13-b": set()}
    cmd_topics: set[str] = set()
    with RecordedMessages(out / "session.mcap", ("cvvc/**",)) as rec:
        for msg in rec:
            feeder = msg.topic.split("/")[1]
            assert feeder in ids_by_feeder, msg.topic
            fid = json.loads(msg.data).get("feeder_id")
            if fid is not None:
                ids_by_feeder[feeder].add(fid)
            if "/cmd/" in msg.topic:
                cmd_topics.add(msg.topic)
                assert b"cross-feeder-probe" not in msg.data, msg.topic
    assert ids_by_feeder == {"ieee13-a": {"ieee13-a"}, "ieee13-b": {"ieee13-b"}}
    assert {t.split("/")[1] for t in cmd_topics} == {"ieee13-a", "ieee13-b"}  # both agents commanded
    assert s["crossing_messages"] == 0 and s["messages_checked"] > 0 and s["foreign_topics"] == []
    assert s["wrong_feeder_acks"] == {}


def test_check_recording_counts_a_message_that_names_another_feeder(tmp_path) -> None:
    path = tmp_path / "r.mcap"
    with path.open("wb") as f:
        w = Writer(f)
        w.start()
        schema = w.register_schema(name="x", encoding="jsonschema", data=b"{}")
        chans = {t: w.register_channel(topic=t, message_encoding="json", schema_id=schema)
                 for t in ("cvvc/a/meas/head", "cvvc/b/agent/decision", "cvvc/c/sim/status", "cvvc/a/ack/pv/p")}
        w.add_message(chans["cvvc/a/meas/head"], log_time=1, publish_time=1, data=b'{"feeder_id": "a"}')
        w.add_message(chans["cvvc/a/meas/head"], log_time=2, publish_time=2, data=b'{"feeder_id": "b"}')
        w.add_message(chans["cvvc/b/agent/decision"], log_time=3, publish_time=3,
                      data=b'{"feeder_id": "b", "timings": {"total_s": 0.004}}')
        w.add_message(chans["cvvc/c/sim/status"], log_time=4, publish_time=4, data=b"not json")
        for t, reason in ((5, b"wrong_feeder: no bridge runs feeder 'a'; this bridge runs 'b'"), (6, b"replay: old")):
            w.add_message(chans["cvvc/a/ack/pv/p"], log_time=t, publish_time=t, data=b'{"cmd_id": "c", '
                          b'"device_id": "p", "status": "rejected", "reason": "' + reason + b'"}')
        w.finish()
    check = check_recording(path, ["a", "b"])
    assert (check.messages, check.checked, check.crossing, check.wrong_feeder_acks) == (6, 3, 1, {"a": 1})
    assert check.foreign_topics == ["cvvc/c/sim/status"] and check.decision_s == {"b": [0.004]}


@pytest.fixture
def fleet_router(tmp_path: Path) -> Iterator[tuple[str, Path]]:
    """The fleet's router (feeders ieee13-a and ieee13-b) on a free port, and the certificates' root folder."""
    ca, root = tmp_path / "ca", tmp_path / "security"
    init_ca(ca)
    init_security_dir(root, ca_dir=ca)
    for fid in ("ieee13-a", "ieee13-b"):
        init_security_dir(root / "feeders" / fid, ca_dir=ca, feeder=fid)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with _open_router(endpoint, str(root), ["ieee13-a", "ieee13-b"]):
        yield endpoint, root


@pytest.mark.process
def test_b_an_agent_certificate_of_one_feeder_cannot_command_or_read_another(fleet_router, tmp_path,
                                                                              profile_cache) -> None:
    endpoint, root = fleet_router
    cache = cache_year_profiles(IEEE13, profile_cache)
    a_dir, b_dir = root / "feeders" / "ieee13-a", root / "feeders" / "ieee13-b"
    seen, a_seen = Seen(), Seen()
    log = open(tmp_path / "bridge.log", "wb")  # noqa: SIM115  (closed below)
    bridge = subprocess.Popen(
        [sys.executable, "-m", "cvvc", "bridge", "--feeder", str(IEEE13), "--feeder-id", "ieee13-b",
         "--cache-dir", str(cache), "--year-seed", "1", "--start", "2023-07-01T12:00", "--truth-every", "0",
         "--realtime", "--speed", "60", "--steps", "100000", "--wait-agent-s", "0", "--secure-dir", str(b_dir),
         "--own-commands-only", "--connect", endpoint],
        cwd=REPO, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    log.close()
    key = "cvvc/ieee13-b/cmd/pv/pv675"
    try:
        with (zenoh.open(zenoh_config(BusConfig(connect=(endpoint,), tls_dir=str(root), role="recorder"))) as obs,
              zenoh.open(zenoh_config(BusConfig(connect=(endpoint,), tls_dir=str(a_dir), role="agent"))) as a,
              zenoh.open(zenoh_config(BusConfig(connect=(endpoint,), tls_dir=str(b_dir), role="agent"))) as b):
            subs = [obs.declare_subscriber("cvvc/ieee13-b/meas/head", seen.on_head),
                    obs.declare_subscriber("cvvc/ieee13-b/ack/**", seen.on_ack),
                    obs.declare_subscriber("cvvc/ieee13-b/cmd/**", seen.on_cmd),
                    a.declare_subscriber("cvvc/ieee13-b/meas/head", a_seen.on_head)]
            pub_a = a.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
            pub_b = b.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
            pub_x = b.declare_publisher("cvvc/ieee13-x/cmd/pv/pv675")
            assert wait_for(lambda: len(seen.head_t_ns) >= 2 and has_subscribers(pub_b), 90.0), \
                (tmp_path / "bridge.log").read_text()[-2000:]
            # --own-commands-only (what `cvvc fleet` gives its bridges): no subscription to another feeder's
            # commands (without it the bridge subscribes to cvvc/*/cmd/**, and this publisher would match)
            assert not has_subscribers(pub_x)

            def put(pub: zenoh.Publisher, name: str, seq: int) -> None:
                with seen.lock:
                    t = seen.head_t_ns[-1]
                pub.put(msgspec.json.encode(m.PvCommand(
                    t_ns=t, seq=seq, source="agent", cmd_id=name, in_reply_to=0, valid_until_t_ns=t + 10 * MIN_NS,
                    plant_id="pv675", q_kvar=50.0)))

            put(pub_a, "from-a", 5)  # feeder A's agent certificate on feeder B's command key
            put(pub_b, "from-b", 6)  # B's own agent: the positive control
            assert wait_for(lambda: "from-b" in seen.acks, 30.0), (tmp_path / "bridge.log").read_text()[-2000:]
            put(pub_b, "from-b2", 7)  # put after from-a was long sent: from-a would have been acked before it
            assert wait_for(lambda: "from-b2" in seen.acks, 30.0)
            assert seen.acks["from-b"].status in ("accepted", "clipped"), seen.acks["from-b"]
            with seen.lock:
                assert "from-a" not in seen.acks and "from-a" not in seen.cmd_ids, (seen.acks, seen.cmd_ids)
                assert {"from-b", "from-b2"} <= set(seen.cmd_ids)
                n_heads = len(seen.head_t_ns)
            assert wait_for(lambda: len(seen.head_t_ns) >= n_heads + 2, 30.0)  # two more frames, seen by the observer
            with a_seen.lock:  # A's session reads none of B's frames while the observer got every one
                assert a_seen.head_t_ns == []
            for sub in subs:
                sub.undeclare()
    finally:
        if bridge.poll() is None:
            bridge.send_signal(signal.SIGINT)
            try:
                bridge.wait(timeout=20)
            except subprocess.TimeoutExpired:
                bridge.kill()
                bridge.wait(timeout=10)


def test_the_fleet_policy_scopes_every_data_rule_of_a_feeder_and_leaves_the_roles_as_they_were() -> None:
    from schemas.security import access_control_policy

    plain, fleet = access_control_policy(), access_control_policy(("f1", "f2"))
    assert fleet["rules"][:len(plain["rules"])] == plain["rules"]  # the roles of `cvvc run` unchanged
    scoped = {r["id"]: r for r in fleet["rules"][len(plain["rules"]):]}
    assert scoped["agent.f1-agent-send"]["key_exprs"] == ["cvvc/f1/cmd/**", "cvvc/f1/agent/decision",
                                                          "cvvc/f1/agent/status"]
    assert scoped["devices.f2-devices-receive"]["key_exprs"] == [
        "cvvc/f2/cmd/**", "cvvc/f2/agent/decision", "cvvc/f2/meas/head",
        *(f"cvvc/f2/{group}/{kind}/*" for kind in ("pv", "vr", "cap") for group in ("meas", "ack"))]
    for rid, rule in scoped.items():  # data rules on the feeder's keys only; interest-only rules on every feeder
        interest = set(rule["messages"]) <= {"declare_subscriber", "declare_liveliness_subscriber",
                                             "liveliness_query"}
        own = rid.split("-")[0].split(".", 1)[1]
        assert interest or all(k.startswith(f"cvvc/{own}/") for k in rule["key_exprs"]), rule
    policies = {p["id"]: p for p in fleet["policies"]}
    assert policies["agent.f1"]["subjects"] == ["agent.f1"]
    assert all(r.startswith("agent.f1-") for r in policies["agent.f1"]["rules"])
    assert {"agent.f2", "devices.f2"} <= set(policies["declarations"]["subjects"])
    assert {s["id"]: s["cert_common_names"] for s in fleet["subjects"]}["devices.f1"] == ["devices.f1"]



@pytest.mark.process
def test_an_agent_subscribes_to_its_own_feeders_keys_only(router_endpoint, tmp_path, ieee13_model) -> None:
    """What keeps a plain fleet's agents apart: an agent of ``ieee13-a`` declares subscriptions that match its own
    feeder's frames and acks and no other feeder's (the router tells publishers whether any subscriber matches)."""
    log = open(tmp_path / "agent.log", "wb")  # noqa: SIM115  (closed below)
    agent = subprocess.Popen([sys.executable, "-m", "cvvc", "agent", "--model", str(ieee13_model), "--feeder-id",
                              "ieee13-a", "--connect", router_endpoint, "--insecure"], cwd=REPO, stdout=log,
                             stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    log.close()
    try:
        with zenoh.open(zenoh_config(BusConfig(connect=(router_endpoint,)))) as c:
            pubs = {(f, k): c.declare_publisher(f"cvvc/{f}/{k}") for f in ("ieee13-a", "ieee13-b")
                    for k in ("meas/head", "meas/pv/pv675", "meas/step", "ack/pv/pv675")}
            own = [p for (f, _), p in pubs.items() if f == "ieee13-a"]
            assert wait_for(lambda: all(has_subscribers(p) for p in own), 90.0), \
                (tmp_path / "agent.log").read_text()[-2000:]
            assert not any(has_subscribers(p) for (f, _), p in pubs.items() if f == "ieee13-b")
    finally:
        if agent.poll() is None:
            agent.send_signal(signal.SIGINT)
            try:
                agent.wait(timeout=20)
            except subprocess.TimeoutExpired:
                agent.kill()
                agent.wait(timeout=10)
