"""End to end on IEEE 123 (real OpenDSS): training, model file, out-of-sample accuracy."""

import numpy as np
import pytest

from regression.model import ModelArrays, ModelError, features, read_model, write_model
from tests.training.conftest import IEEE123, REPO
from training.errors import TrainingError


def test_summary_and_model_are_consistent(trained_123):
    s, m = trained_123.summary, trained_123.model
    assert s.scenarios == m.settings.scenarios > 9  # 3x3 blocks, several minutes each
    assert s.power_flows == m.settings.power_flows > 10 * s.scenarios
    assert s.failed_power_flows == 0
    assert s.critical_nodes == len(m.critical_nodes)
    assert m.node_count == 278
    assert len(m.alpha) == len(m.critical_nodes) and len(m.alpha[0]) == len(m.feature_names) + 1
    assert np.all(np.isfinite(np.asarray(m.alpha)))
    # training and held-out residuals of eq. (5) on IEEE 123 (measured about 0.0005 pu rmse, 0.005 max)
    assert s.voltage_rmse_pu < 0.002 and s.validation_max_abs_pu < 0.01


def test_critical_nodes_include_the_required_set(trained_123):
    m = trained_123.model
    names = {c.name: c for c in m.critical_nodes}
    required = {"150r.1", "150r.2", "150r.3"}  # feeder head: the head meter's bus (Line.sw1 from 150r)
    required |= {"150r.1", "9r.1", "25r.1", "25r.3", "160r.1", "160r.2", "160r.3"}  # regulator secondaries
    required |= {"9.1", "25.1", "25.3", "160.1", "160.2", "160.3"}  # regulator primaries inside the zone
    required |= {f"{bus}.{ph}" for bus in ("66", "83", "300") for ph in (1, 2, 3)}  # PV plants
    assert required <= set(names)
    # creg1a's primary is the source bus 150: upstream of the head meter and moved by no device, never critical
    assert not any(n.startswith("150.") for n in names)
    assert "pv" in names["83.2"].kinds and "reg_secondary" in names["9r.1"].kinds
    assert any("extreme" in c.kinds for c in m.critical_nodes)


def test_upstream_regulator_of_each_secondary_is_itself(trained_123):
    m = trained_123.model
    for r, reg in enumerate(m.regulators):
        assert m.critical_nodes[reg.secondary_node].upstream_regulator == r
    names = {c.name: c for c in m.critical_nodes}
    ids = [r.id for r in m.regulators]
    assert names["66.1"].upstream_regulator == ids.index("creg1a")
    assert 0.6 < m.regulators[0].step_v120 < 0.9  # about 0.75 V per step on the 120 V base


def test_model_file_round_trip_and_fingerprint(trained_123, tmp_path):
    path = tmp_path / "m.json"
    write_model(trained_123.model, path)
    back = read_model(path, expect_fingerprint=trained_123.model.fingerprint)
    assert back == trained_123.model
    with pytest.raises(ModelError, match="fingerprint"):
        read_model(path, expect_fingerprint="0" * 16)


def test_estimates_opendss_out_of_sample(trained_123, profile_cache):
    """Random minutes of another year (seed 2), random plant Q and taps near tap0: eq. (5)-(7) vs OpenDSS."""
    from regression.batch import estimate_v_pu, eval_sensitivities, sensitivity_arrays
    from schemas.devicemap import load_device_map
    from simulator_bridge.opendss.engine import FeederEngine
    from training.train import load_profiles

    m = trained_123.model
    dm = load_device_map(IEEE123)
    e = FeederEngine(dm, tolerance=1e-8)
    prof = load_profiles(dm, e, seed=2, cache_dir=profile_cache)
    rng = np.random.default_rng(11)
    idx = [e.node_names.index(c.name) for c in m.critical_nodes]
    arrays = ModelArrays.of(m)
    sens = sensitivity_arrays(m.sens_q)
    errs, errs_corr, rel = [], [], []
    for i, step in enumerate(rng.integers(0, prof.n_steps, 150)):
        p = prof.pv_kw(int(step), int(step) + 1)[0].astype(float)
        e.set_loads_kw(prof.load_kw(int(step), int(step) + 1)[0].astype(float))
        headroom = np.sqrt(np.maximum(e.pv_kva**2 - np.minimum(p, e.pv_pmpp_kw) ** 2, 0.0))
        e.set_pv(p, rng.uniform(-1, 1, p.size) * headroom)
        taps = np.clip(np.asarray(m.tap0) + rng.integers(-2, 3, len(m.tap0)), -16, 16)
        e.set_taps(taps)
        e.solve()
        r = e.readings()
        x = features(r.head_p_kw, r.head_q_kvar, r.pv_p_kw.sum(axis=1), r.pv_q_kvar.sum(axis=1))
        v = e.node_voltages_pu()[idx]
        errs.append(estimate_v_pu(arrays, x[None], taps[None])[0] - v)
        errs_corr.append(estimate_v_pu(arrays, x[None], taps[None], r.reg_v120[None])[0] - v)
        if i % 15 == 0:  # eq. (3) vs perturbation truth at 10 states
            dv_dq = e.perturbation_sensitivities().dv_dq
            pred = eval_sensitivities(sens, np.array([r.head_q_kvar.sum()]))[0]
            truth = dv_dq[idx]
            big = np.abs(truth) > 0.2 * np.nanmax(np.abs(truth), axis=1, keepdims=True)
            rel.append(np.abs(pred[big] - truth[big]) / np.abs(truth[big]))
    errs, errs_corr = np.abs(np.asarray(errs)), np.abs(np.asarray(errs_corr))
    # stated tolerance: every sample within 0.01 pu, rmse under 0.002 pu (measured ~0.0006 / 0.006 max)
    assert errs.max() < 0.01 and errs_corr.max() < 0.01
    assert np.sqrt(np.mean(errs_corr**2)) < 0.002
    assert np.sqrt(np.mean(errs_corr**2)) < np.sqrt(np.mean(errs**2))  # the correction helps
    assert np.median(np.concatenate(rel)) < 0.05  # measured about 1 %


def test_accuracy_report_on_a_short_window(trained_123, profile_cache, tmp_path):
    from training.accuracy import accuracy_report

    path = tmp_path / "m.json"
    write_model(trained_123.model, path)
    rep = accuracy_report(
        path,
        IEEE123,
        7,
        2,
        png_path=tmp_path / "fig8.png",
        max_minutes=90,
        sens_minutes=3,
        cache_dir=profile_cache,
        progress=False,
    )
    assert rep.minutes == 90
    assert [e.label for e in rep.errors] == ["guided, no correction", "guided, with correction"]
    for e in rep.errors:
        assert e.samples == 90 * len(trained_123.model.critical_nodes)
        assert e.max_abs_pu < 0.01 and e.within_001 == 1.0
    assert rep.sensitivities[0].minutes == 3 and rep.sensitivities[0].median_rel_err < 0.05
    assert (tmp_path / "fig8.png").stat().st_size > 10_000
    # the calibrated bounds, predicted against realised out of sample (a July the training never saw)
    assert rep.bound_alpha == {"guided": 0.01}
    assert rep.bound_miss_rate["guided"] < 0.05, rep.bound_miss_rate  # zero-width bounds would miss about half


def test_the_model_carries_calibrated_bounds_and_the_training_envelope(trained_123):
    """Split conformal on held-out minutes of the training year (``training.calibration``)."""
    s, m = trained_123.summary, trained_123.model
    b = m.bounds
    assert b is not None and b.alpha == 0.01
    assert 1400 <= b.calibration_minutes == s.calibration_minutes <= 1440  # less the training scenarios
    up, lo = np.asarray(b.upper_pu), np.asarray(b.lower_pu)
    assert up.shape == lo.shape == (len(m.critical_nodes),)
    assert np.all(up >= 0) and np.all(lo >= 0) and (up + lo).max() > 0
    assert (up + lo).max() < 0.02  # IEEE 123's estimates hold to a few thousandths of a pu
    env_lo, env_hi = np.asarray(b.envelope_lo), np.asarray(b.envelope_hi)
    assert env_lo.shape == (len(m.feature_names),) and np.all(env_lo < env_hi)


def test_conformal_quantile_is_the_ceil_n_plus_1_level_th_score():
    from training.conformal import conformal_quantile

    scores = np.arange(1.0, 100.0)[:, None]  # 1..99
    assert conformal_quantile(scores, 0.9)[0] == 90.0  # ceil(100 * 0.9) = 90th smallest
    assert conformal_quantile(scores, 0.999)[0] == 99.0  # too few samples: the largest
    assert conformal_quantile(-scores, 0.5)[0] == 0.0  # never below 0


def _map(tmp_path, *, pv: bool, regulator: bool):
    master = (REPO.parent / "shared" / "feeders" / "ieee13" / "IEEE13Nodeckt.dss").resolve()
    text = f'[feeder]\nname = "t13"\nmaster = "{master}"\nhead_element = "Line.650632"\nsource_bus = "650"\n'
    if regulator:
        text += '[[regulator]]\nid = "reg1"\nregcontrol = "Reg1"\n'
    if pv:
        text += '[[pv]]\nid = "pv1"\nbus = "675"\nkv_ll = 4.16\nkva = 500.0\npmpp_kw = 450.0\n'
    path = tmp_path / "map.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize(("pv", "regulator", "what"), [(False, True, "no PV plant"), (True, False, "no regulator")])
def test_feeder_without_pv_or_regulator_is_refused(tmp_path, pv, regulator, what):
    from training.train import train

    with pytest.raises(TrainingError, match=what):
        train(_map(tmp_path, pv=pv, regulator=regulator), cache_dir=None)


def test_model_records_settings_and_held_out_error(trained_123):
    m = trained_123.model
    assert m.settings.combined_pct == [-100.0, -50.0, 50.0, 100.0]
    assert m.settings.tolerance == 1e-8 and m.settings.rcond == 1e-6
    assert 0 < m.fit.validation_rmse_pu < 0.002 and m.fit.condition_number > 1


def test_non_finite_model_is_refused(trained_123):
    import msgspec

    from training.train import _check_finite

    m = trained_123.model
    bad = msgspec.structs.replace(m, alpha=[[float("nan")] * len(row) for row in m.alpha])
    with pytest.raises(TrainingError, match="non-finite alpha"):
        _check_finite(bad)
