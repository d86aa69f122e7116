"""Capacitor banks as field devices on the bus: real Zenoh (loopback router) and real OpenDSS (IEEE 13 with its
two banks in the device map, one of them under a voltage CapControl added by ``extra_commands``).

The test client is plain ``zenoh`` + ``msgspec``: it plays the agent (liveliness token, commands, decisions),
sends bad commands, and checks acks, the frames of the next steps, truth and the final metrics.
"""

from __future__ import annotations

import json
import queue
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest
import zenoh
from busclient import BusClient as Client
from dssthread import run_in_dss_thread

from schemas import keys
from schemas import messages as m
from schemas.bus import BusConfig
from schemas.devicemap import load_device_map
from tests.capmap import write_ieee13_caps_map
from tests.yearcache import cache_year_profiles

FEEDER = "ieee13caps"
T0 = "2023-07-01T12:00"
STEP_NS = 60 * 1_000_000_000


@pytest.fixture(scope="module")
def cap_map(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """IEEE 13's own map plus its banks (``tests.capmap``)."""
    return write_ieee13_caps_map(tmp_path_factory.mktemp("capmap"))


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory, cap_map: Path) -> Path:
    """Profiles of the test map (its own cache: the map's fingerprint differs from IEEE 13's)."""
    return cache_year_profiles(cap_map, tmp_path_factory.mktemp("capprofiles"))


@pytest.fixture
def client(router_endpoint: str) -> Iterator[Client]:
    c = Client(router_endpoint, FEEDER)
    try:
        yield c
    finally:
        c.close()


def _config(cap_map: Path, cache_dir: Path, **kw: Any) -> Any:
    from simulator_bridge.bus.bridge import BridgeConfig

    base = dict(device_map_path=str(cap_map), start=T0, steps=11, clock="lockstep", timeout_s=10.0,
                wait_agent_s=10.0, cache_dir=str(cache_dir), truth_every=1)
    base.update(kw)
    return BridgeConfig(**base)


def _run(config: Any, endpoint: str, drive: Callable[[], None]) -> Any:
    """Run the bridge on the session's OpenDSS thread (``dssthread``) while ``drive()`` plays the agent; returns
    the bridge's summary."""
    from simulator_bridge.bus.bridge import run_bridge

    stop = threading.Event()
    th = run_in_dss_thread(lambda: run_bridge(config, BusConfig(mode="peer", connect=(endpoint,)), stop=stop))
    out = th.out
    try:
        drive()
        th.join(timeout=60)
    finally:
        stop.set()
        th.join(timeout=30)
    assert not th.is_alive(), "bridge thread did not finish"
    assert out and not isinstance(out[0], BaseException), out
    return out[0]


# ------------------------------------------------------------------------------------ tests
@pytest.mark.parametrize("publisher", ["inline", pytest.param("process", marks=pytest.mark.process)])
def test_cap_commands_acked_applied_expired_and_counted(client: Client, router_endpoint: str, cap_map: Path,
                                                         cache_dir: Path, publisher: str) -> None:
    """Every ack outcome of a bank, its effect on the next frames, expiry back to local control, and the
    switchings in truth and metrics."""
    client.be_agent()
    got: dict[str, Any] = {}

    def drive() -> None:
        head = client.next(lambda k, x: isinstance(x, m.HeadFrame))
        t0 = got["t0"] = head.t_ns
        c1, c2 = client.cap(t_ns=t0, cap_id="cap1"), client.cap(t_ns=t0, cap_id="cap2")
        got["f0"] = (c1, c2)
        open1 = client.cap_cmd("cap1", 0, t0, valid_s=60)  # in force for t0 + 1 min only
        open2 = client.cap_cmd("cap2", 0, t0)
        too_many = client.cap_cmd("cap2", 2, t0)  # cap2 has one step
        unknown = client.cap_cmd("nope", 0, t0)
        wrong = client.cap_cmd("cap1", 1, t0, key_cap="cap2")  # payload names cap1, sent to cap2
        replay = client.cap_cmd("cap2", 1, t0, seq=open2.seq)
        stale = client.cap_cmd("cap1", 1, t0, valid_s=0)
        client.put(keys.cmd(FEEDER, "cap", "cap2"),  # does not decode: -1 closed steps
                   json.dumps({**msgspec.to_builtins(open2), "seq": 900, "closed_steps": -1}).encode())
        client.decide(t0, [open1, open2])
        got["acks"] = {name: client.ack(c.cmd_id) for name, c in
                       (("open1", open1), ("open2", open2), ("too_many", too_many), ("unknown", unknown),
                        ("wrong", wrong), ("replay", replay), ("stale", stale))}
        got["f1"] = (client.cap("cap1", t0 + STEP_NS), client.cap("cap2", t0 + STEP_NS))
        got["expired"] = client.ack(open1.cmd_id, "expired")
        got["f2"] = (client.cap("cap1", t0 + 2 * STEP_NS), client.cap("cap2", t0 + 2 * STEP_NS))
        got["f4"] = client.cap("cap1", t0 + 4 * STEP_NS)
        t5 = t0 + 5 * STEP_NS
        client.next(lambda k, x: isinstance(x, m.HeadFrame) and x.t_ns == t5)
        release = client.cap_cmd("cap2", None, t5)
        client.decide(t5, [release])
        got["release"] = client.ack(release.cmd_id)
        got["f6"] = client.cap("cap2", t5 + STEP_NS)
        t10 = t0 + 10 * STEP_NS
        client.next(lambda k, x: isinstance(x, m.HeadFrame) and x.t_ns == t10)
        client.decide(t10)
        got["final"] = client.next(lambda k, x: isinstance(x, m.MetricsFrame) and x.final)

    summary = _run(_config(cap_map, cache_dir, publisher=publisher), router_endpoint, drive)
    t0 = got["t0"]
    c1, c2 = got["f0"]
    assert (c1.closed_steps, c1.steps, c1.control_type, c1.mode, c1.cmd_id) == (1, 1, "voltage", "local", None)
    assert (c2.closed_steps, c2.control_type, c2.control_value, c2.mode) == (1, "none", None, "local")
    assert c1.kvar_rated == pytest.approx(600.0) and c2.kvar_rated == pytest.approx(100.0)
    assert 2000.0 < c1.v_v < 3000.0 and 2000.0 < c2.v_v < 3000.0  # 4.16 kV buses, line to neutral
    assert c1.control_value is not None and 110.0 < c1.control_value < 130.0  # its PT's secondary [V]

    a = got["acks"]
    assert (a["open1"].status, a["open1"].applied_value, a["open1"].device_id) == ("accepted", 0.0, "cap1")
    assert (a["open2"].status, a["open2"].applied_value) == ("accepted", 0.0)
    for name, reason in (("too_many", "out_of_range"), ("unknown", "unknown_device"), ("wrong", "wrong_device"),
                         ("replay", "replay"), ("stale", "expired")):
        assert a[name].status == "rejected" and a[name].reason.startswith(reason), (name, a[name])

    f1_1, f1_2 = got["f1"]
    assert (f1_1.closed_steps, f1_1.mode, f1_1.cmd_id) == (0, "commanded", a["open1"].cmd_id)
    assert f1_1.valid_until_t_ns == t0 + STEP_NS
    assert (f1_2.closed_steps, f1_2.mode) == (0, "commanded")  # the rejected 2-step command never reached it
    assert got["expired"].t_ns == t0 + STEP_NS and "local control (voltage)" in got["expired"].reason
    f2_1, f2_2 = got["f2"]
    assert (f2_1.mode, f2_1.cmd_id, f2_1.valid_until_t_ns) == ("local", None, None)
    assert got["f4"].closed_steps == 1  # back on local control: its CapControl closed it again (30 s delay)
    assert f2_2.mode == "commanded"
    assert (got["release"].status, got["release"].applied_value) == ("accepted", None)
    assert (got["f6"].mode, got["f6"].cmd_id, got["f6"].closed_steps) == ("local", None, 0)  # no control: holds

    truth = [x for _, x, _ in client.seen if isinstance(x, m.TruthPack)]
    by_t = {tr.t_ns: tr.cap_states for tr in truth}
    assert by_t[t0] == [1, 1] and by_t[t0 + STEP_NS] == [0, 0]
    final = got["final"]
    switches = final.cap_switches_per_bank
    assert switches["cap2"] == 1  # opened once, then held (no control)
    assert switches["cap1"] == 2  # opened by the command, closed again by its CapControl
    assert final.cap_switches == sum(switches.values())
    assert final.cap_cost == pytest.approx(2.0 * switches["cap1"] + 1.0 * switches["cap2"])
    assert final.total_cost == pytest.approx(final.q_cost + final.t_cost + final.cap_cost)
    assert summary.metrics == final
    r = summary.rejected
    assert (r["out_of_range"], r["unknown_device"], r["wrong_device"], r["replay"], r["expired"]) == (1, 1, 1, 1, 1)
    assert r.get("decode_out_of_range", 0) == 1, r
    assert summary.acks == {"accepted": 3, "rejected": 5, "expired": 1}
    assert summary.lockstep_misses == 0


def test_cap_tokens_and_frames_every_step(client: Client, router_endpoint: str, cap_map: Path,
                                          cache_dir: Path) -> None:
    """Each bank has its own liveliness token and publishes one frame per step with increasing seq."""
    tokens: list[str] = []

    from schemas.bus import wait_for

    client.be_agent()  # the bridge waits for the agent's subscription, and for its decision at t0
    up: queue.Queue[str] = queue.Queue()
    watcher = client.session.liveliness().declare_subscriber(
        f"cvvc/{FEEDER}/alive/cap/*", lambda s: up.put(str(s.key_expr)) if s.kind == zenoh.SampleKind.PUT else None,
        history=True)

    def drive() -> None:
        t0 = client.next(lambda k, x: isinstance(x, m.HeadFrame)).t_ns

        def both() -> bool:
            while not up.empty():
                tokens.append(up.get_nowait())
            return len(set(tokens)) == 2

        wait_for(both, 10.0)  # while the bridge waits for the decision at t0: its tokens are up
        client.decide(t0)
        for i in range(4):  # every step's frame (the status may overtake the last: it goes at a higher priority)
            client.cap("cap1", t0 + i * STEP_NS)

    try:
        summary = _run(_config(cap_map, cache_dir, steps=4, truth_every=0), router_endpoint, drive)
    finally:
        watcher.undeclare()
    assert sorted(set(tokens)) == [f"cvvc/{FEEDER}/alive/cap/cap1", f"cvvc/{FEEDER}/alive/cap/cap2"]
    frames = sorted((x for _, x, _ in client.seen if isinstance(x, m.CapFrame) and x.capacitor_id == "cap1"),
                    key=lambda f: f.seq)
    assert [f.seq for f in frames] == list(range(1, summary.steps + 1))
    assert np.all(np.diff([f.t_ns for f in frames]) == STEP_NS)


def test_packed_cap_settings_come_back(cap_map: Path, cache_dir: Path) -> None:
    """The publisher process's slot layout carries the banks' states, switchings and the commands in force."""
    from simulator_bridge.bus.bridge import cached_profiles
    from simulator_bridge.bus.publisher_process import StepPacker
    from simulator_bridge.bus.publishing import DeviceSettings
    from simulator_bridge.opendss.engine import FeederEngine
    from simulator_bridge.simulation.qsts import Qsts

    dm = load_device_map(cap_map)
    engine = FeederEngine(dm)
    try:
        q = Qsts(engine, cached_profiles(dm, engine, seed=1, cache_dir=cache_dir), start_step=12 * 60)
        q.command_cap(1, 0)
        res = q.step()
    finally:
        engine.close()
    k, r, c = len(engine.pv_ids), len(engine.regulator_ids), len(engine.capacitor_ids)
    packer = StepPacker(len(engine.node_names), k, r, c)
    fs, ints = np.full(packer.n_float, -1.0), np.full(packer.n_int, -1, np.int64)
    long_id = "agent:" + "9" * 90  # the schema's longest cmd_id, 96 characters
    settings = DeviceSettings(pv_q_setpoint_kvar=(None,) * k, reg_setpoint_v120=(122.0,) * r,
                              reg_band_v120=(2.0,) * r, reg_mode=("local",) * r,
                              cap_command=(None, (long_id, 1_688_230_860_000_000_000)))
    assert packer.pack(fs, ints, res, 3, settings)  # cap1's NaN control reading is no non-finite step
    back, n_step, got = packer.unpack(fs, ints)
    assert n_step == 3 and got == settings
    np.testing.assert_array_equal(back.cap_states, res.cap_states)
    np.testing.assert_array_equal(back.cap_switches, [0, 1])
    np.testing.assert_array_equal(back.readings.cap_v_v, res.readings.cap_v_v)


@pytest.mark.process
def test_inline_and_process_publish_the_same_cap_frames(router_endpoint: str, cap_map: Path,
                                                        cache_dir: Path) -> None:
    """The same lockstep run with bank commands, SCADA noise and drops, published inline and by the publisher
    process: every bank frame both received, the truth, the metrics and the acks are the same."""
    runs: dict[str, dict[str, dict[int, Any]]] = {}
    for publisher in ("inline", "process"):
        client = Client(router_endpoint, FEEDER, also=("cvvc/otherfeeder/ack/**",))
        try:
            client.be_agent()

            def drive(client: Client = client) -> None:
                t0 = client.next(lambda k, x: isinstance(x, m.TruthPack)).t_ns
                for i, t in enumerate(t0 + 5 * j * STEP_NS for j in range(2)):
                    client.next(lambda k, x, t=t: isinstance(x, m.TruthPack) and x.t_ns == t)
                    client.decide(t, [client.cap_cmd("cap1", i % 2, t, valid_s=120),
                                      client.cap_cmd("cap2", (i + 1) % 2, t)])
                client.next(lambda k, x: isinstance(x, m.BridgeStatus) and x.done)

            _run(_config(cap_map, cache_dir, steps=10, noise_scada_pct=1.0, drop_prob=0.1, noise_seed=5,
                         publisher=publisher), router_endpoint, drive)
            by_key: dict[str, dict[int, Any]] = {}
            for key, msg, _ in client.seen:
                if not key.endswith("/sim/status"):
                    by_key.setdefault(key, {})[msg.seq] = msg
            runs[publisher] = by_key
        finally:
            client.close()
    inline, process = runs["inline"], runs["process"]
    cap_keys = {k for k in inline if "/meas/cap/" in k}
    assert cap_keys == {keys.meas_cap(FEEDER, "cap1"), keys.meas_cap(FEEDER, "cap2")} == \
        {k for k in process if "/meas/cap/" in k}
    assert any(f.mode == "commanded" for f in inline[keys.meas_cap(FEEDER, "cap1")].values())
    for key in inline.keys() | process.keys():
        if "/meas/" in key:  # DROP congestion control: a loaded machine loses frames, so compare what both received
            common = inline[key].keys() & process[key].keys()
            assert common, key
            assert all(inline[key][n] == process[key][n] for n in common), key
        else:
            assert inline[key] == process[key], key


def test_recorded_banks_in_recordings_info_and_the_run_report(client: Client, router_endpoint: str, cap_map: Path,
                                                              cache_dir: Path, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    """A recorded run with a bank command: ``recordings info`` lists the bank channels with their schema and
    counts, and ``cvvc report run`` draws the banks' states from the recording's truth."""
    from cvvc.cli import main as cvvc_main
    from cvvc.report import plot_run, read_trace
    from recordings.info import recording_info
    from recordings.recorder import Recorder, RecorderConfig
    from schemas.bus import open_session, wait_for

    rec_path = tmp_path / "session.mcap"
    bus = BusConfig(mode="peer", connect=(router_endpoint,))
    client.be_agent()
    got: dict[str, Any] = {}

    def drive() -> None:
        t0 = client.next(lambda k, x: isinstance(x, m.HeadFrame)).t_ns
        got["cmd"] = client.cap_cmd("cap2", 0, t0)
        client.decide(t0, [got["cmd"]])
        t5 = t0 + 5 * STEP_NS
        client.next(lambda k, x: isinstance(x, m.HeadFrame) and x.t_ns == t5)
        client.decide(t5)
        got["final"] = client.next(lambda k, x: isinstance(x, m.MetricsFrame) and x.final)

    with open_session(bus) as session, Recorder(session, RecorderConfig(out_path=str(rec_path), bus=bus)) as rec:
        # the recorder's subscription reached the router before the run's first message (only its cvvc/** matches)
        probe = client.session.declare_publisher("cvvc/recorder-probe")
        assert wait_for(lambda: probe.matching_status.matching, 10.0)
        probe.undeclare()
        summary = _run(_config(cap_map, cache_dir, steps=8), router_endpoint, drive)
        n_seen = sum(1 for k, _, _ in client.seen if "/cmd/" not in k)  # the recorder sees what the client saw
        assert wait_for(lambda: rec.stats().messages >= n_seen, 10.0), rec.stats()

    info = recording_info(rec_path)
    channels = {c.topic: c for c in info.channels}
    for cap_id in ("cap1", "cap2"):
        ch = channels[keys.meas_cap(FEEDER, cap_id)]
        assert (ch.schema_name, ch.schema_encoding, ch.messages) == ("cvvc.CapFrame", "jsonschema", summary.steps)
    assert channels[keys.cmd(FEEDER, "cap", "cap2")].schema_name == "cvvc.CapCommand"
    assert channels[keys.ack(FEEDER, "cap", "cap2")].messages == 1
    assert info.devices["cap"] == ["cap1", "cap2"] and info.devices["vr"] == ["reg1", "reg2", "reg3"]
    assert cvvc_main(["recordings", "info", str(rec_path)]) == 0
    out = capsys.readouterr().out
    assert "devices: 2 cap (cap1, cap2)" in out and f"{summary.steps}  {keys.meas_cap(FEEDER, 'cap1')}" in out

    final = got["final"]
    assert final.cap_switches_per_bank == {"cap1": 0, "cap2": 1}
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    from cvvc.launch import RunSummary

    (run_dir / "summary.json").write_bytes(msgspec.json.encode(RunSummary(
        feeder=str(cap_map), feeder_id=FEEDER, case="local", start=T0, days=summary.steps / 1440.0,
        steps=summary.steps, wall_s=0.0, metrics=final, baseline=None, lockstep_misses=0, decisions=0,
        out_dir=str(run_dir), recording=str(rec_path), model=None)))
    trace = read_trace(rec_path, capacitor_ids=("cap1", "cap2"))
    assert trace.cap_states.shape == (summary.steps, 2)
    assert trace.cap_states[0].tolist() == [1, 1] and trace.cap_states[1:, 1].max() == 0
    paths = plot_run(run_dir)
    assert {p.name for p in paths} == {"voltage_envelope.png", "pv_q.png", "taps.png", "cap_states.png"}
    cap_png = next(p for p in paths if p.name == "cap_states.png").read_bytes()
    assert cap_png[:8] == b"\x89PNG\r\n\x1a\n" and len(cap_png) > 10_000
