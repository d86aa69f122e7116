import numpy as np

from regression.batch import estimate_v_pu, eval_sensitivities, sensitivity_arrays
from regression.model import ModelArrays, SensitivityFit


def _arrays():
    # 3 nodes, 1 feature, 2 regulators; node 0 = reg0 secondary, node 1 = reg1 secondary (behind reg0),
    # node 2 behind reg1
    return ModelArrays(
        alpha=np.array([[1e-4, 1.0], [2e-4, 0.99], [3e-4, 0.98]]),
        tap0=np.array([0.0, 2.0]),
        dv_dtap_pu=np.array([[0.006, 0.0], [0.006, 0.006], [0.006, 0.006]]),
        upstream_regulator=np.array([0, 1, 1]),
        reg_secondary_node=np.array([0, 1]),
        reg_pu_per_v120=np.array([1 / 120, 1 / 120]),
    )


def test_eq5_feature_and_tap_terms():
    v = estimate_v_pu(_arrays(), np.array([[10.0]]), np.array([[1.0, 2.0]]))
    np.testing.assert_allclose(v, [[1.001 + 0.006, 0.992 + 0.006, 0.983 + 0.006]])


def test_eq6_7_correction_uses_nearest_upstream_regulator():
    a = _arrays()
    x, t = np.array([[10.0]]), np.array([[0.0, 2.0]])
    plain = estimate_v_pu(a, x, t)
    measured_v120 = np.array([[(plain[0, 0] + 0.002) * 120, (plain[0, 1] - 0.003) * 120]])
    corr = estimate_v_pu(a, x, t, measured_v120)
    np.testing.assert_allclose(corr - plain, [[0.002, -0.003, -0.003]], atol=1e-12)


def test_sensitivity_forms_and_clipping():
    fits = [
        [
            SensitivityFit(form="power", a=2.0, b=1.0, c=1000.0, q_min_kvar=-500.0, q_max_kvar=500.0),
            SensitivityFit(form="linear", a=1e-5, b=1e-9, q_min_kvar=-500.0, q_max_kvar=500.0),
            SensitivityFit(form="constant", a=3e-6),
        ]
    ]
    s = eval_sensitivities(sensitivity_arrays(fits), np.array([0.0, 900.0]))
    np.testing.assert_allclose(s[0, 0], [2e-3, 1e-5, 3e-6])
    np.testing.assert_allclose(s[1, 0], [2.0 / 1500.0, 1e-5 + 5e-7, 3e-6])  # q clipped to 500
