"""The publisher process (``simulator_bridge/bus/publisher_process.py``) in real bridge runs on real Zenoh and OpenDSS
(IEEE 13): the same messages as inline publishing, the shared-memory slot layout, its failure and its end."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from bridgeutil import FEEDER, STARTUP_S, STEP_NS, bridge_cmd, bridge_config, bridge_thread, finish
from busclient import BusClient as Client

from schemas import messages as m
from schemas.bus import BusConfig
from schemas.devicemap import load_device_map


def _collect(client: Client, until: Callable[[str, Any], bool]) -> dict[str, dict[int, Any]]:
    """Every message seen until ``until`` and half a second more (frames, at a lower priority than the status,
    may still be on their way), by key and seq."""
    client.next(until)
    with pytest.raises(AssertionError, match="no matching sample"):
        client.next(lambda k, x: False, timeout_s=0.5)
    out: dict[str, dict[int, Any]] = {}
    for key, msg, _ in client.seen:
        out.setdefault(key, {})[msg.seq] = msg
    return out


@pytest.mark.process
def test_the_publisher_process_sends_what_inline_publishing_sends(router_endpoint: str, device_map_path: Path,
                                                                  cache_dir: Path) -> None:
    """The same lockstep run (commands, noise, drops, volt-var, truth), published inline and by the process:
    every message is the same, key by key and seq by seq."""
    runs = {}
    for publisher in ("inline", "process"):
        client = Client(router_endpoint, FEEDER, also=("cvvc/otherfeeder/ack/**",))
        try:
            client.be_agent()
            th, stop, out = bridge_thread(bridge_config(
                device_map_path, cache_dir, steps=16, truth_every=1, pv_local="volt_var", noise_pmu_pct=0.2,
                noise_scada_pct=1.0, drop_prob=0.1, noise_seed=5, publisher=publisher), router_endpoint)
            try:
                t0 = client.next(lambda k, x: isinstance(x, m.TruthPack), STARTUP_S).t_ns  # a process starts first
                for i, t in enumerate(t0 + 5 * j * STEP_NS for j in range(4)):
                    client.next(lambda k, x, t=t: isinstance(x, m.TruthPack) and x.t_ns == t)
                    cmds = [client.pv_cmd("pv675", 100.0 + 50 * i, t, valid_s=120),
                            client.reg_cmd("reg1", m.TapAction(tap=i), t)]
                    client.decide(t, cmds)
                summary = finish(th, stop, out)
                runs[publisher] = (summary, _collect(client, lambda k, x: isinstance(x, m.BridgeStatus) and x.done))
            finally:
                stop.set()
                th.join(timeout=30)
        finally:
            client.close()
    (a, inline), (b, process) = runs["inline"], runs["process"]
    assert a.lockstep_misses == b.lockstep_misses == 0 and a.acks == b.acks and a.acks["expired"] >= 1
    assert a.metrics == b.metrics and a.frames_dropped == b.frames_dropped > 0
    assert (a.frames_published, a.truth_frames) == (b.frames_published, b.truth_frames)
    assert b.publisher_cpu_s > 0 == a.publisher_cpu_s
    assert inline.keys() == process.keys()
    for key in inline:
        if "/meas/" in key:  # frames go with congestion control DROP: compare what both runs received
            common = inline[key].keys() & process[key].keys()
            assert len(common) >= 0.8 * max(len(inline[key]), len(process[key])), (key, inline[key], process[key])
            assert all(inline[key][n] == process[key][n] for n in common), key
        elif key.endswith("/sim/status"):  # the status says how the run was published: nothing else differs
            assert inline[key].keys() == process[key].keys()
        else:  # truth, metrics, acks
            assert inline[key] == process[key], key


def test_packed_steps_come_back_as_they_went_in(device_map_path: Path, cache_dir: Path) -> None:
    """The shared-memory slot layout: a real step and the device settings in force, packed and unpacked."""
    from simulator_bridge.bus.bridge import cached_profiles
    from simulator_bridge.bus.publisher_process import StepPacker
    from simulator_bridge.bus.publishing import DeviceSettings
    from simulator_bridge.opendss.engine import FeederEngine
    from simulator_bridge.simulation.qsts import Qsts

    engine = FeederEngine(load_device_map(device_map_path))
    try:
        profiles = cached_profiles(load_device_map(device_map_path), engine, seed=1, cache_dir=cache_dir)
        res = Qsts(engine, profiles, start_step=12 * 60).step()  # 12:00 on 1 January: PV produces
    finally:
        engine.close()
    assert res.pv_p_kw.max() > 0
    k, r = len(engine.pv_ids), len(engine.regulator_ids)
    packer = StepPacker(len(engine.node_names), k, r)
    fs, ints = np.full(packer.n_float, -1.0), np.full(packer.n_int, -1, np.int64)
    settings = DeviceSettings(pv_q_setpoint_kvar=(None, 120.5, *([None] * (k - 2))),
                              reg_setpoint_v120=tuple(121.0 + i for i in range(r)), reg_band_v120=(2.0,) * r,
                              reg_mode=("locked", *(("local",) * (r - 1))))
    assert packer.pack(fs, ints, res, 7, settings)
    back, n_step, got = packer.unpack(fs, ints)
    assert n_step == 7 and got == settings
    assert (back.step, back.t_ns) == (res.step, res.t_ns)
    for name in ("v_pu", "taps", "tap_changes", "pv_q_kvar", "pv_p_kw"):
        np.testing.assert_array_equal(getattr(back, name), getattr(res, name))
    for name in ("head_v_mag_v", "head_i_ang_deg", "pv_p_kw", "pv_v_v", "reg_v120_compared", "reg_tap"):
        np.testing.assert_array_equal(getattr(back.readings, name), getattr(res.readings, name))
    # a NaN or an infinity anywhere in the numbers the frames are made of is caught by the one-sum check
    for bad in (math.nan, math.inf):
        res.v_pu[3] = bad
        assert not packer.pack(fs, ints, res, 8, settings)
    res.v_pu[3] = 1.0
    res.readings.pv_q_kvar[0, 1] = -math.inf
    assert not packer.pack(fs, ints, res, 8, settings)


@pytest.mark.process
def test_the_publisher_process_fails_the_run_and_is_stopped(client: Client, router_endpoint: str,
                                                            device_map_path: Path, cache_dir: Path) -> None:
    """A publisher process killed mid-run: the bridge stops with an error at its next hand-over, in bounded time,
    and withdraws its tokens (the client sees the bridge's token go)."""
    import simulator_bridge.bus.publisher_process as pub

    procs: list[Any] = []
    orig = pub.PublisherProcess.__init__

    def spy(self: Any, *a: Any, **k: Any) -> None:
        orig(self, *a, **k)
        procs.append(self._proc)

    pub.PublisherProcess.__init__ = spy  # type: ignore[method-assign]
    try:
        th, stop, out = bridge_thread(bridge_config(device_map_path, cache_dir, steps=100000, clock="realtime",
                                               speed=600.0, wait_agent_s=0.0, publisher="process"),
                                       router_endpoint)
        client.next(lambda k, x: isinstance(x, m.HeadFrame) and x.seq >= 3, STARTUP_S)  # the publisher process starts
    finally:
        pub.PublisherProcess.__init__ = orig  # type: ignore[method-assign]
    assert len(procs) == 1
    os.kill(procs[0].pid, signal.SIGKILL)
    th.join(timeout=30)  # the bounded wait: a run of 100000 steps at speed 600 that went on would still be alive
    assert not th.is_alive()  # ended by itself: ``stop`` is only set below
    stop.set()
    assert out and "publisher process" in str(out[0]), out
    assert not procs[0].is_alive()


def test_publisher_process_cannot_hold_frames_for_latency(device_map_path: Path, cache_dir: Path) -> None:
    from simulator_bridge.bus.bridge import BridgeError, run_bridge

    with pytest.raises(BridgeError, match="latency"):
        run_bridge(bridge_config(device_map_path, cache_dir, latency_s=0.1, publisher="process"),
                   BusConfig(mode="peer", connect=()))


def test_auto_publishes_from_a_process_where_it_pays_and_the_child_can_join(device_map_path: Path,
                                                                             cache_dir: Path) -> None:
    from simulator_bridge.bus.bridge import BridgeError
    from simulator_bridge.bus.bridge_runtime import publisher_bus

    router = BusConfig(mode="peer", connect=("tcp/127.0.0.1:7447",))
    auto = bridge_config(device_map_path, cache_dir)
    assert publisher_bus(auto, router, 41) is None  # IEEE 13: no faster, only a start more
    child = publisher_bus(auto, router, 278)
    assert child is not None and child.connect == router.connect and child.listen == ()
    # a bridge that only listens: the child connects there (it cannot listen on the same port)
    listening = BusConfig(mode="peer", listen=("tcp/127.0.0.1:7448",))
    assert publisher_bus(auto, listening, 1283).connect == ("tcp/127.0.0.1:7448",)  # type: ignore[union-attr]
    for no in (BusConfig(mode="peer"), BusConfig(mode="peer", config_file="z.json5", connect=router.connect)):
        assert publisher_bus(auto, no, 1283) is None
        with pytest.raises(BridgeError, match="publisher='process' needs a bus"):
            publisher_bus(bridge_config(device_map_path, cache_dir, publisher="process"), no, 1283)
    assert publisher_bus(bridge_config(device_map_path, cache_dir, latency_s=0.1), router, 1283) is None
    assert publisher_bus(bridge_config(device_map_path, cache_dir, publisher="inline"), router, 8531) is None
    assert publisher_bus(bridge_config(device_map_path, cache_dir, publisher="process"), router, 41) is not None


def _children(pid: int) -> set[int]:
    """The child processes of ``pid`` (Linux /proc)."""
    out: set[int] = set()
    for task in Path(f"/proc/{pid}/task").iterdir():
        out |= {int(c) for c in (task / "children").read_text().split()}
    return out


def _gone(pid: int, timeout_s: float) -> bool:
    """Whether process ``pid`` has exited (a zombie counts), waiting up to ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            if "zombie" in Path(f"/proc/{pid}/status").read_text():
                return True
        except FileNotFoundError:
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.05)


@pytest.mark.parametrize("how", ["sigterm", "sigkill"])
@pytest.mark.process
def test_the_publisher_process_ends_with_the_bridge(client: Client, router_endpoint: str, device_map_path: Path,
                                                    cache_dir: Path, repo_root_module: Path, how: str) -> None:
    """SIGTERM: the bridge ends cleanly (final metrics from the child, exit 0) and so does its child. SIGKILL of the
    bridge: the orphaned child notices and exits by itself."""
    children: set[int] = set()
    proc = subprocess.Popen(
        bridge_cmd(router_endpoint, device_map_path, cache_dir, "--steps", "100000", "--realtime", "--speed", "600",
                    "--publisher", "process"),
        cwd=repo_root_module, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        client.next(lambda k, x: isinstance(x, m.HeadFrame) and x.seq >= 3, timeout_s=STARTUP_S)
        children = _children(proc.pid)
        assert len(children) >= 1  # the publisher process (multiprocessing may add its resource tracker)
        if how == "sigterm":
            proc.send_signal(signal.SIGTERM)
            stdout, stderr = proc.communicate(timeout=30)
            assert proc.returncode == 0, stderr
            summary = json.loads(stdout)
            assert summary["publisher"] == "process" and summary["stopped_early"] is True
            final = client.next(lambda k, x: isinstance(x, m.MetricsFrame) and x.final)
            assert final.steps == summary["steps"]
        else:
            proc.kill()
            proc.communicate(timeout=10)
        assert all(_gone(c, 10.0) for c in children), children
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        for c in children:  # only if the test failed: leave nothing behind
            if not _gone(c, 0.0):
                os.kill(c, signal.SIGKILL)
