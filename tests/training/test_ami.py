"""AMI meters, the accuracy report's explicit option (``training.ami``): pure functions, then IEEE 13 (real OpenDSS)."""

import json

import msgspec
import numpy as np
import pytest

from regression.model import read_model, write_model
from tests.training.conftest import REPO
from training.accuracy import accuracy_report
from training.ami import ami_estimate_v_pu, ami_placement
from training.errors import TrainingError

IEEE13 = REPO / "feeders" / "ieee13.toml"
MINUTES = 60


def test_placement_takes_the_widest_bounds_ties_by_index():
    up = np.array([0.001, 0.004, 0.002, 0.003, 0.001])
    lo = np.array([0.001, 0.000, 0.002, 0.001, 0.003])  # widths 0.002 0.004 0.004 0.004 0.004
    assert ami_placement(up, lo, 3).tolist() == [1, 2, 3]
    assert ami_placement(up, lo, 5).tolist() == [1, 2, 3, 4, 0]
    assert ami_placement(up, lo, 0).tolist() == []
    with pytest.raises(TrainingError, match="6 AMI meters asked for, but the model has 5 critical nodes"):
        ami_placement(up, lo, 6)


def test_estimate_follows_the_latest_usable_reading():
    t = np.arange(10.0)
    est = np.stack([np.zeros(10), 0.01 * t], axis=1)  # node 0: flat estimate; node 1: estimate drifting up
    true = np.stack([1 + 0.001 * t, np.full(10, 0.98)], axis=1)
    out = ami_estimate_v_pu(est, true, interval_min=4, noise_pu=0.0, latency_min=1)
    # readings at minutes 0, 4, 8, usable from 1, 5, 9: minute 0 keeps the estimate
    r = np.array([-1, 0, 0, 0, 0, 4, 4, 4, 4, 8])
    assert out[0].tolist() == est[0].tolist()
    np.testing.assert_allclose(out[1:, 0], 1 + 0.001 * r[1:], rtol=0, atol=1e-15)
    np.testing.assert_allclose(out[1:, 1], 0.98 + 0.01 * (t[1:] - r[1:]), rtol=0, atol=1e-15)
    assert est[1, 1] == 0.01  # inputs untouched


def test_estimate_with_a_meter_every_minute_is_the_reading():
    rng = np.random.default_rng(3)
    est, true = rng.normal(1, 0.02, (50, 4)), rng.normal(1, 0.02, (50, 4))
    assert np.array_equal(ami_estimate_v_pu(est, true, interval_min=1, noise_pu=0.0, latency_min=0), true)
    noisy = ami_estimate_v_pu(est, true, interval_min=1, noise_pu=0.001, latency_min=0)
    assert 0.0006 < np.std(noisy - true) < 0.0014  # the noise, seeded: same result twice
    assert np.array_equal(noisy, ami_estimate_v_pu(est, true, interval_min=1, noise_pu=0.001, latency_min=0))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"interval_min": 0, "noise_pu": 0.0, "latency_min": 0}, "interval 0 min"),
        ({"interval_min": 15, "noise_pu": -0.1, "latency_min": 0}, "noise -0.1 pu"),
        ({"interval_min": 15, "noise_pu": 0.0, "latency_min": -1}, "latency -1 min"),
    ],
)
def test_estimate_refuses_bad_options(kwargs, message):
    with pytest.raises(TrainingError, match=message):
        ami_estimate_v_pu(np.zeros((3, 1)), np.ones((3, 1)), **kwargs)


def _report(model, profile_cache, **ami):
    return accuracy_report(model, IEEE13, 4, 2, max_minutes=MINUTES, sens_minutes=2, cache_dir=profile_cache,
                           progress=False, **ami)


@pytest.fixture(scope="module")
def without_meters(ieee13_model, profile_cache):
    return _report(ieee13_model, profile_cache)


def test_zero_meters_leave_the_report_as_it_was(ieee13_model, profile_cache, without_meters):
    zero = _report(ieee13_model, profile_cache, ami_meters=0, ami_interval_min=1, ami_noise_pu=0.0)
    assert msgspec.json.encode(zero) == msgspec.json.encode(without_meters)
    assert "ami_nodes" not in json.loads(msgspec.json.encode(zero))
    assert [e.label for e in zero.errors] == ["guided, no correction", "guided, with correction"]
    three = _report(ieee13_model, profile_cache, ami_meters=3)
    assert three.errors[:2] == without_meters.errors  # the option only adds its row and its nodes
    assert msgspec.structs.replace(three, errors=three.errors[:2], ami_nodes=msgspec.UNSET) == without_meters


def test_noiseless_meters_every_minute_are_exact_at_their_nodes(ieee13_model, profile_cache, without_meters):
    m = read_model(ieee13_model)
    n = len(m.critical_nodes)
    exact = dict(ami_interval_min=1, ami_noise_pu=0.0, ami_latency_min=0)
    rep = _report(ieee13_model, profile_cache, ami_meters=n, **exact)
    ami = rep.errors[2]
    assert ami.label == f"guided, with correction + {n} AMI meters (1 min)"
    assert ami.samples == MINUTES * n and ami.max_abs_pu == 0.0 and ami.rmse_pu == 0.0
    assert without_meters.errors[1].max_abs_pu > 0  # not zero without them
    # one meter: the other nodes keep the correction's errors, the metered one contributes exact zeros
    one = _report(ieee13_model, profile_cache, ami_meters=1, **exact)
    widest = int(np.argmax(np.asarray(m.bounds.upper_pu) + np.asarray(m.bounds.lower_pu)))
    assert one.ami_nodes == {"guided": [m.critical_nodes[widest].name]}
    assert one.errors[2].rmse_pu < one.errors[1].rmse_pu
    assert one.errors[2].within_001 >= one.errors[1].within_001


def test_meters_every_15_minutes_do_not_worsen_the_estimate(ieee13_model, profile_cache, without_meters):
    m = read_model(ieee13_model)
    # noise 0.0001 pu: with the default 0.001 pu the meters worsen IEEE 13's RMSE (measured 0.00067 -> 0.00074 pu),
    # its corrected estimate being better than such a meter; on epri-ckt24 they take it from 0.0031 to 0.0011 pu
    rep = _report(ieee13_model, profile_cache, ami_meters=min(3, len(m.critical_nodes)), ami_interval_min=15,
                  ami_noise_pu=0.0001)
    assert rep.errors[2].label.endswith("AMI meters (15 min)")
    assert rep.errors[2].rmse_pu <= rep.errors[1].rmse_pu, rep.errors


def test_too_many_meters_or_no_bounds_is_a_clear_error(ieee13_model, profile_cache, tmp_path):
    m = read_model(ieee13_model)
    n = len(m.critical_nodes)
    with pytest.raises(TrainingError, match=f"{n + 1} AMI meters asked for, but the model has {n} critical nodes"):
        _report(ieee13_model, profile_cache, ami_meters=n + 1)
    with pytest.raises(TrainingError, match="AMI interval 0 min"):
        _report(ieee13_model, profile_cache, ami_meters=1, ami_interval_min=0)
    unbounded = tmp_path / "no-bounds.json"
    write_model(msgspec.structs.replace(m, bounds=None), unbounded)
    with pytest.raises(TrainingError, match="no calibrated bounds"):
        _report(unbounded, profile_cache, ami_meters=1)
    _report(unbounded, profile_cache)  # without meters the bounds are not needed


def test_command_line_prints_the_meters(ieee13_model, tmp_path, capsys):
    from cvvc.cli import main

    argv = ["report", "accuracy", "--model", str(ieee13_model), "--feeder", str(IEEE13), "--month", "4",
            "--max-minutes", "20", "--cache", str(tmp_path / "cache"), "--ami-meters", "2", "--ami-interval-min", "5"]
    assert main([*argv, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["errors"][2]["label"] == "guided, with correction + 2 AMI meters (5 min)"
    assert len(report["ami_nodes"]["guided"]) == 2
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "+ 2 AMI meters (5 min)" in out and f"AMI meters (guided): {', '.join(report['ami_nodes']['guided'])}" in out
    assert main([*argv[:-4], "--ami-meters", "999"]) == 2
    assert "999 AMI meters asked for" in capsys.readouterr().err
