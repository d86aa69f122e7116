"""``cvvc adapter sim`` and ``cvvc adapter sunspec`` as processes: frames on the bus, a clean stop on SIGTERM."""

from __future__ import annotations

import signal

import pytest

from schemas import keys
from schemas import messages as m
from schemas.bus import BusConfig, Inbox, free_port, open_session, wait_for

pytestmark = [pytest.mark.bus, pytest.mark.process]  # ``cvvc adapter`` programs on a router

def test_the_commands_serve_an_inverter_and_put_its_frames_on_the_bus_then_stop_cleanly(router_endpoint,
                                                                                        cvvc_program):
    modbus = f"tcp/127.0.0.1:{free_port()}"
    sim = cvvc_program("adapter", "sim", "--modbus", modbus, "--device", "pv7", "--s-rated-kva", "500", "--p-kw",
                       "300", "--v-nominal-v", "240")
    with open_session(BusConfig(mode="peer", connect=(router_endpoint,))) as session:
        inbox = Inbox()
        inbox.subscribe(session, keys.meas_pv("f9", "pv7"))
        inbox.subscribe(session, keys.link("f9", "pv", "pv7"))
        adapter = cvvc_program("adapter", "sunspec", "--feeder-id", "f9", "--device", "pv7", "--modbus", modbus,
                               "--scan-period-s", "0.2", "--status-period-s", "0.5", "--connect", router_endpoint,
                               "--insecure")
        got: list = []

        def frame_seen() -> bool:
            got.extend(r.msg for r in inbox.drain())
            return any(isinstance(x, m.PvFrame) for x in got)

        assert wait_for(frame_seen, 30.0, poll_s=0.05), "no frame from the adapter"
        frame = next(x for x in got if isinstance(x, m.PvFrame))
        assert frame.plant_id == "pv7" and abs(frame.p_kw - 300.0) < 0.1 and frame.s_rated_kva == 500.0
        assert wait_for(lambda: frame_seen() and any(isinstance(x, m.LinkStatus) and x.state == "ok"
                                                     for x in got), 10.0, poll_s=0.05)
        adapter.send_signal(signal.SIGTERM)
        out, err = adapter.communicate(timeout=20)
        assert adapter.returncode == 0, err
        assert "adapter pv7" in out and "frames" in out
    sim.send_signal(signal.SIGTERM)
    sim.communicate(timeout=20)
    assert sim.returncode == 0
