"""The CVVC optimization problem, paper eq. (9)-(17), built as a scaled QP (pure code, no solver call).

Decision variables (paper section III), in this order:

- ``dT+_r, dT-_r`` (R each): tap steps up and down per single-phase regulator [steps];
- ``Q+_k, Q-_k`` (K each): reactive power injected and absorbed by each plant, as a fraction of the plant's
  rating ``q_rating_kvar`` (so 1.0 = rating);
- soft form only: ``w_i``: signed voltage violation of each soft critical node (all nodes, or only those
  no action can bring within the limits) [% of its base voltage].

Constraints (``lower <= A x <= upper``, one block each):

- eq. (13)/(16)-(17), voltage [%]: ``v0 + sum_k (Q+_k - Q-_k - Q0_k) dQ_ik + sum_r (dT+_r - dT-_r) dVR_ir``
  within the optimization limits; the soft form subtracts ``w_i`` (one row per node: ``w_i`` is free and
  its square is penalised, so ``|w_i|`` is exactly the paper's ``V_i^vio`` of the violated side);
- eq. (11)-(12) as variable bounds: ``0 <= dT+ <= min(max_taps, tap_max - T)``,
  ``0 <= dT- <= min(max_taps, T - tap_min)`` (room clipped at 0, so a tap outside its limits is never forced
  to move). The net change ``dT+ - dT-`` then always meets eq. (11) and ``|dT| <= max_taps`` (eq. 12 for the
  net change; with positive costs and the proximal term, the optimum never has both parts non-zero);
- eq. (10) as variable bounds: ``max(q_min, 0) <= Q+ <= max(q_max, 0)``, ``max(-q_max, 0) <= Q- <= max(-q_min,
  0)`` (a fraction of the rating), which gives ``q_min <= Q+ - Q- <= q_max`` in every case.

Dropping the paper's separate rows (10)-(12) removes redundant, degenerate constraints that slow ADMM down.

Objective: eq. (9) with eq. (14)-(15), ``sum_r c_r (dT+ + dT-) + sum_k c_k (Q+ + Q-)`` [cost units, ``c_k`` per
kvar of the new set point], divided by the largest cost coefficient so it is O(1). The soft form is eq.
(17): ``alpha * cost + beta * sum_i V_vio_i^2`` with ``beta`` in cost units per pu^2.

Deviations from the paper, for the solver's sake (see docs/optimizer.md):

- scaling: voltages in %, Q in fractions of the rating, cost normalised; every coefficient is then O(0.1..10);
- a proximal term ``(PROX_WEIGHT / 2) * ||x_taps, x_q||^2`` on the scaled tap and Q variables makes the QP
  strongly convex: OSQP (ADMM) converges much faster on it than on the pure LP, and ties between equally
  cheap actions are broken towards the smallest actions, deterministically. It only adds pressure in the
  direction the (non-negative) costs already push; the MILP reference measures the cost it adds.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
from dataclasses import dataclass
from typing import Any

import numpy as np
import qpsolvers
import scipy.sparse as sp

from agent.dense_split import DenseSplit, dense_split
from agent.errors import AgentInputError

__all__ = [
    "DEFAULT_SOFT_ALPHA",
    "DEFAULT_SOFT_BETA_PER_PU2",
    "PROX_WEIGHT",
    "CvvcInputs",
    "CvvcQp",
    "VariableLayout",
    "build_cvvc_qp",
]

#: Weight of the proximal term on the scaled tap and Q variables (normalised cost units per unit^2).
PROX_WEIGHT = 1e-2
#: Eq. (17)'s alpha: weight of the action cost in the soft form.
DEFAULT_SOFT_ALPHA = 1.0
#: Eq. (17)'s beta [cost units per pu^2]: a 0.001 pu violation at one node weighs as 1 cost unit (about 7 taps
#: at 0.14 per tap), so the soft form spends actions freely to shrink violations.
DEFAULT_SOFT_BETA_PER_PU2 = 1e6

_PCT_PER_PU = 100.0
#: Largest problem kept as a dense matrix as well, for the active-set polish (whose cost grows with the
#: number of variables times the square of the active rows): variables, and rows x variables (16 MB).
DENSE_MAX_VARS = 400
DENSE_LIMIT = 2_000_000


def _vec(name: str, value, n: int, dtype=float) -> np.ndarray:
    # (array methods, not np.all / np.any: a problem is built several times a decision, this is on its hot path)
    if dtype is int and isinstance(value, np.ndarray) and value.dtype.kind in "iu":
        a = value.astype(int)  # integers already (the controller's taps): a copy, nothing to check but the shape
        if a.shape != (n,):
            raise AgentInputError(f"CvvcInputs.{name} has shape {a.shape}, expected ({n},)")
        a.flags.writeable = False
        return a
    a = np.array(value, dtype=float)
    if a.shape != (n,):
        raise AgentInputError(f"CvvcInputs.{name} has shape {a.shape}, expected ({n},)")
    if not np.isfinite(a).all():
        raise AgentInputError(f"CvvcInputs.{name} is not finite: reject the measurement that produced it")
    if dtype is int:
        if not (a == np.round(a)).all():
            raise AgentInputError(f"CvvcInputs.{name} must hold integers, got {a}")
        a = a.astype(int)
    a.flags.writeable = False
    return a


def _mat(name: str, value, shape: tuple[int, int]) -> np.ndarray:
    a = np.array(value, dtype=float).reshape(shape) if np.size(value) == shape[0] * shape[1] else None
    if a is None:
        raise AgentInputError(f"CvvcInputs.{name} has {np.size(value)} entries, expected shape {shape}")
    if not np.isfinite(a).all():
        raise AgentInputError(f"CvvcInputs.{name} is not finite: check the model's sensitivity fits")
    a.flags.writeable = False
    return a


def _converted(name: str, value: Any, n: int, k: int, r: int) -> Any:
    """``CvvcInputs``' field ``name`` as stored: a checked read-only array of its shape (``n`` nodes, ``k`` plants,
    ``r`` regulators), a float, or None (``soft_weight`` only). Raises ``AgentInputError``.
    """
    if name == "dv_dq_pu_per_kvar":
        return _mat(name, value, (n, k))
    if name == "dv_dtap_pu":
        return _mat(name, value, (n, r))
    if name in ("q0_kvar", "q_min_kvar", "q_max_kvar", "q_rating_kvar", "cost_per_kvar"):
        return _vec(name, value, k)
    if name in ("taps", "tap_min", "tap_max", "max_taps_per_interval"):
        return _vec(name, value, r, int)
    if name == "cost_per_tap":
        return _vec(name, value, r)
    if name in ("v0_pu", "v_min_pu", "v_max_pu"):
        if name != "v0_pu" and np.shape(value) != (n,):  # one limit for every node (or any shape that broadcasts)
            value = np.broadcast_to(np.asarray(value, float), (n,))
        return _vec(name, value, n)
    if name == "soft_weight":
        if value is None:
            return None
        weight = _vec(name, value, n)
        if not ((weight > 0.0) & (weight <= 1.0)).all():
            raise AgentInputError("CvvcInputs.soft_weight must be within (0, 1] at every node")
        return weight
    scalar = float(value)  # soft_alpha, soft_beta_per_pu2, dv_dq_rel_error
    if not np.isfinite(scalar):
        raise AgentInputError(f"CvvcInputs.{name} is not finite")
    return scalar


@dataclass(frozen=True)
class CvvcInputs:
    """Everything one CVVC solve needs. Arrays are copied, checked and made read-only on construction.

    Attributes
    ----------
    v0_pu : (N,) estimated critical-node voltages now [pu].
    dv_dq_pu_per_kvar : (N, K) sensitivity to each plant's Q, eq. (3) [pu/kvar].
    dv_dtap_pu : (N, R) sensitivity to each regulator's tap, eq. (4) [pu/step].
    q0_kvar : (K,) present Q set point of each plant [kvar], generator convention.
    q_min_kvar, q_max_kvar : (K,) limits of the new Q set point, eq. (10) [kvar]; equal to fix a plant.
    q_rating_kvar : (K,) plant rating used to scale Q [kvar] (its kVA), > 0.
    taps : (R,) present tap positions [steps].
    tap_min, tap_max : (R,) tap limits, eq. (11) [steps].
    max_taps_per_interval : (R,) eq. (12) [steps]; 0 freezes a regulator.
    cost_per_tap : (R,) eq. (14) [cost units/step], >= 0.
    cost_per_kvar : (K,) eq. (15) [cost units/kvar], >= 0.
    v_min_pu, v_max_pu : optimization voltage limits, eq. (13) [pu]: one for every node, or (N,) per node
        (stored as (N,) arrays).
    soft_alpha : eq. (17)'s alpha (weight of the action cost) [-].
    soft_beta_per_pu2 : eq. (17)'s beta [cost units/pu^2].
    dv_dq_rel_error : beyond the paper, soft form only: relative error of the Q sensitivities [-] (0: the paper's
        eq. 17). Each node with a violation variable adds the expected square of its voltage error under the
        plants' Q, ``beta * sum_k (err * dv/dq_ik * Q_k)^2``: plants then no longer pull against each other
        on sensitivity differences a regression cannot resolve (a diagonal term in the Q variables).
    soft_weight : beyond the paper: (N,) weight of each node's squared violation in eq. (17), in (0, 1]; None: 1
        at every node (the paper's).
    """

    v0_pu: np.ndarray
    dv_dq_pu_per_kvar: np.ndarray
    dv_dtap_pu: np.ndarray
    q0_kvar: np.ndarray
    q_min_kvar: np.ndarray
    q_max_kvar: np.ndarray
    q_rating_kvar: np.ndarray
    taps: np.ndarray
    tap_min: np.ndarray
    tap_max: np.ndarray
    max_taps_per_interval: np.ndarray
    cost_per_tap: np.ndarray
    cost_per_kvar: np.ndarray
    v_min_pu: np.ndarray | float
    v_max_pu: np.ndarray | float
    soft_alpha: float = DEFAULT_SOFT_ALPHA
    soft_beta_per_pu2: float = DEFAULT_SOFT_BETA_PER_PU2
    dv_dq_rel_error: float = 0.0
    soft_weight: np.ndarray | None = None

    def __post_init__(self) -> None:
        self._check(_INPUT_FIELDS)
        object.__setattr__(self, "_feasible_set_memo", {})

    def replaced(self, **changes: Any) -> CvvcInputs:
        """A copy with ``changes`` (as ``dataclasses.replace``): only the changed fields are converted and checked
        again, with every relation between fields; the others are this object's checked read-only arrays.

        A problem is re-made several times a decision (the regulators' tap ranges for the locks, the deadband's
        limits, the tap offer's costs); checking its every array again each time was most of that.
        """
        unknown = set(changes) - set(_INPUT_FIELDS)
        if unknown:
            raise TypeError(f"CvvcInputs has no field {', '.join(sorted(unknown))}")
        new = copy.copy(self)
        for name, value in changes.items():
            object.__setattr__(new, name, value)
        new._check(tuple(name for name in _INPUT_FIELDS if name in changes))
        if not set(changes) <= _PRICE_FIELDS:
            object.__setattr__(new, "_feasible_set_memo", {})
        return new

    @property
    def feasible_set_memo(self) -> dict[Any, Any]:
        """Results the solver derives from the feasible set alone (the limits, the sensitivities, the device ranges
        and ``dv_dq_rel_error``), not from the prices (the costs and the soft form's weights): a copy ``replaced``
        makes with new prices only shares them (the tap offer's problem is the decision's with the taps free).
        """
        memo: dict[Any, Any] = self.__dict__["_feasible_set_memo"]
        return memo

    def _check(self, names: tuple[str, ...]) -> None:
        """Convert and check the fields ``names`` (copies, read-only), then every relation between the fields."""
        n, k, r = np.size(self.v0_pu), np.size(self.q0_kvar), np.size(self.taps)
        for name in names:
            object.__setattr__(self, name, _converted(name, getattr(self, name), n, k, r))
        if (self.q_min_kvar > self.q_max_kvar).any():
            raise AgentInputError("CvvcInputs.q_min_kvar exceeds q_max_kvar for some plant; pass q_min <= q_max")
        if (self.q_rating_kvar <= 0).any():
            raise AgentInputError("CvvcInputs.q_rating_kvar must be positive (the plant's kVA rating)")
        if (self.tap_min > self.tap_max).any() or (self.max_taps_per_interval < 0).any():
            raise AgentInputError("tap limits must satisfy tap_min <= tap_max and max_taps_per_interval >= 0")
        if (self.cost_per_tap < 0).any() or (self.cost_per_kvar < 0).any():
            raise AgentInputError("costs must be non-negative")
        if not np.asarray(self.v_min_pu < self.v_max_pu).all():
            raise AgentInputError("v_min_pu must be below v_max_pu at every node")
        if self.soft_alpha < 0 or self.soft_beta_per_pu2 <= 0:
            raise AgentInputError("soft_alpha must be >= 0 and soft_beta_per_pu2 > 0")
        if not 0.0 <= self.dv_dq_rel_error <= 1.0:
            raise AgentInputError(f"CvvcInputs.dv_dq_rel_error must be within 0 to 1, not {self.dv_dq_rel_error}")

    @property
    def n_nodes(self) -> int:
        """Number of constrained nodes N."""
        return int(self.v0_pu.shape[0])

    @property
    def n_pv(self) -> int:
        """Number of PV plants K."""
        return int(self.q0_kvar.shape[0])

    @property
    def n_reg(self) -> int:
        """Number of regulators R."""
        return int(self.taps.shape[0])

    def predict_v_pu(self, d_tap: np.ndarray, q_new_kvar: np.ndarray) -> np.ndarray:
        """Linear model of eq. (13): voltages after tap changes ``d_tap`` and new Q set points [pu]."""
        return (
            self.v0_pu
            + self.dv_dq_pu_per_kvar @ (np.asarray(q_new_kvar, float) - self.q0_kvar)
            + self.dv_dtap_pu @ np.asarray(d_tap, float)
        )

    def cost(self, d_tap: np.ndarray, q_new_kvar: np.ndarray) -> float:
        """Eq. (9) with (14)-(15): flat cost per tap change plus per kvar of the new set point [cost units]."""
        return float(self.cost_per_tap @ np.abs(d_tap) + self.cost_per_kvar @ np.abs(q_new_kvar))


#: Every field of ``CvvcInputs``, in the order they are declared and checked.
_INPUT_FIELDS = tuple(f.name for f in dataclasses.fields(CvvcInputs))
#: The fields that price a problem without changing which actions meet its limits (``feasible_set_memo``).
_PRICE_FIELDS = frozenset({"cost_per_tap", "cost_per_kvar", "soft_alpha", "soft_beta_per_pu2", "soft_weight"})


@dataclass(frozen=True)
class VariableLayout:
    """Where each variable group sits in the QP's ``x``; ``None`` for groups the problem does not have."""

    n: int
    tap_up: slice | None
    tap_down: slice | None
    q_inj: slice
    q_abs: slice
    vio: slice | None


@dataclass(frozen=True)
class CvvcQp:
    """A scaled CVVC problem in OSQP form: minimise ``x'Px/2 + c'x`` subject to ``lower <= A x <= upper``.

    ``P`` is diagonal (upper triangle = whole matrix), ``A`` CSC. ``fixed_d_tap`` is set for the Q re-solve
    with integer taps (then the problem has no tap variables). Use ``to_qpsolvers`` to cross-check with any
    solver that ``qpsolvers`` knows, and ``d_tap``/``q_kvar``/``vio_pu`` to read a solution in physical units.
    """

    soft_nodes: np.ndarray  # (N,) bool: nodes with a violation variable (eq. 16-17); the others are hard
    nodes: np.ndarray  # (n,) sorted indices of the critical nodes that have a voltage row, in row order
    layout: VariableLayout
    c: np.ndarray
    a_sparse: sp.csc_matrix | None  # ``A`` of a large problem (no dense copy), else None: see ``A``
    lower: np.ndarray
    upper: np.ndarray
    q_rating_kvar: np.ndarray
    cost_scale: float
    dv_dtap_pct: np.ndarray  # (N, R) voltage-row coefficient of a tap step [%/step]
    a_dense: np.ndarray | None  # ``A`` as a dense array when small (the active-set polish needs it), else None
    p_diag: np.ndarray  # diagonal of ``P``
    fixed_d_tap: np.ndarray | None = None

    @functools.cached_property
    def A(self) -> sp.csc_matrix:  # noqa: N802 (the QP's name for it)
        """The constraint matrix in CSC form (built on first use: only OSQP and the cross-checks need it)."""
        if self.a_sparse is not None:
            return self.a_sparse
        if self.a_dense is None:
            raise AgentInputError("CvvcQp has neither a dense nor a sparse A: build it with build_cvvc_qp")
        return _dense_to_csc(self.a_dense)

    @functools.cached_property
    def dense_split(self) -> DenseSplit | None:
        """How the dense active-set method takes ``a_dense``'s rows (made on first use, shared by every solve of this
        problem: the rounding re-solves one tap-fixed problem for many candidates); None without a dense copy.
        """
        return None if self.a_dense is None else dense_split(self.a_dense)

    @functools.cached_property
    def P(self) -> sp.csc_matrix:  # noqa: N802
        """The diagonal quadratic cost in CSC form (built on first use)."""
        return _diag_csc(self.p_diag)

    @property
    def n_rows(self) -> int:
        """Rows of ``A``."""
        return int(self.lower.shape[0])

    @property
    def soft(self) -> bool:
        """Some node has a violation variable (eq. 16-17 form, fully or partly)."""
        return bool(self.soft_nodes.any())

    @property
    def soft_rows(self) -> np.ndarray:
        """(n,) bool: which voltage rows (in row order) have a violation variable."""
        return self.soft_nodes[self.nodes]

    @property
    def voltage_rows(self) -> slice:
        """Rows of ``A`` holding the voltage constraints (eq. 13 / 17), one per critical node, first."""
        return slice(0, self.dv_dtap_pct.shape[0])

    def bounds_with_d_tap(self, d_tap: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(lower, upper)`` of this tap-fixed problem re-fixed at ``d_tap`` (same ``A``, ``P``, ``c``)."""
        if self.fixed_d_tap is None:
            raise AgentInputError("bounds_with_d_tap is for problems built with fixed_d_tap")
        shift = self.dv_dtap_pct @ (np.asarray(d_tap, float) - self.fixed_d_tap)
        rows = self.voltage_rows
        lo, hi = self.lower.copy(), self.upper.copy()
        lo[rows] -= shift
        hi[rows] -= shift
        return lo, hi

    def d_tap(self, x: np.ndarray) -> np.ndarray:
        """(R,) net tap change of a solution [steps] (fractional for the relaxation)."""
        lay = self.layout
        if lay.tap_up is None or lay.tap_down is None:
            return np.array(self.fixed_d_tap, float)
        return x[lay.tap_up] - x[lay.tap_down]

    def q_kvar(self, x: np.ndarray) -> np.ndarray:
        """(K,) new Q set point of a solution [kvar]."""
        return (x[self.layout.q_inj] - x[self.layout.q_abs]) * self.q_rating_kvar

    def objective(self, x: np.ndarray) -> float:
        """Objective of ``x`` in unscaled cost units (including the proximal and violation terms)."""
        return float((0.5 * x @ (self.p_diag * x) + self.c @ x) * self.cost_scale)

    def to_qpsolvers(self) -> qpsolvers.Problem:
        """The same problem as a ``qpsolvers.Problem`` (``Gx <= h``, ``Ax = b``, no variable bounds)."""
        eq = self.lower == self.upper
        upper = ~eq & np.isfinite(self.upper)
        lower = ~eq & np.isfinite(self.lower)
        a = self.A.tocsr()
        g = sp.vstack([a[upper], -a[lower]]).tocsc()
        h = np.concatenate([self.upper[upper], -self.lower[lower]])
        a_eq = a[eq].tocsc() if eq.any() else None
        b_eq = self.upper[eq] if eq.any() else None
        return qpsolvers.Problem(self.P, self.c, g, h, a_eq, b_eq)


def _dense_to_csc(a: np.ndarray) -> sp.csc_matrix:
    """CSC of a small dense matrix without scipy's generic conversion path (a few microseconds)."""
    at = a.T
    nz = at != 0.0
    indptr = np.concatenate([[0], np.cumsum(nz.sum(axis=1))]).astype(np.int32)
    indices = np.nonzero(nz)[1].astype(np.int32)
    return sp.csc_matrix((at[nz], indices, indptr), shape=a.shape)


def _diag_csc(d: np.ndarray) -> sp.csc_matrix:
    n = d.shape[0]
    index = np.arange(n + 1, dtype=np.int32)
    return sp.csc_matrix((d.astype(float), index[:n], index), shape=(n, n))


def build_cvvc_qp(
    inputs: CvvcInputs,
    *,
    soft: bool | np.ndarray,
    fixed_d_tap: np.ndarray | None = None,
    nodes: np.ndarray | None = None,
) -> CvvcQp:
    """Build the scaled CVVC QP, paper eq. (9)-(15) (``soft=False``) or (16)-(17) (``soft=True``).

    Parameters
    ----------
    inputs : the problem data.
    soft : ``True``: eq. (17)'s squared-violation form at every node; ``False``: hard limits everywhere;
        an (N,) bool mask: violation variables at those nodes only, hard limits at the others (used for
        nodes that no action can bring within the limits, e.g. a feeder head above 1.04 pu).
    fixed_d_tap : (R,) integer tap changes to hold fixed; the problem then has only Q (and violation)
        variables: the "re-solve Q with taps fixed" step after rounding.
    nodes : indices of the critical nodes that get a voltage row (default: all). A subset is a relaxation
        of the full problem; ``agent.solve`` adds the rows of violated nodes until none is left.

    Returns
    -------
    The problem; its matrices depend on ``inputs`` and ``soft`` only (not on ``fixed_d_tap``), so one
    solver set-up serves every rounding candidate by updating ``lower`` and ``upper``.
    """
    k, r = inputs.n_pv, inputs.n_reg
    rating = inputs.q_rating_kvar
    with_taps = fixed_d_tap is None
    n_tap = 2 * r if with_taps else 0
    # (array methods and plain allocations, not np.broadcast_to / np.hstack / np.max: a problem is built several
    # times a decision, and numpy's function wrappers cost microseconds each)
    soft_given = np.asarray(soft, bool)
    soft_nodes = (soft_given.copy() if soft_given.shape == (inputs.n_nodes,)
                  else np.broadcast_to(soft_given, (inputs.n_nodes,)).copy())
    soft_nodes.flags.writeable = False
    rows_of = np.arange(inputs.n_nodes) if nodes is None else np.unique(np.asarray(nodes, int))
    rows_of.flags.writeable = False
    n = rows_of.size  # voltage rows
    soft_idx = soft_nodes[rows_of].nonzero()[0]  # rows (not nodes) with a violation variable
    n_vio = soft_idx.size
    n_var = n_tap + 2 * k + n_vio
    tap_up = slice(0, r) if with_taps else None
    tap_down = slice(r, 2 * r) if with_taps else None
    q_inj = slice(n_tap, n_tap + k)
    q_abs = slice(n_tap + k, n_tap + 2 * k)
    vio = slice(n_tap + 2 * k, n_var) if n_vio else None
    layout = VariableLayout(n=n_var, tap_up=tap_up, tap_down=tap_down, q_inj=q_inj, q_abs=q_abs, vio=vio)

    # Objective: normalised linear cost, proximal term, squared violations (eq. 17).
    q_cost = inputs.cost_per_kvar * rating
    cost_scale = float(max(inputs.cost_per_tap.max(initial=0.0), q_cost.max(initial=0.0), 1e-9))
    alpha = inputs.soft_alpha if n_vio else 1.0
    c = np.zeros(n_var)
    p_diag = np.zeros(n_var)
    if with_taps:
        c[tap_up] = c[tap_down] = alpha * inputs.cost_per_tap / cost_scale
        p_diag[:n_tap] = PROX_WEIGHT
    c[q_inj] = c[q_abs] = alpha * q_cost / cost_scale
    p_diag[q_inj] = p_diag[q_abs] = PROX_WEIGHT
    row_weight = (np.ones(rows_of.size) if inputs.soft_weight is None
                  else np.asarray(inputs.soft_weight)[rows_of])  # eq. (17)'s weight of each row's violation
    if vio is not None:
        # beta * (w_pct / 100)^2 in cost units, normalised: P entry = 2 beta / (cost_scale * 1e4).
        p_diag[vio] = 2.0 * inputs.soft_beta_per_pu2 / (cost_scale * _PCT_PER_PU**2) * row_weight[soft_idx]

    # Voltage rows (eq. 13 / 17) in %.
    s_q = _PCT_PER_PU * inputs.dv_dq_pu_per_kvar[rows_of] * rating  # (n, K) % per rating
    s_t = _PCT_PER_PU * inputs.dv_dtap_pu[rows_of]  # (n, R) % per step
    a_act = np.empty((n, n_tap + 2 * k))  # (N, n_tap + 2K): the action columns, dense
    if with_taps:
        a_act[:, tap_up], a_act[:, tap_down] = s_t, -s_t
    a_act[:, q_inj], a_act[:, q_abs] = s_q, -s_q
    v_base = _PCT_PER_PU * inputs.v0_pu[rows_of] - s_q @ (inputs.q0_kvar / rating)
    if not with_taps:
        v_base = v_base + s_t @ np.asarray(fixed_d_tap, float)
    if vio is not None and inputs.dv_dq_rel_error > 0.0:
        # E[beta (err s_ik x_k)^2] summed over the soft rows, in the scaled units of the violation term above;
        # diagonal in x+ and x- (never both non-zero at an optimum: lowering both alike keeps Q and costs less).
        h = (2.0 * inputs.soft_beta_per_pu2 / (cost_scale * _PCT_PER_PU**2)
             * inputs.dv_dq_rel_error**2 * (row_weight[soft_idx] @ s_q[soft_idx] ** 2))  # (K,)
        p_diag[q_inj] += h
        p_diag[q_abs] += h
    v_lo = _PCT_PER_PU * np.asarray(inputs.v_min_pu)[rows_of] - v_base
    v_hi = _PCT_PER_PU * np.asarray(inputs.v_max_pu)[rows_of] - v_base

    # Variable bounds, one identity row each. They carry eq. (10)-(12) exactly for the *net* actions
    # dT = dT+ - dT- and Q = Q+ - Q- (0 <= dT+ <= min(max, room up) gives dT <= room up and |dT| <= max,
    # and so on), so the paper's rows (10)-(12) would be redundant (and degenerate: bad for ADMM).
    lo = [v_lo]
    hi = [v_hi]
    if with_taps:
        max_t = inputs.max_taps_per_interval.astype(float)
        room_up = np.maximum(inputs.tap_max - inputs.taps, 0).astype(float)
        room_down = np.maximum(inputs.taps - inputs.tap_min, 0).astype(float)
        lo.append(np.zeros(2 * r))
        hi.append(np.concatenate([np.minimum(max_t, room_up), np.minimum(max_t, room_down)]))
    q_min, q_max = inputs.q_min_kvar / rating, inputs.q_max_kvar / rating
    lo.append(np.concatenate([np.maximum(q_min, 0.0), np.maximum(-q_max, 0.0)]))
    hi.append(np.concatenate([np.maximum(q_max, 0.0), np.maximum(-q_min, 0.0)]))
    n_bounded = n_tap + 2 * k
    m = n + n_bounded
    if n_var <= DENSE_MAX_VARS and m * n_var <= DENSE_LIMIT:
        # Small (the usual case): one dense matrix, kept for the active-set polish.
        full = np.zeros((m, n_var))
        full[:n, :n_bounded] = a_act
        full[n + np.arange(n_bounded), np.arange(n_bounded)] = 1.0
        if n_vio:
            full[soft_idx, n_bounded + np.arange(n_vio)] = -1.0
        full.flags.writeable = False
        a_dense: np.ndarray | None = full
        a_matrix: sp.csc_matrix | None = None  # built on first use (CvvcQp.A)
    else:
        # Large (every node of a big feeder, soft form): sparse only; a dense copy could take gigabytes.
        a_dense = None
        vio_block = sp.csr_matrix((-np.ones(n_vio), (soft_idx, np.arange(n_vio))), shape=(n, n_vio))
        a_matrix = sp.vstack(
            [
                sp.hstack([sp.csr_matrix(a_act), vio_block]),
                sp.hstack([sp.identity(n_bounded, format="csr"), sp.csr_matrix((n_bounded, n_vio))]),
            ],
            format="csc",
        )
    p_diag.flags.writeable = False
    return CvvcQp(
        soft_nodes=soft_nodes,
        nodes=rows_of,
        layout=layout,
        c=c,
        a_sparse=a_matrix,
        lower=np.concatenate(lo),
        upper=np.concatenate(hi),
        q_rating_kvar=rating,
        cost_scale=cost_scale,
        dv_dtap_pct=s_t,
        a_dense=a_dense,
        p_diag=p_diag,
        fixed_d_tap=None if with_taps else np.array(fixed_d_tap, float),
    )
