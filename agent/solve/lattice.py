"""Integer taps near "no move" with Lagrangian bounds: the rounding's search before its MILP (beyond the paper).

When no rounding of the relaxed taps meets the hard limits, the rounding (``agent.solve.rounding``) searches the
integer tap changes within ``k`` steps in all of no move (``tap_lattice``). With the taps fixed, the rest of the
score (Q's cost and proximal terms, the Q re-solve) is a QP whose Lagrangian dual function, at any multipliers
``y`` of its rows, is a lower bound (weak duality) and is *affine in the taps*: the taps only shift the voltage rows'
bounds. So every solved candidate gives a bound on every other one (``LagrangianCut``, a Benders cut): its optimal
multipliers where it is feasible, the multipliers of a least-violation problem (``phase_one_multipliers``) where it
is not, scaled to the best bound at that candidate (``cut_at``). An infeasible candidate's Farkas certificate (from its
least-violation problem) is affine in the taps too (``feasibility_cut``): every point it covers is infeasible and is
never re-solved. Candidates are solved cheapest bound first; the
search stops when the best score found is at most every remaining bound, and it is *optimal over all integer
taps* when it is also at most the bound of every point further away (``region_bound``: at least ``k + 1`` steps in
all, the tap cost and any cut over that region, in closed form). Without that proof the MILP decides.

Pure functions of arrays and the tap-fixed ``CvvcQp``; the rounding owns the Q re-solves.
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass

import numpy as np

from agent.cvvc_qp import CvvcInputs, CvvcQp
from agent.solve.polish import farkas_excess, least_violation, least_violation_multipliers
from agent.solve.settings import FARKAS_MIN_EXCESS

__all__ = ["FeasibilityCut", "LagrangianCut", "cut_at", "feasibility_cut", "phase_one_multipliers", "region_bound",
           "tap_bounds", "tap_lattice"]

#: Largest scale of a least-violation problem's multipliers in a cut (a near-certificate of infeasibility has
#: almost no curvature: the best scale could be huge and the cut numerically meaningless).
_MAX_SCALE = 1e8


@dataclass(frozen=True)
class LagrangianCut:
    """A lower bound on the Q part of the score for every integer tap change ``d``: ``const + slope @ d``
    [cost units] (the dual function of a tap-fixed problem at fixed multipliers, affine in the taps).
    """

    const: float
    slope: np.ndarray  # (R,) [cost units/step]


@dataclass(frozen=True)
class FeasibilityCut:
    """Integer tap changes ``d`` with ``const + slope @ d > 0`` have no Q meeting the hard limits (a Farkas
    certificate of the tap-fixed problem, affine in the taps) [% of voltage].
    """

    const: float
    slope: np.ndarray  # (R,) [%/step]


def feasibility_cut(fixed: CvvcQp, d_tap: np.ndarray) -> FeasibilityCut | None:
    """A Farkas certificate of the tap-fixed ``fixed`` at ``d_tap`` as a cut in the taps, or None when it proves
    nothing there (``d_tap`` feasible, or infeasible by too little).

    The multipliers ``y`` of the least-violation problem at ``d_tap`` (``least_violation_multipliers``), their
    ``farkas_excess``: the least of ``(A'y)'x`` over the variables' box less ``hi(d)'y+ + lo(d)'y-``. The voltage
    rows' bounds shift by ``-dv_dtap_pct @ d``, so the excess is affine in ``d`` with slope ``y_rows @ dv_dtap_pct``;
    less ``FARKAS_MIN_EXCESS`` per unit of ``|y|`` on the rows with more than one entry (what
    ``agent.solve.polish.proven_infeasible`` asks too).
    """
    a = fixed.a_dense
    if a is None or fixed.fixed_d_tap is None:
        return None
    lo, hi = fixed.bounds_with_d_tap(d_tap)
    y = least_violation_multipliers(a, lo, hi)
    if y is None:
        return None
    rows = np.count_nonzero(a, axis=1) > 1
    excess = farkas_excess(a, lo, hi, y) - FARKAS_MIN_EXCESS * float(np.sum(np.abs(y[rows])))
    if not excess > 0.0:
        return None
    slope = y[fixed.voltage_rows] @ fixed.dv_dtap_pct
    return FeasibilityCut(const=excess - float(slope @ d_tap), slope=slope)


def tap_bounds(inputs: CvvcInputs) -> tuple[np.ndarray, np.ndarray]:
    """(R,) lowest and highest integer tap change of each device [steps]: eq. (11)-(12), room clipped at 0."""
    max_t = inputs.max_taps_per_interval
    room_up = np.maximum(inputs.tap_max - inputs.taps, 0)
    room_down = np.maximum(inputs.taps - inputs.tap_min, 0)
    return -np.minimum(max_t, room_down).astype(int), np.minimum(max_t, room_up).astype(int)


def tap_lattice(lo_steps: np.ndarray, hi_steps: np.ndarray, max_points: int) -> tuple[np.ndarray, int, bool]:
    """``(points, k, complete)``: every integer tap change within the bounds and at most ``k`` steps in all,
    ``(M, R)`` float [steps], by steps in all then lexicographically; ``k`` the largest with at most ``max_points``
    points (at least 0); ``complete`` when no integer point within the bounds is left out.
    """
    movable = np.flatnonzero(hi_steps > lo_steps)
    r = lo_steps.size
    most = int(np.sum(np.maximum(-lo_steps, hi_steps)))
    points = [np.zeros((1, r))]
    count, k = 1, 0
    while k < most:
        ring = _ring(movable.size, k + 1)
        full = np.zeros((ring.shape[0], r))
        full[:, movable] = ring
        full = full[np.all((full >= lo_steps) & (full <= hi_steps), axis=1)]
        if count + full.shape[0] > max_points:
            break
        points.append(full)
        count += full.shape[0]
        k += 1
    return np.vstack(points), k, k >= most


@functools.lru_cache(maxsize=16)
def _ring(n: int, k: int) -> np.ndarray:
    """Every integer vector of length ``n`` with ``k`` steps in all (sum of magnitudes), lexicographically."""
    out = []
    for size in range(1, min(n, k) + 1):
        for support in itertools.combinations(range(n), size):
            for parts in _compositions(k, size):
                for signs in itertools.product((-1, 1), repeat=size):
                    v = [0] * n
                    for i, part, sign in zip(support, parts, signs, strict=True):
                        v[i] = sign * part
                    out.append(v)
    ring = np.array(sorted(out), float).reshape(-1, n)
    ring.flags.writeable = False
    return ring


def _compositions(k: int, size: int) -> list[tuple[int, ...]]:
    """Ways of writing ``k`` as an ordered sum of ``size`` positive integers."""
    if size == 1:
        return [(k,)]
    return [(first, *rest) for first in range(1, k - size + 2) for rest in _compositions(k - first, size - 1)]


def _support(y: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
    """``max_{lo <= z <= hi} y'z`` (inf when a multiplier leans on a missing bound)."""
    up, down = y > 0.0, y < 0.0
    if np.any(np.isinf(hi[up])) or np.any(np.isinf(lo[down])):
        return np.inf
    return float(np.sum(y[up] * hi[up]) + np.sum(y[down] * lo[down]))


def cut_at(fixed: CvvcQp, y: np.ndarray, d_tap: np.ndarray, *, scale_to_best: bool) -> LagrangianCut | None:
    """The dual function of the tap-fixed ``fixed`` at multipliers ``t y``, as an affine bound in the taps.

    ``g(t y, d) = min_x x'Px/2 + c'x + t y'(A x) - t max_{lo(d) <= z <= hi(d)} y'z``, times ``cost_scale``; the
    voltage rows' bounds shift by ``-dv_dtap_pct @ (d - fixed_d_tap)``, so ``g`` is affine in ``d``. ``t = 1``,
    or with ``scale_to_best`` the ``t >= 0`` that maximises ``g`` at ``d_tap`` (closed form: ``g`` is a concave
    quadratic in ``t``). ``None`` when the bound is useless there (``t = 0`` or a missing bound).
    """
    if fixed.a_dense is None or fixed.fixed_d_tap is None or y.shape != fixed.lower.shape:
        return None
    lo, hi = fixed.bounds_with_d_tap(d_tap)
    sigma = _support(y, lo, hi)
    if not np.isfinite(sigma):
        return None
    u = fixed.a_dense.T @ y
    t = 1.0
    if scale_to_best:
        curvature = float(np.sum(u * u / fixed.p_diag))
        slope_t = -float(np.sum(fixed.c * u / fixed.p_diag)) - sigma
        if curvature <= 0.0 or slope_t <= 0.0:
            return None
        t = min(slope_t / curvature, _MAX_SCALE)
    grad = fixed.c + t * u
    g_at = -0.5 * float(np.sum(grad * grad / fixed.p_diag)) - t * sigma  # g(t y, d_tap) in scaled cost units
    rows = fixed.voltage_rows
    slope = t * (y[rows] @ fixed.dv_dtap_pct)  # d g / d d: each step shifts both bounds of every voltage row
    return LagrangianCut(const=fixed.cost_scale * (g_at - float(slope @ d_tap)), slope=fixed.cost_scale * slope)


def phase_one_multipliers(fixed: CvvcQp, d_tap: np.ndarray) -> np.ndarray | None:
    """Multipliers of ``fixed``'s rows from its least-violation problem at ``d_tap`` (for a cut), or None.

    One slack ``s >= 0`` widens every hard row's bounds; minimise ``x'Px/2 + c'x + s^2/2`` (``least_violation``,
    with ``fixed``'s own objective). The rows' multipliers are valid for the hard problem's dual function (any
    multipliers are); where the hard problem is infeasible, scaled by ``cut_at`` they give a large bound there and
    nearby.
    """
    if fixed.a_dense is None:
        return None
    lo, hi = fixed.bounds_with_d_tap(d_tap)
    out = least_violation(fixed.a_dense, lo, hi, ~np.asarray(fixed.soft_rows, bool), fixed.p_diag, fixed.c)
    return None if out is None else out[0]


def region_bound(cut: LagrangianCut | None, cost_per_tap: np.ndarray, lo_steps: np.ndarray, hi_steps: np.ndarray,
                 min_steps: int) -> float:
    """A lower bound on the score [cost units] of every integer tap change within the bounds and at least
    ``min_steps`` steps in all: its tap cost plus ``cut`` (or plus 0, the Q part's least value, without one).

    Each step up of device ``r`` adds ``cost_per_tap[r] + slope[r]``, each step down ``cost_per_tap[r] - slope[r]``;
    letting a device step both ways (a relaxation) the least sum with ``min_steps`` steps takes every negative
    step and then the cheapest others (the proximal term, >= 0, is left out).
    """
    slope = np.zeros(cost_per_tap.size) if cut is None else cut.slope
    const = 0.0 if cut is None else cut.const
    price = np.concatenate([cost_per_tap + slope, cost_per_tap - slope])
    count = np.concatenate([hi_steps, -lo_steps]).astype(float)
    order = np.argsort(price, kind="stable")
    price, count = price[order], count[order]
    total, steps = const, 0.0
    for p, c in zip(price, count, strict=True):
        if c <= 0.0:
            continue
        if p < 0.0:
            total += p * c
            steps += c
        elif steps < min_steps:
            take = min(c, min_steps - steps)
            total += p * take
            steps += take
    return total if steps >= min_steps else np.inf
