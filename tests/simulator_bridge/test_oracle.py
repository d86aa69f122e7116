"""The case-A oracle: its perturbations run on a twin engine, so the simulated state is never
disturbed, and its answers equal perturbing the stepping engine itself. Real OpenDSS (IEEE 123 with caps moved)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from schemas.bus import MAX_PAYLOAD_BYTES, codec_for
from schemas.devicemap import DeviceMap, load_device_map
from schemas.messages import OracleReply
from simulator_bridge.opendss.engine import EngineError, FeederEngine
from simulator_bridge.simulation.oracle import Oracle

REPO = Path(__file__).resolve().parents[2]


def _busy_state(e: FeederEngine) -> None:
    """Loads, PV, every RegControl's tap and every bank away from the compiled state."""
    rng = np.random.default_rng(3)
    e.set_loads_kw(e.load_kw_nominal * rng.uniform(0.4, 1.1, len(e.load_kw_nominal)))
    e.set_pv(0.6 * e.pv_pmpp_kw, np.array([120.0, -60.0, 30.0]))
    for r, t in enumerate(e.control_taps()):
        e.set_control_tap(r, int(t) + (r % 3) - 1)
    for j, n in enumerate(e.control_cap_states()):
        e.set_control_cap_state(j, 1 - int(n))
    e.solve()


def test_a_twin_in_the_same_state_solves_the_same_voltages(map123: DeviceMap) -> None:
    a, b = FeederEngine(map123), FeederEngine(map123)
    try:
        _busy_state(a)
        b.solve()
        assert np.max(np.abs(a.node_voltages_pu() - b.node_voltages_pu())) > 1e-3  # the states differ ...
        b.set_state(a.state())
        b.solve()
        np.testing.assert_allclose(b.node_voltages_pu(), a.node_voltages_pu(), atol=1e-7)  # ... then do not
        sa, sb = a.state(), b.state()
        for field in ("load_kw", "pv_p_kw", "pv_q_kvar", "control_taps", "bank_states"):
            np.testing.assert_array_equal(getattr(sb, field), getattr(sa, field))
    finally:
        a.close()
        b.close()


def test_set_state_refuses_another_circuits_state(map123: DeviceMap) -> None:
    a, b = FeederEngine(map123), FeederEngine(load_device_map(REPO / "feeders" / "ieee13.toml"))
    try:
        with pytest.raises(EngineError, match="another circuit"):
            a.set_state(b.state())
    finally:
        a.close()
        b.close()


def test_the_oracle_leaves_the_simulation_untouched_and_answers_as_perturbing_it(map123: DeviceMap) -> None:
    e = FeederEngine(map123)
    oracle = Oracle(e)
    try:
        _busy_state(e)
        before, v_before = e.state(), e.node_voltages_pu()
        reply = oracle.reply(t_ns=60_000_000_000, seq=1, feeder_id="ieee123", include_sensitivities=True)
        # the stepping engine: the same state, the same solution, bit for bit
        after = e.state()
        for field in ("load_kw", "pv_p_kw", "pv_q_kvar", "control_taps", "bank_states"):
            np.testing.assert_array_equal(getattr(after, field), getattr(before, field))
        np.testing.assert_array_equal(e.node_voltages_pu(), v_before)
        # the answer: the zone's true voltages and the sensitivities of perturbing the engine itself
        zone = np.flatnonzero(e.node_in_feeder)
        assert reply.node_names == [e.node_names[i] for i in zone]
        np.testing.assert_array_equal(reply.v_pu, v_before[zone])
        s = e.perturbation_sensitivities()  # on the stepping engine, restored
        for got, want in ((reply.dv_dq_pu_per_kvar, s.dv_dq), (reply.dv_dtap_pu, s.dv_dtap),
                          (reply.dv_dp_pu_per_kw, s.dv_dp)):
            np.testing.assert_allclose(np.array(got), np.nan_to_num(want[zone]), atol=1e-6)
        assert np.max(np.abs(reply.dv_dtap_pu)) > 1e-3  # not an empty answer
        # a second answer after the state moved is of the new state
        e.set_pv(0.3 * e.pv_pmpp_kw, np.zeros(3))
        e.solve()
        again = oracle.reply(t_ns=120_000_000_000, seq=2, feeder_id="ieee123", include_sensitivities=False)
        np.testing.assert_array_equal(again.v_pu, e.node_voltages_pu()[zone])
        assert again.dv_dq_pu_per_kvar == []
    finally:
        oracle.close()
        e.close()


def test_the_oracle_reply_has_its_own_size_limit() -> None:
    """: epri-ckt24's reply (7,516 zone nodes) was 1.49 MB; every other message keeps the 1 MiB bound."""
    n, cols = 7522, 12
    reply = OracleReply(t_ns=1, seq=1, source="bridge", feeder_id="f", node_names=[f"bus{i}.1" for i in range(n)],
                        v_pu=[1.0123456789] * n, dv_dq_pu_per_kvar=[[1.23456789e-5] * 3] * n,
                        dv_dtap_pu=[[6.2345678e-3] * cols] * n, dv_dp_pu_per_kw=[[-2.3456789e-5] * 3] * n)
    raw = codec_for(OracleReply).encode(reply)
    assert len(raw) > MAX_PAYLOAD_BYTES
    assert codec_for(OracleReply).decode(raw) == reply
