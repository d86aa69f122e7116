"""The CVVC solve, in qpsolvers' shape: one entry point, one module per job.

- ``cvvc``: ``solve_cvvc``, the stages in order (presolve, relaxation, rounding);
- ``relaxation``: OSQP set-up and ADMM in chunks; ``polish``: the exact active-set polish with its KKT check;
- ``active_set``: the dense dual active-set QP solve (DAQP, in C) the polish, Q re-solves and robust check use;
- ``rows``: row generation and the presolve's interval arithmetic; ``rounding``: taps to integers, Q re-solved;
- ``lattice``: the rounding's search of integer taps near "no move", with Lagrangian cuts, before its MILP;
- ``milp``: the exact MILP reference (tests, benchmarks) and the rounding's MILP fallback (``highspy``);
  ``solution``: the typed results and ``WarmStart``;
- ``settings``: every fixed limit and OSQP setting.
"""

from agent.solve.cvvc import solve_cvvc
from agent.solve.milp import solve_milp_reference
from agent.solve.settings import MAX_ENUMERATED_FRACTIONAL, OSQP_SETTINGS, V_TOL_PU
from agent.solve.solution import CvvcSolution, MilpReference, StageSeconds, WarmStart

__all__ = [
    "MAX_ENUMERATED_FRACTIONAL",
    "OSQP_SETTINGS",
    "V_TOL_PU",
    "CvvcSolution",
    "MilpReference",
    "StageSeconds",
    "WarmStart",
    "solve_cvvc",
    "solve_milp_reference",
]
