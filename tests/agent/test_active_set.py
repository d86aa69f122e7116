"""The dense dual active-set QP solve (agent/solve/active_set.py, DAQP) against Clarabel and HiGHS, random problems."""

from __future__ import annotations

import numpy as np
import pytest
import qpsolvers
import scipy.optimize
import scipy.sparse as sp

from agent.cvvc_qp import build_cvvc_qp
from agent.dense_split import dense_split
from agent.solve.active_set import solve_dense_qp
from benchmarks.synthetic import random_cvvc_inputs


def _random_problem(rng: np.random.Generator, feasible: bool = True):
    """A strictly convex QP with a diagonal P: dependent rows, one-sided rows, equalities, bound rows."""
    n = int(rng.integers(1, 12))
    m = int(rng.integers(1, 40))
    p = rng.uniform(0.01, 10.0, n)
    c = rng.normal(size=n)
    a = rng.normal(size=(m, n))
    a[rng.random((m, n)) < 0.3] = 0.0
    if m > 3:
        a[1] = 2.0 * a[0]  # a dependent pair
    if m > 5:
        a[2] = 0.0
        a[2, 0] = 1.0  # a bound row
    x_feasible = rng.normal(size=n)
    mid = a @ x_feasible
    lo = mid - rng.uniform(0.0, 2.0, m)
    hi = mid + rng.uniform(0.0, 2.0, m)
    equal = rng.random(m) < 0.05
    lo[equal] = hi[equal] = mid[equal]
    lo[rng.random(m) < 0.2] = -np.inf
    if not feasible:
        row = int(rng.integers(0, m))
        a[row] = rng.normal(size=n) + 0.1
        lo = np.append(lo, hi[row] + 1.0 if np.isfinite(hi[row]) else 1.0)  # a copy of ``row`` above its range
        hi = np.append(hi, np.inf)
        a = np.vstack([a, a[row]])
        hi[row] = lo[-1] - 1.0
        lo[row] = min(lo[row], hi[row])
    return p, c, a, lo, hi


def _clarabel(p, c, a, lo, hi):
    upper, lower = np.isfinite(hi), np.isfinite(lo)
    g = sp.csc_matrix(np.vstack([a[upper], -a[lower]]))
    h = np.concatenate([hi[upper], -lo[lower]])
    return qpsolvers.solve_qp(sp.diags(p).tocsc(), c, g, h, solver="clarabel")


@pytest.mark.parametrize("seed", range(4))
def test_optimum_matches_clarabel(seed):
    rng = np.random.default_rng(seed)
    for _ in range(50):
        p, c, a, lo, hi = _random_problem(rng)
        out = solve_dense_qp(p, c, a, lo, hi)
        assert out.status == "optimal", out.reason
        reference = _clarabel(p, c, a, lo, hi)
        np.testing.assert_allclose(out.x, reference, atol=1e-5)  # Clarabel's own accuracy
        # KKT in OSQP's sign convention: stationarity, complementarity
        np.testing.assert_allclose(p * out.x + c + a.T @ out.y, 0.0, atol=1e-8)
        ax = a @ out.x
        assert np.all(ax >= lo - 1e-8) and np.all(ax <= hi + 1e-8)
        assert np.all((out.y <= 1e-9) | (ax >= hi - 1e-8)) and np.all((out.y >= -1e-9) | (ax <= lo + 1e-8))


def test_a_variable_with_two_single_entry_rows_keeps_both():
    """The first single-entry row of a variable is its bound, the second stays a row: both hold at the optimum."""
    p, c = np.array([1.0, 1.0]), np.array([-4.0, 1.0])  # unconstrained minimum (4, -1)
    a = np.array([[1.0, 0.0], [0.0, 1.0], [2.0, 0.0], [1.0, 1.0]])
    lo, hi = np.array([-1.0, -0.5, -np.inf, -np.inf]), np.array([3.0, 0.5, 5.0, 10.0])  # x0 <= 3, 2 x0 <= 5 binds
    out = solve_dense_qp(p, c, a, lo, hi)
    assert out.status == "optimal", out.reason
    np.testing.assert_allclose(out.x, [2.5, -0.5], atol=1e-9)
    np.testing.assert_allclose(out.x, _clarabel(p, c, a, lo, hi), atol=1e-6)
    assert out.y[0] == 0.0 and out.y[2] > 0.0 and out.y[1] < 0.0  # OSQP's signs: upper > 0, lower < 0


def test_any_guess_gives_the_same_optimum():
    """A guess only changes the start: right, wrong or random, the answer is the same."""
    rng = np.random.default_rng(7)
    for _ in range(100):
        p, c, a, lo, hi = _random_problem(rng)
        exact = solve_dense_qp(p, c, a, lo, hi)
        for guess in (np.sign(exact.y).astype(np.int8), rng.integers(-1, 2, a.shape[0]).astype(np.int8)):
            out = solve_dense_qp(p, c, a, lo, hi, guess=guess)
            assert out.status == "optimal", out.reason
            np.testing.assert_allclose(out.x, exact.x, atol=1e-7)


def test_the_right_guess_needs_no_step_but_the_check():
    rng = np.random.default_rng(3)
    p, c, a, lo, hi = _random_problem(rng)
    exact = solve_dense_qp(p, c, a, lo, hi)
    assert exact.steps > 1
    assert solve_dense_qp(p, c, a, lo, hi, guess=np.sign(exact.y).astype(np.int8)).steps == 1  # DAQP's check


def test_infeasibility_agrees_with_highs():
    rng = np.random.default_rng(11)
    verdicts = []
    for _ in range(60):
        p, c, a, lo, hi = _random_problem(rng, feasible=False)
        out = solve_dense_qp(p, c, a, lo, hi)
        upper, lower = np.isfinite(hi), np.isfinite(lo)
        lp = scipy.optimize.linprog(
            np.zeros(a.shape[1]),
            A_ub=np.vstack([a[upper], -a[lower]]),
            b_ub=np.concatenate([hi[upper], -lo[lower]]),
            bounds=(None, None),
        )
        verdicts.append((out.status, lp.status))
        assert out.status != "optimal" or lp.status == 0
    assert ("infeasible", 2) in verdicts  # the constructed conflicts are found, and HiGHS agrees


def test_inconsistent_data_fails_with_a_reason():
    out = solve_dense_qp(np.array([1.0, -1.0]), np.zeros(2), np.eye(2), np.zeros(2), np.ones(2))
    assert out.status == "failed" and "positive" in out.reason
    out = solve_dense_qp(np.ones(2), np.zeros(2), np.eye(2), np.ones(2), np.zeros(2))
    assert out.status == "failed" and "lo > hi" in out.reason


def test_step_limit_is_respected():
    rng = np.random.default_rng(5)
    p, c, a, lo, hi = _random_problem(rng)
    c = c - 100.0  # the unconstrained minimum far outside: several steps needed
    assert solve_dense_qp(p, c, a, lo, hi).steps > 1
    out = solve_dense_qp(p, c, a, lo, hi, max_steps=1)
    assert out.status == "failed" and "step limit" in out.reason


def test_one_split_serves_every_solve_with_its_matrix():
    """The rounding re-solves one tap-fixed problem with other bounds: the matrix's split, made once
    (``CvvcQp.dense_split``), gives each solve the answer a split of its own gives, bit for bit, and the solves
    leave the split's copy of the rows as it was.
    """
    rng = np.random.default_rng(11)
    inputs = random_cvvc_inputs(rng)
    qp = build_cvvc_qp(inputs, soft=True, fixed_d_tap=np.zeros(inputs.n_reg))  # always feasible
    split = qp.dense_split
    assert split is not None and split.general.size == qp.nodes.size  # the voltage rows; the rest are bounds
    rows = split.a_rows.copy()
    compared = 0
    for d in rng.integers(-2, 3, (20, inputs.n_reg)):
        lo, hi = qp.bounds_with_d_tap(d)
        shared = solve_dense_qp(qp.p_diag, qp.c, qp.a_dense, lo, hi, split=split)
        own = solve_dense_qp(qp.p_diag, qp.c, qp.a_dense, lo, hi, split=dense_split(qp.a_dense))
        assert (shared.status, shared.steps) == (own.status, own.steps)
        assert shared.x.tobytes() == own.x.tobytes() and shared.y.tobytes() == own.y.tobytes()
        compared += shared.status == "optimal"
    assert compared >= 5
    assert split.a_rows.tobytes() == rows.tobytes()


@pytest.mark.filterwarnings("ignore:Clarabel.rs terminated")  # infeasible random problems are expected
@pytest.mark.parametrize("soft", [False, True])
def test_cvvc_problems_match_clarabel(soft):
    """The agent's own problems (scaled CVVC relaxations), hard and soft form."""
    rng = np.random.default_rng(2)
    solved = 0
    for _ in range(30):
        qp = build_cvvc_qp(random_cvvc_inputs(rng), soft=soft)
        out = solve_dense_qp(qp.p_diag, qp.c, qp.a_dense, qp.lower, qp.upper)
        reference = qpsolvers.solve_problem(qp.to_qpsolvers(), solver="clarabel")
        if not reference.found:
            assert out.status != "optimal"
            continue
        assert out.status == "optimal", out.reason
        assert qp.objective(out.x) == pytest.approx(qp.objective(reference.x), rel=1e-6, abs=1e-7)
        solved += 1
    assert solved >= 20
