import numpy as np
import pytest

from training.errors import TrainingError
from training.fits import (
    choose_c_kvar,
    fit_sensitivity,
    fit_voltage_regression,
    sensitivity_samples,
    tap_sensitivities,
)


def test_voltage_regression_recovers_known_coefficients():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(300, 8)) * [100, 120, 90, 30, 40, 20, 500, 200] + [1000, 900, 800, 0, 0, 0, 300, 0]
    coef = rng.normal(size=(8, 5)) * 1e-5
    v = 1.0 + x @ coef + rng.normal(size=(300, 5)) * 1e-6
    fit = fit_voltage_regression(x, v)
    np.testing.assert_allclose(fit.alpha[:, :-1], coef.T, atol=2e-7)
    np.testing.assert_allclose(x @ fit.alpha[:, :-1].T + fit.alpha[:, -1], v, atol=5e-6)
    assert fit.max_abs_pu < 5e-6
    assert fit.condition_number < 10


def test_collinear_features_give_bounded_coefficients():
    # trap 1: two nearly identical inputs; plain least squares puts huge opposite weights on them
    rng = np.random.default_rng(2)
    base = rng.normal(size=300) * 100
    x = np.stack([base, base + rng.normal(size=300) * 1e-9, rng.normal(size=300) * 50], axis=1)
    v = (1.0 + 2e-5 * base + 1e-5 * x[:, 2] + rng.normal(size=300) * 1e-6)[:, None]
    fit = fit_voltage_regression(x, v)
    assert np.all(np.abs(fit.alpha[0, :2]) < 1e-4)
    np.testing.assert_allclose(fit.alpha[0, 0] + fit.alpha[0, 1], 2e-5, rtol=1e-2)
    assert fit.rank == 2
    assert fit.condition_number > 1e6


def test_constant_feature_gets_zero_coefficient():
    rng = np.random.default_rng(3)
    x = np.stack([rng.normal(size=50), np.full(50, 7.0)], axis=1)
    fit = fit_voltage_regression(x, (1 + 0.01 * x[:, 0])[:, None])
    assert fit.dropped_features == (1,)
    assert fit.alpha[0, 1] == 0.0
    np.testing.assert_allclose(fit.alpha[0, [0, 2]], [0.01, 1.0], rtol=1e-9)


def test_too_few_flows_is_a_clear_error():
    with pytest.raises(TrainingError, match="singular regression"):
        fit_voltage_regression(np.random.default_rng(0).normal(size=(4, 6)), np.ones((4, 2)))


def test_non_finite_input_is_refused():
    x = np.ones((20, 2))
    x[3, 1] = np.nan
    with pytest.raises(TrainingError, match="non-finite"):
        fit_voltage_regression(x, np.ones((20, 1)))


def test_tap_sensitivity_is_the_difference():
    np.testing.assert_allclose(tap_sensitivities([1.0, 1.01], [[1.00625, 1.0163]]), [[0.00625], [0.0063]])


@pytest.mark.parametrize(
    ("a_true", "b_true"),
    [
        (2e-2, 1.0),  # the paper's inverse shape
        (4e-9, -1.2),  # trap 2: sensitivity rising with head Q
    ],
)
def test_power_form_recovers_parameters(a_true, b_true):
    q = np.linspace(-1000, 2500, 120)
    c = choose_c_kvar(q.min(), q.max())
    y = a_true / (c + q) ** b_true
    holdout = np.arange(q.size) % 5 == 0
    fit, scores = fit_sensitivity(q, y, c_kvar=c, q_range_kvar=(q.min(), q.max()), holdout=holdout)
    assert fit.form == "power"
    assert fit.c == c
    np.testing.assert_allclose([fit.a, fit.b], [a_true, b_true], rtol=1e-3)
    assert scores["power"] < scores["linear"] < scores["constant"]


def test_linear_and_constant_forms_are_chosen_when_they_fit():
    rng = np.random.default_rng(5)
    q = np.linspace(-500, 1500, 100)
    c = choose_c_kvar(q.min(), q.max())
    holdout = np.arange(q.size) % 4 == 0
    y_lin = 1e-5 - 3e-9 * q + rng.normal(size=q.size) * 1e-9  # crosses no zero, but the trend is linear
    fit, _ = fit_sensitivity(q, y_lin, c_kvar=c, q_range_kvar=(q.min(), q.max()), holdout=holdout)
    assert fit.form in ("linear", "power")
    if fit.form == "linear":
        np.testing.assert_allclose([fit.a, fit.b], [1e-5, -3e-9], rtol=2e-2)
    y_const = 5e-6 + rng.normal(size=q.size) * 1e-9
    fit, _ = fit_sensitivity(q, y_const, c_kvar=c, q_range_kvar=(q.min(), q.max()), holdout=holdout)
    assert fit.form == "constant"
    np.testing.assert_allclose(fit.a, 5e-6, rtol=1e-3)


def test_mixed_sign_samples_never_take_the_power_form():
    q = np.linspace(0, 1000, 50)
    y = 1e-7 * np.sin(q / 50)
    fit, scores = fit_sensitivity(q, y, c_kvar=2000.0, q_range_kvar=(0.0, 1000.0))
    assert "power" not in scores
    assert fit.form in ("constant", "linear")


def test_sensitivity_samples_from_a_sweep():
    # one scenario, plant 0 swept -20, 0 (base), +20 kvar; plant 1 swept only at +50
    scenario = np.zeros(4, int)
    plant = np.array([-1, 0, 0, 1])
    pv_q = np.array([[0, 0], [-20, 0], [20, 0], [0, 50]], float)
    q_head = np.array([100, 120, 80, 50], float)
    v = np.array([[1.0], [0.998], [1.002], [1.01]])
    s = sensitivity_samples(scenario, plant, pv_q, q_head, v)
    assert s.plant.tolist() == [0, 0, 1]
    np.testing.assert_allclose(s.dv_dq_pu_per_kvar[:, 0], [1e-4, 1e-4, 2e-4])
    np.testing.assert_allclose(s.q_head_kvar, [110, 90, 75])


def test_integer_weights_are_repeated_flows():
    """A flow of weight 3 counts as the same flow three times (the calendar cover's weighting)."""
    rng = np.random.default_rng(4)
    x = rng.normal(size=(40, 3)) * [100, 50, 10] + [500, 0, 0]
    v = 1.0 + x @ (rng.normal(size=(3, 2)) * 1e-5) + rng.normal(size=(40, 2)) * 1e-3  # noisy: the weights matter
    w = rng.integers(1, 4, size=40)
    weighted = fit_voltage_regression(x, v, weights=w)
    repeated = fit_voltage_regression(np.repeat(x, w, axis=0), np.repeat(v, w, axis=0))
    np.testing.assert_allclose(weighted.alpha, repeated.alpha, rtol=1e-9, atol=1e-12)
    assert not np.allclose(weighted.alpha, fit_voltage_regression(x, v).alpha, rtol=1e-6, atol=0)


@pytest.mark.parametrize("weights", [np.zeros(20), -np.ones(20), np.ones(19)])
def test_bad_weights_are_refused(weights):
    x = np.random.default_rng(5).normal(size=(20, 2))
    with pytest.raises(TrainingError, match="weights"):
        fit_voltage_regression(x, np.ones((20, 1)), weights=weights)


def test_seasonal_calendar_recovers_a_daily_shape_that_changes_with_the_season():
    """A secondary whose customer peaks at night in summer and in the evening in winter (IEEE 8500's deep
    secondaries, docs/method.md): the additive calendar cannot fit it, the seasonal one recovers it exactly."""
    from regression.model import calendar_features

    t_ns = (1672549200 + np.arange(0, 365 * 86400, 3 * 3600 + 420)) * 10**9  # every 3 h 7 min through a year
    base = calendar_features(t_ns, -5.0)
    v = (1.0 + 0.004 * base[:, 0] * base[:, 4] - 0.003 * base[:, 1] * base[:, 5]
         + 0.002 * base[:, 2] * base[:, 4])[:, None]  # harmonics 1 and 2 of the day times the year's
    plain = fit_voltage_regression(base, v)
    one = fit_voltage_regression(calendar_features(t_ns, -5.0, seasonal=1), v)
    two = fit_voltage_regression(calendar_features(t_ns, -5.0, seasonal=2), v)
    assert plain.rmse_pu[0] > 0.002  # the additive terms see none of it
    assert abs(one.rmse_pu[0] - 0.001) < 5e-5  # what is left: harmonic 2's term, rms 0.002 / 2
    assert two.max_abs_pu < 1e-9
    np.testing.assert_allclose(two.alpha[0, [6, 9, 10]], [0.004, -0.003, 0.002], atol=1e-9)


def test_weekly_calendar_marks_local_weekends_and_recovers_their_daily_shape():
    """A shop's load: its own daily shape on weekdays and another on weekends; the weekly terms recover it."""
    from regression.model import WEEKLY_CALENDAR_FEATURES, calendar_features, n_calendar_features

    sat_4am_local = 1688198400 * 10**9  # 2023-07-01 08:00 UTC, a Saturday at 03:00 local (UTC-5)
    days = np.arange(7) * 86400 * 10**9  # Saturday .. Friday
    cal = calendar_features(sat_4am_local + days, -5.0, weekly=True)
    assert cal.shape == (7, n_calendar_features(True, 0, True)) == (7, 6 + len(WEEKLY_CALENDAR_FEATURES))
    assert cal[:, 6].tolist() == [1, 1, 0, 0, 0, 0, 0]
    np.testing.assert_allclose(cal[:, 7:], cal[:, 6:7] * cal[:, :4])
    # 05:30 UTC is Saturday 00:30 local (weekend) but still Friday 23:30 one hour earlier
    edge = calendar_features(np.array([1688189400, 1688185800]) * 10**9, -5.0, weekly=True)
    assert edge[:, 6].tolist() == [1, 0]
    t_ns = (1672549200 + np.arange(0, 365 * 86400, 3 * 3600 + 420)) * 10**9
    base = calendar_features(t_ns, -5.0)
    weekly = calendar_features(t_ns, -5.0, weekly=True)
    v = (1.0 + 0.002 * base[:, 0] - 0.004 * weekly[:, 6] * base[:, 1] + 0.001 * weekly[:, 6])[:, None]
    assert fit_voltage_regression(base, v).rmse_pu[0] > 0.001
    fit = fit_voltage_regression(weekly, v)
    assert fit.max_abs_pu < 1e-9
    np.testing.assert_allclose(fit.alpha[0, [0, 6, 8]], [0.002, 0.001, -0.004], atol=1e-9)
