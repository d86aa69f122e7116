"""The paper's IV.F metrics on small hand-made series with known answers (simulator_bridge/simulation/metrics.py)."""

import msgspec
import numpy as np
import pytest

from schemas.errors import CvvcError
from simulator_bridge.simulation.metrics import (
    Metrics,
    MetricsError,
    combine_metrics,
    metrics_from_series,
    over_tap_rate,
    q_cost_per_plant,
    rolling_mean_pu,
    tap_cost_per_regulator,
    tap_rate_allowance,
    violation_pu,
)
from simulator_bridge.simulation.metrics_stream import MetricsAccumulator

REGS = ("vr1", "vr2")
PVS = ("pv1", "pv2")


def _stream(v, taps, q, **kw):
    """Feed whole arrays one row at a time into an accumulator; return its result."""
    kw = {"regulator_ids": REGS, "pv_ids": PVS, "cost_per_tap": 0.14, "cost_per_kvar": 0.001} | kw
    acc = MetricsAccumulator(n_nodes=v.shape[1], **kw)
    for row in range(v.shape[0]):
        acc.update(v[row], taps[row], q[row])
    assert acc.n_steps == v.shape[0]
    return acc.result()


def _batch(v, taps, q, **kw):
    kw = {"regulator_ids": REGS, "pv_ids": PVS, "cost_per_tap": 0.14, "cost_per_kvar": 0.001} | kw
    return metrics_from_series(v, taps, q, **kw)


def _hand_series():
    """60 one-minute steps, 4 nodes.

    node 0: 1.00, then 1.06 for the 15 minutes t = 20..34, then 1.00 again.
    node 1: 1.00 with a 3-minute dip to 0.95 at t = 40..42.
    node 2: 0.96 all the time (just below 0.965).
    node 3: 1.00 all the time.
    """
    v = np.ones((60, 4))
    v[20:35, 0] = 1.06
    v[40:43, 1] = 0.95
    v[:, 2] = 0.96
    return v, np.zeros((60, 2), dtype=int), np.zeros((60, 2))


def test_hand_made_voltage_series():
    v, taps, q = _hand_series()
    # 10-minute causal average, judged from t = 9 on (51 judged steps).
    # node 0: k samples of 1.06 in the window give 1 + 0.006 k; above 1.05 when k >= 9:
    #   k = 9 at t = 28 and t = 35, k = 10 at t = 29..34 -> 8 samples, worst 1.06 - 1.05 = 0.010 pu.
    # node 1: at most 3 samples of 0.95 -> 1 - 0.005 * 3 = 0.985 >= 0.965: no violation.
    # node 2: 0.96 < 0.965 at every judged step -> 51 samples of 0.005 pu.
    # NVV = 8 + 51 = 59; minutes in violation = the 51 judged minutes (node 0's 8 fall among them).
    for m in (_stream(v, taps, q), _batch(v, taps, q)):
        assert m.n_steps == 60 and m.n_steps_judged == 51
        assert m.mvvm_pu == pytest.approx(0.010, abs=1e-12)
        assert m.mvvm_node == 0
        assert m.nvv == 59
        assert m.steps_in_violation == 51 and m.minutes_in_violation == 51.0
        assert m.v_min_pu == pytest.approx(0.95) and m.v_max_pu == pytest.approx(1.06)
        assert m.v_avg_min_pu == pytest.approx(0.96) and m.v_avg_max_pu == pytest.approx(1.06)
        assert (m.ntc, m.t_cost, m.q_cost, m.total_cost) == (0, 0.0, 0.0, 0.0)


def test_single_node_above_limit_for_fifteen_minutes():
    # The brief's example alone: one node at 1.06 for 15 minutes, 1.00 otherwise, 40 minutes in all.
    # Rolling average above 1.05 needs >= 9 of the 10 samples at 1.06: windows ending at t = 28..35
    # (k = 9, 10, 10, 10, 10, 10, 10, 9) -> NVV = 8, 8 minutes in violation, MVVM = 0.01 pu.
    v = np.ones((40, 1))
    v[20:35, 0] = 1.06
    m = _stream(v, np.zeros((40, 2), dtype=int), np.zeros((40, 2)))
    assert (m.nvv, m.minutes_in_violation, m.mvvm_node) == (8, 8.0, 0)
    assert m.mvvm_pu == pytest.approx(0.01, abs=1e-12)


def test_short_spikes_are_averaged_away_and_limits_are_strict():
    v = np.ones((30, 2))
    v[12:14, 0] = 1.20  # two minutes at 1.20: average 1 + 0.4 / 10 = 1.04, inside
    v[:, 1] = 1.05  # exactly on the limit: not a violation
    m = _stream(v, np.zeros((30, 2), dtype=int), np.zeros((30, 2)))
    assert (m.nvv, m.mvvm_pu, m.mvvm_node, m.steps_in_violation) == (0, 0.0, -1, 0)
    assert m.v_max_pu == pytest.approx(1.20) and m.v_avg_max_pu == pytest.approx(1.05)


def test_run_shorter_than_window_judges_nothing():
    v = np.full((9, 3), 1.2)
    for m in (_stream(v, np.zeros((9, 2), dtype=int), np.zeros((9, 2))), _batch(v, np.zeros((9, 2)), np.zeros((9, 2)))):
        assert (m.n_steps, m.n_steps_judged, m.nvv, m.mvvm_pu) == (9, 0, 0, 0.0)
        assert m.v_avg_min_pu is None and m.v_max_pu == pytest.approx(1.2)


def test_tap_cost():
    # vr1 moves 1 tap at 5 steps and 2 taps at one step (7 taps); vr2 moves 3 taps once.
    taps = np.zeros((20, 2), dtype=int)
    taps[[1, 3, 5, 7, 9], 0] = 1
    taps[11, 0] = 2
    taps[4, 1] = 3
    v = np.ones((20, 1))
    m = _stream(v, taps, np.zeros((20, 2)))
    assert m.tap_changes_per_regulator == (7, 3) and m.ntc == 10
    assert m.t_cost == pytest.approx(10 * 0.14) and m.total_cost == pytest.approx(1.4)
    # Per-regulator costs: 7 x 0.2 + 3 x 0.1 = 1.7.
    m = _stream(v, taps, np.zeros((20, 2)), cost_per_tap=[0.2, 0.1])
    assert m.t_cost == pytest.approx(1.7)
    np.testing.assert_allclose(tap_cost_per_regulator(taps, np.array([0.2, 0.1])), [1.4, 0.3])


def test_q_cost_and_reactive_energy():
    # pv1 holds +100 kvar for 60 one-minute steps = 12 five-minute control intervals;
    # pv2 holds -50 kvar (absorbing) for the first 30 steps = 6 intervals.
    # Q cost = 0.001 x 100 x 12 + 0.002 x 50 x 6 = 1.2 + 0.6 = 1.8.
    # kvarh: 100 kvar x 1 h = 100; 50 kvar x 0.5 h = 25. Mvar-intervals: 0.1 x 12 = 1.2; 0.05 x 6 = 0.3.
    q = np.zeros((60, 2))
    q[:, 0] = 100.0
    q[:30, 1] = -50.0
    for m in (
        _stream(np.ones((60, 1)), np.zeros((60, 2), dtype=int), q, cost_per_kvar=[0.001, 0.002]),
        _batch(np.ones((60, 1)), np.zeros((60, 2), dtype=int), q, cost_per_kvar=[0.001, 0.002]),
    ):
        assert m.q_cost == pytest.approx(1.8)
        np.testing.assert_allclose(m.q_cost_per_plant, [1.2, 0.6])
        np.testing.assert_allclose(m.q_kvarh_per_plant, [100.0, 25.0])
        np.testing.assert_allclose(m.q_mvar_intervals_per_plant, [1.2, 0.3])
        assert m.total_cost == pytest.approx(1.8) and m.t_cost == 0.0
    np.testing.assert_allclose(
        q_cost_per_plant(q, np.array([0.001, 0.002]), step_s=60, control_period_s=300), [1.2, 0.6]
    )
    # A 10-second step with a 60-second control period: 100 kvar for 6 steps = 1 interval.
    np.testing.assert_allclose(
        q_cost_per_plant(np.full((6, 1), 100.0), np.array([0.5]), step_s=10, control_period_s=60), [50.0]
    )


def test_pure_functions():
    v = np.array([[1.0], [2.0], [3.0], [4.0]])
    np.testing.assert_allclose(rolling_mean_pu(v, 2), [[np.nan], [1.5], [2.5], [3.5]])
    np.testing.assert_allclose(rolling_mean_pu(v, 1), v)
    assert np.isnan(rolling_mean_pu(v, 5)).all()
    np.testing.assert_allclose(
        violation_pu(np.array([0.96, 0.965, 1.0, 1.05, 1.07]), (0.965, 1.05)), [0.005, 0, 0, 0, 0.02], atol=1e-12
    )


def test_stream_equals_batch_on_random_series():
    rng = np.random.default_rng(3)
    v = 1.0 + 0.03 * np.cumsum(rng.standard_normal((500, 30)), axis=0) / 10
    taps = rng.integers(0, 3, (500, 2)) * (rng.random((500, 2)) < 0.1)
    q = rng.normal(0, 300, (500, 2))
    a, b = _stream(v, taps, q), _batch(v, taps, q)
    assert a.nvv > 0 and a.ntc > 0  # the series does exercise the metrics
    assert (a.nvv, a.steps_in_violation, a.ntc, a.mvvm_node) == (b.nvv, b.steps_in_violation, b.ntc, b.mvvm_node)
    for name in ("mvvm_pu", "q_cost", "t_cost", "total_cost", "v_min_pu", "v_max_pu", "v_avg_min_pu", "v_avg_max_pu"):
        assert getattr(a, name) == pytest.approx(getattr(b, name), rel=1e-12, abs=1e-12), name



def test_stream_at_the_limits_and_with_integer_or_float_taps():
    # Averages of samples exactly at a limit round to 1.0500000000000002: within the tolerance, not violations,
    # whether the streaming update takes its shortcut (no node near a limit) or not. Float tap changes that are
    # whole numbers are accepted as integer ones are.
    v = np.ones((30, 3))
    v[:, 0] = 1.05
    v[:, 1] = 0.965
    v[12:20, 2] = 1.2
    taps = np.zeros((30, 2), dtype=int)
    taps[3, 0] = 2
    q = np.zeros((30, 2))
    a, b = _stream(v, taps, q), _batch(v, taps, q)
    c = _stream(v, taps.astype(float), q)
    assert a == c
    assert (a.nvv, a.steps_in_violation, a.mvvm_node, a.ntc) == (b.nvv, b.steps_in_violation, b.mvvm_node, b.ntc)
    assert a.nvv > 0 and a.mvvm_node == 2
    assert a.v_avg_max_pu == pytest.approx(b.v_avg_max_pu, rel=1e-12)
    assert a.mvvm_pu == pytest.approx(b.mvvm_pu, rel=1e-12)

def test_combine_adds_months():
    v, taps, q = _hand_series()
    taps[5, 1] = 2
    q[:, 0] = 10.0
    one = _stream(v, taps, q)
    both = one.combine(one)
    assert (both.n_steps, both.nvv, both.ntc, both.steps_in_violation) == (120, 118, 4, 102)
    assert both.mvvm_pu == one.mvvm_pu and both.mvvm_node == 0
    assert both.q_cost == pytest.approx(2 * one.q_cost) and both.total_cost == pytest.approx(2 * one.total_cost)
    assert both.tap_changes_per_regulator == (0, 4)
    # A month with a worse violation elsewhere wins MVVM; extremes combine.
    v2 = np.ones((30, 4))
    v2[:, 3] = 0.90
    other = _stream(v2, np.zeros((30, 2), dtype=int), np.zeros((30, 2)))
    total = combine_metrics([one, other, one])
    assert total.mvvm_pu == pytest.approx(0.065) and total.mvvm_node == 3
    assert total.v_min_pu == pytest.approx(0.90) and total.v_max_pu == pytest.approx(1.06)
    assert total.nvv == 2 * 59 + 21  # node 3 at 0.90 over the 21 judged steps of the other run
    # Runs shorter than a window still combine (None extremes are skipped).
    empty = _stream(np.ones((3, 4)), np.zeros((3, 2), dtype=int), np.zeros((3, 2)))
    assert one.combine(empty).v_avg_min_pu == one.v_avg_min_pu
    with pytest.raises(MetricsError, match="different pv_ids"):
        one.combine(_stream(v, taps, q, pv_ids=("a", "b")))
    with pytest.raises(MetricsError, match="at least one"):
        combine_metrics([])


def test_metrics_round_trip_as_json():
    v, taps, q = _hand_series()
    m = _stream(v, taps, q)
    back = msgspec.json.decode(msgspec.json.encode(m), type=Metrics)
    assert back == m
    with pytest.raises(msgspec.ValidationError):
        msgspec.json.decode(msgspec.json.encode(m).replace(b'"nvv":59', b'"nvv":-1'), type=Metrics)


def test_memory_stays_bounded():
    acc = MetricsAccumulator(n_nodes=50, regulator_ids=REGS, pv_ids=PVS, cost_per_tap=0.14, cost_per_kvar=0.001)
    before = sum(a.nbytes for a in vars(acc).values() if isinstance(a, np.ndarray))
    for _ in range(3000):
        acc.update(np.ones(50), np.zeros(2, dtype=int), np.zeros(2))
    after = sum(a.nbytes for a in vars(acc).values() if isinstance(a, np.ndarray))
    assert after == before <= 10 * 50 * 8 + 1000
    assert acc.result().n_steps_judged == 2991


@pytest.mark.parametrize(
    ("v", "taps", "q", "message"),
    [
        (np.ones(3), np.zeros(2), np.zeros(2), r"v_pu has shape \(3,\); expected \(4,\)"),
        (np.r_[1.0, np.nan, 1.0, 1.0], np.zeros(2), np.zeros(2), "NaN"),
        (np.ones(4), np.array([1, -1]), np.zeros(2), "whole numbers >= 0"),
        (np.ones(4), np.array([0.5, 0]), np.zeros(2), "whole numbers >= 0"),
        (np.ones(4), np.zeros(3), np.zeros(2), r"tap_changes has shape \(3,\)"),
        (np.ones(4), np.zeros(2), np.array([np.inf, 0.0]), "pv_q_kvar has NaN or infinite"),
        (np.ones(4), np.zeros(2), np.zeros(1), r"pv_q_kvar has shape \(1,\)"),
    ],
)
def test_bad_updates_are_rejected(v, taps, q, message):
    acc = MetricsAccumulator(n_nodes=4, regulator_ids=REGS, pv_ids=PVS, cost_per_tap=0.14, cost_per_kvar=0.001)
    with pytest.raises(MetricsError, match=message):
        acc.update(v, taps, q)
    assert acc.n_steps == 0


def test_bad_configuration():
    kw = {"n_nodes": 4, "regulator_ids": REGS, "pv_ids": PVS, "cost_per_tap": 0.14, "cost_per_kvar": 0.001}
    with pytest.raises(MetricsError, match="cost_per_tap has 3 values for 2 regulators"):
        MetricsAccumulator(**kw | {"cost_per_tap": [0.1, 0.2, 0.3]})
    with pytest.raises(MetricsError, match="cost_per_kvar"):
        MetricsAccumulator(**kw | {"cost_per_kvar": -1.0})
    with pytest.raises(MetricsError, match="limits_pu"):
        MetricsAccumulator(**kw | {"limits_pu": (1.05, 0.965)})
    with pytest.raises(MetricsError, match="window_steps"):
        MetricsAccumulator(**kw | {"window_steps": 0})
    with pytest.raises(MetricsError, match=r"expected \(n_steps, n_nodes\)"):
        metrics_from_series(
            np.ones(4),
            np.zeros((4, 2)),
            np.zeros((4, 2)),
            regulator_ids=REGS,
            pv_ids=PVS,
            cost_per_tap=0.14,
            cost_per_kvar=0.001,
        )
    assert issubclass(MetricsError, CvvcError)
    # the settings are keywords written once (MetricsSettings): a misspelt or missing one is a TypeError, as for
    # any call, in both metrics paths
    with pytest.raises(TypeError, match=r"unexpected keyword\(s\) \['window'\]"):
        MetricsAccumulator(**kw | {"window": 3})
    with pytest.raises(TypeError, match=r"missing \['cost_per_kvar'\]"):
        metrics_from_series(np.ones((4, 4)), np.zeros((4, 2)), np.zeros((4, 2)), regulator_ids=REGS, pv_ids=PVS,
                            cost_per_tap=0.14)


# ------------------------------------------------------------------------------------ capacitor banks
CAPS = ("c83", "c88a", "c90b")


def test_capacitor_switchings_counted_and_costed():
    """Switchings per bank add up over steps; cost per bank from cost_per_switch; part of the total cost."""
    v, taps, q = _hand_series()
    sw = np.zeros((60, 3), dtype=int)
    sw[5, 0] = 1  # c83 closes
    sw[30, 0] = 1  # and opens again
    sw[12, 2] = 2  # a two-step bank closes both steps in one minute
    kw = {"capacitor_ids": CAPS, "cost_per_switch": [1.0, 2.5, 0.5]}
    base = _batch(v, taps, q)
    for r in (_batch(v, taps, q, cap_switches=sw, **kw), _stream_caps(v, taps, q, sw, **kw)):
        assert r.capacitor_ids == CAPS
        assert r.cap_switches_per_bank == (2, 0, 2)
        assert r.cap_switches == 4
        assert r.cap_cost == pytest.approx(2 * 1.0 + 2 * 0.5)
        assert r.total_cost == pytest.approx(base.total_cost + 3.0)
        assert r.ntc == base.ntc  # switchings are not tap changes
    both = combine_metrics([_batch(v, taps, q, cap_switches=sw, **kw)] * 2)
    assert both.cap_switches_per_bank == (4, 0, 4) and both.cap_cost == pytest.approx(6.0)


def _stream_caps(v, taps, q, sw, **kw):
    kw = {"regulator_ids": REGS, "pv_ids": PVS, "cost_per_tap": 0.14, "cost_per_kvar": 0.001} | kw
    acc = MetricsAccumulator(n_nodes=v.shape[1], **kw)
    for row in range(v.shape[0]):
        acc.update(v[row], taps[row], q[row], sw[row])
    return acc.result()


@pytest.mark.parametrize("bad", [np.array([1, -1, 0]), np.array([0.5, 0, 0]), np.array([1, 0])],
                         ids=["negative", "fraction", "wrong shape"])
def test_bad_capacitor_switchings_rejected(bad):
    acc = MetricsAccumulator(n_nodes=4, regulator_ids=REGS, pv_ids=PVS, cost_per_tap=0.14, cost_per_kvar=0.001,
                             capacitor_ids=CAPS)
    with pytest.raises(MetricsError, match="cap_switches"):
        acc.update(np.ones(4), np.zeros(2, dtype=int), np.zeros(2), bad)


def test_metrics_without_capacitors_decode_from_old_json():
    v, taps, q = _hand_series()
    r = _batch(v, taps, q)
    old = {k: val for k, val in msgspec.to_builtins(r).items()
           if k not in ("capacitor_ids", "cap_switches_per_bank", "cap_switches", "cap_cost")}
    assert msgspec.convert(old, Metrics) == r


def test_only_the_judged_nodes_count():
    """Nodes outside the feeder zone (a source bus at 1.06 pu) are neither violations nor the run's extremes."""
    v = np.full((12, 4), 1.0)
    v[:, 0] = 1.06  # upstream of the head meter
    v[:, 3] = 0.95  # in the zone, below 0.965 pu
    kw = {"regulator_ids": REGS, "pv_ids": PVS, "cost_per_tap": 0.14, "cost_per_kvar": 0.001}
    judged = MetricsAccumulator(n_nodes=4, judged_nodes=[1, 2, 3], **kw)
    every = MetricsAccumulator(n_nodes=4, **kw)
    for row in v:
        for acc in (judged, every):
            acc.update(row, np.zeros(len(REGS), int), np.zeros(len(PVS)))
    r, a = judged.result(), every.result()
    assert r.nvv == 3 and a.nvv == 6  # 3 judged windows (12 steps, 10-step window) x 1 or 2 nodes
    assert r.mvvm_node == 3 and r.mvvm_pu == pytest.approx(0.015)  # the index of the whole row
    assert r.v_max_pu == 1.0 and a.v_max_pu == 1.06
    with pytest.raises(MetricsError, match="judged_nodes"):
        MetricsAccumulator(n_nodes=4, judged_nodes=[4], **kw)


def test_for_feeder_judges_the_zone_phase_nodes_of_ieee13(repo_root):
    from schemas.devicemap import load_device_map
    from simulator_bridge.opendss.engine import FeederEngine

    dm = load_device_map(repo_root / "feeders" / "ieee13.toml")
    engine = FeederEngine(dm)
    try:
        acc = MetricsAccumulator.for_feeder(dm, engine)
        v = engine.node_voltages_pu().copy()
        names = engine.node_names
    finally:
        engine.close()
    src = names.index("sourcebus.1")
    v[src] = 1.2  # the transmission side: not this feeder's
    for _ in range(10):
        acc.update(v, np.zeros(3, int), np.zeros(3))
    r = acc.result()
    assert r.v_max_pu < 1.1 and (r.nvv == 0 or names[r.mvvm_node].split(".")[0] not in ("sourcebus", "650"))


def test_a_feeder_without_regulators_has_no_tap_cost():
    """epri-ckt5 has no regulator: R = 0 must give NTC 0 and T cost 0, not an error."""
    acc = MetricsAccumulator(n_nodes=3, regulator_ids=[], pv_ids=PVS, cost_per_tap=0.14, cost_per_kvar=0.001)
    for _ in range(10):
        acc.update(np.ones(3), np.zeros(0, int), np.array([10.0, -5.0]))
    r = acc.result()
    assert r.ntc == 0 and r.t_cost == 0.0 and r.q_cost > 0.0


def test_a_minute_the_ten_minute_average_hides_is_counted_every_minute():
    """One node dips to 0.945 pu for one minute and another rises to 1.045 pu for two: the 10-minute averages stay
    inside the judged limits (NVV 0), while each minute on its own is outside ANSI Range A (0.95-1.05: 1
    node-minute) and the optimization limits (0.975-1.04: 3 node-minutes in 3 minutes), the same in the stream."""
    v = np.full((30, 4), 1.0)
    v[12, 1] = 0.945
    v[20:22, 2] = 1.045
    taps, q = np.zeros((30, 2), int), np.zeros((30, 2))
    for r in (_stream(v, taps, q), _batch(v, taps, q)):
        assert r.nvv == 0 and r.mvvm_pu == 0.0
        assert (r.node_minutes_outside_ansi, r.minutes_outside_ansi) == (1.0, 1.0)
        assert (r.node_minutes_outside_opt, r.minutes_outside_opt) == (3.0, 3.0)
        assert r.opt_limits_pu == (0.975, 1.04) and r.v_min_pu == 0.945
    wide = _stream(v, taps, q, opt_limits_pu=(0.94, 1.06))
    assert (wide.node_minutes_outside_opt, wide.minutes_outside_opt) == (0.0, 0.0)
    both = combine_metrics([_stream(v, taps, q), _batch(v, taps, q)])
    assert (both.node_minutes_outside_opt, both.minutes_outside_ansi) == (6.0, 2.0)
    with pytest.raises(MetricsError, match="opt_limits_pu"):
        _stream(v, taps, q, opt_limits_pu=(1.0, 0.9))


def test_stream_and_batch_count_the_same_minutes_on_random_series():
    rng = np.random.default_rng(7)
    v = 1.0 + 0.03 * rng.standard_normal((200, 12))
    taps, q = rng.integers(0, 2, (200, 2)), rng.normal(0, 50, (200, 2))
    s, b = _stream(v, taps, q), _batch(v, taps, q)
    assert s.node_minutes_outside_opt > 0 and s.node_minutes_outside_ansi > 0
    for name in ("node_minutes_outside_opt", "minutes_outside_opt", "node_minutes_outside_ansi",
                 "minutes_outside_ansi"):
        assert getattr(s, name) == getattr(b, name), name


def test_moves_faster_than_the_regcontrols_tapdelay_are_counted_step_by_step():
    """A tapdelay of 45 s allows 2 moves in a minute and 3 in two (moves 45 s apart in a closed span); 2 s, 31."""
    allowance = tap_rate_allowance([45.0, 2.0, 0.0], 60)
    assert allowance[:2, 0].tolist() == [2.0, 3.0] and allowance[0, 1] == 31.0 and np.isinf(allowance[0, 2])
    moves = np.zeros((8, 2), dtype=int)
    moves[1, 0] = 2  # at the limit
    moves[4, 0], moves[5, 0] = 2, 2  # 2 and 2: 4 in two minutes, past 3
    moves[7, 0] = 3  # past 2 in a minute
    moves[7, 1] = 31  # at the limit of a 2 s tapdelay
    v, q = np.ones((8, 3)), np.zeros((8, 2))
    s = _stream(v, moves, q, tap_delay_s=[45.0, 2.0])
    b = _batch(v, moves, q, tap_delay_s=[45.0, 2.0])
    assert s.steps_over_tap_rate_per_regulator == b.steps_over_tap_rate_per_regulator == (2, 0)
    assert _stream(v, moves, q).steps_over_tap_rate_per_regulator == ()  # no tapdelays: not judged
    assert over_tap_rate(np.array([[1, 0], [2, 0]]), allowance[:, :2]).tolist() == [False, False]  # 3 in two
    assert over_tap_rate(np.array([[2, 0], [2, 0]]), allowance[:, :2]).tolist() == [True, False]
    with pytest.raises(MetricsError, match="one finite tapdelay"):
        _stream(v, moves, q, tap_delay_s=[45.0])


def test_for_feeder_holds_each_regulator_to_its_regcontrols_tapdelay(repo_root):
    from schemas.devicemap import load_device_map
    from simulator_bridge.opendss.engine import FeederEngine

    dm = load_device_map(repo_root / "feeders" / "ieee13.toml")
    engine = FeederEngine(dm)
    try:
        acc = MetricsAccumulator.for_feeder(dm, engine)
        delays = [c.tap_delay_s for c in engine.reg_controls[:len(engine.regulator_ids)]]
        n_nodes = len(engine.node_names)
    finally:
        engine.close()
    allowed = int(tap_rate_allowance(delays, 60)[0, 0])
    acc.update(np.ones(n_nodes), np.array([allowed, 0, 0]), np.zeros(3))
    acc.update(np.ones(n_nodes), np.array([0, allowed + 1, 0]), np.zeros(3))
    assert acc.result().steps_over_tap_rate_per_regulator == (0, 1, 0)


def test_combined_runs_count_the_steps_over_the_tap_rate_only_when_both_were_judged():
    v, q = np.ones((3, 3)), np.zeros((3, 2))
    moves = np.array([[3, 0], [0, 0], [0, 0]])
    judged = _batch(v, moves, q, tap_delay_s=[45.0, 45.0])
    assert judged.combine(judged).steps_over_tap_rate_per_regulator == (2, 0)
    assert judged.combine(_batch(v, moves, q)).steps_over_tap_rate_per_regulator == ()
