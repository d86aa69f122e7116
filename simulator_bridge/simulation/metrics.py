"""Evaluation metrics of the paper (IV.F), from the ground truth: MVVM, NVV, NTC, Q, T and total cost.

Pure numpy. ``metrics_from_series`` computes them for whole arrays at once; ``MetricsAccumulator``
(``metrics_stream.py``) computes the same numbers step by step with bounded memory (a ring buffer of
``window_steps`` x nodes), so a month of QSTS never has to be held. ``Metrics.combine`` adds runs (for
example months) together.

Our reading of IV.F (the paper gives names, not formulas), also in ``docs/profiles-and-metrics.md``:

* Rolling average: causal, over the last ``window_steps`` steps of each node (10 x 60 s = 10 minutes),
  ``v_avg[t] = mean(v[t - w + 1 .. t])``. It exists from the ``w``-th step of a run on; the first
  ``w - 1`` steps of every run are not judged.
* Violation magnitude of a sample: ``max(v_avg - v_max, v_min - v_avg, 0)`` [pu] against the judged
  limits ``(v_min, v_max)`` = (0.965, 1.05) pu; magnitudes up to ``VIOLATION_TOLERANCE_PU`` (1e-9 pu)
  are rounding and count as 0.
* MVVM: the largest violation magnitude over every node and judged step [pu].
* NVV: the number of (node, step) samples of the rolling average strictly outside the limits. At 1-minute
  steps that is node-minutes; a node above the limit for 8 minutes counts 8.
* Minutes in violation: judged steps in which any node's rolling average is outside, x ``step_s`` / 60.
* NTC: tap steps moved, summed over regulators and steps. T cost = sum_r cost_per_tap_r x NTC_r (eq. 14).
* Capacitor switchings (beyond the paper, which has no switched banks): switching operations per bank, one per
  step of the bank opened or closed, counted like NTC; cap cost = sum_c cost_per_switch_c x switchings_c, and
  it is part of the total cost.
* Q cost (eq. 15): the paper charges ``c_k (Q_k^+ + Q_k^-)`` per kvar of set point per 5-minute control
  interval. We charge every step its share of an interval: ``sum_t sum_k c_k |Q_k[t]| step_s /
  control_period_s``, so a set point held for one interval costs exactly ``c_k |Q_k|``.
* Every minute on its own (beyond the paper, whose 10-minute averages can hide a worse minute): node-minutes and
  minutes with any judged node's voltage (not averaged) outside the optimization limits ``opt_limits_pu``
  (0.975, 1.04) and outside ANSI C84.1 Range A (``ANSI_RANGE_A_PU``, 0.95-1.05) [pu], with the same tolerance; the
  1-minute extremes are ``v_min_pu`` / ``v_max_pu``.
* Reactive energy per plant: ``sum_t |Q_k[t]| step_s / 3600`` [kvarh], and the paper's Table IV unit,
  ``sum_t |Q_k[t]| / 1000 x step_s / control_period_s`` [Mvar x control intervals].
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Annotated, TypedDict, Unpack

import msgspec
import numpy as np
from msgspec import Meta

from schemas.settings import ANSI_RANGE_A_PU
from simulator_bridge.errors import SimulatorError

__all__ = [
    "ANSI_RANGE_A_PU",
    "JUDGED_LIMITS_PU",
    "OPTIMIZATION_LIMITS_PU",
    "Metrics",
    "MetricsError",
    "MetricsSettings",
    "VIOLATION_TOLERANCE_PU",
    "cap_cost_per_bank",
    "combine_metrics",
    "metrics_from_series",
    "q_cost_per_plant",
    "rolling_mean_pu",
    "tap_cost_per_regulator",
    "violation_pu",
]

JUDGED_LIMITS_PU = (0.965, 1.05)
"""The paper's judged voltage limits (IV) [pu of each node's nominal]."""

OPTIMIZATION_LIMITS_PU = (0.975, 1.04)
"""The paper's optimization limits (IV) [pu]: the default of the per-minute count ``opt_limits_pu``."""


VIOLATION_TOLERANCE_PU = 1e-9
"""Violations no larger than this are floating-point rounding and are not counted [pu]."""

NonNegInt = Annotated[int, Meta(ge=0)]
NonNegFloat = Annotated[float, Meta(ge=0.0)]


class MetricsError(SimulatorError):
    """Inputs to the metrics that do not fit (shapes, NaN voltages, negative counts, mixed runs)."""


class Metrics(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The paper's IV.F metrics of one run (or of several, after :meth:`combine`).

    Voltages are in pu of each node's own nominal; costs in the device map's currency units.
    ``v_*`` fields are ``None`` when there is nothing to report (no step, or no judged step).
    """

    n_steps: NonNegInt
    n_steps_judged: NonNegInt
    step_s: Annotated[int, Meta(gt=0)]
    window_steps: Annotated[int, Meta(gt=0)]
    control_period_s: Annotated[int, Meta(gt=0)]
    limits_pu: tuple[float, float]
    mvvm_pu: NonNegFloat
    mvvm_node: int  # node index of the MVVM sample; -1 without violation
    nvv: NonNegInt
    steps_in_violation: NonNegInt
    minutes_in_violation: NonNegFloat
    v_min_pu: float | None
    v_max_pu: float | None
    v_avg_min_pu: float | None
    v_avg_max_pu: float | None
    ntc: NonNegInt
    t_cost: NonNegFloat
    q_cost: NonNegFloat
    total_cost: NonNegFloat
    regulator_ids: tuple[str, ...]
    tap_changes_per_regulator: tuple[NonNegInt, ...]
    pv_ids: tuple[str, ...]
    q_kvarh_per_plant: tuple[NonNegFloat, ...]
    q_mvar_intervals_per_plant: tuple[NonNegFloat, ...]
    q_cost_per_plant: tuple[NonNegFloat, ...]
    # capacitor banks (append-only: metrics stored before them still decode)
    capacitor_ids: tuple[str, ...] = ()
    cap_switches_per_bank: tuple[NonNegInt, ...] = ()
    cap_switches: NonNegInt = 0
    cap_cost: NonNegFloat = 0.0
    # every minute on its own (append-only): judged nodes outside the optimization limits / ANSI Range A
    opt_limits_pu: tuple[float, float] = OPTIMIZATION_LIMITS_PU
    node_minutes_outside_opt: NonNegFloat = 0.0
    minutes_outside_opt: NonNegFloat = 0.0
    node_minutes_outside_ansi: NonNegFloat = 0.0
    minutes_outside_ansi: NonNegFloat = 0.0
    # steps at which a regulator had moved faster than its RegControl's tapdelay allows (append-only; empty: the
    # tapdelays were not given, nothing judged): :func:`over_tap_rate`
    steps_over_tap_rate_per_regulator: tuple[NonNegInt, ...] = ()

    def combine(self, other: Metrics) -> Metrics:
        """The metrics of this run and ``other`` together (counts and costs add, extremes combine).

        Both must have the same devices, limits and timing; each run keeps its own rolling windows.
        """
        for name in ("step_s", "window_steps", "control_period_s", "limits_pu", "regulator_ids", "pv_ids",
                     "capacitor_ids", "opt_limits_pu"):
            if getattr(self, name) != getattr(other, name):
                raise MetricsError(
                    f"cannot combine metrics with different {name}: {getattr(self, name)!r} vs "
                    f"{getattr(other, name)!r}; combine runs of the same feeder and settings only"
                )
        worst = self if self.mvvm_pu >= other.mvvm_pu else other
        return msgspec.structs.replace(
            self,
            n_steps=self.n_steps + other.n_steps,
            n_steps_judged=self.n_steps_judged + other.n_steps_judged,
            mvvm_pu=worst.mvvm_pu,
            mvvm_node=worst.mvvm_node,
            nvv=self.nvv + other.nvv,
            steps_in_violation=self.steps_in_violation + other.steps_in_violation,
            minutes_in_violation=self.minutes_in_violation + other.minutes_in_violation,
            v_min_pu=_opt(min, self.v_min_pu, other.v_min_pu),
            v_max_pu=_opt(max, self.v_max_pu, other.v_max_pu),
            v_avg_min_pu=_opt(min, self.v_avg_min_pu, other.v_avg_min_pu),
            v_avg_max_pu=_opt(max, self.v_avg_max_pu, other.v_avg_max_pu),
            ntc=self.ntc + other.ntc,
            t_cost=self.t_cost + other.t_cost,
            q_cost=self.q_cost + other.q_cost,
            total_cost=self.total_cost + other.total_cost,
            tap_changes_per_regulator=_add(self.tap_changes_per_regulator, other.tap_changes_per_regulator),
            q_kvarh_per_plant=_add(self.q_kvarh_per_plant, other.q_kvarh_per_plant),
            q_mvar_intervals_per_plant=_add(self.q_mvar_intervals_per_plant, other.q_mvar_intervals_per_plant),
            q_cost_per_plant=_add(self.q_cost_per_plant, other.q_cost_per_plant),
            cap_switches_per_bank=_add(self.cap_switches_per_bank, other.cap_switches_per_bank),
            cap_switches=self.cap_switches + other.cap_switches,
            cap_cost=self.cap_cost + other.cap_cost,
            node_minutes_outside_opt=self.node_minutes_outside_opt + other.node_minutes_outside_opt,
            minutes_outside_opt=self.minutes_outside_opt + other.minutes_outside_opt,
            node_minutes_outside_ansi=self.node_minutes_outside_ansi + other.node_minutes_outside_ansi,
            minutes_outside_ansi=self.minutes_outside_ansi + other.minutes_outside_ansi,
            # judged over both runs or not at all
            steps_over_tap_rate_per_regulator=_add(self.steps_over_tap_rate_per_regulator,
                                                   other.steps_over_tap_rate_per_regulator)
            if self.steps_over_tap_rate_per_regulator and other.steps_over_tap_rate_per_regulator else (),
        )


def combine_metrics(items: Iterable[Metrics]) -> Metrics:
    """Combine several runs' metrics (for example the four season months) with :meth:`Metrics.combine`."""
    items = list(items)
    if not items:
        raise MetricsError("combine_metrics needs at least one Metrics")
    out = items[0]
    for m in items[1:]:
        out = out.combine(m)
    return out


# ---------------------------------------------------------------------------------------------------
# Pure functions
# ---------------------------------------------------------------------------------------------------


def rolling_mean_pu(v_pu: np.ndarray, window_steps: int) -> np.ndarray:
    """Causal rolling mean over ``window_steps`` rows of ``v_pu`` (T, N) [pu]; NaN where not yet full.

    Row ``t`` is ``mean(v_pu[t - window_steps + 1 : t + 1])`` for ``t >= window_steps - 1``.
    """
    v = np.asarray(v_pu, dtype=float)
    out = np.full(v.shape, np.nan)
    w = int(window_steps)
    if w < 1:
        raise MetricsError(f"window_steps = {w}; must be at least 1")
    if v.shape[0] >= w:
        c = np.cumsum(np.concatenate([np.zeros((1,) + v.shape[1:]), v]), axis=0)
        out[w - 1 :] = (c[w:] - c[:-w]) / w
    return out


def violation_pu(v_pu: np.ndarray, limits_pu: tuple[float, float]) -> np.ndarray:
    """Violation magnitude ``max(v - v_max, v_min - v, 0)`` of every sample [pu]; 0 inside the limits.

    Magnitudes up to ``VIOLATION_TOLERANCE_PU`` count as 0: averaging ten samples of exactly 1.05 gives
    1.0500000000000002, which is rounding, not a violation.
    """
    lo, hi = limits_pu
    v = np.asarray(v_pu, dtype=float)
    m = np.maximum(v - hi, lo - v)
    return np.where(m > VIOLATION_TOLERANCE_PU, m, 0.0)


def outside_count(v_pu: np.ndarray, limits_pu: tuple[float, float]) -> np.ndarray:
    """How many voltages of each row of ``v_pu`` (..., N) [pu] are outside ``limits_pu`` (beyond
    ``VIOLATION_TOLERANCE_PU``, as :func:`violation_pu`); shape (...).
    """
    return np.count_nonzero(violation_pu(v_pu, limits_pu) > 0.0, axis=-1)


def tap_cost_per_regulator(tap_changes: np.ndarray, cost_per_tap: np.ndarray) -> np.ndarray:
    """T cost of each regulator, paper eq. (14): ``cost_per_tap_r x`` taps moved (summed over rows)."""
    taps = np.asarray(tap_changes, dtype=float)
    # summed over every leading axis (not reshape(-1, R): that fails for a feeder without regulators, R = 0)
    return np.asarray(cost_per_tap, dtype=float) * taps.sum(axis=tuple(range(taps.ndim - 1)))


def cap_cost_per_bank(cap_switches: np.ndarray, cost_per_switch: np.ndarray) -> np.ndarray:
    """Switching cost of each capacitor bank: ``cost_per_switch_c x`` switching operations (summed over rows)."""
    sw = np.asarray(cap_switches, dtype=float)
    return np.asarray(cost_per_switch, dtype=float) * sw.sum(axis=tuple(range(sw.ndim - 1)))


def q_cost_per_plant(
    q_kvar: np.ndarray, cost_per_kvar: np.ndarray, *, step_s: float, control_period_s: float
) -> np.ndarray:
    """Q cost of each plant, paper eq. (15) per control interval, integrated over steps.

    ``sum_t cost_per_kvar_k |q_kvar[t, k]| step_s / control_period_s``; ``q_kvar`` is (T, K) [kvar].
    """
    q = np.abs(np.asarray(q_kvar, dtype=float))
    q = q.reshape(-1, q.shape[-1])
    return np.asarray(cost_per_kvar, dtype=float) * q.sum(axis=0) * (step_s / control_period_s)


#: The longest run of steps whose tap moves are held to the RegControls' tapdelays [steps].
TAP_RATE_WINDOW_STEPS = 10


def tap_rate_allowance(tap_delay_s: Sequence[float], step_s: int, window_steps: int = TAP_RATE_WINDOW_STEPS
                       ) -> np.ndarray:
    """(window_steps, R) the most tap moves each regulator's RegControl can make in ``k`` consecutive steps
    (row ``k - 1``): ``floor(k * step_s / tapdelay) + 1``, moves at least ``tapdelay`` apart within a closed span of
    ``k * step_s`` seconds (the ``delay`` before a first move only lowers it); no limit where ``tapdelay <= 0``.
    """
    td = np.asarray(tap_delay_s, dtype=float)
    k = np.arange(1, window_steps + 1, dtype=float)[:, None] * step_s
    with np.errstate(divide="ignore"):
        return np.where(td > 0.0, np.floor(k / np.where(td > 0.0, td, 1.0)) + 1.0, np.inf)


def over_tap_rate(recent_moves: np.ndarray, allowance: np.ndarray) -> np.ndarray:
    """(R,) bool: a regulator's moves over the latest ``k`` steps exceed ``allowance[k - 1]`` for some ``k``
    (``recent_moves`` (k_max, R), the latest step last, ``k_max <= len(allowance)``): it moved faster than its
    RegControl allows. Moves are what the simulation counted (an up-then-down is 2), a locked tap's jump included.
    """
    sums = np.cumsum(recent_moves[::-1], axis=0)
    return np.any(sums > allowance[: len(recent_moves)], axis=0)


def metrics_from_series(
    v_pu: np.ndarray,
    tap_changes: np.ndarray,
    pv_q_kvar: np.ndarray,
    *,
    cap_switches: np.ndarray | None = None,
    **settings: Unpack[MetricsSettings],
) -> Metrics:
    """The metrics of one run given as whole arrays.

    Parameters
    ----------
    v_pu : ndarray, shape (T, n_nodes)
        Every node's voltage at every step [pu].
    tap_changes : ndarray of int, shape (T, R)
        Tap steps moved by each regulator during each step (>= 0).
    pv_q_kvar : ndarray, shape (T, K)
        Each plant's reactive power [kvar] (either sign).
    cap_switches : ndarray of int, shape (T, C), optional
        Switching operations of each capacitor bank during each step (>= 0); None: no bank.
    **settings
        :class:`MetricsSettings`: regulator_ids, pv_ids, cost_per_tap, cost_per_kvar, limits_pu [pu],
        window_steps [steps], step_s [s], control_period_s [s], capacitor_ids, cost_per_switch; as for
        ``metrics_stream.MetricsAccumulator``.
    """
    if np.ndim(v_pu) != 2:
        raise MetricsError(f"v_pu has shape {np.shape(v_pu)}; expected (n_steps, n_nodes)")
    cfg = MetricsConfig.make(n_nodes=np.shape(v_pu)[1], **settings)
    n_steps = int(np.shape(v_pu)[0])
    v, taps, q = cfg.check(v_pu, tap_changes, pv_q_kvar, rows=(n_steps,))
    sw = cfg.check_switches(cap_switches, rows=(n_steps,))
    over = None
    if cfg.tap_delay_s is not None:
        allowance = tap_rate_allowance(cfg.tap_delay_s, cfg.step_s)
        w = len(allowance)
        over = np.zeros(cfg.n_regs, dtype=np.int64)
        for t in range(n_steps):
            over += over_tap_rate(taps[max(0, t - w + 1): t + 1], allowance)
    avg = rolling_mean_pu(v, cfg.window_steps)[cfg.window_steps - 1 :]
    n_opt, n_ansi = outside_count(v, cfg.opt_limits_pu), outside_count(v, ANSI_RANGE_A_PU)
    viol = violation_pu(avg, cfg.limits_pu)
    outside = viol > 0.0
    worst = int(np.argmax(viol)) if viol.size else 0
    mvvm = float(viol.flat[worst]) if viol.size else 0.0
    return cfg.result(
        n_steps=n_steps,
        n_steps_judged=avg.shape[0],
        mvvm_pu=mvvm,
        mvvm_node=worst % cfg.n_nodes if mvvm > 0 else -1,
        nvv=int(outside.sum()),
        steps_in_violation=int(outside.any(axis=1).sum()),
        v_min_max=(float(v.min()), float(v.max())) if n_steps else None,
        v_avg_min_max=(float(avg.min()), float(avg.max())) if avg.size else None,
        taps=taps.astype(np.int64).sum(axis=0),
        abs_q_kvar_steps=np.abs(q).sum(axis=0),
        cap_switches=sw.sum(axis=0),
        minute_counts=MinuteCounts(opt_nodes=int(n_opt.sum()), opt_steps=int(np.count_nonzero(n_opt)),
                                   ansi_nodes=int(n_ansi.sum()), ansi_steps=int(np.count_nonzero(n_ansi))),
        steps_over_tap_rate=over,
    )


# ---------------------------------------------------------------------------------------------------
# Shared configuration and checks
# ---------------------------------------------------------------------------------------------------


class _RequiredSettings(TypedDict):
    regulator_ids: Sequence[str]
    pv_ids: Sequence[str]
    cost_per_tap: float | Sequence[float]
    cost_per_kvar: float | Sequence[float]


class MetricsSettings(_RequiredSettings, total=False):
    """The keywords, besides ``n_nodes``, of :meth:`MetricsConfig.make`, :func:`metrics_from_series` and
    ``metrics_stream.MetricsAccumulator`` (written once here; their meaning and units are in
    ``MetricsAccumulator``'s docstring).

    The first four are required; the others default to ``limits_pu = JUDGED_LIMITS_PU`` [pu],
    ``window_steps = 10`` [steps], ``step_s = 60`` [s], ``control_period_s = 300`` [s], ``capacitor_ids = ()``,
    ``cost_per_switch = 1.0``, ``opt_limits_pu = OPTIMIZATION_LIMITS_PU`` [pu], ``tap_delay_s = None`` (each
    regulator's RegControl ``tapdelay`` [s]; None: how fast the regulators moved is not judged).
    """

    limits_pu: tuple[float, float]
    window_steps: int
    step_s: int
    control_period_s: int
    capacitor_ids: Sequence[str]
    cost_per_switch: float | Sequence[float]
    opt_limits_pu: tuple[float, float]
    tap_delay_s: Sequence[float] | None


class MinuteCounts(msgspec.Struct, frozen=True, kw_only=True):
    """Every step judged on its own: (node, step) samples and steps with a judged node outside the optimization
    limits (``opt_*``) and ANSI C84.1 Range A (``ansi_*``).
    """

    opt_nodes: int = 0
    opt_steps: int = 0
    ansi_nodes: int = 0
    ansi_steps: int = 0


class MetricsConfig(msgspec.Struct, frozen=True, kw_only=True):
    """What the metrics of a run are computed over: nodes, devices, costs, limits and steps (built by :meth:`make`,
    which checks them; shared by :func:`metrics_from_series` and ``metrics_stream.MetricsAccumulator``).
    """

    n_nodes: int
    regulator_ids: tuple[str, ...]
    pv_ids: tuple[str, ...]
    cost_per_tap: tuple[float, ...]
    cost_per_kvar: tuple[float, ...]
    limits_pu: tuple[float, float]
    window_steps: int
    step_s: int
    control_period_s: int
    capacitor_ids: tuple[str, ...] = ()
    cost_per_switch: tuple[float, ...] = ()
    opt_limits_pu: tuple[float, float] = OPTIMIZATION_LIMITS_PU
    tap_delay_s: tuple[float, ...] | None = None

    @property
    def n_regs(self) -> int:
        return len(self.regulator_ids)

    @property
    def n_pv(self) -> int:
        return len(self.pv_ids)

    @classmethod
    def make(cls, *, n_nodes: int, **settings: Unpack[MetricsSettings]) -> MetricsConfig:
        """The checked configuration of ``n_nodes`` nodes and :class:`MetricsSettings` (defaults filled in).

        Raises
        ------
        TypeError
            A keyword is not one of :class:`MetricsSettings` or a required one is missing (as for any call).
        MetricsError
            A value is out of range.
        """
        unknown = sorted(settings.keys() - MetricsSettings.__required_keys__ - MetricsSettings.__optional_keys__)
        missing = sorted(MetricsSettings.__required_keys__ - settings.keys())
        if unknown or missing:
            raise TypeError(f"metrics settings: unexpected keyword(s) {unknown}, missing {missing}")
        regulator_ids, pv_ids = settings["regulator_ids"], settings["pv_ids"]
        cost_per_tap, cost_per_kvar = settings["cost_per_tap"], settings["cost_per_kvar"]
        limits_pu = settings.get("limits_pu", JUDGED_LIMITS_PU)
        window_steps, step_s = settings.get("window_steps", 10), settings.get("step_s", 60)
        control_period_s = settings.get("control_period_s", 300)
        capacitor_ids, cost_per_switch = settings.get("capacitor_ids", ()), settings.get("cost_per_switch", 1.0)
        opt_lo, opt_hi = (float(x) for x in settings.get("opt_limits_pu", OPTIMIZATION_LIMITS_PU))
        tap_delay = settings.get("tap_delay_s")
        if int(n_nodes) < 1:
            raise MetricsError(f"n_nodes = {n_nodes}; voltages must be (n_steps, n_nodes) with n_nodes >= 1")
        regs, pvs = tuple(str(r) for r in regulator_ids), tuple(str(p) for p in pv_ids)
        lo, hi = (float(x) for x in limits_pu)
        if not (np.isfinite(lo) and np.isfinite(hi) and 0.0 < lo < hi):
            raise MetricsError(f"limits_pu = {limits_pu}; need 0 < v_min < v_max")
        if not (np.isfinite(opt_lo) and np.isfinite(opt_hi) and 0.0 < opt_lo < opt_hi):
            raise MetricsError(f"opt_limits_pu = {(opt_lo, opt_hi)}; need 0 < v_min < v_max")
        for name, value in (("window_steps", window_steps), ("step_s", step_s), ("control_period_s", control_period_s)):
            if int(value) != value or value < 1:
                raise MetricsError(f"{name} = {value}; must be a positive whole number")
        return cls(
            n_nodes=int(n_nodes),
            regulator_ids=regs,
            pv_ids=pvs,
            cost_per_tap=_costs(cost_per_tap, len(regs), "cost_per_tap", "regulator"),
            cost_per_kvar=_costs(cost_per_kvar, len(pvs), "cost_per_kvar", "PV plant"),
            limits_pu=(lo, hi),
            window_steps=int(window_steps),
            step_s=int(step_s),
            control_period_s=int(control_period_s),
            capacitor_ids=tuple(str(c) for c in capacitor_ids),
            cost_per_switch=_costs(cost_per_switch, len(tuple(capacitor_ids)), "cost_per_switch", "capacitor bank"),
            opt_limits_pu=(opt_lo, opt_hi),
            tap_delay_s=None if tap_delay is None else _tap_delays(tap_delay, len(regs)),
        )

    def check_switches(self, cap_switches: np.ndarray | None, rows: tuple[int, ...] = ()) -> np.ndarray:
        """Validate capacitor switchings of one step (``rows = ()``) or ``rows = (T,)`` steps; int64. None: zeros."""
        n = len(self.capacitor_ids)
        if cap_switches is None:
            return np.zeros(rows + (n,), dtype=np.int64)
        sw = np.asarray(cap_switches)
        if sw.shape != rows + (n,):
            raise MetricsError(f"cap_switches has shape {sw.shape}; expected {rows + (n,)}, one per capacitor bank")
        bad = sw.size and (sw.dtype.kind not in "iu" and (not np.all(np.isfinite(sw)) or np.any(sw != np.round(sw))))
        if bad or (sw.size and sw.min() < 0):
            raise MetricsError("cap_switches must be whole numbers >= 0 (switching operations), got "
                               + repr(sw.tolist()))
        return sw.astype(np.int64, copy=False)

    def check_step(
        self, v_pu: np.ndarray, tap_changes: np.ndarray, pv_q_kvar: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
        """:meth:`check` of one step, plus the step's lowest and highest voltage [pu].

        The same checks and messages with fewer array passes: the voltages are finite and positive exactly
        when their minimum is positive and their maximum finite (a NaN makes both NaN); whole-number and
        finiteness checks of tap changes are needed only when they do not come as integers.
        """
        v = np.asarray(v_pu, dtype=float)
        taps = np.asarray(tap_changes)
        q = np.asarray(pv_q_kvar, dtype=float)
        if v.shape == (self.n_nodes,) and taps.shape == (self.n_regs,) and q.shape == (self.n_pv,) \
                and taps.dtype.kind in "iu":
            v_lo, v_hi = float(v.min()), float(v.max())
            if v_lo > 0.0 and v_hi < np.inf and not (taps.size and taps.min() < 0) and np.isfinite(q).all():
                return v, taps.astype(np.int64, copy=False), q, v_lo, v_hi
        v, taps, q = self.check(v_pu, tap_changes, pv_q_kvar)  # raises with its message, or takes float taps
        return v, taps, q, float(v.min()), float(v.max())

    def check(
        self, v_pu: np.ndarray, tap_changes: np.ndarray, pv_q_kvar: np.ndarray, rows: tuple[int, ...] = ()
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Validate one step (``rows = ()``) or ``rows = (T,)`` steps; return float, int64, float arrays."""
        v = np.asarray(v_pu, dtype=float)
        taps = np.asarray(tap_changes)
        q = np.asarray(pv_q_kvar, dtype=float)
        if v.shape != rows + (self.n_nodes,):
            raise MetricsError(f"v_pu has shape {v.shape}; expected {rows + (self.n_nodes,)}, one voltage per node")
        if not np.all(np.isfinite(v)) or np.any(v <= 0.0):
            raise MetricsError("v_pu has NaN, infinite or non-positive voltages; the solve that made them failed")
        if taps.shape != rows + (self.n_regs,):
            raise MetricsError(
                f"tap_changes has shape {taps.shape}; expected {rows + (self.n_regs,)}, one per regulator"
            )
        if taps.size and (not np.all(np.isfinite(taps)) or np.any(taps != np.round(taps)) or taps.min() < 0):
            raise MetricsError("tap_changes must be whole numbers >= 0 (tap steps moved), got " + repr(taps.tolist()))
        if q.shape != rows + (self.n_pv,):
            raise MetricsError(f"pv_q_kvar has shape {q.shape}; expected {rows + (self.n_pv,)}, one per PV plant")
        if not np.all(np.isfinite(q)):
            raise MetricsError("pv_q_kvar has NaN or infinite values")
        return v, taps.astype(np.int64), q

    def result(
        self,
        *,
        n_steps: int,
        n_steps_judged: int,
        mvvm_pu: float,
        mvvm_node: int,
        nvv: int,
        steps_in_violation: int,
        v_min_max: tuple[float, float] | None,
        v_avg_min_max: tuple[float, float] | None,
        taps: np.ndarray,
        abs_q_kvar_steps: np.ndarray,
        cap_switches: np.ndarray,
        minute_counts: MinuteCounts,
        steps_over_tap_rate: np.ndarray | None = None,
    ) -> Metrics:
        t_cost = tap_cost_per_regulator(taps[None, :], np.array(self.cost_per_tap))
        c_cost = cap_cost_per_bank(cap_switches[None, :], np.array(self.cost_per_switch))
        q_cost = q_cost_per_plant(
            abs_q_kvar_steps[None, :],
            np.array(self.cost_per_kvar),
            step_s=self.step_s,
            control_period_s=self.control_period_s,
        )
        intervals = self.step_s / self.control_period_s
        minutes = self.step_s / 60.0
        return Metrics(
            n_steps=n_steps,
            n_steps_judged=n_steps_judged,
            step_s=self.step_s,
            window_steps=self.window_steps,
            control_period_s=self.control_period_s,
            limits_pu=self.limits_pu,
            mvvm_pu=mvvm_pu,
            mvvm_node=mvvm_node,
            nvv=nvv,
            steps_in_violation=steps_in_violation,
            minutes_in_violation=steps_in_violation * self.step_s / 60.0,
            v_min_pu=None if v_min_max is None else v_min_max[0],
            v_max_pu=None if v_min_max is None else v_min_max[1],
            v_avg_min_pu=None if v_avg_min_max is None else v_avg_min_max[0],
            v_avg_max_pu=None if v_avg_min_max is None else v_avg_min_max[1],
            ntc=int(taps.sum()),
            t_cost=float(t_cost.sum()),
            q_cost=float(q_cost.sum()),
            total_cost=float(t_cost.sum() + q_cost.sum() + c_cost.sum()),
            regulator_ids=self.regulator_ids,
            tap_changes_per_regulator=tuple(int(t) for t in taps),
            pv_ids=self.pv_ids,
            q_kvarh_per_plant=tuple(float(x) for x in abs_q_kvar_steps * self.step_s / 3600.0),
            q_mvar_intervals_per_plant=tuple(float(x) for x in abs_q_kvar_steps / 1000.0 * intervals),
            q_cost_per_plant=tuple(float(x) for x in q_cost),
            capacitor_ids=self.capacitor_ids,
            cap_switches_per_bank=tuple(int(x) for x in cap_switches),
            cap_switches=int(cap_switches.sum()),
            cap_cost=float(c_cost.sum()),
            opt_limits_pu=self.opt_limits_pu,
            node_minutes_outside_opt=minute_counts.opt_nodes * minutes,
            minutes_outside_opt=minute_counts.opt_steps * minutes,
            node_minutes_outside_ansi=minute_counts.ansi_nodes * minutes,
            minutes_outside_ansi=minute_counts.ansi_steps * minutes,
            steps_over_tap_rate_per_regulator=() if steps_over_tap_rate is None
            else tuple(int(x) for x in steps_over_tap_rate),
        )


def _costs(value: float | Sequence[float], n: int, name: str, what: str) -> tuple[float, ...]:
    c = np.asarray(value, dtype=float)
    if c.ndim == 0:
        c = np.full(n, float(c))
    if c.shape != (n,):
        raise MetricsError(f"{name} has {c.size} values for {n} {what}s; give one per {what} or one for all")
    if not np.all(np.isfinite(c)) or (c.size and c.min() < 0):
        raise MetricsError(f"{name} {c.tolist()} must be finite and >= 0")
    return tuple(float(x) for x in c)


def _tap_delays(value: Sequence[float], n: int) -> tuple[float, ...]:
    out = tuple(float(x) for x in value)
    if len(out) != n or not all(np.isfinite(x) and x >= 0.0 for x in out):
        raise MetricsError(f"tap_delay_s = {value!r}; need one finite tapdelay >= 0 [s] per regulator ({n})")
    return out


def _opt(f, a: float | None, b: float | None) -> float | None:
    if a is None:
        return b
    if b is None:
        return a
    return f(a, b)


def _add(a: tuple, b: tuple) -> tuple:
    return tuple(x + y for x, y in zip(a, b, strict=True))
