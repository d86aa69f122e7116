"""Qsts device physics on real OpenDSS solves of IEEE 123 (and the pure curves it uses)."""

from __future__ import annotations

from pathlib import Path

import msgspec
import numpy as np
import pytest

from schemas.devicemap import DeviceMap, load_device_map
from simulator_bridge.opendss.engine import FeederEngine
from simulator_bridge.simulation.qsts import VOLT_VAR_RESPONSE, Qsts, QstsError, tap_direction, volt_var_q_pu

REPO = Path(__file__).resolve().parents[2]


class ArrayProfiles:
    """A tiny stand-in for YearProfiles: the same methods over explicit arrays (1-minute steps)."""

    def __init__(self, load_kw: np.ndarray, pv_kw: np.ndarray, *, start_t_ns: int = 1_700_000_000 * 10**9):
        self._load, self._pv = np.asarray(load_kw, float), np.asarray(pv_kw, float)
        self.n_steps, self.n_loads = self._load.shape
        self.n_pv = self._pv.shape[1]
        self.step_s = 60
        self.start_t_ns = start_t_ns

    def t_ns(self, step: int) -> int:
        return self.start_t_ns + step * self.step_s * 10**9

    def load_kw(self, start: int, stop: int) -> np.ndarray:
        return self._load[start:stop]

    def pv_kw(self, start: int, stop: int) -> np.ndarray:
        return self._pv[start:stop]


def constant(engine: FeederEngine, n: int, load_frac: float, pv_frac: float) -> ArrayProfiles:
    return ArrayProfiles(np.tile(engine.load_kw_nominal * load_frac, (n, 1)),
                         np.tile(engine.pv_pmpp_kw * pv_frac, (n, 1)))


@pytest.fixture
def eng(map123: DeviceMap) -> FeederEngine:
    return FeederEngine(map123, tolerance=1e-6)


# --------------------------------------------------------------------------- pure curves
@pytest.mark.parametrize(
    ("v_pu", "q_pu"),
    [
        (0.90, 0.44),   # below V1: saturated at Q1
        (0.92, 0.44),   # V1
        (0.95, 0.22),   # halfway V1..V2
        (0.98, 0.0),    # V2: dead band starts
        (1.00, 0.0),    # inside the dead band
        (1.02, 0.0),    # V3
        (1.05, -0.22),  # halfway V3..V4
        (1.08, -0.44),  # V4
        (1.20, -0.44),  # above V4: saturated at Q4
    ],
)
def test_ieee1547_cat_b_volt_var(v_pu: float, q_pu: float) -> None:
    assert volt_var_q_pu(np.array([v_pu]))[0] == pytest.approx(q_pu, abs=1e-12)


def test_tap_direction() -> None:
    d = tap_direction(np.array([118.9, 119.1, 120.0, 120.9, 121.1]), np.full(5, 120.0), np.full(5, 2.0))
    np.testing.assert_array_equal(d, [1, 0, 0, 0, -1])


# --------------------------------------------------------------------------- regulators
def test_local_control_ends_inside_band(eng: FeederEngine) -> None:
    """Started cold (not settled), from tap 0 at nominal load creg1a compares ~115 V (band 119-121): it must end
    inside its band."""
    q = Qsts(eng, constant(eng, 5, 1.0, 0.0), start_step=0, settle_s=0)
    first = q.step()
    assert first.tap_changes.sum() > 0
    for _ in range(4):
        last = q.step()
    r = last.readings
    half = eng.reg_default_band_v120 / 2
    assert np.all(np.abs(r.reg_v120_compared - eng.reg_default_setpoint_v120) <= half + 1e-9)
    assert last.tap_changes.sum() == 0  # settled
    np.testing.assert_array_equal(last.taps, eng.taps())
    np.testing.assert_array_equal(r.reg_tap, last.taps)


def _with_commands(dm: DeviceMap, *commands: str) -> DeviceMap:
    feeder = msgspec.structs.replace(dm.feeder, extra_commands=[*dm.feeder.extra_commands, *commands])
    return msgspec.structs.replace(dm, feeder=feeder)


def test_taps_per_step_follow_the_regulators_delays(map123: DeviceMap) -> None:
    """creg1a with delay=30 s, tapdelay=10 s, ~5 V (7 taps) low: in the first minute it arms at 0 s and taps at
    30, 40 and 50 s (the one due at 60 s belongs to the next minute), then one tap every 10 s (60..110 s)."""
    eng = FeederEngine(_with_commands(map123, "edit regcontrol.creg1a delay=30 tapdelay=10"))
    q = Qsts(eng, constant(eng, 10, 1.0, 0.0), start_step=0, settle_s=0)
    t0 = eng.taps()
    results = [q.step() for _ in range(10)]
    changes = np.array([r.tap_changes for r in results])
    assert changes[0, 0] == 3
    assert changes[1, 0] == min(6, abs(results[1].taps[0] - results[0].taps[0]))
    assert changes[:, 0].max() <= 6
    # every tap move is counted: downstream regulators move back when creg1a raises their input, so
    # the count is at least the net move and differs from it by pairs of up/down moves
    net = np.abs(results[-1].taps - t0)
    assert np.all(changes.sum(axis=0) >= net)
    np.testing.assert_array_equal((changes.sum(axis=0) - net) % 2, 0)
    assert changes.sum(axis=0)[0] == net[0]  # creg1a itself only rises


def test_no_hunting_with_a_band_under_one_tap(eng: FeederEngine) -> None:
    """A band narrower than one tap (0.3 V < 0.75 V): creg1a (the others held) moves only toward its set
    point, as OpenDSS's pending change rounds to whole taps (within 0.375 V of vreg it wants none), and
    settles instead of hunting."""
    q = Qsts(eng, constant(eng, 6, 1.0, 0.0), start_step=0)
    q.command_setpoint(0, None, 0.3)
    for r in range(1, 7):
        q.command_tap(r, int(eng.taps()[r]))
    prev = eng.taps()
    moves = []
    for _ in range(6):
        res = q.step()
        assert res.tap_changes[0] == abs(res.taps[0] - prev[0])
        moves.append(res.tap_changes[0])
        prev = res.taps
    assert moves[0] > 0 and moves[-1] == 0 and moves[-2] == 0
    assert abs(res.readings.reg_v120_compared[0] - 120.0) < 0.375 + 0.05


def test_delay_longer_than_a_step(map123: DeviceMap) -> None:
    """delay=150 s: out of band from 0 s, creg1a's first tap comes at 150 s, in the third minute."""
    eng = FeederEngine(_with_commands(map123, "edit regcontrol.creg1a delay=150 tapdelay=5"))
    q = Qsts(eng, constant(eng, 4, 1.0, 0.0), start_step=0, settle_s=0)
    changes = [q.step().tap_changes[0] for _ in range(4)]
    assert changes[0] == 0 and changes[1] == 0 and 1 <= changes[2] <= 6  # 150, 155, ..., 175 s at most


def test_locked_tap_stays_then_unlocks(eng: FeederEngine) -> None:
    q = Qsts(eng, constant(eng, 6, 1.0, 0.0), start_step=0)
    settled = int(eng.taps()[0])  # where the settled start left creg1a
    assert q.command_tap(0, 40) == 16  # clipped to the regulator's range
    assert q.command_tap(0, -3) == -3
    first = q.step()
    assert first.taps[0] == -3 and first.tap_changes[0] == abs(settled + 3)  # commanded move counted
    for _ in range(2):
        res = q.step()
        assert res.taps[0] == -3 and res.tap_changes[0] == 0
    # creg1a is far below its band at tap -3; unlocked, local control takes it back up
    assert res.readings.reg_v120_compared[0] < 119.0
    q.command_tap(0, None)
    res = q.step()
    assert res.taps[0] > -3 and res.tap_changes[0] > 0


def test_the_start_is_settled_and_its_moves_are_not_counted(map123: DeviceMap) -> None:
    """The model leaves creg1a ~5 V under its band at nominal load. Started settled, the first step finds every
    regulator inside its band and counts no move; started cold, the same load moves taps in the first step."""
    cold_engine = FeederEngine(map123, tolerance=1e-6)
    model_taps = cold_engine.taps()
    cold = Qsts(cold_engine, constant(cold_engine, 2, 1.0, 0.0), start_step=0, settle_s=0)
    assert cold.step().tap_changes.sum() > 0
    eng = FeederEngine(map123, tolerance=1e-6)
    first = Qsts(eng, constant(eng, 2, 1.0, 0.0), start_step=0).step()
    assert first.tap_changes.sum() == 0 and first.cap_switches.sum() == 0
    assert np.any(first.taps != model_taps)  # the settling moved them, uncounted
    half = eng.reg_default_band_v120 / 2
    assert np.all(np.abs(first.readings.reg_v120_compared - eng.reg_default_setpoint_v120) <= half + 1e-9)
    for bad in (-1.0, float("nan")):
        with pytest.raises(QstsError, match="settle_s"):
            Qsts(eng, constant(eng, 2, 1.0, 0.0), start_step=0, settle_s=bad)


def test_commanded_setpoint_and_band(eng: FeederEngine) -> None:
    q = Qsts(eng, constant(eng, 4, 0.8, 0.0), start_step=0)
    q.command_setpoint(0, 123.0, 1.5)
    for _ in range(3):
        res = q.step()
    assert abs(res.readings.reg_v120_compared[0] - 123.0) <= 0.75
    q.command_setpoint(0, None, None)
    for _ in range(1):
        res = q.step()
    assert abs(res.readings.reg_v120_compared[0] - 120.0) <= 1.0


# --------------------------------------------------------------------------- PV
def test_pv_command_clipped_and_night(eng: FeederEngine) -> None:
    n = 4
    pv = np.tile(eng.pv_pmpp_kw, (n, 1))
    pv[2:] = 0.0  # sunset after two steps
    q = Qsts(eng, ArrayProfiles(np.tile(eng.load_kw_nominal * 0.5, (n, 1)), pv), start_step=0)
    q.command_pv_q(0, 2000.0)
    q.command_pv_q(1, -100.0)
    res = q.step()
    headroom = np.sqrt(eng.pv_kva**2 - eng.pv_pmpp_kw**2)
    np.testing.assert_allclose(res.pv_q_kvar, [headroom[0], -100.0, 0.0])  # plant 2: unity by default
    np.testing.assert_allclose(res.readings.pv_q_kvar.sum(axis=1), res.pv_q_kvar, atol=1e-2)
    np.testing.assert_allclose(res.pv_p_kw, eng.pv_pmpp_kw)
    q.step()
    night = q.step()
    np.testing.assert_array_equal(night.pv_q_kvar, 0.0)  # no Q at night
    np.testing.assert_allclose(night.readings.pv_q_kvar, 0.0, atol=1e-3)
    np.testing.assert_allclose(night.readings.pv_p_kw, 0.0, atol=1e-3)
    assert q.command_pv_q(0, 500.0) == 0.0  # what would apply now: nothing at night


def test_pv_q_at_night_when_asked(eng: FeederEngine) -> None:
    q = Qsts(eng, constant(eng, 2, 0.5, 0.0), start_step=0, pv_q_at_night=True)
    assert q.command_pv_q(1, -5000.0) == pytest.approx(-eng.pv_kva[1])  # full kVA available with P = 0
    res = q.step()
    assert res.pv_q_kvar[1] == pytest.approx(-eng.pv_kva[1])
    assert res.readings.pv_q_kvar[1].sum() == pytest.approx(-eng.pv_kva[1], abs=1e-2)


def test_a_plant_gives_q_at_night_where_its_map_entry_says_so(map123: DeviceMap) -> None:
    pvs = [msgspec.structs.replace(p, q_at_night=k == 1) for k, p in enumerate(map123.pv)]
    eng = FeederEngine(msgspec.structs.replace(map123, pv=pvs), tolerance=1e-6)
    q = Qsts(eng, constant(eng, 2, 0.5, 0.0), start_step=0)
    np.testing.assert_array_equal(q.pv_q_at_night, [k == 1 for k in range(len(pvs))])
    assert q.command_pv_q(0, -500.0) == 0.0
    assert q.command_pv_q(1, -500.0) == -500.0
    res = q.step()
    np.testing.assert_allclose(res.pv_q_kvar[:2], [0.0, -500.0])
    np.testing.assert_allclose(res.readings.pv_q_kvar[:2].sum(axis=1), [0.0, -500.0], atol=1e-2)
    everyone = Qsts(eng, constant(eng, 2, 0.5, 0.0), start_step=0, pv_q_at_night=False)  # the map overridden
    assert not everyone.pv_q_at_night.any() and everyone.command_pv_q(1, -500.0) == 0.0


def test_the_epri_ckt5_q_at_night_map_is_epri_ckt5_with_every_plant_giving_q_at_night() -> None:
    """``feeders/epri-ckt5-q-at-night.toml`` is a copy: it must not drift from the map it copies, nor ask for another
    model."""
    base = load_device_map(REPO / "feeders" / "epri-ckt5.toml")
    night = load_device_map(REPO / "feeders" / "epri-ckt5-q-at-night.toml")
    assert all(p.q_at_night for p in night.pv) and not any(p.q_at_night for p in base.pv)
    pvs = [msgspec.structs.replace(p, q_at_night=False) for p in night.pv]
    assert msgspec.structs.replace(night, pv=pvs) == base and night.fingerprint() == base.fingerprint()


def test_volt_var_uses_previous_step_voltage(eng: FeederEngine) -> None:
    """Light load and full sun raise the plants' voltages; volt-var moves Q toward curve(V of step k-1)·kVA,
    a share VOLT_VAR_RESPONSE of the way each step (first-order lag), and settles on the curve."""
    q = Qsts(eng, constant(eng, 60, 0.2, 1.0), start_step=0, pv_local="volt_var")
    prev = q.step()
    for _ in range(3):
        res = q.step()
        v_prev = np.array([prev.v_pu[list(ix)].mean() for ix in eng.pv_node_index])
        headroom = np.sqrt(eng.pv_kva**2 - res.pv_p_kw**2)
        target = prev.pv_q_kvar + VOLT_VAR_RESPONSE * (volt_var_q_pu(v_prev) * eng.pv_kva - prev.pv_q_kvar)
        np.testing.assert_allclose(res.pv_q_kvar, np.clip(target, -headroom, headroom), rtol=1e-12)
        prev = res
    for _ in range(30):  # the lag converges onto the curve's fixed point (no oscillation)
        prev, res = res, q.step()
    v_prev = np.array([prev.v_pu[list(ix)].mean() for ix in eng.pv_node_index])
    np.testing.assert_allclose(res.pv_q_kvar, volt_var_q_pu(v_prev) * eng.pv_kva, atol=1e-3 * eng.pv_kva.max())
    assert np.all(res.pv_q_kvar < 0)  # above 1.02 pu: absorbing
    # a command overrides the curve; None returns to it
    q.command_pv_q(2, 50.0)
    assert q.step().pv_q_kvar[2] == 50.0
    q.command_pv_q(2, None)
    back = [q.step().pv_q_kvar[2] for _ in range(8)]  # back toward the curve through the lag
    assert back[0] < 50.0 and back[-1] < 0


def test_volt_var_silent_at_night(eng: FeederEngine) -> None:
    """At night volt-var makes no Q even where the curve asks for it (low load: high voltage)."""
    q = Qsts(eng, constant(eng, 3, 0.1, 0.0), start_step=0, pv_local="volt_var")
    q.command_tap(0, 8)  # creg1a high: every plant above 1.02 pu, where the curve absorbs
    for _ in range(3):
        res = q.step()
    v_pv = np.array([res.v_pu[list(ix)].mean() for ix in eng.pv_node_index])
    assert np.all(volt_var_q_pu(v_pv) < 0)
    np.testing.assert_array_equal(res.pv_q_kvar, 0.0)


def test_step_result_shapes_and_time(eng: FeederEngine) -> None:
    prof = constant(eng, 3, 0.7, 0.3)
    q = Qsts(eng, prof, start_step=1)
    res = q.step()
    assert res.step == 1 and res.t_ns == prof.t_ns(1) and q.next_step == 2
    assert res.v_pu.shape == (len(eng.node_names),)
    assert res.taps.shape == res.tap_changes.shape == (7,)
    assert res.pv_q_kvar.shape == res.pv_p_kw.shape == (3,)
    assert res.readings.pv_p_kw.shape == (3, 3)
    q.step()
    with pytest.raises(QstsError, match="past the end"):
        q.step()


def test_profiles_that_do_not_fit(eng: FeederEngine) -> None:
    with pytest.raises(QstsError, match="91 and 3"):
        Qsts(eng, ArrayProfiles(np.ones((2, 5)), np.ones((2, 3))), start_step=0)
    with pytest.raises(QstsError, match="start_step"):
        Qsts(eng, constant(eng, 2, 1.0, 0.0), start_step=2)


def test_commands_reject_unknown_devices(eng: FeederEngine) -> None:
    q = Qsts(eng, constant(eng, 2, 1.0, 0.0), start_step=0)
    with pytest.raises(QstsError, match="no PV plant 3"):
        q.command_pv_q(3, 10.0)
    with pytest.raises(QstsError, match="no regulator 7"):
        q.command_tap(7, 1)
    with pytest.raises(QstsError, match="must be positive"):
        q.command_setpoint(0, float("nan"), None)


def test_staged_loads_solve_exactly_what_the_step_would_have(map123: DeviceMap) -> None:
    """The bridge sets the next step's loads while it waits for a decision (stage_loads): the steps, bit for bit,
    are those of a run without it, with commands in between; unstage_loads puts the present state back for a
    power flow of it (the oracle's)."""
    results = {}
    for staged in (False, True):
        e = FeederEngine(map123, tolerance=1e-6)
        rng = np.random.default_rng(3)
        load = e.load_kw_nominal * rng.uniform(0.3, 1.2, size=(8, len(e.load_kw_nominal)))
        q = Qsts(e, ArrayProfiles(load, np.tile(e.pv_pmpp_kw * 0.6, (8, 1))), start_step=0)
        out = []
        for i in range(7):
            out.append(q.step())
            if staged:
                q.stage_loads()
            if i == 2:  # a power flow of the present state between steps (the oracle's): back to its loads first
                if staged:
                    q.unstage_loads()
                e.solve()
                np.testing.assert_allclose(e.node_voltages_pu(), out[-1].v_pu, rtol=0, atol=1e-6)  # a re-solve
                if staged:
                    q.stage_loads()
            if i == 1:
                q.command_pv_q(0, 50.0)
                q.command_tap(0, 3)
        results[staged] = out
    for a, b in zip(results[False], results[True], strict=True):
        np.testing.assert_array_equal(a.v_pu, b.v_pu)
        np.testing.assert_array_equal(a.taps, b.taps)
    # the loads differ from step to step, so a run that left the staged loads in place would not match
    assert not np.array_equal(results[False][0].v_pu, results[False][1].v_pu)


# --------------------------------------------------------------------------- capacitor commands
def test_command_cap_holds_and_counts_switches(map123: DeviceMap) -> None:
    """A commanded bank is switched at the next step, counted once per step moved, and held."""
    from schemas.devicemap import CapacitorSpec

    dm = msgspec.structs.replace(map123, capacitor=[CapacitorSpec(id="c83", capacitor="c83")])
    e = FeederEngine(dm)
    q = Qsts(e, constant(e, 3, 1.0, 0.0), start_step=0)
    assert e.cap_states().tolist() == [1]
    assert q.command_cap(0, 0) == 0
    assert q.command_cap(0, 5) == 1  # clipped to the bank's one step
    assert q.command_cap(0, 0) == 0
    r0 = q.step()
    assert r0.cap_states.tolist() == [0] and r0.cap_switches.tolist() == [1]
    assert r0.readings.cap_states.tolist() == [0]
    r1 = q.step()
    assert r1.cap_states.tolist() == [0] and r1.cap_switches.tolist() == [0]
    assert q.command_cap(0, None) == 0  # no CapControl: it stays where it is
    assert q.step().cap_states.tolist() == [0]
    with pytest.raises(QstsError, match="no capacitor"):
        q.command_cap(1, 0)



def test_a_plants_own_local_mode_replaces_pv_local_for_it_alone(map123: DeviceMap) -> None:
    """set_pv_local (a plant's inverter set on its own, e.g. SunSpec 705): that plant follows the volt-var law of
    pv_local='volt_var' (toward curve(V of step k-1)·kVA through the lag), the others stay on unity; and back.
    Light load, full sun: the plants are above 1.02 pu, where the curve absorbs."""
    eng = FeederEngine(map123, tolerance=1e-6)
    mixed = Qsts(eng, constant(eng, 6, 0.2, 1.0), start_step=0, pv_local="unity")
    mixed.set_pv_local(1, True)
    prev = mixed.step()
    for _ in range(3):
        res = mixed.step()
        v_prev = float(prev.v_pu[list(eng.pv_node_index[1])].mean())
        target = prev.pv_q_kvar[1] + VOLT_VAR_RESPONSE * (volt_var_q_pu(v_prev) * eng.pv_kva[1] - prev.pv_q_kvar[1])
        assert res.pv_q_kvar[1] == pytest.approx(target, rel=1e-12) and res.pv_q_kvar[1] < 0
        np.testing.assert_array_equal(np.delete(res.pv_q_kvar, 1), 0.0)  # the others on unity
        prev = res
    mixed.set_pv_local(1, False)
    assert mixed.step().pv_q_kvar[1] == 0.0
    with pytest.raises(QstsError, match="PV plant"):
        mixed.set_pv_local(99, True)
