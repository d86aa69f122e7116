"""Device logic without a bus: command checks, replay protection, watchdogs, acks, frames, noise, drops, latency."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from schemas import messages as m
from schemas.bus import codec_for
from simulator_bridge.field import devices as dv

NOW = 1_700_000_000 * 10**9
MIN = 60 * 10**9


def _pv_cmd(q: float = 100.0, *, seq: int = 1, source: str = "agent", plant: str = "pv1",
            valid_until: int = NOW + 5 * MIN, t_ns: int = NOW) -> m.PvCommand:
    return m.PvCommand(t_ns=t_ns, seq=seq, source=source, cmd_id=f"c{seq}", in_reply_to=0,
                       valid_until_t_ns=valid_until, plant_id=plant, q_kvar=q)


def _reg_cmd(action: m.TapAction | m.SetpointAction, *, seq: int = 1, reg: str = "r1",
             valid_until: int = NOW + 5 * MIN) -> m.RegCommand:
    return m.RegCommand(t_ns=NOW, seq=seq, source="agent", cmd_id=f"r{seq}", in_reply_to=0,
                        valid_until_t_ns=valid_until, regulator_id=reg, action=action)


@pytest.fixture
def pv() -> dv.PvInverter:
    return dv.PvInverter("pv1", 0, 1000.0, "unity_pf")


@pytest.fixture
def reg() -> dv.RegulatorController:
    return dv.RegulatorController("r1", 0, 16, 122.0, 2.0)


# ------------------------------------------------------------------------------ checks and replay
def test_a_valid_command_passes_and_becomes_active(pv: dv.PvInverter) -> None:
    c = _pv_cmd(150.0)
    assert pv.check(c, now_t_ns=NOW) is None
    pv.guard.apply(c, c.q_kvar)
    assert pv.q_setpoint_kvar == 150.0 and pv.guard.active is not None and pv.guard.active.cmd_id == "c1"


@pytest.mark.parametrize(("cmd", "reason"), [
    (_pv_cmd(plant="pv2"), "wrong_device"),          # payload names another device than the key
    (_pv_cmd(math.inf), "non_finite"),               # only reachable in process: JSON decode refuses inf
    (_pv_cmd(math.nan), "non_finite"),
    (_pv_cmd(valid_until=NOW), "expired"),           # valid until exactly now: never applies to a step
    (_pv_cmd(valid_until=NOW - 1), "expired"),
    (_pv_cmd(t_ns=NOW + 5 * MIN + 1), "out_of_window"),  # stamped more than one period ahead
    (_pv_cmd(valid_until=NOW + 60 * MIN + 1), "out_of_window"),  # in force for more than 12 periods
    (_pv_cmd(valid_until=2**63 - 1), "out_of_window"),
])
def test_generic_rejections(pv: dv.PvInverter, cmd: m.PvCommand, reason: str) -> None:
    v = pv.check(cmd, now_t_ns=NOW)
    assert v is not None and v.status == "rejected" and v.reason_kind == reason and v.reason.startswith(reason)
    assert pv.guard.active is None  # a rejected command changes nothing


def test_replays_are_rejected_per_source(pv: dv.PvInverter) -> None:
    first = _pv_cmd(seq=5)
    pv.guard.apply(first, first.q_kvar)
    for seq in (5, 4):  # the same seq again, or an older one
        v = pv.check(_pv_cmd(seq=seq), now_t_ns=NOW)
        assert v is not None and v.reason_kind == "replay"
    assert pv.check(_pv_cmd(seq=6), now_t_ns=NOW) is None
    assert pv.check(_pv_cmd(seq=1, source="other-agent"), now_t_ns=NOW) is None  # seqs are per source


def test_a_forged_huge_seq_locks_a_source_out_for_at_most_one_period(pv: dv.PvInverter) -> None:
    """ (b): two commands from 'agent' with seq 2**63-1 locked the real agent out for good."""
    forged = _pv_cmd(seq=2**63 - 1)
    assert pv.check(forged, now_t_ns=NOW) is None
    pv.guard.apply(forged, forged.q_kvar)
    later = NOW + 4 * MIN
    v = pv.check(_pv_cmd(seq=3, t_ns=later, valid_until=later + 10 * MIN), now_t_ns=later)
    assert v is not None and v.reason_kind == "replay"  # within the period: still a replay
    t = NOW + 5 * MIN  # one control period later the real agent is obeyed again
    assert pv.check(_pv_cmd(seq=3, t_ns=t, valid_until=t + 10 * MIN), now_t_ns=t) is None
    assert pv.check(_pv_cmd(seq=2**63 - 1), now_t_ns=t) is not None  # the old forgery replayed: refused


def test_without_an_identity_each_source_has_its_own_sequence(pv: dv.PvInverter) -> None:
    pv.guard.apply(_pv_cmd(seq=5), 1.0)
    assert pv.check(_pv_cmd(seq=1, source="agent2"), now_t_ns=NOW) is None  # another sender, by its own word


def test_with_an_authenticated_identity_naming_another_source_does_not_escape_replay_protection() -> None:
    """in secure mode every command comes under the one certificate that may command, so the
    sequence is that identity's, whatever ``source`` a command names; forgetting a lost sender forgets it.
    """
    from schemas.security import COMMAND_ROLE

    pv = dv.PvInverter("pv1", 0, 100.0, "unity_pf", sender_identity=COMMAND_ROLE)
    pv.guard.apply(_pv_cmd(seq=5), 1.0)
    for source in ("agent2", "bridge", "agent"):
        v = pv.check(_pv_cmd(seq=5, source=source), now_t_ns=NOW)
        assert v is not None and v.reason_kind == "replay" and repr(COMMAND_ROLE) in v.reason, source
    assert pv.check(_pv_cmd(seq=6, source="agent2"), now_t_ns=NOW) is None
    pv.guard.forget_source("agent2")  # an agent's liveliness token went: the identity counts from 1 again
    assert pv.check(_pv_cmd(seq=1), now_t_ns=NOW) is None
    t = NOW + 5 * MIN  # and a forged huge seq still locks it out for at most one control period
    pv.guard.apply(_pv_cmd(seq=2**63 - 1, source="x"), 1.0)
    assert pv.check(_pv_cmd(seq=2, t_ns=t, valid_until=t + 10 * MIN), now_t_ns=t) is None


def test_a_rejected_command_does_not_advance_the_seq(pv: dv.PvInverter) -> None:
    pv.guard.apply(_pv_cmd(seq=1), 1.0)
    assert pv.check(_pv_cmd(seq=7, valid_until=NOW), now_t_ns=NOW) is not None  # expired, not applied
    assert pv.check(_pv_cmd(seq=2), now_t_ns=NOW) is None


@pytest.mark.parametrize(("action", "ok"), [
    (m.TapAction(tap=16), True),
    (m.TapAction(tap=-16), True),
    (m.SetpointAction(setpoint_v120=124.0, band_v120=4.0), True),
    (m.SetpointAction(setpoint_v120=dv.SETPOINT_RANGE_V120[0], band_v120=dv.BAND_RANGE_V120[1]), True),
    (m.SetpointAction(setpoint_v120=139.0, band_v120=2.0), False),   # schema allows 100..140, device 108..132
    (m.SetpointAction(setpoint_v120=105.0, band_v120=2.0), False),
    (m.SetpointAction(setpoint_v120=122.0, band_v120=0.5), False),   # too narrow: would hunt
    (m.SetpointAction(setpoint_v120=122.0, band_v120=11.0), False),
])
def test_regulator_range(reg: dv.RegulatorController, action: m.TapAction | m.SetpointAction, ok: bool) -> None:
    v = reg.check(_reg_cmd(action), now_t_ns=NOW)
    assert (v is None) == ok
    if not ok:
        assert v is not None and v.reason_kind == "out_of_range"


def test_a_regulator_with_fewer_taps_rejects_taps_beyond_its_range() -> None:
    small = dv.RegulatorController("r1", 0, 8, 122.0, 2.0)
    v = small.check(_reg_cmd(m.TapAction(tap=9)), now_t_ns=NOW)
    assert v is not None and v.reason_kind == "out_of_range" and "-8..8" in v.reason


def test_regulator_modes_and_settings(reg: dv.RegulatorController) -> None:
    assert (reg.mode, reg.setpoint_v120, reg.band_v120) == ("local", 122.0, 2.0)
    v = reg.apply(_reg_cmd(m.TapAction(tap=3)))
    assert (v.status, v.applied_value, reg.mode) == ("accepted", 3.0, "locked")
    v = reg.apply(_reg_cmd(m.SetpointAction(setpoint_v120=125.0, band_v120=4.0), seq=2))
    assert (v.applied_value, reg.mode, reg.setpoint_v120, reg.band_v120) == (125.0, "local", 125.0, 4.0)


# ------------------------------------------------------------------------------------- watchdog
def test_watchdog_expires_after_valid_until_and_returns_to_default(reg: dv.RegulatorController) -> None:
    reg.apply(_reg_cmd(m.SetpointAction(setpoint_v120=125.0, band_v120=4.0), valid_until=NOW + MIN))
    assert reg.expire(NOW + MIN) is None  # in force for every step with t_ns <= valid_until
    gone = reg.expire(NOW + 2 * MIN)
    assert gone is not None and gone.cmd_id == "r1"
    assert (reg.mode, reg.setpoint_v120, reg.band_v120) == ("local", 122.0, 2.0)
    assert reg.expire(NOW + 3 * MIN) is None  # expires once


def test_pv_watchdog(pv: dv.PvInverter) -> None:
    c = _pv_cmd(-80.0, valid_until=NOW + MIN)
    pv.guard.apply(c, c.q_kvar)
    assert pv.guard.expire(NOW + MIN + 1) is not None and pv.q_setpoint_kvar is None


# ---------------------------------------------------------------------------------- verdicts, acks
def test_pv_verdict_accepts_or_clips_with_the_applied_value() -> None:
    assert dv.pv_verdict(100.0, 100.0, 400.0) == dv.Verdict(status="accepted", applied_value=100.0)
    v = dv.pv_verdict(900.0, 400.0, 400.0)
    assert v.status == "clipped" and v.applied_value == 400.0 and "headroom 400.000 kvar" in v.reason


def test_acks_round_trip_through_the_schema() -> None:
    for verdict in (dv.Verdict(status="accepted", applied_value=1.5), dv.reject("replay", "x" * 600),
                    dv.Verdict(status="expired", reason="back to unity_pf")):
        ack = dv.make_ack(device_id="pv1", source="pv1", cmd_id="c" * 120, verdict=verdict, t_ns=NOW, seq=3)
        codec = codec_for(m.Ack)
        assert codec.decode(codec.encode(ack)) == ack  # bounds (lengths) are checked on decode


# ------------------------------------------------------------------------------------- frames
def test_frames_from_readings_decode_within_schema_bounds(pv: dv.PvInverter, reg: dv.RegulatorController) -> None:
    v = np.array([2400.0, 2410.0, 0.0])  # phase c absent
    head = dv.head_frame(feeder_id="f", t_ns=NOW, seq=1, v_mag_v=v, v_ang_deg=np.array([0.0, -120.0, 0.0]),
                         i_mag_a=np.array([10.0, 11.0, 0.0]), i_ang_deg=np.array([-179.9, 181.0, 0.0]),
                         p_kw=np.array([20.0, 22.0, 0.0]), q_kvar=np.array([5.0, -1.0, 0.0]))
    assert [p.phase for p in head.phases] == ["a", "b"] and head.p_kw == 42.0 and head.q_kvar == 4.0
    assert head.phases[1].i_ang_deg == pytest.approx(-179.0)  # wrapped into (-180, 180]
    pv.guard.apply(_pv_cmd(120.0), 120.0)
    frame = dv.pv_frame(plant=pv, t_ns=NOW, seq=1, p_kw=np.full(3, 200.0), q_kvar=np.full(3, 40.0),
                        v_v=np.full(3, 2400.0), available_p_kw=600.0, q_setpoint_kvar=pv.q_setpoint_kvar)
    assert frame.q_available_kvar == pytest.approx(800.0) and frame.q_setpoint_kvar == 120.0
    assert frame.p_kw == 600.0 and frame.q_kvar == 120.0
    night = dv.pv_frame(plant=pv, t_ns=NOW, seq=2, p_kw=np.zeros(3), q_kvar=np.zeros(3), v_v=np.full(3, 2400.0),
                        available_p_kw=0.0, q_setpoint_kvar=None)
    assert night.q_available_kvar == 0.0  # no reactive power without active power (unless q_at_night)
    # (h): the frame reports the set point the inverter applies, not the request
    huge = dv.pv_frame(plant=pv, t_ns=NOW, seq=3, p_kw=np.full(3, 200.0), q_kvar=np.full(3, 266.0),
                       v_v=np.full(3, 2400.0), available_p_kw=600.0, q_setpoint_kvar=1e6)
    assert huge.q_setpoint_kvar == pytest.approx(800.0)
    assert dv.pv_frame(plant=pv, t_ns=NOW, seq=4, p_kw=np.zeros(3), q_kvar=np.zeros(3), v_v=np.full(3, 2400.0),
                       available_p_kw=0.0, q_setpoint_kvar=-300.0).q_setpoint_kvar == 0.0  # night: none applied
    rf = dv.reg_frame(reg=reg, t_ns=NOW, seq=1, phase="b", v120=121.5, v_compared_120=120.9, tap=4,
                      setpoint_v120=reg.setpoint_v120, band_v120=reg.band_v120, mode=reg.mode)
    assert rf.phases == [m.RegPhase(phase="b", v_120=121.5)] and rf.mode == "local"
    for msg in (head, frame, rf):
        codec = codec_for(type(msg))
        assert codec.decode(codec.encode(msg)) == msg


# ------------------------------------------------------------------------- measurement realism
def test_noise_off_is_exact_and_on_has_the_stated_sigma() -> None:
    exact = dv.MeasurementNoise(pmu_pct=0.0, scada_pct=0.0, seed=1)
    v = np.full(3, 2400.0)
    assert exact.regulator(121.0, 120.0) == (121.0, 120.0)
    assert np.array_equal(exact.pv(v, v, v, 1000.0)[2], v)

    noisy = dv.MeasurementNoise(pmu_pct=0.1, scada_pct=1.0, seed=1)
    n = 20_000
    reg = np.array([noisy.regulator(120.0, 120.0) for _ in range(n)])
    assert np.std(reg[:, 0]) == pytest.approx(1.2, rel=0.05)  # 1 % of 120 V
    heads = np.array([noisy.head(v, np.zeros(3), np.full(3, 100.0), np.zeros(3), np.full(3, 300.0),
                                 np.full(3, 400.0))[0] for _ in range(n // 10)])
    assert np.std(heads) == pytest.approx(2.4, rel=0.1)  # 0.1 % of 2400 V
    assert np.mean(heads) == pytest.approx(2400.0, abs=0.2)


def test_noise_is_seeded() -> None:
    a = dv.MeasurementNoise(pmu_pct=1.0, scada_pct=1.0, seed=7)
    b = dv.MeasurementNoise(pmu_pct=1.0, scada_pct=1.0, seed=7)
    assert [a.regulator(120.0, 120.0) for _ in range(5)] == [b.regulator(120.0, 120.0) for _ in range(5)]


@pytest.mark.parametrize("p", [0.0, 0.2, 1.0])
def test_drop_rate(p: float) -> None:
    d = dv.FrameDropper(p=p, seed=3)
    rate = np.mean([d.drop() for _ in range(10_000)])
    assert rate == pytest.approx(p, abs=0.02)


@pytest.mark.parametrize("p", [0.05, 0.2])
def test_drop_bursts_lose_the_share_in_outages_of_the_burst_length_per_device(p: float) -> None:
    d = dv.FrameDropper(p=p, seed=3, burst_s=600.0, step_s=60.0)
    minute = 60_000_000_000
    lost = {src: np.array([d.drop(src, k * minute) for k in range(40_000)]) for src in ("head", "pv1")}
    for x in lost.values():
        assert x.mean() == pytest.approx(p, rel=0.1)
        edges = np.flatnonzero(np.diff(np.r_[0, x.astype(int), 0]))
        runs = (edges[1::2] - edges[::2])[:-1]  # lengths of the outages [frames] (the last may be cut short)
        assert runs.min() >= 10 and np.mean(runs == 10) > 0.8  # 10-minute outages (back to back ones merge)
    assert np.mean(lost["head"] & lost["pv1"]) < 2 * p * p + 0.01  # the devices lose their links independently


def test_delay_line_releases_in_order_after_the_latency() -> None:
    line = dv.DelayLine(0.5)
    line.put("a", 10.0)
    line.put("b", 10.1)
    assert line.due(10.4) == [] and line.next_due_s() == pytest.approx(10.5)
    assert line.due(10.55) == ["a"] and line.due(11.0) == ["b"] and len(line) == 0
    zero = dv.DelayLine(0.0)
    zero.put("x", 1.0)
    assert zero.due(1.0) == ["x"]


@pytest.mark.parametrize("bad", [
    lambda: dv.DelayLine(-1.0), lambda: dv.DelayLine(math.nan), lambda: dv.FrameDropper(p=1.5, seed=0),
    lambda: dv.FrameDropper(p=0.1, seed=0, burst_s=-1.0),
    lambda: dv.MeasurementNoise(pmu_pct=-1.0, scada_pct=0.0, seed=0),
])
def test_bad_realism_settings_raise(bad) -> None:  # noqa: ANN001
    with pytest.raises(dv.DeviceError):
        bad()


def test_reject_reasons_are_listed() -> None:
    assert set(dv.REJECT_REASONS) == set(msgspec.inspect.type_info(dv.RejectReason).values)


# ------------------------------------------------------------------------------ capacitor banks
def _cap_cmd(steps: int | None = 1, *, seq: int = 1, cap: str = "c83", valid_until: int = NOW + 5 * MIN
             ) -> m.CapCommand:
    return m.CapCommand(t_ns=NOW, seq=seq, source="agent", cmd_id=f"k{seq}", in_reply_to=0,
                        valid_until_t_ns=valid_until, capacitor_id=cap, closed_steps=steps)


@pytest.fixture
def cap() -> dv.CapBankController:
    return dv.CapBankController("c83", 0, 2, 600.0, "voltage")


@pytest.mark.parametrize(("cmd", "reason"), [
    (_cap_cmd(cap="c88a"), "wrong_device"),             # payload names another bank than the key
    (_cap_cmd(3), "out_of_range"),                      # the bank has 2 steps
    (_cap_cmd(valid_until=NOW), "expired"),             # not valid after the present time
])
def test_cap_command_rejections(cap: dv.CapBankController, cmd: m.CapCommand, reason: str) -> None:
    v = cap.check(cmd, now_t_ns=NOW)
    assert v is not None and v.status == "rejected" and v.reason_kind == reason
    assert cap.mode == "local" and cap.guard.active is None  # a rejected command changes nothing


def test_cap_command_apply_replay_expire_release(cap: dv.CapBankController) -> None:
    c = _cap_cmd(2, seq=5)
    assert cap.check(c, now_t_ns=NOW) is None
    v = cap.apply(c, 2)
    assert (v.status, v.applied_value, cap.mode) == ("accepted", 2.0, "commanded")
    replay = cap.check(_cap_cmd(0, seq=5), now_t_ns=NOW)
    assert replay is not None and replay.reason_kind == "replay"
    assert cap.expire(NOW + 5 * MIN) is None  # in force up to and including valid_until
    gone = cap.expire(NOW + 6 * MIN)
    assert gone is not None and gone.cmd_id == "k5" and cap.mode == "local"
    c = _cap_cmd(0, seq=6)
    cap.apply(c, 0)
    release = _cap_cmd(None, seq=7)
    assert cap.check(release, now_t_ns=NOW) is None
    v = cap.apply(release, None)
    assert (v.status, v.applied_value, cap.mode) == ("accepted", None, "local")
    assert cap.expire(NOW + 60 * MIN) is None  # nothing left to expire


def test_cap_frame_round_trips_and_says_what_is_in_force(cap: dv.CapBankController) -> None:
    codec = codec_for(m.CapFrame)
    f = dv.cap_frame(cap=cap, t_ns=NOW, seq=1, closed_steps=1, v_v=2401.5, control_value=float("nan"), active=None)
    assert (f.mode, f.control_value, f.cmd_id, f.closed_steps, f.steps) == ("local", None, None, 1, 2)
    cap.apply(_cap_cmd(2, seq=1), 2)
    f = dv.cap_frame(cap=cap, t_ns=NOW, seq=2, closed_steps=2, v_v=2401.5, control_value=121.0,
                     active=cap.guard.active)
    assert (f.mode, f.cmd_id, f.valid_until_t_ns, f.control_value) == ("commanded", "k1", NOW + 5 * MIN, 121.0)
    assert codec.decode(codec.encode(f)) == f


def test_cap_noise_is_scada_class() -> None:
    noise = dv.MeasurementNoise(pmu_pct=0.0, scada_pct=1.0, seed=3)
    vs = np.array([noise.capacitor(2400.0, 120.0) for _ in range(2000)])
    assert abs(vs[:, 0].std() / 2400.0 - 0.01) < 0.002 and abs(vs[:, 1].std() / 120.0 - 0.01) < 0.002
    assert noise.capacitor(2400.0, None)[1] is None
    assert all(type(x) is float for x in noise.capacitor(2400.0, 120.0))  # msgspec encodes no NumPy scalars
    exact = dv.MeasurementNoise(pmu_pct=0.0, scada_pct=0.0, seed=3)
    assert exact.capacitor(2400.0, 120.0) == (2400.0, 120.0)


def test_cap_control_type_must_be_one_the_schema_knows() -> None:
    with pytest.raises(dv.DeviceError, match="control type 'powerfactor'"):
        dv.CapBankController("c1", 0, 1, 300.0, "powerfactor")  # type: ignore[arg-type]
