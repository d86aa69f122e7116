"""AMI meter readings in the agent (``agent.ami``) and their calibrated bounds (``training.calibration``)."""

from __future__ import annotations

import msgspec
import numpy as np
import pytest

from agent.ami import AmiReadings
from agent.state import GridState
from regression.model import read_model
from schemas import messages as m
from schemas.devicemap import MeterSpec
from training.calibration import ami_residual

_NS = 1_000_000_000
T0 = 1_688_983_200 * _NS  # 2023-07-10 10:00 UTC, a multiple of 15 minutes


@pytest.fixture(scope="module")
def model(ieee13_model):
    return read_model(ieee13_model)


def _state(v: np.ndarray) -> GridState:
    n = v.size
    return GridState(v0_pu=v, dv_dq_pu_per_kvar=np.zeros((n, 1)), dv_dtap_pu=np.zeros((n, 1)),
                     dv_dp_pu_per_kw=np.zeros((n, 1)), taps=np.zeros(1, int), corrected=True, critical=True)


def _frame(node: str, t_ns: int, v_pu: float, interval_s: int = 900, meter_id: str = "ami1") -> m.MeterFrame:
    return m.MeterFrame(t_ns=t_ns, seq=1, source=meter_id, meter_id=meter_id, node=node, v_pu=v_pu,
                        interval_s=interval_s)


def _meter(node: str, meter_id: str = "ami1", interval_s: int = 900) -> MeterSpec:
    return MeterSpec(id=meter_id, node=node, interval_s=interval_s)


@pytest.mark.process
def test_a_reading_moves_its_node_by_its_offset_to_the_estimate_of_its_minute(model):
    n, node = len(model.critical_nodes), model.critical_nodes[2].name
    ami = AmiReadings(model, [_meter(node)])
    est0 = np.full(n, 1.01)
    assert ami.correct(T0, _state(est0)).v0_pu.tolist() == est0.tolist()  # no reading yet: unchanged
    assert ami.add(_frame(node.upper(), T0, 1.03), T0) is None  # node names are case-insensitive (OpenDSS)
    est1 = np.full(n, 1.02)
    v = ami.correct(T0 + 300 * _NS, _state(est1)).v0_pu
    assert v[2] == pytest.approx(1.03 + (1.02 - 1.01)) and np.delete(v, 2).tolist() == np.delete(est1, 2).tolist()
    assert ami.fresh.tolist() == [i == 2 for i in range(n)] and ami.tight[2]
    lo, hi = ami.bounds(np.full(n, 0.05), np.full(n, 0.05))
    b = model.bounds
    assert lo[2] == min(0.05, b.ami_lower_pu[2]) and hi[2] == min(0.05, b.ami_upper_pu[2])
    assert np.delete(lo, 2).tolist() == [0.05] * (n - 1)


def test_old_foreign_and_implausible_readings_are_counted_and_never_used(model):
    n, node = len(model.critical_nodes), model.critical_nodes[0].name
    ami = AmiReadings(model, [_meter(node), _meter("nowhere.1", "ami2")])
    ami.correct(T0, _state(np.full(n, 1.0)))
    assert "not a critical node" in ami.add(_frame("nowhere.1", T0, 1.0, meter_id="ami2"), T0)[1]
    assert "outside" in ami.add(_frame(node, T0, 1.7), T0)[1]
    assert "future" in ami.add(_frame(node, T0 + 3600 * _NS, 1.0), T0)[1]
    assert ami.add(_frame(node, T0, 1.02), T0) is None
    assert "not newer" in ami.add(_frame(node, T0, 1.04), T0)[1]
    assert ami.correct(T0 + 300 * _NS, _state(np.full(n, 1.0))).v0_pu[0] == pytest.approx(1.02)
    stale = ami.correct(T0 + 2 * 900 * _NS + 300 * _NS, _state(np.full(n, 1.0)))  # older than two intervals
    assert stale.v0_pu[0] == 1.0 and not ami.fresh.any()
    assert {k: ami.counts[k] for k in ("ami_not_critical", "ami_out_of_range", "ami_future", "ami_not_newer")} == {
        "ami_not_critical": 1, "ami_out_of_range": 1, "ami_future": 1, "ami_not_newer": 1}


def test_a_reading_stamped_more_than_5_s_ahead_of_the_newest_frame_is_refused_future(model):
    """A meter's reading may be 5 s ahead of the agent's clock (its newest frame), not more: a forged one stamped 30 s
    ahead was taken (the tolerance was a whole step) and stood as the meter's newest, so the meter's real readings
    of the next half minute were refused as not newer."""
    n, node = len(model.critical_nodes), model.critical_nodes[0].name
    ami = AmiReadings(model, [_meter(node)])
    ami.correct(T0, _state(np.full(n, 1.0)))
    kind, why = ami.add(_frame(node, T0 + 30 * _NS, 0.80), T0)
    assert kind == "ami_future" and "future" in why
    assert ami.add(_frame(node, T0 + 5 * _NS, 1.02), T0) is None  # within the tolerance: a clock a little ahead
    assert ami.counts["ami_future"] == 1 and ami.counts["ami_readings"] == 1


def test_a_model_without_ami_bounds_keeps_the_ordinary_bounds_of_a_metered_node(model):
    bare = msgspec.structs.replace(model, bounds=msgspec.structs.replace(model.bounds, ami_interval_s=0,
                                                                          ami_upper_pu=[], ami_lower_pu=[]))
    n, node = len(model.critical_nodes), model.critical_nodes[1].name
    ami = AmiReadings(bare, [_meter(node)])
    ami.correct(T0, _state(np.full(n, 1.0)))
    ami.add(_frame(node, T0, 1.01), T0)
    assert ami.correct(T0 + 300 * _NS, _state(np.full(n, 1.0))).v0_pu[1] == pytest.approx(1.01)
    lo, hi = np.full(n, 0.02), np.full(n, 0.03)
    assert [x.tolist() for x in ami.bounds(lo, hi)] == [lo.tolist(), hi.tolist()]


def test_only_the_maps_meters_count_each_at_its_node_and_for_the_maps_interval(model):
    """Identity from the device map: a meter the map does not declare, or a declared meter naming another node, is
    refused; a reading that declares a day-long interval still serves only two of the map's intervals."""
    n, node, other = len(model.critical_nodes), model.critical_nodes[0].name, model.critical_nodes[1].name
    assert AmiReadings(model).add(_frame(node, T0, 0.8), T0)[0] == "ami_unknown_meter"  # a map without meters
    ami = AmiReadings(model, [_meter(node)])
    ami.correct(T0, _state(np.full(n, 1.0)))
    assert ami.add(_frame(node, T0, 0.8, meter_id="x1"), T0)[0] == "ami_unknown_meter"
    assert ami.add(_frame(other, T0, 0.8), T0)[0] == "ami_wrong_node"
    assert ami.add(_frame(node, T0, 1.02, interval_s=86_400), T0) is None
    assert ami.latest[0][2] == 900  # the map's interval, not the payload's
    assert ami.correct(T0 + 300 * _NS, _state(np.full(n, 1.0))).v0_pu[0] == pytest.approx(1.02)
    late = ami.correct(T0 + 2 * 900 * _NS + 300 * _NS, _state(np.full(n, 1.0)))
    assert late.v0_pu[0] == 1.0 and not ami.fresh.any()  # two map intervals old: no longer used


def test_a_reading_kept_from_before_the_first_frame_never_locks_its_meter_out(model):
    n, node = len(model.critical_nodes), model.critical_nodes[0].name
    ami = AmiReadings(model, [_meter(node)])
    assert ami.add(_frame(node, 4_102_444_800 * _NS, 0.8), None) is None  # 2100, before any frame dated it
    ami.correct(T0, _state(np.full(n, 1.0)))
    assert ami.correct(T0 + 300 * _NS, _state(np.full(n, 1.0))).v0_pu[0] == 1.0  # a future reading is not used
    assert ami.add(_frame(node, T0, 1.02), T0) is None  # and the meter's real reading replaces it
    assert ami.correct(T0 + 300 * _NS, _state(np.full(n, 1.0))).v0_pu[0] == pytest.approx(1.02)


def test_calibrations_ami_residual_is_the_error_change_since_the_last_earlier_reading():
    t_ns = T0 + np.arange(40) * 60 * _NS  # readings at rows 0, 15, 30
    err = np.arange(40, dtype=float)[:, None] * np.array([[1e-4, -2e-4]])
    keep = np.zeros(40, bool)
    keep[[0, 1, 15, 16, 39]] = True
    r = ami_residual(err, t_ns, keep, 900, 0.0, np.random.default_rng(0))
    # row 0 has no earlier reading (left out); 1 -> 0, 15 -> 0 (strictly before), 16 -> 15, 39 -> 30
    assert r.shape == (4, 2)
    np.testing.assert_allclose(r[:, 0], np.array([1, 15, 1, 9]) * 1e-4)
    np.testing.assert_allclose(r[:, 1], np.array([1, 15, 1, 9]) * -2e-4)
