"""Paper eq. (5)-(7) and the evaluation of the eq. (3) fits, on hand-computed cases."""

import numpy as np
import pytest

from benchmarks.synthetic import synthetic_model
from regression.errors import ModelInputError
from regression.estimator import (
    POWER_BASE_FLOOR_KVAR,
    SensitivityTable,
    apply_correction,
    correction_pu,
    dv_dp_pu_per_kw,
    dv_dq_pu_per_kvar,
    estimate_voltages_pu,
    pv_variability_margins_pu,
)
from regression.model import ModelArrays, SensitivityFit, features


def _arrays() -> ModelArrays:
    # 3 nodes, 2 features, 2 regulators. Node 0 is upstream of both regulators.
    return ModelArrays(
        alpha=np.array([[1e-5, -2e-5, 1.00], [2e-5, 0.0, 1.01], [0.0, 1e-5, 0.99]]),
        tap0=np.array([0.0, 2.0]),
        dv_dtap_pu=np.array([[0.0, 0.0], [0.00625, 0.0], [0.00625, 0.006]]),
        upstream_regulator=np.array([-1, 0, 1]),
        reg_secondary_node=np.array([1, 2]),
        reg_pu_per_v120=np.array([1 / 120, 1 / 120]),
    )


def test_eq5_by_hand():
    v = estimate_voltages_pu(_arrays(), np.array([1000.0, 500.0]), np.array([1, 2]))
    # node 0: 1e-5*1000 - 2e-5*500 + 1.00 = 1.00; node 1: 0.02 + 1.01 + 0.00625*(1-0) = 1.03625
    # node 2: 0.005 + 0.99 + 0.00625*1 + 0.006*(2-2) = 1.00125
    np.testing.assert_allclose(v, [1.00, 1.03625, 1.00125], atol=1e-12)


def test_eq5_batches_over_leading_axes():
    a = _arrays()
    m = np.array([[1000.0, 500.0], [0.0, 0.0]])
    t = np.array([[1, 2], [0, 2]])
    v = estimate_voltages_pu(a, m, t)
    assert v.shape == (2, 3)
    np.testing.assert_allclose(v[1], a.alpha[:, -1])  # at tap0 with zero features: the intercepts
    np.testing.assert_allclose(v[0], estimate_voltages_pu(a, m[0], t[0]))


def test_eq5_rejects_wrong_feature_count():
    with pytest.raises(ModelInputError, match="features"):
        estimate_voltages_pu(_arrays(), np.zeros(3), np.zeros(2))


def test_eq6_correction_and_invalid_readings():
    v_hat = np.array([1.0, 1.02, 1.01])
    eps = correction_pu(v_hat, np.array([1, 2]), np.array([1.03, 1.005]))
    np.testing.assert_allclose(eps, [0.01, -0.005], atol=1e-12)
    eps = correction_pu(v_hat, np.array([1, 2]), np.array([np.nan, 1.005]))
    np.testing.assert_allclose(eps, [0.0, -0.005], atol=1e-12)
    eps = correction_pu(v_hat, np.array([1, 2]), np.array([1.03, 1.005]), valid=np.array([True, False]))
    np.testing.assert_allclose(eps, [0.01, 0.0], atol=1e-12)


def test_eq7_applies_upstream_regulator_and_leaves_others():
    v_hat = np.array([1.0, 1.02, 1.01])
    before = v_hat.copy()
    out = apply_correction(v_hat, np.array([0.01, -0.005]), np.array([-1, 0, 1]))
    np.testing.assert_allclose(out, [1.0, 1.03, 1.005], atol=1e-12)
    np.testing.assert_array_equal(v_hat, before)  # input not mutated


def test_eq6_7_make_the_secondary_equal_its_measurement():
    model = synthetic_model(3)
    a = ModelArrays.of(model)
    m = features(np.full(3, 900.0), np.full(3, 300.0), np.full(3, 700.0), np.zeros(3))
    v_hat = estimate_voltages_pu(a, m, np.zeros(8))
    measured = v_hat[a.reg_secondary_node] + np.linspace(-0.01, 0.01, 8)
    v = apply_correction(v_hat, correction_pu(v_hat, a.reg_secondary_node, measured), a.upstream_regulator)
    # every secondary node has its own regulator upstream in this model
    assert np.all(a.upstream_regulator[a.reg_secondary_node] == np.arange(8))
    np.testing.assert_allclose(v[a.reg_secondary_node], measured, atol=1e-12)


def test_eq3_forms_by_hand():
    fits = [
        [
            SensitivityFit(form="power", a=2e-5, b=0.5, c=3000.0),
            SensitivityFit(form="linear", a=1e-5, b=1e-9),
            SensitivityFit(form="constant", a=7e-6),
        ]
    ]
    s = dv_dq_pu_per_kvar(fits, 1000.0)
    np.testing.assert_allclose(s, [[2e-5 / 4000.0**0.5, 1e-5 + 1e-6, 7e-6]], rtol=1e-12)
    np.testing.assert_allclose(dv_dq_pu_per_kvar(SensitivityTable.of(fits), 1000.0), s)


@pytest.mark.parametrize(
    ("q_head", "q_used"),
    [
        (-5000.0, -1000.0),  # below the training range: clipped to q_min
        (500.0, 500.0),  # inside: used as is
        (9000.0, 2000.0),  # above: clipped to q_max
    ],
)
def test_eq3_is_clipped_to_the_training_range(q_head, q_used):
    fit = SensitivityFit(form="linear", a=1e-5, b=2e-9, q_min_kvar=-1000.0, q_max_kvar=2000.0)
    np.testing.assert_allclose(dv_dq_pu_per_kvar([[fit]], q_head), [[1e-5 + 2e-9 * q_used]], rtol=1e-12)


def test_eq3_power_form_guard_keeps_base_positive():
    # c + q = 100 - 500 < 0 would be undefined for a fractional exponent; the base is floored instead.
    fit = SensitivityFit(form="power", a=1e-5, b=-0.3, c=100.0)
    s = dv_dq_pu_per_kvar([[fit]], -500.0)
    np.testing.assert_allclose(s, [[1e-5 / POWER_BASE_FLOOR_KVAR**-0.3]])
    assert np.all(np.isfinite(s))


def test_eq3_rejects_non_finite_head_q():
    with pytest.raises(ModelInputError):
        dv_dq_pu_per_kvar([[SensitivityFit(form="constant", a=1e-5)]], float("nan"))


def test_synthetic_model_sensitivities_are_plausible():
    model = synthetic_model(0)
    s = dv_dq_pu_per_kvar(model.sens_q, 1500.0)
    assert s.shape == (47, 3)
    assert np.all((s > 1e-7) & (s < 1e-4))


def test_dv_dp_is_the_plant_coefficient_minus_the_mean_head_coefficient():
    names = ["head_p_kw_a", "head_p_kw_b", "head_p_kw_c", "head_q_kvar_a", "head_q_kvar_b", "head_q_kvar_c",
             "pv0_p_kw", "pv0_q_kvar"]
    alpha = np.zeros((2, len(names) + 1))
    alpha[0, :3] = [-3e-6, -6e-6, -9e-6]  # more head load, lower voltage
    alpha[0, 6] = 2e-5
    alpha[1, 6] = 1e-5
    arrays = ModelArrays(alpha=alpha, tap0=np.zeros(0), dv_dtap_pu=np.zeros((2, 0)),
                         upstream_regulator=np.array([-1, -1]), reg_secondary_node=np.zeros(0, int),
                         reg_pu_per_v120=np.zeros(0))
    # node 0: 2e-5 - (-6e-6) = 2.6e-5 pu/kW; node 1: 1e-5
    np.testing.assert_allclose(dv_dp_pu_per_kw(arrays, names, 1), [[2.6e-5], [1e-5]], rtol=1e-12)
    with pytest.raises(ModelInputError, match="plant P"):
        dv_dp_pu_per_kw(arrays, names, 2)


@pytest.mark.parametrize(
    ("recent", "rise", "fall"),
    [
        ([[500.0], [100.0]], 0.004, 0.0),  # output fell 400 kW: it may come back, +0.004 pu
        ([[100.0], [100.0]], 0.0, 0.0),  # steady: no margin
        ([[0.0], [100.0]], 0.0, 0.001),  # output rose 100 kW from 0: it may drop back, -0.001 pu
        ([[2000.0], [0.0], [100.0]], 0.01, 0.001),  # a 1900 kW swing: capped at 0.01 pu
    ],
)
def test_variability_margin_by_hand(recent, rise, fall):
    up, down = pv_variability_margins_pu(np.array([[1e-5]]), np.array([100.0]), np.array(recent), 0.01)
    np.testing.assert_allclose([up[0], down[0]], [rise, fall], atol=1e-15)


def test_variability_margin_of_a_node_the_plant_lowers_swaps_sides():
    up, down = pv_variability_margins_pu(np.array([[-1e-5]]), np.array([100.0]), np.array([[500.0], [100.0]]), 1.0)
    np.testing.assert_allclose([up[0], down[0]], [0.0, 0.004], atol=1e-15)
