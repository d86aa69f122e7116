"""``cvvc adapter dnp3`` as a process: a simulated regulator control's frames on the bus, a clean stop on SIGTERM
with its last link status written; a non-loopback endpoint refused before the bus.
"""

from __future__ import annotations

import signal
import time

import msgspec
import pytest

from schemas import keys
from schemas import messages as m
from schemas.bus import BusConfig, Inbox, free_port, open_session, wait_for
from simulator_bridge.field.dnp3_sim import SimulatedRegulatorControl

pytestmark = [pytest.mark.bus, pytest.mark.process]  # a ``cvvc adapter`` program on a router

def test_the_adapter_puts_a_regulators_frames_on_the_bus_and_stops_cleanly(router_endpoint, tmp_path,
                                                                           cvvc_program):
    sim = SimulatedRegulatorControl(regulator_id="reg7", tap_max=16, default_setpoint_v120=121.0,
                                    default_band_v120=2.0, port=free_port(), clock_ns=time.time_ns)
    summary = tmp_path / "link.json"
    with sim, open_session(BusConfig(mode="peer", connect=(router_endpoint,))) as session:
        sim.set_measurements(v_compared_120=120.5, v_120=121.5, tap=-2, load_current_a=90.0)
        inbox = Inbox()
        inbox.subscribe(session, keys.meas_vr("f9", "reg7"))
        try:
            adapter = cvvc_program("adapter", "dnp3", "--feeder-id", "f9", "--device", "reg7", "--kind", "vr",
                                   "--dnp3", sim.endpoint, "--scan-period-s", "0.2", "--status-period-s", "0.5",
                                   "--summary-out", str(summary), "--connect", router_endpoint, "--insecure")
            got: list = []

            def frame_seen() -> bool:
                got.extend(r.msg for r in inbox.drain())
                return any(isinstance(x, m.RegFrame) for x in got)

            assert wait_for(frame_seen, 30.0, poll_s=0.05), "no frame from the adapter"
            frame = next(x for x in got if isinstance(x, m.RegFrame))
            assert (frame.regulator_id, frame.tap, frame.setpoint_v120) == ("reg7", -2, 121.0)
            adapter.send_signal(signal.SIGTERM)
            out, err = adapter.communicate(timeout=20)
            assert adapter.returncode == 0, err
            assert "adapter reg7 (vr" in out
            status = msgspec.json.decode(summary.read_bytes(), type=m.LinkStatus)
            assert (status.protocol, status.kind, status.state) == ("dnp3", "vr", "ok") and status.frames >= 1
        finally:
            inbox.undeclare()


def test_a_non_loopback_endpoint_exits_2_before_joining_the_bus(cvvc_program):
    proc = cvvc_program("adapter", "dnp3", "--feeder-id", "f9", "--device", "reg7", "--dnp3",
                        "tcp/192.0.2.5:20000", "--insecure")
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2 and "loopback only" in err
