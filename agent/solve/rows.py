"""Row generation for large problems, and the interval arithmetic of the presolve over voltage rows."""

from __future__ import annotations

import dataclasses

import numpy as np

from agent.cvvc_qp import CvvcInputs, CvvcQp, build_cvvc_qp
from agent.solve.relaxation import solve_qp
from agent.solve.settings import ROWGEN_ADD, ROWGEN_MIN_NODES, ROWGEN_START, ROWGEN_TOL_PU
from agent.solve.solution import Run, WarmStart, violation_pu

__all__ = ["outside_violations", "remap", "row_ranges", "solve_rows", "start_nodes", "unreachable_rows",
           "zero_is_feasible"]


def remap(src: CvvcQp, x: np.ndarray, y: np.ndarray, dst: CvvcQp) -> tuple[np.ndarray, np.ndarray | None]:
    """Carry a solution of ``src`` over to ``dst`` as a warm start: same variables and rows by node.

    Taps (when both have them) and Q by position, violation variables and voltage-row multipliers by node,
    zeros for what ``src`` lacks. The multipliers are ``None`` when ``y`` does not fit ``src``.
    """
    s_lay, d_lay = src.layout, dst.layout
    x0 = np.zeros(d_lay.n)
    both_taps = s_lay.tap_up is not None and d_lay.tap_up is not None
    if both_taps:
        x0[d_lay.tap_up] = x[s_lay.tap_up]
        x0[d_lay.tap_down] = x[s_lay.tap_down]
    x0[d_lay.q_inj] = x[s_lay.q_inj]
    x0[d_lay.q_abs] = x[s_lay.q_abs]
    if s_lay.vio is not None and d_lay.vio is not None:
        found, where = _positions(src.nodes[src.soft_rows], dst.nodes[dst.soft_rows])
        x0[d_lay.vio][found] = x[s_lay.vio][where]
    if y.shape != (src.n_rows,):
        return x0, None
    y0 = np.zeros(dst.n_rows)
    n_src, n_dst = src.nodes.size, dst.nodes.size
    found, where = _positions(src.nodes, dst.nodes)
    y0[:n_dst][found] = y[:n_src][where]
    tap_src = 0 if s_lay.tap_up is None else 2 * (s_lay.tap_up.stop - s_lay.tap_up.start)
    tap_dst = 0 if d_lay.tap_up is None else 2 * (d_lay.tap_up.stop - d_lay.tap_up.start)
    if both_taps:
        y0[n_dst : n_dst + tap_dst] = y[n_src : n_src + tap_src]
    y0[n_dst + tap_dst :] = y[n_src + tap_src :]  # the Q bound rows
    return x0, y0


def _positions(src_ids: np.ndarray, dst_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For sorted ids: which ``dst_ids`` occur in ``src_ids`` (mask) and where (indices of those found)."""
    pos = np.searchsorted(src_ids, dst_ids)
    inside = pos < src_ids.size
    found = np.zeros(dst_ids.size, bool)
    found[inside] = src_ids[pos[inside]] == dst_ids[inside]
    return found, pos[found]


def outside_violations(inputs: CvvcInputs, qp: CvvcQp, d_tap: np.ndarray, q_kvar: np.ndarray) -> np.ndarray:
    """Nodes without a row in ``qp`` that the actions would take beyond the limits, worst first (capped)."""
    violation = violation_pu(inputs, inputs.predict_v_pu(d_tap, q_kvar))
    violation[qp.nodes] = 0.0
    worst = np.flatnonzero(violation > ROWGEN_TOL_PU)
    return np.sort(worst[np.argsort(-violation[worst], kind="stable")][:ROWGEN_ADD])


def solve_rows(
    inputs: CvvcInputs,
    soft: np.ndarray,
    fixed_d_tap: np.ndarray | None,
    nodes: np.ndarray | None,
    source: tuple[CvvcQp, np.ndarray, np.ndarray] | None,
    prebuilt: CvvcQp | None = None,
) -> tuple[Run, CvvcQp]:
    """Solve with voltage rows for ``nodes`` only (None: all), adding the rows of violated nodes until none.

    A problem with fewer rows is a relaxation, so a solution that violates no other node's limit is optimal
    for the full problem (row generation). Rows only grow, so this ends, at the latest with every node.
    ``source`` is a solved problem to warm-start from.
    """
    iterations = 0
    while True:
        if prebuilt is not None and nodes is None and fixed_d_tap is None and not soft.any():
            qp, prebuilt = prebuilt, None  # the full hard problem the presolve already built
        else:
            qp = build_cvvc_qp(inputs, soft=soft, fixed_d_tap=fixed_d_tap, nodes=nodes)
        x0, y0 = remap(*source, qp) if source is not None else (None, None)
        run = solve_qp(qp, x0, y0)
        iterations += run.iterations
        if not run.ok or qp.nodes.size == inputs.n_nodes:
            break
        outside = outside_violations(inputs, qp, qp.d_tap(run.x), qp.q_kvar(run.x))
        if outside.size == 0:
            break
        nodes = np.union1d(qp.nodes, outside)
        source = (qp, run.x, run.y)
    return dataclasses.replace(run, iterations=iterations), qp


def start_nodes(inputs: CvvcInputs, soft: np.ndarray, warm: WarmStart | None) -> np.ndarray | None:
    """The first rows of a large problem, or ``None`` (every node) for problems of the paper's size.

    The nodes closest to (or beyond) a limit, the soft ones, and the rows the previous interval ended with.
    """
    if inputs.n_nodes <= ROWGEN_MIN_NODES:
        return None
    margin = np.minimum(inputs.v0_pu - inputs.v_min_pu, inputs.v_max_pu - inputs.v0_pu)
    start = np.argsort(margin, kind="stable")[:ROWGEN_START]
    start = np.union1d(start, np.flatnonzero(soft))
    previous = None if warm is None else warm.problem
    if previous is not None and previous.soft_nodes.size == inputs.n_nodes:
        start = np.union1d(start, previous.nodes)
    return start


def row_ranges(qp: CvvcQp) -> tuple[np.ndarray, np.ndarray]:
    """Lowest and highest value each voltage row can take over the variable box (bound rows)."""
    rows = qp.voltage_rows
    nb = qp.n_rows - rows.stop  # one identity bound row per tap/Q variable, in variable order
    dense = qp.a_dense[rows, :nb] if qp.a_dense is not None else qp.A[: rows.stop, :nb].toarray()
    lb, ub = qp.lower[rows.stop :], qp.upper[rows.stop :]
    return np.minimum(dense * lb, dense * ub).sum(axis=1), np.maximum(dense * lb, dense * ub).sum(axis=1)


def unreachable_rows(qp: CvvcQp) -> np.ndarray:
    """Voltage rows that no point of the variable box can satisfy: the hard form is infeasible for sure.

    Interval arithmetic over the bound rows (a sufficient test, exact for one node out of resources).
    """
    lo, hi = row_ranges(qp)
    rows = qp.voltage_rows
    return np.flatnonzero((hi < qp.lower[rows] - 1e-9) | (lo > qp.upper[rows] + 1e-9))


def zero_is_feasible(qp: CvvcQp) -> bool:
    """No action at all (taps kept, every Q set point 0) meets every constraint: it is then optimal."""
    return bool(np.all(qp.lower <= 0.0) and np.all(qp.upper >= 0.0))
