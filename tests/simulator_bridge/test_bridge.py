"""The bridge on real Zenoh (loopback router) and real OpenDSS (IEEE 13 device map).

The test client is plain ``zenoh`` + ``msgspec`` with the message structs of ``schemas.messages``: it
subscribes to every device, plays the agent by hand (liveliness token, commands, decisions) and checks
acks and their effect on the next frames. Runs that must exit cleanly are subprocesses of
``python -m cvvc bridge``; the others run ``run_bridge`` on one long-lived thread (``dssthread``).
"""

from __future__ import annotations

import json
import os
import queue
import re
import signal
import subprocess
from pathlib import Path

import msgspec
import pytest
import zenoh
from bridgeutil import FEEDER, STARTUP_S, STEP_NS, bridge_cmd, bridge_config, bridge_thread, finish
from busclient import BusClient as Client

from schemas import messages as m
from schemas.devicemap import load_device_map
from schemas.truth import truth_arrays


# ------------------------------------------------------------------------------------ tests
# IEEE 13 is small: "auto" would be inline
@pytest.mark.parametrize("publisher", ["inline", pytest.param("process", marks=pytest.mark.process)])
def test_commands_are_acked_and_show_in_the_next_frames(client: Client, router_endpoint: str,
                                                        device_map_path: Path, cache_dir: Path,
                                                        publisher: str) -> None:
    client.be_agent()
    th, stop, out = bridge_thread(bridge_config(device_map_path, cache_dir, steps=11, publisher=publisher),
                                   router_endpoint)
    try:
        h0 = client.head(timeout_s=STARTUP_S)  # a publisher process is a fresh interpreter: it imports first
        t0 = h0.t_ns
        # every device publishes a frame per step, all with the step's t_ns
        frames = {(type(x).__name__, getattr(x, "plant_id", getattr(x, "regulator_id", ""))) for _, x, _ in
                  client.seen if getattr(x, "t_ns", None) == t0}
        pv0 = client.next(lambda k, x: isinstance(x, m.PvFrame) and x.plant_id == "pv680" and x.t_ns == t0)
        rg0 = client.next(lambda k, x: isinstance(x, m.RegFrame) and x.regulator_id == "reg3" and x.t_ns == t0)
        frames |= {(type(x).__name__, getattr(x, "plant_id", getattr(x, "regulator_id", ""))) for _, x, _ in
                   client.seen if getattr(x, "t_ns", None) == t0}
        assert frames >= {("HeadFrame", ""), ("PvFrame", "pv675"), ("PvFrame", "pv680"), ("PvFrame", "pv633"),
                          ("RegFrame", "reg1"), ("RegFrame", "reg2"), ("RegFrame", "reg3")}
        assert pv0.q_setpoint_kvar is None and pv0.local_mode == "unity_pf" and pv0.p_kw > 0
        assert rg0.mode == "local" and rg0.setpoint_v120 == pytest.approx(122.0)

        q_big = pv0.q_available_kvar + 500.0
        c_pv = client.pv_cmd("pv675", 200.0, t0)
        c_clip = client.pv_cmd("pv680", q_big, t0)
        c_tap = client.reg_cmd("reg1", m.TapAction(tap=5), t0)
        c_sp = client.reg_cmd("reg2", m.SetpointAction(setpoint_v120=124.0, band_v120=2.0), t0, valid_s=60)
        c_exp = client.pv_cmd("pv633", -150.0, t0, valid_s=120)
        client.decide(t0, [c_pv, c_clip, c_tap, c_sp, c_exp])
        a = client.ack(c_pv.cmd_id)
        assert (a.status, a.applied_value, a.device_id, a.source) == ("accepted", 200.0, "pv675", "pv675")
        a = client.ack(c_clip.cmd_id)
        assert a.status == "clipped" and a.applied_value == pytest.approx(pv0.q_available_kvar, rel=0.05)
        assert "headroom" in a.reason
        assert client.ack(c_tap.cmd_id).status == "accepted"
        a = client.ack(c_sp.cmd_id)
        assert (a.status, a.applied_value) == ("accepted", 124.0)

        # the next step shows them
        t1 = t0 + STEP_NS
        pv1 = client.next(lambda k, x: isinstance(x, m.PvFrame) and x.plant_id == "pv675" and x.t_ns == t1)
        assert pv1.q_setpoint_kvar == 200.0 and pv1.q_kvar == pytest.approx(200.0, abs=1.0)
        r1 = client.next(lambda k, x: isinstance(x, m.RegFrame) and x.regulator_id == "reg1" and x.t_ns == t1)
        assert (r1.tap, r1.mode) == (5, "locked")
        r2 = client.next(lambda k, x: isinstance(x, m.RegFrame) and x.regulator_id == "reg2" and x.t_ns == t1)
        assert (r2.setpoint_v120, r2.band_v120, r2.mode) == (124.0, 2.0, "local")
        p3 = client.next(lambda k, x: isinstance(x, m.PvFrame) and x.plant_id == "pv633" and x.t_ns == t1)
        assert p3.q_setpoint_kvar == -150.0 and p3.q_kvar == pytest.approx(-150.0, abs=1.0)

        # watchdogs: reg2's set point was valid until t0 + 60 s, so it expires before t0 + 120 s
        a = client.ack(c_sp.cmd_id, "expired")
        assert a.applied_value == pytest.approx(122.0) and a.t_ns == t1
        r2 = client.next(lambda k, x: isinstance(x, m.RegFrame) and x.regulator_id == "reg2"
                         and x.t_ns == t0 + 2 * STEP_NS)
        assert (r2.setpoint_v120, r2.band_v120, r2.mode) == (122.0, 2.0, "local")
        a = client.ack(c_exp.cmd_id, "expired")  # pv633 valid until t0 + 120 s: in force at t0 + 120 s, gone at + 180 s
        assert a.t_ns == t0 + 2 * STEP_NS and "unity_pf" in a.reason
        p3 = client.next(lambda k, x: isinstance(x, m.PvFrame) and x.plant_id == "pv633"
                         and x.t_ns == t0 + 3 * STEP_NS)
        assert p3.q_setpoint_kvar is None and abs(p3.q_kvar) < 1.0

        # second control step (t0 + 5 min): answer with an empty decision; the lock still holds
        t5 = t0 + 5 * STEP_NS
        client.head(t5)
        client.decide(t5)
        r = client.next(lambda k, x: isinstance(x, m.RegFrame) and x.regulator_id == "reg1"
                        and x.t_ns == t0 + 6 * STEP_NS)
        assert r.tap == 5
        t10 = t0 + 10 * STEP_NS
        client.head(t10)
        client.decide(t10)
        summary = finish(th, stop, out)
    finally:
        stop.set()
        th.join(timeout=30)
    assert summary.steps == 11 and summary.control_steps == 3 and summary.decisions == 3
    assert summary.lockstep_misses == 0 and summary.lockstep_skipped == 0
    assert summary.acks == {"accepted": 4, "clipped": 1, "expired": 2}
    assert summary.round_trip_p50_s is not None and summary.round_trip_p50_s > 0
    assert (summary.publisher_cpu_s > 0) == (publisher == "process") and summary.publisher == publisher
    # frames carry one t_ns per step and increasing seq per source
    heads = [x for _, x, _ in client.seen if isinstance(x, m.HeadFrame)]
    assert [h.seq for h in heads] == sorted({h.seq for h in heads})
    assert all(b.t_ns - a.t_ns == STEP_NS for a, b in zip(heads, heads[1:], strict=False))


def test_a_plant_the_map_gives_q_at_night_takes_its_set_point_at_night_and_the_others_do_not(
        client: Client, router_endpoint: str, device_map_path: Path, cache_dir: Path, tmp_path: Path) -> None:
    """IEEE 13 at 02:00 with ``q_at_night`` on pv675 alone: its frames offer its rating and it applies a set point;
    pv680 offers nothing and clips the same set point to 0."""
    master = load_device_map(device_map_path).master_path.as_posix()
    text = re.sub(r"^master = .*$", f'master = "{master}"', device_map_path.read_text(), count=1, flags=re.M)
    night_map = tmp_path / "ieee13-q-at-night.toml"
    night_map.write_text(text.replace('id = "pv675"\n', 'id = "pv675"\nq_at_night = true\n'))
    client.be_agent()
    th, stop, out = bridge_thread(bridge_config(night_map, cache_dir, steps=3, start="2023-07-01T02:00"),
                                   router_endpoint)
    try:
        t0 = client.head(timeout_s=STARTUP_S).t_ns
        on, off = (client.next(lambda k, x, p=p: isinstance(x, m.PvFrame) and x.plant_id == p and x.t_ns == t0)
                   for p in ("pv675", "pv680"))
        assert on.p_kw == off.p_kw == 0.0  # night
        assert (on.q_available_kvar, off.q_available_kvar) == (1200.0, 0.0)
        c_on, c_off = client.pv_cmd("pv675", -300.0, t0), client.pv_cmd("pv680", -300.0, t0)
        client.decide(t0, [c_on, c_off])
        a = client.ack(c_on.cmd_id)
        assert (a.status, a.applied_value) == ("accepted", -300.0)
        a = client.ack(c_off.cmd_id)
        assert (a.status, a.applied_value) == ("clipped", 0.0) and "headroom 0.000 kvar" in a.reason
        t1 = t0 + STEP_NS
        on, off = (client.next(lambda k, x, p=p: isinstance(x, m.PvFrame) and x.plant_id == p and x.t_ns == t1)
                   for p in ("pv675", "pv680"))
        assert on.q_setpoint_kvar == -300.0 and on.q_kvar == pytest.approx(-300.0, abs=3.0)
        assert off.q_setpoint_kvar == 0.0 and off.q_kvar == pytest.approx(0.0, abs=1e-3)
        summary = finish(th, stop, out)
    finally:
        stop.set()
        th.join(timeout=30)
    assert summary.acks == {"accepted": 1, "clipped": 1}


def test_every_bad_command_is_rejected_with_a_reason_and_counted(
        client: Client, router_endpoint: str, device_map_path: Path, cache_dir: Path) -> None:
    client.be_agent()
    th, stop, out = bridge_thread(bridge_config(device_map_path, cache_dir, steps=6), router_endpoint)
    try:
        t0 = client.head().t_ns
        good = client.pv_cmd("pv675", 50.0, t0)
        assert client.ack(good.cmd_id).status == "accepted"
        bad = {
            "unknown_device": client.pv_cmd("nope", 10.0, t0),
            "wrong_feeder": client.pv_cmd("pv675", 10.0, t0, feeder="otherfeeder"),
            "wrong_device": client.pv_cmd("pv675", 10.0, t0, plant_id="pv680"),
            "replay": client.pv_cmd("pv675", 60.0, t0, seq=good.seq),
            "expired": client.pv_cmd("pv675", 10.0, t0, valid_s=0),
            "out_of_range": client.reg_cmd("reg1", m.SetpointAction(setpoint_v120=139.0, band_v120=2.0), t0),
        }
        band = client.reg_cmd("reg2", m.SetpointAction(setpoint_v120=122.0, band_v120=11.0), t0)
        for reason, cmd in bad.items():
            a = client.ack(cmd.cmd_id)
            assert a.status == "rejected" and a.reason.startswith(reason), (reason, a)
        assert client.ack(band.cmd_id).reason.startswith("out_of_range")
        # payloads that do not decode cannot be acked: counted by kind
        base = msgspec.json.decode(msgspec.json.encode(good))
        inf = json.dumps({**base, "q_kvar": 12345.0, "seq": 99}).replace("12345.0", "1e999")  # JSON for +inf
        client.put(f"cvvc/{FEEDER}/cmd/pv/pv675", inf.encode())
        client.put(f"cvvc/{FEEDER}/cmd/pv/pv675", b"{not json")
        client.put(f"cvvc/{FEEDER}/cmd/vr/reg1", json.dumps({**base, "seq": 98}).encode())  # a PV command
        client.decide(t0, [good])
        # the simulation is unaffected: pv675 holds the good command's 50 kvar
        p = client.next(lambda k, x: isinstance(x, m.PvFrame) and x.plant_id == "pv675" and x.t_ns == t0 + STEP_NS)
        assert p.q_setpoint_kvar == 50.0
        t5 = t0 + 5 * STEP_NS
        client.head(t5)
        client.decide(t5)
        summary = finish(th, stop, out)
        status = client.next(lambda k, x: isinstance(x, m.BridgeStatus) and x.done)
    finally:
        stop.set()
        th.join(timeout=30)
    r = summary.rejected
    for reason in ("unknown_device", "wrong_feeder", "wrong_device", "replay", "expired"):
        assert r[reason] == 1, (reason, r)
    assert r["out_of_range"] == 2
    assert r.get("decode_out_of_range", 0) + r.get("decode_non_finite", 0) == 1, r
    assert r["decode_malformed"] == 1
    assert sum(n for k, n in r.items() if k.startswith("decode_")) == 3, r
    assert status.rejected == r and summary.lockstep_misses == 0


def test_oracle_answers_from_the_stepping_thread(client: Client, router_endpoint: str, device_map_path: Path,
                                                 cache_dir: Path) -> None:
    client.be_agent()  # alive before the bridge starts, and the bridge is not told to wait for it:
    th, stop, out = bridge_thread(bridge_config(device_map_path, cache_dir, steps=1, wait_agent_s=0.0, oracle=True),
                                   router_endpoint)
    try:
        t0 = client.head().t_ns
        replies = list(client.session.get(f"cvvc/{FEEDER}/sim/oracle",
                                          payload=msgspec.json.encode(m.OracleRequest(t_ns=t0)), timeout=10.0))
        # (i): at most two replies per simulated step; the third query is refused, not computed
        more = [list(client.session.get(f"cvvc/{FEEDER}/sim/oracle",
                                        payload=msgspec.json.encode(m.OracleRequest(t_ns=t0)), timeout=10.0))
                for _ in range(2)]
        client.decide(t0)
        summary = finish(th, stop, out)
    finally:
        stop.set()
        th.join(timeout=30)
    assert len(replies) == 1 and replies[0].ok is not None
    rep = msgspec.json.decode(replies[0].ok.payload.to_bytes(), type=m.OracleReply)
    n = len(rep.node_names)
    # the feeder's own nodes: IEEE 13's 41 less sourcebus and 650, upstream of the head meter (Line.650632)
    assert rep.t_ns == t0 and n == len(rep.v_pu) == 35
    assert not any(name.split(".")[0] in ("sourcebus", "650") for name in rep.node_names)
    assert len(rep.dv_dq_pu_per_kvar) == n and all(len(row) == 3 for row in rep.dv_dq_pu_per_kvar)
    assert len(rep.dv_dtap_pu) == n and all(len(row) == 3 for row in rep.dv_dtap_pu)
    assert len(rep.dv_dp_pu_per_kw) == n and all(len(row) == 3 for row in rep.dv_dp_pu_per_kw)
    for k, bus in enumerate(("675", "680", "633")):  # injecting Q or P raises the plant's own voltage
        for sens in (rep.dv_dq_pu_per_kvar, rep.dv_dp_pu_per_kw):
            at_plant = [sens[i][k] for i, name in enumerate(rep.node_names) if name.startswith(bus + ".")]
            assert at_plant and min(at_plant) > 0
    assert more[0][0].ok is not None and more[1][0].err is not None
    assert b"rate limited" in more[1][0].err.payload.to_bytes()
    assert summary.oracle_replies == 2 and summary.rejected.get("oracle_rate") == 1 and summary.lockstep_misses == 0
    assert summary.lockstep_skipped == 0 and summary.decisions == 1  # it found the agent before step 0


def test_no_oracle_unless_asked_for(client: Client, router_endpoint: str, device_map_path: Path,
                                    cache_dir: Path) -> None:
    """ (i): the oracle answered any session with every node's true voltage; now only case A has one."""
    client.be_agent()
    th, stop, out = bridge_thread(bridge_config(device_map_path, cache_dir, steps=1, wait_agent_s=0.0), router_endpoint)
    try:
        t0 = client.head().t_ns
        replies = list(client.session.get(f"cvvc/{FEEDER}/sim/oracle",
                                          payload=msgspec.json.encode(m.OracleRequest(t_ns=t0)), timeout=1.0))
        client.decide(t0)
        summary = finish(th, stop, out)
    finally:
        stop.set()
        th.join(timeout=30)
    assert replies == [] and summary.oracle_replies == 0


@pytest.mark.process
def test_lockstep_with_a_silent_agent_times_out_and_goes_on(client: Client, router_endpoint: str,
                                                            device_map_path: Path, cache_dir: Path,
                                                            repo_root_module: Path) -> None:
    client.be_agent()
    alive: list[tuple[str, bool]] = []
    watch = client.session.liveliness().declare_subscriber(
        f"cvvc/{FEEDER}/alive/**", lambda s: alive.append((str(s.key_expr), s.kind == zenoh.SampleKind.PUT)),
        history=True)
    try:
        # the bounded wait: a bridge that waited on the silent agent for more than its timeouts would not end
        proc = subprocess.run(
            bridge_cmd(router_endpoint, device_map_path, cache_dir, "--steps", "11", "--lockstep",
                        "--timeout-s", "0.2", "--wait-agent-s", "10", "--truth-every", "5"),
            cwd=repo_root_module, capture_output=True, text=True, timeout=60)
        assert proc.returncode == 0, proc.stderr
        summary = json.loads(proc.stdout)
        assert summary["lockstep_misses"] == 3 and summary["control_steps"] == 3 and summary["steps"] == 11
        assert 3 * 0.2 <= summary["decision_wait_s"] < summary["wall_s"]  # three whole timeouts waited
        assert summary["agent_alive"] is True and summary["truth_frames"] == 3
        assert "lockstep miss" in proc.stderr
        status = client.next(lambda k, x: isinstance(x, m.BridgeStatus) and x.done)
        assert status.lockstep_misses == 3 and status.agent_alive and status.clock == "lockstep"
        final = client.next(lambda k, x: isinstance(x, m.MetricsFrame) and x.final)
        assert final.steps == 11
        truth = [x for _, x, _ in client.seen if isinstance(x, m.TruthPack)]
        assert truth[0].node_names is not None and len(truth[0].node_names) == len(truth_arrays(truth[0]).v_pu) == 41
        # every token was declared and withdrawn again
        ups = {k for k, up in alive if up and "/agent/" not in k}
        downs = {k for k, up in alive if not up}
        assert len(ups) == 1 + 1 + 3 + 3 and ups <= downs
    finally:
        watch.undeclare()


@pytest.mark.parametrize("publisher", ["inline", pytest.param("process", marks=pytest.mark.process)])
def test_realtime_keeps_its_clock_and_serves_commands_without_an_agent(
        client: Client, router_endpoint: str, device_map_path: Path, cache_dir: Path, publisher: str) -> None:
    # 1-minute steps at speed 1200: 20 steps per wall second; real time never waits for anyone
    th, stop, out = bridge_thread(bridge_config(device_map_path, cache_dir, steps=41, clock="realtime", speed=1200.0,
                                           wait_agent_s=0.0, publisher=publisher), router_endpoint)
    try:
        t0 = client.head(timeout_s=STARTUP_S).t_ns  # a publisher process is a fresh interpreter: it imports first
        c = client.pv_cmd("pv680", -100.0, t0)
        a = client.ack(c.cmd_id)
        frame = client.next(lambda k, x: isinstance(x, m.PvFrame) and x.plant_id == "pv680" and x.t_ns > a.t_ns)
        summary = finish(th, stop, out)
    finally:
        stop.set()
        th.join(timeout=30)
    assert a.status == "accepted" and frame.q_setpoint_kvar == -100.0
    heads = sorted(t for _, x, t in client.seen if isinstance(x, m.HeadFrame))
    while True:
        try:
            key, _, t = client.q.get_nowait()
        except queue.Empty:
            break
        if key.endswith("/meas/head"):
            heads.append(t)
    assert summary.steps == 41 and summary.clock == "realtime" and summary.lockstep_misses == 0
    # never ahead of its clock: step 40 is not made before 40 / 20 s (a bound no load can break)
    assert summary.steps_per_s <= 41 / (40 / 20)
    # behind it only as far as it says: a step more than a period late is counted (its speed: bench_bridge)
    assert summary.steps_per_s >= 20.0 / 1.15 or summary.realtime_late_steps > 0
    assert len(heads) >= 38  # DROP congestion control may lose one or two under load
    assert heads[-1] - heads[0] >= 0.5 * 40 / 20  # the heads go out as the steps are made, not in one burst


def test_lockstep_without_an_agent_token_does_not_wait(client: Client, router_endpoint: str,
                                                       device_map_path: Path, cache_dir: Path) -> None:
    th, stop, out = bridge_thread(bridge_config(device_map_path, cache_dir, steps=20, wait_agent_s=0.0,
                                           timeout_s=30.0), router_endpoint)
    summary = finish(th, stop, out)
    assert summary.steps == 20 and summary.lockstep_skipped == 4 and summary.lockstep_misses == 0
    # every control step skipped: not one of its 30 s timeouts was waited out
    assert not summary.agent_alive and summary.decision_wait_s < 30.0


@pytest.mark.process
def test_sigterm_ends_the_run_cleanly(client: Client, router_endpoint: str, device_map_path: Path,
                                      cache_dir: Path, repo_root_module: Path) -> None:
    proc = subprocess.Popen(
        bridge_cmd(router_endpoint, device_map_path, cache_dir, "--steps", "100000", "--realtime",
                    "--speed", "600", "--noise-pmu-pct", "0.1", "--noise-scada-pct", "1", "--drop-prob", "0.1",
                    "--latency-s", "0.05"),
        cwd=repo_root_module, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        # a fresh interpreter compiles the feeder first: a generous bound (it only bounds a failure)
        client.next(lambda k, x: isinstance(x, m.HeadFrame) and x.seq >= 3,  # seq counts dropped frames
                    timeout_s=STARTUP_S)
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()  # closes the pipes too
    assert proc.returncode == 0, stderr
    summary = json.loads(stdout)
    assert summary["stopped_early"] is True and 3 <= summary["steps"] < 100000
    assert summary["frames_dropped"] > 0
    final = client.next(lambda k, x: isinstance(x, m.MetricsFrame) and x.final)
    assert final.steps == summary["steps"]


@pytest.mark.process
def test_a_stopped_run_publishes_every_simulated_step_before_its_final_metrics(
        client: Client, router_endpoint: str, device_map_path: Path, cache_dir: Path) -> None:
    th, stop, out = bridge_thread(bridge_config(device_map_path, cache_dir, steps=100000, clock="realtime",
                                           speed=6000.0, wait_agent_s=0.0, truth_every=1, publisher="process"),
                                   router_endpoint)
    client.next(lambda k, x: isinstance(x, m.HeadFrame) and x.seq >= 20, STARTUP_S)  # the publisher process starts
    summary = finish(th, stop, out, stop_now=True)
    final = client.next(lambda k, x: isinstance(x, m.MetricsFrame) and x.final)
    assert summary.stopped_early and final.steps == summary.steps == summary.truth_frames
    assert summary.frames_published == 7 * summary.steps  # head, 3 PV, 3 regulators per step
    last = client.next(lambda k, x: isinstance(x, m.TruthPack) and x.seq == summary.steps)
    assert last.t_ns == summary.end_t_ns
