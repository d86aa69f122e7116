"""The polish's infeasibility proof (agent/solve/polish.py): Farkas certificates from the least-violation problem."""

import numpy as np
import scipy.optimize

from agent.cvvc_qp import build_cvvc_qp
from agent.solve.lattice import tap_bounds, tap_lattice
from agent.solve.polish import farkas_excess, proven_infeasible
from benchmarks.synthetic import random_cvvc_inputs


def _feasible_by_highs(a: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    upper, lower = np.isfinite(hi), np.isfinite(lo)
    lp = scipy.optimize.linprog(np.zeros(a.shape[1]), A_ub=np.vstack([a[upper], -a[lower]]),
                                b_ub=np.concatenate([hi[upper], -lo[lower]]), bounds=(None, None))
    assert lp.status in (0, 2)
    return lp.status == 0


def test_proof_agrees_with_highs_on_tap_fixed_cvvc_problems():
    """Never a feasible problem proven infeasible; the infeasible ones (beyond the margin) proven."""
    rng = np.random.default_rng(5)
    verdicts = []
    for _ in range(12):
        inputs = random_cvvc_inputs(rng)
        fixed = build_cvvc_qp(inputs, soft=False, fixed_d_tap=np.zeros(inputs.n_reg))
        points, _, _ = tap_lattice(*tap_bounds(inputs), 60)
        for d in points[rng.choice(points.shape[0], min(8, points.shape[0]), replace=False)]:
            lo, hi = fixed.bounds_with_d_tap(d)
            proven, feasible = proven_infeasible(fixed.a_dense, lo, hi), _feasible_by_highs(fixed.a_dense, lo, hi)
            assert not (proven and feasible)
            verdicts.append((proven, feasible))
    assert (True, False) in verdicts and (False, True) in verdicts
    assert verdicts.count((False, False)) <= verdicts.count((True, False)) // 4  # the margin leaves few unproven


def test_farkas_excess_of_a_plain_conflict():
    """x <= 1 and x >= 2 (two rows of one entry each, the second a 2-entry row with a zero-cost helper)."""
    a = np.array([[1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])  # x in [-5, 1]; x + z >= 2; z in [0, 0.5]
    lo, hi = np.array([-5.0, 2.0, 0.0]), np.array([1.0, np.inf, 0.5])
    y = np.array([0.0, -1.0, 0.0])  # -(x + z) <= -2 while x + z <= 1.5 on the box
    assert farkas_excess(a, lo, hi, y) == 0.5
    assert proven_infeasible(a, lo, hi)
    assert not proven_infeasible(a, lo, np.array([1.6, np.inf, 0.5]))  # x = 1.6, z = 0.4
    assert farkas_excess(a, lo, hi, np.array([0.0, 1.0, 0.0])) == -np.inf  # leans on the missing upper bound
