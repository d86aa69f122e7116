"""The rounding's search near "no move": the lattice of tap changes, Lagrangian cuts, the bound beyond the lattice."""

import itertools

import numpy as np
import pytest

from agent.cvvc_qp import CvvcInputs, build_cvvc_qp
from agent.solve import V_TOL_PU, solve_cvvc, solve_milp_reference
from agent.solve.lattice import (
    LagrangianCut,
    cut_at,
    feasibility_cut,
    phase_one_multipliers,
    region_bound,
    tap_bounds,
    tap_lattice,
)
from agent.solve.polish import active_set_polish
from benchmarks.synthetic import random_cvvc_inputs


def _brute(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Every integer point of the box."""
    return np.array(list(itertools.product(*[range(a, b + 1) for a, b in zip(lo, hi, strict=True)])), float)


@pytest.mark.parametrize(
    ("lo", "hi", "max_points"),
    [
        ([-2, -2, -2], [2, 2, 2], 40),  # k = 2 (25 points), k = 3 would be 63
        ([-2, 0, -1], [2, 0, 3], 1000),  # a frozen device, lopsided room: every point (complete)
        ([0, 0], [0, 0], 10),  # nothing can move: the one point, complete
    ],
)
def test_lattice_holds_every_point_within_k_steps_cheapest_first(lo, hi, max_points):
    lo, hi = np.array(lo), np.array(hi)
    points, k, complete = tap_lattice(lo, hi, max_points)
    every = _brute(lo, hi)
    steps = np.abs(every).sum(axis=1)
    expected = every[steps <= k]
    assert points.shape[0] <= max_points
    assert sorted(map(tuple, points)) == sorted(map(tuple, expected))
    assert np.all(np.diff(np.abs(points).sum(axis=1)) >= 0)  # by steps in all
    assert complete == (expected.shape[0] == every.shape[0])
    if not complete:
        assert np.count_nonzero(steps <= k + 1) > max_points  # k is the largest that fits


def test_region_bound_is_below_every_point_further_away():
    rng = np.random.default_rng(3)
    lo, hi = np.array([-2, -3, 0, -1]), np.array([2, 1, 0, 3])
    every = _brute(lo, hi)
    steps = np.abs(every).sum(axis=1)
    for _ in range(50):
        cost = rng.uniform(0.1, 1.0, 4)
        cut = LagrangianCut(const=float(rng.normal()), slope=rng.normal(0.0, 0.6, 4))
        for m in (1, 3, 5):
            far = every[steps >= m]
            exact = np.min(np.abs(far) @ cost + cut.const + far @ cut.slope)
            assert region_bound(cut, cost, lo, hi, m) <= exact + 1e-12
        # without a cut: the m cheapest steps (the Q part is at least 0)
        assert region_bound(None, cost, lo, hi, 2) == pytest.approx(np.sort(np.repeat(cost[[0, 1, 3]], 2))[:2].sum())
    assert region_bound(None, np.ones(4), lo, hi, 100) == np.inf  # no point that far


def _q_part(fixed, d):
    """The Q part of a candidate's score (the tap-fixed QP's optimum) [cost units], or inf when infeasible."""
    lo, hi = fixed.bounds_with_d_tap(d)
    res = active_set_polish(fixed, lo, hi, None, None, "test")
    assert res is not None
    return fixed.objective(res.x) if res.ok else np.inf, res


def test_cuts_are_lower_bounds_on_every_candidates_q_part():
    """Weak duality: the dual function at any multipliers is below the optimum, for every tap change (affine)."""
    rng = np.random.default_rng(8)
    checked = infeasible_cuts = 0
    for _ in range(15):
        inputs = random_cvvc_inputs(rng)
        fixed = build_cvvc_qp(inputs, soft=False, fixed_d_tap=np.zeros(inputs.n_reg))
        lo_steps, hi_steps = tap_bounds(inputs)
        points, _, _ = tap_lattice(lo_steps, hi_steps, 200)
        values = [_q_part(fixed, d)[0] for d in points]
        for d in points[rng.choice(points.shape[0], 6, replace=False)]:
            value, res = _q_part(fixed, d)
            if res.ok:
                cut = cut_at(fixed, res.y, d, scale_to_best=False)
                assert cut is not None
                assert cut.const + cut.slope @ d == pytest.approx(value, rel=1e-6, abs=1e-9)  # tight where solved
            else:
                y = phase_one_multipliers(fixed, d)
                assert y is not None
                cut = cut_at(fixed, y, d, scale_to_best=True)
                if cut is None:
                    continue
                infeasible_cuts += 1
            for other, v in zip(points, values, strict=True):
                assert cut.const + cut.slope @ other <= v + 1e-7 * max(1.0, abs(cut.const))
            checked += 1
    assert checked >= 40 and infeasible_cuts >= 3


def _slab(dv_dtap, v_min, v_max, cost_per_tap=(1.0, 1.0), max_taps=(4, 4)) -> CvvcInputs:
    """One node, two regulators, a plant that cannot help: the node must land in a thin band."""
    return CvvcInputs(
        v0_pu=np.array([1.0]),
        dv_dq_pu_per_kvar=np.array([[0.0]]),
        dv_dtap_pu=np.array([dv_dtap]),
        q0_kvar=np.array([0.0]),
        q_min_kvar=np.array([0.0]),
        q_max_kvar=np.array([0.0]),
        q_rating_kvar=np.array([1000.0]),
        taps=np.array([0, 0]),
        tap_min=np.array([-16, -16]),
        tap_max=np.array([16, 16]),
        max_taps_per_interval=np.array(max_taps),
        cost_per_tap=np.array(cost_per_tap),
        cost_per_kvar=np.array([1e-4]),
        v_min_pu=v_min,
        v_max_pu=v_max,
    )


@pytest.mark.parametrize(
    ("inputs", "taps"),
    [
        # +0.019-0.022 pu: the relaxation moves regulator 1 by 19/30 of a step, and neither rounding (0 or 1) meets
        # the limits; regulator 2 one step down does (and 2 up with 2 down, at twice the cost)
        (_slab([0.03, -0.02], 1.019, 1.022), [0, -1]),
        # +0.038-0.041 pu: the relaxation's 1.27 steps of regulator 1 round to 0.03 or 0.06; regulator 2 two down
        (_slab([0.03, -0.02], 1.038, 1.041), [0, -2]),
        # the cheap regulator's steps (0.011 pu) miss the band around 0.03: one step of the dear one
        (_slab([0.03, 0.011], 1.0295, 1.0305, cost_per_tap=(1.0, 0.1)), [1, 0]),
    ],
)
def test_integer_taps_beyond_one_tap_of_the_relaxation_are_the_exact_optimum_without_the_milp(inputs, taps):
    sol = solve_cvvc(inputs)
    assert sol.relaxed_form == "hard" and sol.candidates_tried > 0  # the rounding re-solved its candidates first
    assert sol.status == "optimal", sol.reason
    assert sol.milp_solves == 0 and sol.lattice_tried > 0
    ref = solve_milp_reference(inputs)
    assert sol.taps_new.tolist() == taps == ref.taps_new.tolist()
    assert sol.cost == pytest.approx(ref.cost, abs=1e-9)
    assert sol.max_violation_pu <= V_TOL_PU
    assert solve_cvvc(inputs).taps_new.tolist() == sol.taps_new.tolist()  # deterministic


def test_no_integer_taps_at_all_is_proven_without_the_milp():
    """The band lies between the reachable steps (0.03 apart, band 0.001 wide): the lattice holds every point."""
    inputs = _slab([0.03, 0.03], 1.0445, 1.0455, max_taps=(1, 1))
    sol = solve_cvvc(inputs)
    assert sol.status == "soft" and "no rounding" in sol.reason
    assert sol.milp_solves == 0
    assert solve_milp_reference(inputs).status == "infeasible"


def test_feasibility_cuts_exclude_only_infeasible_points():
    """A point a Farkas certificate (taken at another, infeasible point) covers has no Q meeting the hard limits."""
    rng = np.random.default_rng(13)
    cuts = excluded = 0
    for _ in range(15):
        inputs = random_cvvc_inputs(rng)
        fixed = build_cvvc_qp(inputs, soft=False, fixed_d_tap=np.zeros(inputs.n_reg))
        points, _, _ = tap_lattice(*tap_bounds(inputs), 200)
        feasible = np.array([np.isfinite(_q_part(fixed, d)[0]) for d in points])
        for i in np.flatnonzero(~feasible)[:4]:
            cut = feasibility_cut(fixed, points[i])
            if cut is None:
                continue
            cuts += 1
            covered = cut.const + points @ cut.slope > 0.0
            assert covered[i] and not np.any(covered & feasible)
            excluded += int(covered.sum())
    assert cuts >= 5 and excluded > cuts  # each covers more than its own point
