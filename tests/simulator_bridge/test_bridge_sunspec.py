"""The bridge with plants behind SunSpec (``BridgeConfig.pv_sunspec``): real OpenDSS (IEEE 13), real Zenoh on a
loopback router, real Modbus TCP between each simulated inverter and its ``cvvc adapter sunspec`` (threads).

The test client plays the agent by hand (``busclient``). Two of the three plants are behind SunSpec, the third stays
the bridge's own, so each side is checked against the other in the same run.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from bridgeutil import FEEDER, STARTUP_S, STEP_NS
from bridgeutil import bridge_config as _config
from bridgeutil import bridge_thread as _bridge_thread
from bridgeutil import finish as _finish
from busclient import BusClient as Client

from adapters.sunspec_runtime import AdapterConfig, run_adapter
from schemas import messages as m
from schemas.bus import BusConfig, free_port

SUNSPEC = ("pv675", "pv633")
PV_ORDER = ("pv675", "pv680", "pv633")  # the device map's order: the truth frame's pv_q_kvar columns
W_STEP_KW = 0.1  # W_SF 2 for these 1.2 MVA / 0.8 MVA plants (1.5 x rating must fit an int16): 100 W steps


class _Adapter:
    """One ``cvvc adapter sunspec --clock head`` on a thread, for plant ``pid`` at a free port's endpoint."""

    def __init__(self, pid: str, router_endpoint: str, **settings: Any) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.stop = threading.Event()
        config = AdapterConfig(feeder_id=FEEDER, device_id=pid, modbus=self.endpoint, clock="head",
                               scan_period_s=60.0, control_period_s=300.0, **settings)
        ready = threading.Event()
        bus = BusConfig(mode="peer", connect=(router_endpoint,))
        self.thread = threading.Thread(target=lambda: run_adapter(config, bus, stop=self.stop, ready=ready),
                                       daemon=True)
        self.thread.start()
        assert ready.wait(30.0), "adapter did not come up"

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=30)
        assert not self.thread.is_alive()


@pytest.fixture
def adapters(router_endpoint: str) -> Iterator[dict[str, _Adapter]]:
    """One adapter per plant behind SunSpec, each on its own free port; yields plant -> adapter."""
    running: dict[str, _Adapter] = {}
    try:
        for pid in SUNSPEC:
            running[pid] = _Adapter(pid, router_endpoint)
        yield running
    finally:
        for a in running.values():
            a.close()


def _pv(client: Client, plant: str, t_ns: int) -> m.PvFrame:
    return client.next(lambda k, x: isinstance(x, m.PvFrame) and x.plant_id == plant and x.t_ns == t_ns)


def _truth_q(client: Client, plant: str, t_ns: int) -> float:
    tr = client.next(lambda k, x: isinstance(x, m.TruthPack) and x.t_ns == t_ns)
    return tr.pv_q_kvar[PV_ORDER.index(plant)]


def _on_step(x: float, step: float) -> bool:
    return abs(x / step - round(x / step)) < 1e-6


def test_set_points_go_through_the_inverters_and_revert_there_when_the_agent_stops(
        client: Client, router_endpoint: str, device_map_path: Path, cache_dir: Path,
        adapters: dict[str, _Adapter]) -> None:
    client.be_agent()
    config: Any = _config(device_map_path, cache_dir, steps=8, truth_every=1, publisher="inline",
                          pv_sunspec={pid: a.endpoint for pid, a in adapters.items()})
    th, stop, out = _bridge_thread(config, router_endpoint)
    try:
        t0 = client.next(lambda k, x: isinstance(x, m.HeadFrame), STARTUP_S).t_ns  # a loaded machine
        f675, f680, f633 = (_pv(client, p, t0) for p in PV_ORDER)
        # the adapters' frames carry what the 701 registers hold: per phase, on the scale factor's 100 W step
        assert all(_on_step(ph.p_kw, W_STEP_KW) for ph in f675.phases + f633.phases)
        assert not all(_on_step(ph.p_kw, W_STEP_KW) for ph in f680.phases)  # the bridge's own: not rounded
        assert f675.p_kw > 0 and f675.q_setpoint_kvar is None and f675.s_rated_kva == pytest.approx(1200.0)

        c675 = client.pv_cmd("pv675", 200.0, t0, valid_s=240)  # in force up to t0 + 4 min, gone at t0 + 5 min
        c633 = client.pv_cmd("pv633", -150.0, t0, valid_s=120)
        c680 = client.pv_cmd("pv680", 100.0, t0)
        client.decide(t0, [c675, c633, c680])
        a = client.ack(c675.cmd_id)
        assert (a.status, a.applied_value, a.source) == ("accepted", 200.0, "pv675")  # the adapter's read-back
        assert client.ack(c633.cmd_id).status == "accepted"
        assert client.ack(c680.cmd_id).status == "accepted"

        # the set point written into the inverter is the simulated plant's command from the next step on
        t1 = t0 + STEP_NS
        assert _truth_q(client, "pv675", t1) == pytest.approx(200.0, abs=1e-6)
        assert _truth_q(client, "pv633", t1) == pytest.approx(-150.0, abs=1e-6)
        f = _pv(client, "pv675", t1)
        assert f.q_setpoint_kvar == 200.0 and f.q_kvar == pytest.approx(200.0, abs=3 * W_STEP_KW / 2 + 1e-9)
        client.token.undeclare()  # the agent stops: nothing more is sent
        client.token = None

        # the inverter's own timer: pv633 (valid until t0 + 2 min) is back on unity at t0 + 3 min, pv675 at + 5 min
        assert _truth_q(client, "pv633", t0 + 2 * STEP_NS) == pytest.approx(-150.0, abs=1e-6)
        assert _truth_q(client, "pv633", t0 + 3 * STEP_NS) == 0.0
        assert _truth_q(client, "pv675", t0 + 4 * STEP_NS) == pytest.approx(200.0, abs=1e-6)
        assert _truth_q(client, "pv675", t0 + 5 * STEP_NS) == 0.0
        assert _pv(client, "pv675", t0 + 5 * STEP_NS).q_setpoint_kvar is None
        assert client.ack(c633.cmd_id, "expired").source == "pv633"  # acked by its adapter at its next scan
        assert client.ack(c675.cmd_id, "expired").t_ns == t0 + 5 * STEP_NS
        summary = _finish(th, stop, out)
    finally:
        stop.set()
        th.join(timeout=30)
    assert summary.steps == 8 and summary.lockstep_misses == 0 and summary.sunspec_frame_misses == 0
    # the bridge acked only its own plant's command: the others were the adapters'
    assert summary.acks == {"accepted": 1}
    t_last = t0 + 7 * STEP_NS
    for pid in PV_ORDER:
        _pv(client, pid, t_last)
    client.next(lambda k, x: isinstance(x, m.StepEnd) and x.t_ns == t_last)  # frames come before their marker
    pv_frames = [x for _, x, _ in client.seen if isinstance(x, m.PvFrame)]
    for pid in PV_ORDER:  # one frame per plant and step: the bridge published none for the SunSpec plants
        assert sorted(f.t_ns for f in pv_frames if f.plant_id == pid) == [t0 + i * STEP_NS for i in range(8)]
    ends = [x for _, x, _ in client.seen if isinstance(x, m.StepEnd)]
    assert ends and all(sorted(e.pv) == sorted(PV_ORDER) for e in ends)  # the agent waits for the adapters' frames


def test_an_adapter_gone_costs_the_bridge_one_bounded_wait_not_one_per_step(
        client: Client, router_endpoint: str, device_map_path: Path, cache_dir: Path,
        adapters: dict[str, _Adapter]) -> None:
    client.be_agent()
    config: Any = _config(device_map_path, cache_dir, steps=6, timeout_s=2.0, publisher="inline",
                          pv_sunspec={pid: a.endpoint for pid, a in adapters.items()})
    th, stop, out = _bridge_thread(config, router_endpoint)
    try:
        t0 = client.next(lambda k, x: isinstance(x, m.HeadFrame), STARTUP_S).t_ns  # a loaded machine
        _pv(client, "pv633", t0)
        adapters["pv633"].close()  # its adapter stops after the first step's frame
        client.decide(t0)
        client.head(t0 + 5 * STEP_NS)
        client.decide(t0 + 5 * STEP_NS)
        summary = _finish(th, stop, out)
    finally:
        stop.set()
        th.join(timeout=30)
    assert summary.steps == 6 and summary.lockstep_misses == 0
    assert summary.sunspec_frame_misses == 1  # waited once (2 s) for pv633's frame, then no more
    for i in range(6):  # the other adapter went on scanning every step
        _pv(client, "pv675", t0 + i * STEP_NS)


def test_the_plant_takes_the_local_mode_its_adapter_set_in_705(client: Client, router_endpoint: str,
                                                                device_map_path: Path, cache_dir: Path) -> None:
    """The bridge's plants are on unity; pv675's adapter sets volt-var in its inverter's 705 at its first scan, and
    from the next step on the simulated plant follows the curve (above 1.02 pu at noon: it absorbs)."""
    running = {"pv675": _Adapter("pv675", router_endpoint, local_mode="volt_var", set_local_mode=True),
               "pv633": _Adapter("pv633", router_endpoint, set_local_mode=True)}
    try:
        config: Any = _config(device_map_path, cache_dir, steps=4, truth_every=1, publisher="inline",
                              pv_sunspec={pid: a.endpoint for pid, a in running.items()})
        th, stop, out = _bridge_thread(config, router_endpoint)
        try:
            t0 = client.next(lambda k, x: isinstance(x, m.HeadFrame), STARTUP_S).t_ns  # a loaded machine
            assert _pv(client, "pv675", t0).local_mode == "volt_var"  # read back after the adapter's write
            assert _pv(client, "pv633", t0).local_mode == "unity_pf"
            assert _truth_q(client, "pv675", t0) == 0.0  # step t0 was simulated before the first scan
            for i in (1, 2, 3):
                t = t0 + i * STEP_NS
                assert _truth_q(client, "pv675", t) < -1.0  # volt-var, absorbing
                assert _truth_q(client, "pv633", t) == 0.0 and _truth_q(client, "pv680", t) == 0.0
                assert _pv(client, "pv675", t).q_kvar < -1.0
            summary = _finish(th, stop, out)
        finally:
            stop.set()
            th.join(timeout=30)
    finally:
        for a in running.values():
            a.close()
    assert summary.steps == 4 and summary.sunspec_frame_misses == 0


def test_a_plant_that_is_not_on_the_feeder_or_a_bad_endpoint_is_refused(device_map_path: Path,
                                                                         cache_dir: Path) -> None:
    from simulator_bridge.bus.bridge import BridgeError, run_bridge

    for pv_sunspec, why in (({"pv999": f"tcp/127.0.0.1:{free_port()}"}, "pv999"),
                            ({"pv675": "tcp/192.0.2.1:502"}, "127.0.0.1 only"),
                            ({"pv675": "127.0.0.1:502"}, "tcp/HOST:PORT")):
        with pytest.raises(BridgeError, match=why):
            run_bridge(_config(device_map_path, cache_dir, pv_sunspec=pv_sunspec),
                       BusConfig(mode="peer", connect=(f"tcp/127.0.0.1:{free_port()}",)))
    with pytest.raises(BridgeError, match="no SCADA noise"):
        run_bridge(_config(device_map_path, cache_dir, noise_scada_pct=1.0,
                           pv_sunspec={"pv675": f"tcp/127.0.0.1:{free_port()}"}),
                   BusConfig(mode="peer", connect=(f"tcp/127.0.0.1:{free_port()}",)))
