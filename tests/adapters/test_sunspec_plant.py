"""The SunSpec link and plant (adapters/sunspec.py, sunspec_plant.py) against a simulated inverter over real
Modbus TCP, without the bus: frames, the command contract, refused register values, a lost link.
"""

from __future__ import annotations

import time

import pytest

from adapters.errors import AdapterError, LinkDownError, RegisterValueError
from adapters.sunspec import SunSpecLink
from adapters.sunspec_plant import PlantSettings, SunSpecPlant
from adapters.sunspec_runtime import parse_modbus_endpoint
from schemas import messages as m
from schemas.bus import free_port

S = 1_000_000_000
PERIOD_NS = 300 * S


def _plant(inverter) -> SunSpecPlant:
    link = SunSpecLink("127.0.0.1", inverter.port, timeout_s=2.0)
    return SunSpecPlant(PlantSettings(feeder_id="f1", device_id="pv1", control_period_ns=PERIOD_NS), link)


def _cmd(q_kvar: float, now_ns: int, *, seq: int = 1, valid_s: float = 600.0, plant: str = "pv1") -> m.PvCommand:
    return m.PvCommand(t_ns=now_ns, seq=seq, source="agent", cmd_id=f"agent:{seq}:{plant}", in_reply_to=seq,
                       valid_until_t_ns=now_ns + int(valid_s * S), plant_id=plant, q_kvar=q_kvar)


@pytest.fixture
def plant(inverter):
    p = _plant(inverter)
    yield p
    p.link.close()


def test_a_scan_makes_the_plants_frame_in_our_units(plant):
    frame = plant.scan(7 * PERIOD_NS)
    assert frame is not None and plant.state == "ok"
    assert (frame.t_ns, frame.plant_id, frame.source) == (7 * PERIOD_NS, "pv1", "pv1")
    assert frame.p_kw == pytest.approx(600.0)
    assert [(p.phase, p.p_kw, p.v_mag_v) for p in frame.phases] == [("a", 200.0, 7250.0), ("b", 200.0, 7260.0),
                                                                     ("c", 200.0, 7270.0)]
    assert frame.s_rated_kva == 1000.0
    assert frame.q_available_kvar == pytest.approx(800.0)
    assert frame.q_setpoint_kvar is None  # on its local default


def test_a_command_is_written_read_back_and_acked_with_what_the_inverter_holds(plant, inverter):
    plant.scan(0)
    now = time.time_ns()
    ack = plant.command(_cmd(-123.4567, now), now)
    # VarSet_SF = 0: 1 var steps; -123.457 kvar is the request within half a step, so accepted
    assert (ack.status, ack.applied_value) == ("accepted", pytest.approx(-123.457))
    assert inverter.q_command_kvar() == pytest.approx(-123.457)
    state = inverter.control_state()
    assert state["VarSetEna"] == 1 and state["VarSetRvrtTms"] == 600  # the revert timer follows valid_until
    frame = plant.scan(PERIOD_NS)
    assert frame is not None and frame.q_setpoint_kvar == pytest.approx(-123.457)


def test_a_set_point_beyond_the_headroom_is_clipped_and_the_ack_says_so(plant, inverter):
    plant.scan(0)
    now = time.time_ns()
    ack = plant.command(_cmd(5000.0, now), now)
    assert ack.status == "clipped" and ack.applied_value == pytest.approx(800.0)
    assert "800.000" in ack.reason
    assert inverter.q_command_kvar() == pytest.approx(800.0)


def test_the_generic_checks_of_the_command_contract_apply(plant, inverter):
    plant.scan(0)
    now = time.time_ns()
    assert plant.command(_cmd(10.0, now, plant="pv2"), now).reason.startswith("wrong_device")
    assert plant.command(_cmd(10.0, now - 700 * S, valid_s=600.0), now).reason.startswith("expired")
    assert plant.command(_cmd(10.0, now, valid_s=13 * 300.0), now).reason.startswith("out_of_window")
    assert plant.command(_cmd(10.0, now, seq=5), now).status == "accepted"
    assert plant.command(_cmd(20.0, now, seq=5), now).reason.startswith("replay")
    assert plant.commands_failed == 4
    assert inverter.q_command_kvar() == pytest.approx(10.0)  # the rejected ones wrote nothing


@pytest.mark.parametrize(("model", "point", "raw", "refused"), [
    (701, "W_SF", None, "701.W_SF"),          # a scale factor not implemented: never read raw values as scaled
    (701, "W_SF", 11, "701.W_SF"),            # a scale factor outside -10..10
    (701, "W", 20_000, "701.W"),              # 2,000 kW (W_SF = 2) on a 1,000 kVA inverter: beyond 1.5 x rating
    (701, "Var", None, "701.Var"),            # not implemented
    (702, "VAMax", 0, "702.VAMax"),           # a zero rating
    (704, "VarSetEna", 7, "704.VarSetEna"),   # an enum value the model does not define
])
def test_a_malformed_or_out_of_range_register_is_refused_counted_and_gives_no_frame(plant, inverter, model, point,
                                                                                    raw, refused):
    assert plant.scan(0) is not None
    inverter.set_raw(model, point, raw)
    with pytest.raises(RegisterValueError, match=refused.replace(".", r"\.")):
        plant.link.read()
    assert plant.scan(PERIOD_NS) is None
    assert plant.state == "refusing" and plant.refused[refused] == 1
    assert refused in plant.reason
    status = plant.status(PERIOD_NS)
    assert status.state == "refusing" and status.refused == {refused: 1} and status.frames == 1


def test_a_refused_value_clears_when_the_inverter_reports_sane_values_again(plant, inverter):
    inverter.set_raw(701, "W", 20_000)
    assert plant.scan(0) is None
    inverter.set_measurements(p_kw=[100.0] * 3, v_v=[7200.0] * 3)
    frame = plant.scan(PERIOD_NS)
    assert frame is not None and frame.p_kw == pytest.approx(300.0) and plant.state == "ok"


def test_a_lost_link_stops_frames_fails_commands_and_recovers(plant, inverter):
    assert plant.scan(0) is not None
    inverter.stop()
    assert plant.scan(PERIOD_NS) is None
    assert plant.state == "down" and "did not answer" in plant.reason
    now = time.time_ns()
    ack = plant.command(_cmd(50.0, now), now)
    assert ack.status == "rejected" and ack.reason.startswith("link_down")
    assert plant.status(now).commands_failed == 1
    inverter.start()
    assert plant.scan(2 * PERIOD_NS) is not None and plant.state == "ok"
    assert plant.command(_cmd(50.0, now, seq=2), now).status == "accepted"


def test_an_expired_command_reverts_in_the_inverter_and_is_acked_expired(plant, inverter, inverter_clock):
    plant.scan(0)
    now = time.time_ns()
    assert plant.command(_cmd(-200.0, now, valid_s=120.0), now).status == "accepted"
    inverter_clock.offset_ns = 121 * S  # two minutes on: nobody talks to the inverter, its timer runs out
    assert inverter.q_command_kvar() is None
    frame = plant.scan(now + 121 * S)
    assert frame is not None and frame.q_setpoint_kvar is None
    ack = plant.expired(now + 121 * S)
    assert ack is not None and (ack.status, ack.cmd_id) == ("expired", "agent:1:pv1")
    assert plant.expired(now + 122 * S) is None


def test_no_inverter_at_the_endpoint_is_a_clear_link_error():
    link = SunSpecLink("127.0.0.1", free_port(), timeout_s=2.0)
    with pytest.raises(LinkDownError, match="no SunSpec device at tcp/127.0.0.1"):
        link.read()


@pytest.mark.parametrize("text", ["127.0.0.1:502", "udp/127.0.0.1:502", "tcp/127.0.0.1:0", "tcp/127.0.0.1:70000",
                                  "tcp/a b:502"])
def test_a_bad_modbus_endpoint_is_refused_with_the_form_to_use(text):
    with pytest.raises(AdapterError, match="tcp/HOST:PORT"):
        parse_modbus_endpoint(text)


def test_a_good_endpoint_parses():
    assert parse_modbus_endpoint("tcp/127.0.0.1:1502") == ("127.0.0.1", 1502)
    assert parse_modbus_endpoint("tcp/[::1]:502") == ("::1", 502)


def test_a_set_point_the_adapter_did_not_write_is_counted_logged_once_reasserted_and_shown(open_inverter, caplog):
    """On an inverter that takes any master's writes, a second Modbus master writes full absorption over our command:
    each scan finds it, writes ours again, and the link's status counts it; without a command in force a foreign set
    point is switched off."""
    inverter = open_inverter
    plant = _plant(inverter)
    plant.scan(0)
    now = time.time_ns()
    assert plant.command(_cmd(-100.0, now), now).status == "accepted"
    rogue = SunSpecLink("127.0.0.1", inverter.port, timeout_s=2.0)
    try:
        rogue.read()  # the other master learns the scale factors, as any would
        with caplog.at_level("WARNING"):
            for k in (1, 2):
                rogue.write_var_setpoint(-800.0, 3000)
                assert inverter.q_command_kvar() == pytest.approx(-800.0)
                frame = plant.scan(now + k * 60 * S)
                assert frame is not None and frame.q_setpoint_kvar == pytest.approx(-100.0)  # what holds now
                assert inverter.q_command_kvar() == pytest.approx(-100.0)
        status = plant.status(now + 120 * S)
        assert status.foreign_writes == 2 and "foreign write" in status.reason
        assert plant.scan(now + 180 * S) is not None and plant.foreign_writes == 2  # ours in force: nothing new
        assert caplog.text.count("did not write") + caplog.text.count("foreign write") == 1
        plant.plant.guard.expire(now + 601 * S)  # our command's time is over: none in force
        rogue.write_var_setpoint(300.0, 3000)
        assert plant.scan(now + 660 * S).q_setpoint_kvar is None and inverter.q_command_kvar() is None
        assert plant.foreign_writes == 3
    finally:
        rogue.close()
        plant.link.close()
