"""Voltage sensitivities of every node by perturbation of a solved engine (the case-A oracle).

:func:`perturbation_sensitivities` moves each plant's Q, each plant's available P and each regulator's tap one at a
time, solves, differences and undoes; it uses only :class:`~simulator_bridge.opendss.engine.FeederEngine`'s public
setters
and readers (``FeederEngine.perturbation_sensitivities`` calls it).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from simulator_bridge.errors import EngineError


class _PvOutput(Protocol):
    @property
    def pv_p_kw(self) -> np.ndarray:
        """(K, phases) each plant's output [kW]."""


class PerturbedEngine(Protocol):
    """What the perturbation needs of an engine (``simulator_bridge.opendss.engine.FeederEngine`` is one): its plants'
    ratings,
    the regulators' top taps, the solver tolerance, the setters and readers it moves and reads.
    """

    pv_kva: np.ndarray
    pv_pmpp_kw: np.ndarray
    reg_tap_max: np.ndarray
    tolerance: float

    def set_pv(self, p_kw: np.ndarray, q_kvar: np.ndarray) -> np.ndarray:
        """Set each plant's available P [kW] and Q set point [kvar]; the Q applied [kvar]."""

    def pv_setpoints(self) -> tuple[np.ndarray, np.ndarray]:
        """The plants' present P [kW] and Q [kvar] set points."""

    def set_taps(self, taps: np.ndarray) -> None:
        """Set every regulator's tap [steps]."""

    def taps(self) -> np.ndarray:
        """Every regulator's tap [steps]."""

    def solve(self) -> None:
        """Solve the power flow."""

    def node_voltages_pu(self) -> np.ndarray:
        """Every node's voltage [pu]."""

    def readings(self) -> _PvOutput:
        """What the field devices measure (the plants' output among them)."""

__all__ = ["PerturbedEngine", "Sensitivities", "one_step_each", "perturbation_sensitivities"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Sensitivities:
    """Perturbation sensitivities of every node at one state (``FeederEngine.perturbation_sensitivities``).

    Attributes
    ----------
    dv_dq : (n_nodes, K) to each plant's reactive power [pu/kvar]; a column is NaN when the plant has less
        than 1 kvar of headroom.
    dv_dtap : (n_nodes, R) to each regulator's tap [pu/step].
    dv_dp : (n_nodes, K) to each plant's active power output, per kW of its measured output [pu/kW]; a
        column is NaN when the plant's output could not be moved by 1 kW.
    restore_drift_pu : largest difference of the node voltages solved after the moves were undone from those
        before [pu]. The set points and taps are restored exactly, but a power flow need not land on the same
        solution: on epri-ckt24 at night (PV off; exponential CVR loads on the secondaries) a +100 kvar excursion
        and back moved it by 3.3e-4 pu, and one tap by 6.8e-4 pu, both converged (training saw this).
    """

    dv_dq: np.ndarray
    dv_dtap: np.ndarray
    dv_dp: np.ndarray
    restore_drift_pu: float = 0.0


def one_step_each(engine: PerturbedEngine, positions0: np.ndarray, top: np.ndarray,
                  set_positions: Callable[[np.ndarray], None], read: Callable[[], np.ndarray],
                  read0: np.ndarray) -> np.ndarray:
    """The change of ``read()`` per step of each device (taps or bank steps), one device at a time.

    Device ``i`` moves one step up from ``positions0`` (down when at its ``top`` position), the others stay at
    ``positions0``; the engine is solved and ``(read() - read0) / step`` is column ``i``. The engine is left in
    the last moved state: the caller restores ``positions0``.

    Parameters
    ----------
    engine : the solved engine (``solve`` is called after each move).
    positions0 : (N,) int, the devices' positions [steps]. top : (N,) their highest positions [steps].
    set_positions : applies (N,) positions (``engine.set_taps`` or ``engine.set_cap_states``).
    read : what is differenced, a 1-D array of the solved state. read0 : ``read()`` at ``positions0``.

    Returns
    -------
    (read0.size, N) change per step [the unit of ``read``, per step].
    """
    out = np.zeros((read0.size, len(positions0)))
    for i in range(len(positions0)):
        step = 1 if positions0[i] < top[i] else -1
        moved = np.array(positions0, copy=True)
        moved[i] += step
        set_positions(moved)
        engine.solve()
        out[:, i] = (read() - read0) / step
    return out


def perturbation_sensitivities(engine: PerturbedEngine, dq_kvar: float = 100.0, dp_kw: float = 100.0, *,
                               restore: bool = True) -> Sensitivities:
    """Voltage sensitivities by perturbation from the present state (the case-A oracle).

    Each plant's Q is moved by ``dq_kvar`` (upwards, or downwards when the headroom is short), each
    plant's available P by ``dp_kw`` (downwards, or upwards when it produces less), and each regulator
    by one tap (up, or down at the top tap), one at a time; each is solved and differenced against the
    present solution, then undone. ``dv_dp`` is per kW of the plant's measured output change; when the
    raised output clips the plant's Q to its headroom, the Q change's share is taken off by ``dv_dq``.
    With ``restore`` the set points and taps are restored (checked; ``EngineError`` otherwise) and solved again,
    and how far the voltages landed from before is returned (``restore_drift_pu``); without it the engine is
    left in its last perturbed state (the oracle's twin, which is put in state before every use).
    """
    engine.solve()
    v0 = engine.node_voltages_pu()
    p0, q0 = engine.pv_setpoints()
    t0 = engine.taps()
    headroom = np.sqrt(np.maximum(engine.pv_kva**2 - p0**2, 0.0))
    dv_dq = np.full((len(v0), len(q0)), np.nan)
    for k in range(len(q0)):
        up, down = headroom[k] - q0[k], headroom[k] + q0[k]
        dq = min(dq_kvar, up) if up >= down else -min(dq_kvar, down)
        if abs(dq) < 1.0:
            continue
        q = q0.copy()
        q[k] += dq
        applied = engine.set_pv(p0, q)
        engine.solve()
        dv_dq[:, k] = (engine.node_voltages_pu() - v0) / (applied[k] - q0[k])
    engine.set_pv(p0, q0)
    dv_dp = np.full((len(v0), len(p0)), np.nan)
    out0 = engine.readings().pv_p_kw.sum(axis=1)
    for k in range(len(p0)):
        p = p0.copy()
        p[k] += -dp_kw if p0[k] >= dp_kw else min(dp_kw, engine.pv_pmpp_kw[k] - p0[k])
        applied = engine.set_pv(p, q0)
        engine.solve()
        moved = float(engine.readings().pv_p_kw[k].sum() - out0[k])
        dv = engine.node_voltages_pu() - v0
        if applied[k] != q0[k]:
            dv = dv - dv_dq[:, k] * (applied[k] - q0[k])  # NaN when Q cannot be moved either
        if abs(moved) >= 1.0:
            dv_dp[:, k] = dv / moved
    engine.set_pv(p0, q0)
    dv_dtap = one_step_each(engine, t0, engine.reg_tap_max, engine.set_taps, engine.node_voltages_pu, v0)
    if not restore:
        return Sensitivities(dv_dq=dv_dq, dv_dtap=dv_dtap, dv_dp=dv_dp)
    engine.set_taps(t0)
    engine.solve()
    drift = float(np.max(np.abs(engine.node_voltages_pu() - v0))) if len(v0) else 0.0
    p1, q1 = engine.pv_setpoints()
    if not (np.array_equal(engine.taps(), t0) and np.array_equal(q1, q0) and np.array_equal(p1, p0)):
        raise EngineError("perturbation_sensitivities: set points or taps not restored")
    if drift >= 100 * engine.tolerance:
        log.info("perturbation_sensitivities: the restored state solved %.2e pu away from before", drift)
    return Sensitivities(dv_dq=dv_dq, dv_dtap=dv_dtap, dv_dp=dv_dp, restore_drift_pu=drift)
