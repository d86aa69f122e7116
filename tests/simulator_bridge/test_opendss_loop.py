"""OpenDSS's own control loop as the ``opendss`` reference case (opendss_loop.py) against our QSTS ``none`` case.

Both are the local control physics of the same model: our event clock (controls.py through Qsts) was checked
tap for tap against OpenDSS's loop at 1 s steps (test_controls.py). The reference runs at 5 s steps, so an action
due between two of its solves lands up to 5 s late; within a minute that changes nothing, and only an action
due in the last seconds of a minute moves into the next, where the voltages then differ for one minute. Hence
tap counts per regulator equal within one tap, and voltage extremes within 0.005 pu.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from schemas.devicemap import load_device_map
from simulator_bridge.opendss.control_check import MinuteProfiles
from simulator_bridge.opendss.engine import EngineError, FeederEngine
from simulator_bridge.opendss.opendss_loop import OpenDssLoop, reference_metrics
from simulator_bridge.simulation.metrics_stream import MetricsAccumulator
from simulator_bridge.simulation.qsts import Qsts

MAPS = Path(__file__).resolve().parents[2] / "feeders"
_NS = 1_000_000_000
_T0_NS = 1_704_067_200 * _NS + 8 * 3600 * _NS  # 2024-01-01 08:00 UTC
MINUTES = 180


def _swing_profiles(dm) -> MinuteProfiles:
    """Every load 0.2 -> 1.3 -> 0.2 of nominal over three hours; PV a half-sine peaking at 80 % of Pmpp."""
    eng = FeederEngine(dm)
    base, pmpp = eng.load_kw_nominal.copy(), eng.pv_pmpp_kw.copy()
    eng.close()
    half = MINUTES // 2
    mult = np.concatenate([np.linspace(0.2, 1.3, half), np.linspace(1.3, 0.2, MINUTES - half)])
    sun = 0.8 * np.sin(np.pi * np.arange(MINUTES) / (MINUTES - 1))
    return MinuteProfiles(mult[:, None] * base[None, :], len(pmpp), start_t_ns=_T0_NS,
                          pv_kw=sun[:, None] * pmpp[None, :])


def _none_case(dm, profiles: MinuteProfiles):
    eng = FeederEngine(dm)
    try:
        sim = Qsts(eng, profiles, start_step=0, pv_local="unity")
        acc = MetricsAccumulator.for_feeder(dm, eng, step_s=60)
        for _ in range(profiles.n_steps):
            r = sim.step()
            acc.update(r.v_pu, r.tap_changes, r.pv_q_kvar, r.cap_switches)
    finally:
        eng.close()
    return acc.result()


@pytest.mark.parametrize("feeder", ["ieee13", "epri-k1"])
def test_first_solve_is_the_engine_snapshot(feeder: str) -> None:
    """Handed to OpenDSS's loop, the feeder solves the loads and PV the engine set (no load shape scales them in
    daily mode; epri-k1's loads carry yearly shapes), and no control acts before its delay."""
    dm = load_device_map(MAPS / f"{feeder}.toml")
    a = FeederEngine(dm)
    load, pv = 0.8 * a.load_kw_nominal, 0.5 * a.pv_pmpp_kw
    a.set_loads_kw(load)
    a.set_pv(pv, np.zeros(len(pv)))
    a.solve()
    v_snapshot = a.node_voltages_pu()
    a.close()
    loop = OpenDssLoop(FeederEngine(dm), step_s=60.0, start_tod_s=12 * 3600.0)
    try:
        r = loop.step(load, pv)
    finally:
        loop.close()
    assert np.abs(r.v_pu - v_snapshot).max() < 1e-5
    assert r.tap_changes.sum() == 0 and r.cap_switches.sum() == 0


def test_reference_taps_agree_with_the_none_case_on_a_load_swing() -> None:
    """IEEE 13, three hours of a load swing with PV, both started settled: the reference moves every regulator, as
    many taps as our none case within one per regulator, and judges the same voltages."""
    dm = load_device_map(MAPS / "ieee13.toml")
    profiles = _swing_profiles(dm)
    ref = reference_metrics(dm, profiles, start_step=0, steps=MINUTES, step_s=5.0)
    ours = _none_case(dm, profiles)
    assert ref.n_steps == ours.n_steps == MINUTES
    assert ref.regulator_ids == ours.regulator_ids
    assert all(n >= 2 for n in ref.tap_changes_per_regulator), ref.tap_changes_per_regulator
    diff = np.abs(np.subtract(ref.tap_changes_per_regulator, ours.tap_changes_per_regulator))
    assert diff.max() <= 1, (ref.tap_changes_per_regulator, ours.tap_changes_per_regulator)
    assert abs(ref.v_min_pu - ours.v_min_pu) < 5e-3 and abs(ref.v_max_pu - ours.v_max_pu) < 5e-3
    assert ref.q_cost == 0.0  # unity power factor


def test_a_held_load_moves_no_tap_after_settling() -> None:
    """The counting is of moves, not positions: an hour at one load moves taps only in its first minutes."""
    dm = load_device_map(MAPS / "ieee13.toml")
    eng = FeederEngine(dm)
    load, pv = 0.2 * eng.load_kw_nominal, np.zeros(len(eng.pv_ids))
    loop = OpenDssLoop(eng, step_s=5.0, start_tod_s=0.0)
    try:
        moves = np.array([loop.step(load, pv).tap_changes.sum() for _ in range(60)])
    finally:
        loop.close()
    assert moves[:10].sum() > 0
    assert moves[30:].sum() == 0


def test_bad_step_and_window_are_clear_errors() -> None:
    dm = load_device_map(MAPS / "ieee13.toml")
    eng = FeederEngine(dm)
    try:
        with pytest.raises(EngineError, match="must divide 60"):
            OpenDssLoop(eng, step_s=7.0, start_tod_s=0.0)
    finally:
        eng.close()
    profiles = _swing_profiles(dm)
    with pytest.raises(EngineError, match="outside the profiles"):
        reference_metrics(dm, profiles, start_step=MINUTES - 10, steps=20, step_s=5.0)


def test_profiles_of_other_than_minute_rows_are_refused() -> None:
    """The reference steps minutes: profiles whose rows are 30 s (``step_s``, part of the ``Profiles`` protocol,
    no longer assumed 60 when absent) are a clear error naming their row length, before any solve."""
    dm = load_device_map(MAPS / "ieee13.toml")
    profiles = _swing_profiles(dm)
    profiles.step_s = 30
    with pytest.raises(EngineError, match="the profiles have 30 s rows"):
        reference_metrics(dm, profiles, start_step=0, steps=10, step_s=5.0)
    profiles.step_s = 60  # the same rows as minutes: accepted
    assert reference_metrics(dm, profiles, start_step=0, steps=2, step_s=60.0).n_steps == 2


def test_skipping_quiet_solves_changes_nothing() -> None:
    """Once OpenDSS's control queue is empty the rest of a minute's solves are skipped: the same counts and costs as
    solving all twelve, voltages equal within the solver's tolerance (1e-6: a repeated solve only refines the
    solution), with most solves skipped (IEEE 13's load swing with PV)."""
    dm = load_device_map(MAPS / "ieee13.toml")
    profiles = _swing_profiles(dm)
    full = reference_metrics(dm, profiles, start_step=0, steps=MINUTES, step_s=5.0, skip_quiet=False)
    fast = reference_metrics(dm, profiles, start_step=0, steps=MINUTES, step_s=5.0, skip_quiet=True)
    for name in ("nvv", "steps_in_violation", "tap_changes_per_regulator", "cap_switches_per_bank", "total_cost"):
        assert getattr(fast, name) == getattr(full, name), name
    for name in ("mvvm_pu", "v_min_pu", "v_max_pu", "v_avg_min_pu", "v_avg_max_pu"):
        assert abs(getattr(fast, name) - getattr(full, name)) < 1e-6, name
    loop = OpenDssLoop(FeederEngine(dm), step_s=5.0, start_tod_s=0.0)
    try:
        for m in range(MINUTES):
            loop.step(profiles.load_kw(m, m + 1)[0], profiles.pv_kw(m, m + 1)[0])
    finally:
        loop.close()
    assert loop.skipped > MINUTES * 11 // 2
