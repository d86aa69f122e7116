"""The CVVC problem (paper eq. 9-17) and its solution: known optima, a second solver, soft fallback, rounding."""

import dataclasses
import itertools
import warnings

import highspy
import numpy as np
import pytest
import qpsolvers
import scipy.optimize

from agent.cvvc_qp import PROX_WEIGHT, CvvcInputs, build_cvvc_qp
from agent.errors import AgentInputError
from agent.solve import V_TOL_PU, solve_cvvc, solve_milp_reference
from agent.solve.milp import milp_tap_changes
from agent.solve.robust import robust_shortfall_pu, robustly_feasible
from agent.solve.rounding import rounding_candidates
from agent.solve.settings import ROUNDING_GAP_REL
from benchmarks.synthetic import random_cvvc_inputs


def _tiny(v0, *, cost_per_kvar=1e-4, cost_per_tap=1.0, dv_dq=(2e-5, 1e-5), q0=0.0) -> CvvcInputs:
    """2 nodes, 1 plant (1000 kVA, +/-1000 kvar), 1 regulator (0.625 %/step at both nodes, 4 steps/interval)."""
    return CvvcInputs(
        v0_pu=np.array(v0, float),
        dv_dq_pu_per_kvar=np.array(dv_dq, float).reshape(2, 1),
        dv_dtap_pu=np.array([[0.00625], [0.00625]]),
        q0_kvar=np.array([q0]),
        q_min_kvar=np.array([-1000.0]),
        q_max_kvar=np.array([1000.0]),
        q_rating_kvar=np.array([1000.0]),
        taps=np.array([0]),
        tap_min=np.array([-16]),
        tap_max=np.array([16]),
        max_taps_per_interval=np.array([4]),
        cost_per_tap=np.array([cost_per_tap]),
        cost_per_kvar=np.array([cost_per_kvar]),
        v_min_pu=0.975,
        v_max_pu=1.04,
    )


# Hand-computed optima. Node 0 is 0.005 pu over 1.04 unless stated.
# A: Q costs 1e-4/kvar: absorbing 250 kvar (0.005 / 2e-5) costs 0.025, a tap step 1.0 -> Q only.
# B: Q costs 1e-2/kvar (250 kvar = 2.5): relaxed 0.8 tap (0.005 / 0.00625); rounded to 1 tap, cost 1.0.
# C: node 0 is 0.0081 over: 1 tap leaves 0.00185 pu = 92.5 kvar (0.925): 1.925 beats 2 taps (2.0).
CASES = {
    "A_q_only": (dict(v0=[1.045, 1.03]), 0, -250.0, 0.025),
    "B_one_tap": (dict(v0=[1.045, 1.03], cost_per_kvar=1e-2), -1, 0.0, 1.0),
    "C_tap_and_q": (dict(v0=[1.0481, 1.0], cost_per_kvar=1e-2), -1, -92.5, 1.925),
}


@pytest.mark.parametrize("name", CASES)
def test_known_optima(name):
    kwargs, d_tap, q_kvar, cost = CASES[name]
    inputs = _tiny(**kwargs)
    sol = solve_cvvc(inputs)
    assert sol.status == "optimal", sol.reason
    assert sol.taps_new.tolist() == [d_tap]
    np.testing.assert_allclose(sol.q_new_kvar, [q_kvar], atol=0.01)
    assert sol.cost == pytest.approx(cost, abs=1e-4)
    assert sol.max_violation_pu <= V_TOL_PU
    milp = solve_milp_reference(inputs)
    assert milp.status == "optimal"
    assert milp.taps_new.tolist() == [d_tap]
    assert milp.cost == pytest.approx(cost, abs=1e-6)


@pytest.mark.parametrize("soft", [False, True])
@pytest.mark.parametrize("name", CASES)
def test_relaxation_matches_a_second_solver(name, soft):
    """The problem object solved by OSQP and by Clarabel (interior point) through qpsolvers agrees."""
    problem = build_cvvc_qp(_tiny(**CASES[name][0]), soft=soft).to_qpsolvers()
    a = qpsolvers.solve_problem(problem, solver="osqp", eps_abs=1e-9, eps_rel=1e-9, max_iter=100000, raise_error=False)
    b = qpsolvers.solve_problem(problem, solver="clarabel")
    assert a.found and b.found
    np.testing.assert_allclose(a.x, b.x, atol=1e-4)
    qp = build_cvvc_qp(_tiny(**CASES[name][0]), soft=soft)
    assert qp.objective(a.x) == pytest.approx(qp.objective(b.x), abs=1e-6)


def test_relaxed_optimum_by_hand():
    # Case B relaxed: 0.8 tap down, no Q; objective 0.8 plus the proximal term 0.5 * w * 0.8^2 (scaled).
    inputs = _tiny(v0=[1.045, 1.03], cost_per_kvar=1e-2)
    qp = build_cvvc_qp(inputs, soft=False)
    x = qpsolvers.solve_problem(qp.to_qpsolvers(), solver="clarabel").x
    np.testing.assert_allclose(qp.d_tap(x), [-0.8], atol=1e-6)
    np.testing.assert_allclose(qp.q_kvar(x), [0.0], atol=1e-3)
    assert solve_cvvc(inputs).relaxed_d_tap == pytest.approx([-0.8], abs=1e-5)


def test_infeasible_falls_back_to_soft_form():
    # Node 0 is 0.01 over, node 1 0.005 under, and every action moves both the same way: no hard solution.
    # Eq. (17) with a large beta balances the two violations: shift down 0.0025 pu -> 0.0075 pu each,
    # done with Q (10 cost units/pu) rather than taps (160/pu): 250 kvar absorbed, no tap.
    inputs = _tiny(v0=[1.05, 0.97], dv_dq=(1e-5, 1e-5))
    sol = solve_cvvc(inputs)
    assert sol.status == "soft"
    assert "infeasible" in sol.reason
    assert sol.relaxed_form == "soft"
    assert sol.taps_new.tolist() == [0]
    np.testing.assert_allclose(sol.q_new_kvar, [-250.0], atol=1.0)
    over, under = sol.v_pred_pu[0] - 1.04, 0.975 - sol.v_pred_pu[1]
    assert over == pytest.approx(0.0075, abs=2e-5) and under == pytest.approx(0.0075, abs=2e-5)
    assert sol.max_violation_pu == pytest.approx(0.0075, abs=2e-5)
    assert solve_milp_reference(inputs).status == "infeasible"


def test_a_soft_weight_shifts_the_balance_toward_the_heavier_node():
    # The same conflict with node 1's violation weighing a quarter: minimise (0.01 - x)^2 + 0.25 (0.005 + x)^2 over
    # the downward shift x: x = 0.007 pu, 700 kvar absorbed (the paper's equal weights: 250 kvar).
    weighted = dataclasses.replace(_tiny(v0=[1.05, 0.97], dv_dq=(1e-5, 1e-5)), soft_weight=np.array([1.0, 0.25]))
    sol = solve_cvvc(weighted)
    assert sol.status == "soft"
    np.testing.assert_allclose(sol.q_new_kvar, [-700.0], atol=2.0)
    for bad in ([1.0, 0.0], [1.0, 1.5], [1.0, np.nan]):
        with pytest.raises(AgentInputError, match="soft_weight"):
            dataclasses.replace(weighted, soft_weight=np.array(bad))


def test_node_out_of_reach_is_soft_while_the_others_stay_hard():
    # Node 0 is 0.06 over: 4 taps + full Q only reach 0.045, so it gets a violation variable; node 1 keeps
    # its hard limit. Q moves node 0 twice as much as node 1 (2e-5 vs 1e-5 pu/kvar), taps move both alike:
    # full absorption (-1000 kvar: -0.02 / -0.01), then taps until node 1 reaches 0.975 (2.4 relaxed,
    # 3 would break node 1's limit, so 2): node 0 ends 0.0275 over, node 1 inside.
    inputs = _tiny(v0=[1.10, 1.0])
    sol = solve_cvvc(inputs)
    assert sol.status == "soft" and "cannot reach" in sol.reason and "hard limits elsewhere" in sol.reason
    assert sol.relaxed_d_tap == pytest.approx([-2.4], abs=1e-4)
    assert sol.taps_new.tolist() == [-2]
    np.testing.assert_allclose(sol.q_new_kvar, [-1000.0], atol=0.01)
    assert sol.v_pred_pu[1] >= 0.975 - V_TOL_PU
    assert sol.max_violation_pu == pytest.approx(0.0275, abs=1e-5)


def test_fully_soft_when_the_reachable_nodes_conflict():
    # Node 0 cannot reach its limit and nodes 1 and 2 pull in opposite directions with equal sensitivities:
    # the partly hard problem is infeasible, so every node gets a violation variable.
    inputs = CvvcInputs(
        **{
            **dataclasses.asdict(_tiny(v0=[1.10, 1.0])),
            "v0_pu": np.array([1.10, 1.05, 0.97]),
            "dv_dq_pu_per_kvar": np.array([[2e-5], [1e-5], [1e-5]]),
            "dv_dtap_pu": np.array([[0.00625], [0.00625], [0.00625]]),
            "v_min_pu": 0.975,  # stored per node: give them again for three nodes
            "v_max_pu": 1.04,
        }
    )
    sol = solve_cvvc(inputs)
    assert sol.status == "soft" and "soft form at every node" in sol.reason
    assert np.all(np.isfinite(sol.v_pred_pu)) and sol.max_violation_pu > 0.0


def test_no_action_needed_is_exactly_zero():
    sol = solve_cvvc(_tiny(v0=[1.0, 1.01], q0=120.0))
    assert sol.status == "optimal" and sol.iterations == 0
    assert sol.taps_new.tolist() == [0] and sol.q_new_kvar.tolist() == [0.0]  # set point back to 0 saves cost


def test_fixed_plant_and_frozen_regulator_are_respected():
    base = _tiny(v0=[1.045, 1.03])
    inputs = CvvcInputs(**{**dataclasses.asdict(base), "q_min_kvar": np.array([50.0]), "q_max_kvar": np.array([50.0]),
                           "max_taps_per_interval": np.array([0])})  # fmt: skip
    sol = solve_cvvc(inputs)
    assert sol.taps_new.tolist() == [0]
    np.testing.assert_allclose(sol.q_new_kvar, [50.0], atol=1e-3)
    assert sol.status == "soft"  # the only remaining freedom cannot fix node 0


def _feasible_with_taps_fixed(inputs: CvvcInputs, d_tap: np.ndarray) -> bool:
    """Exact LP feasibility of the hard limits over Q with the taps fixed (scipy HiGHS)."""
    v_base = inputs.v0_pu - inputs.dv_dq_pu_per_kvar @ inputs.q0_kvar + inputs.dv_dtap_pu @ d_tap
    a = inputs.dv_dq_pu_per_kvar
    res = scipy.optimize.linprog(
        np.zeros(inputs.n_pv),
        A_ub=np.vstack([a, -a]),
        b_ub=np.concatenate([inputs.v_max_pu - v_base, v_base - inputs.v_min_pu]),
        bounds=list(zip(inputs.q_min_kvar, inputs.q_max_kvar, strict=True)),
        method="highs",
    )
    return res.status == 0


def test_rounding_keeps_hard_limits_when_an_integer_point_within_one_tap_exists():
    rng = np.random.default_rng(11)
    checked = 0
    for _ in range(60):
        inputs = random_cvvc_inputs(rng)
        sol = solve_cvvc(inputs)
        if sol.relaxed_form != "hard":
            continue
        d = sol.relaxed_d_tap
        choices = [sorted({np.floor(x + 1e-6), np.ceil(x - 1e-6)}) for x in d]
        if not any(_feasible_with_taps_fixed(inputs, np.array(c)) for c in itertools.product(*choices)):
            continue
        checked += 1
        assert sol.status == "optimal", sol.reason
        assert sol.max_violation_pu <= V_TOL_PU
        assert np.all(np.abs(sol.taps_new - inputs.taps - d) < 1.0 + 1e-6)  # within one tap of the relaxation
    assert checked >= 30


def _score_with_taps_fixed(inputs: CvvcInputs, d_tap: np.ndarray) -> float:
    """The rounding's score of integer tap changes ``d_tap`` (eq. 9 cost plus the proximal terms) with Q re-solved by
    Clarabel over every node, hard limits; inf when no Q meets them."""
    fixed = build_cvvc_qp(inputs, soft=False, fixed_d_tap=d_tap)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # Clarabel's word for an infeasible problem
        out = qpsolvers.solve_problem(fixed.to_qpsolvers(), solver="clarabel")
    if not out.found:
        return np.inf
    v = inputs.predict_v_pu(d_tap, fixed.q_kvar(out.x))
    if np.max(np.maximum(v - inputs.v_max_pu, inputs.v_min_pu - v)) > V_TOL_PU:
        return np.inf
    prox = 0.5 * PROX_WEIGHT * fixed.cost_scale * float(d_tap @ d_tap)
    return fixed.objective(out.x) + float(inputs.cost_per_tap @ np.abs(d_tap)) + prox


def test_the_rounding_s_pruned_search_finds_the_best_of_every_candidate():
    """The rounding skips candidates whose dual bound (at the relaxation's or at a re-solved candidate's multipliers)
    is not below the best score so far; its taps still score within its stopping tolerance of the best of every
    rounding candidate re-solved by a second solver."""
    rng = np.random.default_rng(21)
    checked = 0
    for _ in range(80):
        inputs = random_cvvc_inputs(rng)
        sol = solve_cvvc(inputs)
        candidates = rounding_candidates(sol.relaxed_d_tap)
        if sol.status != "optimal" or sol.relaxed_form != "hard" or len(candidates) < 4:
            continue
        scores = [_score_with_taps_fixed(inputs, d) for d in candidates]
        if not np.isfinite(min(scores)):
            continue  # no rounding meets the hard limits: the search further away decides
        checked += 1
        relaxed = sol.relaxed_problem.objective(sol.relaxed_x)
        chosen = _score_with_taps_fixed(inputs, (sol.taps_new - inputs.taps).astype(float))
        assert chosen <= min(scores) + ROUNDING_GAP_REL * abs(relaxed) + 1e-6
    assert checked >= 30


def test_rounding_gap_to_the_exact_milp_is_small():
    rng = np.random.default_rng(12)
    gaps = []
    for _ in range(40):
        inputs = random_cvvc_inputs(rng)
        sol, milp = solve_cvvc(inputs), solve_milp_reference(inputs)
        if milp.status != "optimal" or sol.status != "optimal":
            continue
        # the MILP is exact: nothing feasible beats it (ours may sit up to 1e-5 pu past a limit: tolerance)
        assert sol.cost >= milp.cost * (1 - 1e-4) - 1e-6
        gaps.append((sol.cost - milp.cost) / max(milp.cost, 1e-9))
    assert len(gaps) >= 25
    assert np.mean(gaps) < 0.02  # the goal for the mean rounding gap


def test_solutions_are_finite_deterministic_and_within_device_limits():
    rng = np.random.default_rng(13)
    for _ in range(25):
        inputs = random_cvvc_inputs(rng)
        a, b = solve_cvvc(inputs), solve_cvvc(inputs)
        for name in ("taps_new", "q_new_kvar", "v_pred_pu", "relaxed_x", "relaxed_y"):
            assert getattr(a, name).tobytes() == getattr(b, name).tobytes()
            assert np.all(np.isfinite(getattr(a, name)))
        assert a.status != "hold", a.reason
        assert np.all((a.q_new_kvar >= inputs.q_min_kvar) & (a.q_new_kvar <= inputs.q_max_kvar))
        assert np.all(np.abs(a.taps_new - inputs.taps) <= inputs.max_taps_per_interval)
        assert np.all((a.taps_new >= inputs.tap_min) & (a.taps_new <= inputs.tap_max))
        warm = solve_cvvc(inputs, warm_start=a)
        assert warm.status == a.status and np.array_equal(warm.taps_new, a.taps_new)


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"v0_pu": np.array([np.nan, 1.0])}, "not finite"),
        ({"dv_dq_pu_per_kvar": np.ones((3, 1))}, "expected shape"),
        ({"q_min_kvar": np.array([2000.0])}, "q_min_kvar exceeds"),
        ({"taps": np.array([0.5])}, "integers"),
        ({"v_min_pu": 1.05}, "below"),
    ],
)
def test_inputs_are_validated(change, match):
    base = _tiny(v0=[1.0, 1.0])
    with pytest.raises(AgentInputError, match=match):
        CvvcInputs(**{**dataclasses.asdict(base), **change})
    with pytest.raises(AgentInputError, match=match):  # a copy with the bad field is refused alike
        base.replaced(**change)


def test_a_replaced_copy_is_the_problem_built_again():
    """``replaced`` checks only what changed, and gives every field as building the problem again does."""
    base = random_cvvc_inputs(np.random.default_rng(3), n_nodes=12, n_pv=3)  # 8 regulators
    changes = {"tap_min": base.tap_min - 1, "v_max_pu": 1.04, "cost_per_tap": np.arange(8) / 10, "soft_alpha": 2}
    copy, rebuilt = base.replaced(**changes), dataclasses.replace(base, **changes)
    for f in dataclasses.fields(CvvcInputs):
        a, b = getattr(copy, f.name), getattr(rebuilt, f.name)
        if isinstance(b, np.ndarray):
            assert a.dtype == b.dtype and np.array_equal(a, b) and not a.flags.writeable, f.name
        else:
            assert a == b and type(a) is type(b), f.name
    assert not np.shares_memory(copy.tap_min, base.tap_min) and copy.v0_pu is base.v0_pu  # unchanged: shared
    np.testing.assert_array_equal(base.tap_max, copy.tap_max)
    with pytest.raises(AgentInputError, match="tap_min <= tap_max"):
        base.replaced(tap_min=base.tap_max + 1)
    with pytest.raises(TypeError, match="no field"):
        base.replaced(taps_now=base.taps)


def test_large_soft_problem_stays_sparse_and_is_solved():
    # Every node of a big feeder (case A), half of them far over and half far under: the soft form would
    # need a 2000 x 2000 dense copy; it is kept sparse and solved by OSQP alone.
    base = random_cvvc_inputs(np.random.default_rng(5), n_nodes=2000)
    v0 = 1.0 + np.where(np.arange(2000) % 2 == 0, 0.07, -0.07)
    inputs = CvvcInputs(**{**dataclasses.asdict(base), "v0_pu": v0})
    assert build_cvvc_qp(inputs, soft=True).a_dense is None
    sol = solve_cvvc(inputs)
    assert sol.status == "soft" and "cannot reach" in sol.reason
    assert np.all(np.isfinite(sol.v_pred_pu)) and np.all(np.isfinite(sol.q_new_kvar))
    assert 0.0 < sol.max_violation_pu < 0.045  # below the worst violation before acting (0.975 - 0.93)


def test_row_generation_on_many_nodes_meets_every_limit():
    # 400 critical nodes: the relaxation starts with the 50 nearest a limit and adds violated ones; an
    # "optimal" answer must meet the hard limits at every node, with fewer rows than nodes.
    rng = np.random.default_rng(21)
    optimal = 0
    for _ in range(12):
        inputs = random_cvvc_inputs(rng, n_nodes=400)
        sol = solve_cvvc(inputs)
        assert np.all(np.isfinite(sol.v_pred_pu)) and sol.status != "hold", sol.reason
        if sol.status != "optimal":
            continue
        optimal += 1
        assert sol.max_violation_pu <= V_TOL_PU
        assert sol.relaxed_problem is not None and sol.relaxed_problem.nodes.size < 400
        milp = solve_milp_reference(inputs)
        assert milp.status == "optimal" and sol.cost >= milp.cost * (1 - 1e-4) - 1e-6
    assert optimal >= 2


def test_the_fallbacks_net_tap_milp_finds_the_exact_milps_optimum():
    """``milp_tap_changes`` (one integer net change per regulator) against ``solve_milp_reference`` (tap steps up
    and down, each integer): same feasibility, and its taps with the best Q for them cost the exact optimum."""
    rng = np.random.default_rng(5)
    compared = 0
    for _ in range(30):
        inputs = random_cvvc_inputs(rng)
        ref = solve_milp_reference(inputs)
        d = milp_tap_changes(inputs, np.zeros(inputs.n_nodes, bool))
        assert (d is None) == (ref.status == "infeasible")
        if d is None or ref.status != "optimal":
            continue
        fixed = build_cvvc_qp(inputs, soft=False, fixed_d_tap=d)  # Q only: an LP for the best Q with these taps
        a = fixed.A.toarray()
        lp = scipy.optimize.linprog(fixed.c, A_ub=np.vstack([a, -a]), b_ub=np.concatenate([fixed.upper, -fixed.lower]),
                                    bounds=(None, None), method="highs")
        assert lp.status == 0
        cost = inputs.cost(d, fixed.q_kvar(lp.x))
        assert cost == pytest.approx(ref.cost, rel=2e-3, abs=1e-6)
        compared += 1
    assert compared >= 15


def _low_and_high(rel_error: float) -> CvvcInputs:
    """Node 0 is 0.015 pu under 0.975, node 1 at 1.04, both 2e-5 pu/kvar, taps frozen: only the soft form."""
    return CvvcInputs(
        **{
            **dataclasses.asdict(_tiny(v0=[0.96, 1.04], dv_dq=(2e-5, 2e-5))),
            "max_taps_per_interval": np.array([0]),
            "v_min_pu": 0.975,
            "v_max_pu": 1.04,
            "dv_dq_rel_error": rel_error,
        }
    )


@pytest.mark.parametrize(("rel_error", "q_kvar"), [(0.0, 375.0), (0.5, 300.0)])
def test_sensitivity_error_shrinks_q_in_the_soft_form(rel_error, q_kvar):
    # Minimise (0.015 - s q)^2 + (s q)^2 + 2 err^2 (s q)^2 (both rows soft): s q = 0.015 / (2 + 2 err^2), so
    # q = 375 kvar with err 0 and 300 kvar with err 0.5 (s = 2e-5; the Q cost of 1e-4 per kvar moves it 0.1 kvar).
    sol = solve_cvvc(_low_and_high(rel_error))
    assert sol.status == "soft" and "hard voltage limits infeasible" in sol.reason
    assert sol.q_new_kvar[0] == pytest.approx(q_kvar, abs=1.0)
    problem = build_cvvc_qp(_low_and_high(rel_error), soft=True)
    b = qpsolvers.solve_problem(problem.to_qpsolvers(), solver="clarabel")
    assert b.found and problem.q_kvar(b.x)[0] == pytest.approx(q_kvar, abs=1.0)


def test_sensitivity_error_leaves_the_hard_form_alone():
    hard = [build_cvvc_qp(_tiny(v0=[1.045, 1.03]), soft=False)]
    inputs = CvvcInputs(**{**dataclasses.asdict(_tiny(v0=[1.045, 1.03])), "dv_dq_rel_error": 0.5})
    hard.append(build_cvvc_qp(inputs, soft=False))
    np.testing.assert_array_equal(hard[0].p_diag, hard[1].p_diag)
    with pytest.raises(AgentInputError, match="dv_dq_rel_error"):
        CvvcInputs(**{**dataclasses.asdict(inputs), "dv_dq_rel_error": 1.5})


def test_nothing_can_move_is_answered_without_a_solve():
    """PV at night (no Q headroom) and every tap frozen: the only point is the present one; a violation stays
    and is reported (OSQP called such all-pinned soft problems infeasible: epri-ckt5 case A held 135 decisions)."""
    pinned = {"q_min_kvar": np.array([0.0]), "q_max_kvar": np.array([0.0]), "max_taps_per_interval": np.array([0])}
    over = solve_cvvc(CvvcInputs(**{**dataclasses.asdict(_tiny(v0=[1.043, 1.03])), **pinned}))
    assert over.status == "soft" and "no action available" in over.reason and "0.0030 pu" in over.reason
    assert over.q_new_kvar.tolist() == [0.0] and over.taps_new.tolist() == [0] and over.iterations == 0
    assert over.max_violation_pu == pytest.approx(0.003)
    inside = solve_cvvc(CvvcInputs(**{**dataclasses.asdict(_tiny(v0=[1.0, 1.0])), **pinned}))
    assert inside.status == "optimal" and inside.reason == "" and inside.cost == 0.0


def _narrow_band(rel_error: float) -> CvvcInputs:
    """Node 0 is 0.001 pu over 1.04, node 1 0.0005 pu above 0.975; two 2000 kVA plants whose sensitivities at the
    two nodes differ by 0.4 uV/V per kvar (4.0 and 3.6 against 3.0 and 3.0), taps frozen. The hard limits hold
    only with the plants pulling against each other: 4 x - 3 y >= 1000 and 3.6 x - 3 y <= 500 (x absorbed by plant
    0, y injected by plant 1, in kvar) give x = 1250, y = 1333 (0.4 x >= 500)."""
    return CvvcInputs(
        v0_pu=np.array([1.041, 0.9755]),
        dv_dq_pu_per_kvar=np.array([[4.0e-6, 3.0e-6], [3.6e-6, 3.0e-6]]),
        dv_dtap_pu=np.array([[0.00625], [0.00625]]),
        q0_kvar=np.zeros(2),
        q_min_kvar=np.full(2, -2000.0),
        q_max_kvar=np.full(2, 2000.0),
        q_rating_kvar=np.full(2, 2000.0),
        taps=np.array([0]),
        tap_min=np.array([-16]),
        tap_max=np.array([16]),
        max_taps_per_interval=np.array([0]),
        cost_per_tap=np.array([1.0]),
        cost_per_kvar=np.full(2, 1e-4),
        v_min_pu=0.975,
        v_max_pu=1.04,
        dv_dq_rel_error=rel_error,
    )


def test_hard_limits_that_need_plants_pulling_apart_on_sensitivity_differences_go_soft():
    """Beyond the paper: with exact sensitivities (error 0) the hard form pulls the plants apart (-1250 / +1333
    kvar, hand-computed); with a 30 % error no action meets the limits for every sensitivity within it (robust
    counterpart infeasible), so the soft form with the error term decides, with far less Q."""
    exact = solve_cvvc(_narrow_band(0.0))
    assert exact.status == "optimal" and exact.reason == ""
    np.testing.assert_allclose(exact.q_new_kvar, [-1250.0, 1333.3], atol=2.0)
    uncertain = solve_cvvc(_narrow_band(0.3))
    assert uncertain.status == "soft" and "not within 30% of them" in uncertain.reason
    assert np.abs(uncertain.q_new_kvar).sum() < 0.2 * np.abs(exact.q_new_kvar).sum()
    assert not robustly_feasible(_narrow_band(0.3), np.ones(2, bool))
    assert robustly_feasible(_narrow_band(0.0), np.ones(2, bool))


def test_a_problem_priced_anew_shares_the_robust_verdict_and_one_with_other_limits_does_not():
    """The robust check depends on the feasible set alone: a copy with new costs (the tap offer's) takes the verdict
    already found; a copy with another sensitivity error or other tap ranges finds its own."""
    hard = np.ones(2, bool)
    tight = _narrow_band(0.3)
    assert not robustly_feasible(tight, hard)
    priced = tight.replaced(cost_per_tap=np.zeros(1), cost_per_kvar=np.full(2, 1e-3))
    assert priced.feasible_set_memo is tight.feasible_set_memo and not robustly_feasible(priced, hard)
    exact = tight.replaced(dv_dq_rel_error=0.0)
    assert exact.feasible_set_memo is not tight.feasible_set_memo and robustly_feasible(exact, hard)
    for other in (tight.replaced(tap_max=np.array([1])), tight.replaced(v_max_pu=1.05)):
        assert other.feasible_set_memo is not tight.feasible_set_memo


def test_hard_limits_that_hold_within_the_sensitivity_error_stay_hard():
    """Case A_q_only with a 30 % error: absorbing 357 kvar (250 / 0.7) would meet the limits at the worst error, so
    the hard form keeps its optimum (-250 kvar at the nominal sensitivity), though that point alone is not robust."""
    inputs = CvvcInputs(**{**dataclasses.asdict(_tiny(v0=[1.045, 1.03])), "dv_dq_rel_error": 0.3})
    sol = solve_cvvc(inputs)
    assert sol.status == "optimal" and sol.reason == ""
    assert sol.q_new_kvar[0] == pytest.approx(-250.0, abs=1.0)
    assert robust_shortfall_pu(inputs, np.zeros(1), sol.q_new_kvar, np.ones(2, bool)) == pytest.approx(0.0015, abs=1e-5)


def test_a_plant_holding_a_large_q_that_keeps_the_limits_stays_hard():
    """The sensitivity's error acts on the change from the present set point: plant absorbing 1500 kvar, node 0 at
    1.039 pu (4 uV/V per kvar), node 1 at 0.976 pu (3 uV/V per kvar), taps frozen. Eq. (13)'s optimum gives up 250
    kvar (node 0 to 1.04 pu); holding -1500 kvar meets both limits whatever the sensitivities, so the hard form stands.
    On the set point's magnitude instead (0.3 x 4 uV/V x 1500 kvar = 0.0018 pu at node 0), every Q absorbing enough
    for node 0 (at most -1786 kvar) would take node 1 under its limit (at least -1410 kvar): the soft form, at every
    decision that holds the plant there.
    """
    inputs = _tiny([1.039, 0.976], dv_dq=(4.0e-6, 3.0e-6), q0=-1500.0).replaced(
        q_min_kvar=[-2000.0], q_max_kvar=[2000.0], q_rating_kvar=[2000.0], max_taps_per_interval=[0],
        dv_dq_rel_error=0.3)
    assert robustly_feasible(inputs, np.ones(2, bool))
    sol = solve_cvvc(inputs)
    assert sol.status == "optimal" and sol.reason == ""
    assert sol.q_new_kvar[0] == pytest.approx(-1250.0, abs=1.0)
    # the decision's own change (+250 kvar) is not robust at node 0: 0.3 x 4 uV/V x 250 kvar over the limit
    assert robust_shortfall_pu(inputs, np.zeros(1), sol.q_new_kvar, np.ones(2, bool)) == pytest.approx(3e-4, abs=1e-5)


def _robust_lp_verdict(inputs: CvvcInputs, hard: np.ndarray) -> bool:
    """The robust counterpart as an LP (HiGHS): feasible unless HiGHS proves it infeasible. Variables: the hard QP's,
    then each plant's change size ``t >= |Q+ - Q- - Q0|`` (rating units)."""
    idx = np.flatnonzero(hard)
    qp = build_cvvc_qp(inputs, soft=False, nodes=idx)
    n, lay, k = idx.size, qp.layout, inputs.n_pv
    rows = qp.A.toarray()[:n]
    spread = inputs.dv_dq_rel_error * np.abs(rows[:, lay.q_inj])
    q0 = inputs.q0_kvar / inputs.q_rating_kvar
    q_net = np.zeros((k, lay.n))
    q_net[:, lay.q_inj], q_net[:, lay.q_abs] = np.eye(k), -np.eye(k)
    a_ub = np.vstack([np.hstack([rows, spread]), -np.hstack([rows, -spread]),
                      np.hstack([q_net, -np.eye(k)]), np.hstack([-q_net, -np.eye(k)])])
    b_ub = np.concatenate([qp.upper[:n], -qp.lower[:n], q0, -q0])
    bounds = list(zip(qp.lower[n:], qp.upper[n:], strict=True)) + [(0.0, None)] * k
    lp = scipy.optimize.linprog(np.zeros(lay.n + k), A_ub=a_ub, b_ub=b_ub, bounds=bounds, method="highs")
    return bool(lp.status != 2)


def test_robust_check_agrees_with_the_lp_it_replaces():
    """The robust feasibility check (dense active set) gives HiGHS's LP verdict on random paper-size problems, both
    verdicts occurring."""
    rng = np.random.default_rng(4)
    verdicts = []
    for _ in range(60):
        base = random_cvvc_inputs(rng)
        inputs = CvvcInputs(**{**dataclasses.asdict(base), "dv_dq_rel_error": float(rng.choice([0.0, 0.1, 0.3, 0.6]))})
        hard = rng.random(inputs.n_nodes) < 0.7
        verdict = robustly_feasible(inputs, hard)
        assert verdict == _robust_lp_verdict(inputs, hard)
        verdicts.append(verdict)
    assert True in verdicts and False in verdicts


def test_the_fallback_milp_runs_after_highs_started_with_another_thread_count():
    """HiGHS keeps one thread scheduler per process and refuses to run a model asking for another thread count: the
    fallback MILP (one thread) must still answer after a Highs object with two threads ran in the process."""
    other = highspy.Highs()
    other.setOptionValue("output_flag", False)
    other.setOptionValue("threads", 2)
    other.addVar(0.0, 1.0)
    other.run()
    inputs = random_cvvc_inputs(np.random.default_rng(5))
    assert solve_milp_reference(inputs).status == "optimal"
    assert milp_tap_changes(inputs, np.zeros(inputs.n_nodes, bool)) is not None
