"""Fixed settings of the CVVC solve: OSQP, polish, rounding and row-generation limits.

Units of the scaled problem (``agent.cvvc_qp``): voltages in %, Q in fractions of rating, taps in steps.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

#: Fixed OSQP settings (units of the scaled problem: voltages in %, Q in fractions of rating, taps in steps).
#: Rho starts at 1 and adapts on a fixed iteration interval (never the time-based rule): ADMM's path depends
#: only on the data. OSQP's own polishing is replaced by ours after every chunk of ``max_iter`` iterations
#: (see ``_osqp_run``); no wall-clock limit.
#: ``eps_prim_inf`` is loose: proving a rounding candidate infeasible took up to 4000 iterations at 1e-6 and
#: about 10x fewer at 1e-3; a false "infeasible" could only cost optimality (a candidate skipped, or the
#: soft form), and none was seen on the benchmark problems.
OSQP_SETTINGS: Mapping[str, object] = MappingProxyType(
    {
        "verbose": False,
        "eps_abs": 1e-6,
        "eps_rel": 1e-6,
        "eps_prim_inf": 1e-3,
        "eps_dual_inf": 1e-6,
        "rho": 1.0,
        "adaptive_rho": 1,  # rho adapted every 50 iterations (iteration-based, hence deterministic)
        "adaptive_rho_interval": 50,
        "sigma": 1e-6,
        "alpha": 1.6,
        "max_iter": 25,  # first chunk; see FIRST_CHUNK_ITER
        "check_termination": 5,
        "polishing": False,
        "scaling": 10,
        "warm_starting": True,
    }
)
#: Problems too large for the dense active-set polish (soft form over many nodes): OSQP's own polishing,
#: tolerance 1e-4 in scaled units (1e-6 pu of voltage).
LARGE_OSQP_SETTINGS: Mapping[str, object] = MappingProxyType(
    {**OSQP_SETTINGS, "polishing": True, "eps_abs": 1e-4, "eps_rel": 1e-4}
)
#: Iteration budget of a rounding candidate's Q re-solve once a feasible candidate is known (before that,
#: ``MAX_ITER``); a candidate not solved within it is skipped: it could only have improved the cost.
MAX_ITER_RESOLVE = 400
#: ADMM iterations before the first polish attempt; each later chunk is twice as long.
FIRST_CHUNK_ITER = 25
#: Iteration budget of one solve (all chunks) [ADMM iterations].
MAX_ITER = 4000
#: OSQP tolerance accepted after half the iteration budget (scaled units: 1e-6 pu of voltage).
LOOSE_EPS = 1e-4
#: Tolerance of the KKT optimality check in scaled units (% of voltage, fraction of rating, steps).
KKT_TOL = 1e-6
#: A Farkas certificate of infeasibility counts only with an excess above this per unit of its multipliers (and a
#: least-violation problem only with a violation above it) [scaled units: % of voltage]: smaller ones prove nothing.
FARKAS_MIN_EXCESS = 1e-5
#: Up to this many fractional taps, every floor/ceil combination is tried (2**3 = 8 Q re-solves).
MAX_ENUMERATED_FRACTIONAL = 3
#: A relaxed tap change this close to an integer counts as integer [steps].
FRACTIONAL_TOL_STEPS = 1e-4
#: A relaxed tap change this close to an integer is taken as integral: its Q needs no re-solve [steps].
INTEGRAL_TOL_STEPS = 1e-6
#: HiGHS options of the MILP that looks for integer taps beyond one tap of the relaxation when no rounding meets the
#: hard limits (``agent.solve.milp.milp_tap_changes``): a node limit (never a time limit: same inputs, same taps), a
#: 0.1 % gap, and no presolve or primal heuristics (sub-MIPs, feasibility jump, RINS/RENS: most of HiGHS's time on
#: these small dense problems; docs/optimizer.md). One thread: HiGHS's thread pool cost 20 % more CPU on the 56
#: fallback problems of an IEEE 8500 day, and on a loaded machine its workers waited for cores (one root node took
#: 6.4 s of wall time for 0.87 s of CPU).
MILP_OPTIONS: Mapping[str, bool | float | str] = MappingProxyType(
    {
        "output_flag": False,
        "threads": 1,
        "mip_rel_gap": 1e-3,
        "mip_max_nodes": 500,
        "presolve": "off",
        "mip_heuristic_effort": 0.0,
        "mip_heuristic_run_feasibility_jump": False,
        "mip_heuristic_run_rins": False,
        "mip_heuristic_run_rens": False,
        "mip_heuristic_run_root_reduced_cost": False,
        "mip_heuristic_run_zi_round": False,
        "mip_heuristic_run_shifting": False,
    }
)
#: When no rounding meets the hard limits: the integer tap changes within k steps in all of no move are searched
#: before the MILP (``agent.solve.lattice``), k the largest with at most this many points (12 regulators: k = 3,
#: 2,625 points).
LATTICE_MAX_POINTS = 3000
#: At most this many of them are re-solved; a search that has not proven its best optimal by then goes to the MILP.
LATTICE_MAX_SOLVES = 40
#: Stop trying rounding candidates once one scores within this fraction of the relaxed objective.
ROUNDING_GAP_REL = 0.01
#: Row generation for large problems (every node of a big feeder): problems up to ROWGEN_MIN_NODES critical
#: nodes get every row at once; larger ones start with the ROWGEN_START nodes closest to a limit and add
#: up to ROWGEN_ADD violated nodes (beyond ROWGEN_TOL_PU) per round.
ROWGEN_MIN_NODES = 100
ROWGEN_START = 50
ROWGEN_ADD = 100
ROWGEN_TOL_PU = 1e-7
#: Q set points are rounded to this many decimals of a kvar.
Q_DECIMALS = 3
#: Voltage-limit tolerance when checking a solution against the linear model [pu].
V_TOL_PU = 1e-5
