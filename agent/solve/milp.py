"""The exact reference: eq. (9)-(15) with integer taps and hard limits by ``scipy.optimize.milp`` (HiGHS)."""

from __future__ import annotations

import numpy as np
import scipy.optimize
import scipy.sparse as sp

from agent.cvvc_qp import CvvcInputs, build_cvvc_qp
from agent.solve.solution import MilpReference

__all__ = ["solve_milp_reference"]


def solve_milp_reference(inputs: CvvcInputs) -> MilpReference:
    """Exact optimum of eq. (9)-(15) with integer taps and hard limits, for tests and benchmarks.

    Same scaled constraints as the relaxation, no proximal term, ``scipy.optimize.milp`` (HiGHS).
    """
    qp = build_cvvc_qp(inputs, soft=False)
    lay = qp.layout
    integrality = np.zeros(lay.n)
    integrality[: 2 * inputs.n_reg] = 1
    lo = np.where(np.isfinite(qp.lower), qp.lower, -np.inf)
    hi = np.where(np.isfinite(qp.upper), qp.upper, np.inf)
    res = scipy.optimize.milp(
        qp.c,
        integrality=integrality,
        bounds=scipy.optimize.Bounds(-np.inf, np.inf),
        constraints=scipy.optimize.LinearConstraint(sp.csr_matrix(qp.A), lo, hi),
        options={"mip_rel_gap": 1e-9},
    )
    if res.status == 2:
        return MilpReference(
            status="infeasible", taps_new=inputs.taps.copy(), q_new_kvar=inputs.q0_kvar.copy(), cost=float("inf")
        )
    if res.x is None or res.status != 0:
        return MilpReference(
            status="failed", taps_new=inputs.taps.copy(), q_new_kvar=inputs.q0_kvar.copy(), cost=float("inf")
        )
    d = np.round(qp.d_tap(res.x))
    q = qp.q_kvar(res.x)
    return MilpReference(
        status="optimal", taps_new=(inputs.taps + d.astype(int)).astype(int), q_new_kvar=q, cost=inputs.cost(d, q)
    )
