"""A run's time series reduced for plotting (``RunTrace``), built step by step from truth frames (``TruthSeries``),
and its file form for the no-control baseline that ``cvvc run`` simulates beside the run (``baseline_trace.npz``).

Pure NumPy: ``cvvc.launch`` fills a ``TruthSeries`` from the baseline's simulated steps, ``cvvc.report`` from the
recording's ``sim/truth`` frames; both reduce the same way (10-minute averages of the voltage envelope and of each
plant's Q, taps and capacitor states at every step), so the case and the baseline are drawn on the same footing.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cvvc.extreme_minutes import ExtremeMinute
from cvvc.step_effect import TapStepEffect
from simulator_bridge.simulation.live_accuracy import LiveAccuracy

__all__ = ["BASELINE_TRACE", "WINDOW_STEPS", "LimitMinutes", "NodeTrace", "RunTrace", "SideMoves", "TruthSeries",
           "read_series", "write_series", "window_envelope_pu"]

WINDOW_STEPS = 10  # 10-minute averages at the 1-minute step
BASELINE_TRACE = "baseline_trace.npz"  # the no-control baseline's series in a ``cvvc run`` folder


@dataclass(frozen=True)
class SideMoves:
    """The tap steps the map's regulators moved up (``up``) and down (``down``) while the decision in force saw one
    ``side`` of the optimization limits crossed at some critical node before its action: ``over`` (estimate + bound
    over the upper limit), ``under`` (estimate - bound under the lower one), ``both`` or ``neither``; or ``before the
    first decision``. A step's taps against the decision of an earlier step, as ``LimitMinutes``.
    """

    side: str
    up: int
    down: int


@dataclass(frozen=True)
class LimitMinutes:
    """The minutes with any node under (``under``) or over (``over``) the optimization limits, while the decision in
    force was of one ``kind``: ``optimal``, ``soft form`` (eq. 17), ``taps held by the tap deadband``, ``hold``, or
    ``before the first decision``. A step's truth is taken before that step's decision acts: the decision in force
    is the latest of an earlier step.
    """

    kind: str
    under: int
    over: int


@dataclass(frozen=True)
class NodeTrace:
    """One critical node at every decision (``t_ns`` (D,)): the estimate, its bounds as promised and the truth [pu];
    ``accuracy`` the run's live figures (``simulator_bridge.simulation.live_accuracy``) over every estimated node.
    """

    node: str
    t_ns: np.ndarray
    v_est_pu: np.ndarray
    bound_low_pu: np.ndarray
    bound_high_pu: np.ndarray
    v_true_pu: np.ndarray
    accuracy: LiveAccuracy


@dataclass(frozen=True)
class RunTrace:
    """One run's recording reduced for plotting. Times are ``t_ns`` of the window's first step.

    ``v_env_*`` are (W,) max/min over nodes of the 10-minute average voltage [pu]; ``taps`` (T, R) the taps at
    every step ``step_t_ns`` (T,); ``pv_q_kvar`` (W, K) 10-minute averages [kvar, + injects]; ``err_t_ns`` (D,)
    decision times with ``err_max_pu``/``err_min_pu``/``err_rms_pu`` over the estimated nodes, and ``errors_pu``
    every error. ``cap_states`` (T, C) each capacitor bank's closed steps at every step (C = 0 without banks).
    """

    t_ns: np.ndarray
    step_t_ns: np.ndarray
    v_env_max_pu: np.ndarray
    v_env_min_pu: np.ndarray
    taps: np.ndarray
    pv_q_kvar: np.ndarray
    regulator_ids: tuple[str, ...]
    pv_ids: tuple[str, ...]
    err_t_ns: np.ndarray
    err_max_pu: np.ndarray
    err_min_pu: np.ndarray
    err_rms_pu: np.ndarray
    errors_pu: np.ndarray
    limits_pu: tuple[float, float]
    cap_states: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    capacitor_ids: tuple[str, ...] = ()
    worst: NodeTrace | None = None  # the critical node whose bounds missed most often
    tap_steps: tuple[TapStepEffect, ...] = ()  # each regulator's single steps against the model (``cvvc.step_effect``)
    limit_minutes: tuple[LimitMinutes, ...] = ()  # minutes outside the optimization limits by the decision in force
    side_moves: tuple[SideMoves, ...] = ()  # tap steps by the side of the limits the decision in force saw crossed
    extremes: tuple[ExtremeMinute, ...] = ()  # the lowest and highest minutes, with what moved before them


def window_envelope_pu(v_pu: np.ndarray, window_steps: int = WINDOW_STEPS) -> tuple[np.ndarray, np.ndarray]:
    """Max and min over nodes of the per-node ``window_steps`` average voltage (paper Fig. 9).

    Parameters
    ----------
    v_pu : (T, N) node voltages [pu]; a last partial window is averaged over the steps it has.

    Returns
    -------
    (W,) max and (W,) min [pu], W = ceil(T / window_steps).
    """
    v = np.asarray(v_pu, dtype=float)
    n_win = -(-v.shape[0] // window_steps)
    means = np.stack([v[w * window_steps:(w + 1) * window_steps].mean(axis=0) for w in range(n_win)])
    return means.max(axis=1), means.min(axis=1)


class TruthSeries:
    """The plotted series of a run, one step at a time with bounded memory per step (nothing per node is kept).

    ``add`` takes a step's true voltages of every node [pu], taps, each plant's Q [kvar, generator convention]
    and each bank's closed steps; ``trace`` gives the :class:`RunTrace` (no estimates: those come from decisions).
    """

    def __init__(self, window_steps: int = WINDOW_STEPS) -> None:
        self.window_steps = window_steps
        self.t_ns: list[int] = []
        self.step_t_ns: list[int] = []
        self.v_max: list[float] = []
        self.v_min: list[float] = []
        self.taps: list[list[int]] = []
        self.caps: list[list[int]] = []
        self.pv_q: list[np.ndarray] = []
        self._acc_v = self._acc_q = np.zeros(0)
        self._n = 0

    def add(self, t_ns: int, v_pu: np.ndarray, taps: np.ndarray, pv_q_kvar: np.ndarray,
            cap_states: np.ndarray) -> None:
        """One step of the run at ``t_ns`` [ns since the UTC epoch]."""
        v, q = np.asarray(v_pu, dtype=float), np.asarray(pv_q_kvar, dtype=float)
        self.step_t_ns.append(int(t_ns))
        self.taps.append(np.asarray(taps).astype(int).tolist())
        self.caps.append(np.asarray(cap_states).astype(int).tolist())
        if self._n == 0:
            self.t_ns.append(int(t_ns))
            self._acc_v, self._acc_q = v.copy(), q.copy()
        else:
            self._acc_v += v
            self._acc_q += q
        self._n += 1
        if self._n == self.window_steps:
            self._close_window()

    def _close_window(self) -> None:
        self.v_max.append(float((self._acc_v / self._n).max()))
        self.v_min.append(float((self._acc_v / self._n).min()))
        self.pv_q.append(self._acc_q / self._n)
        self._n = 0

    def trace(self, *, regulator_ids: tuple[str, ...] = (), pv_ids: tuple[str, ...] = (),
              limits_pu: tuple[float, float] = (0.965, 1.05), capacitor_ids: tuple[str, ...] = ()) -> RunTrace:
        """The series so far (a last partial window averaged over the steps it has) as a :class:`RunTrace`."""
        if self._n:
            self._close_window()
        n_pv = len(self.pv_q[0]) if self.pv_q else 0
        steps = len(self.step_t_ns)
        empty = np.zeros(0)
        return RunTrace(
            t_ns=np.asarray(self.t_ns, dtype=np.int64), step_t_ns=np.asarray(self.step_t_ns, dtype=np.int64),
            v_env_max_pu=np.asarray(self.v_max), v_env_min_pu=np.asarray(self.v_min),
            taps=np.asarray(self.taps, dtype=float).reshape(steps, -1),
            pv_q_kvar=np.asarray(self.pv_q).reshape(-1, n_pv), regulator_ids=regulator_ids, pv_ids=pv_ids,
            err_t_ns=np.zeros(0, dtype=np.int64), err_max_pu=empty, err_min_pu=empty, err_rms_pu=empty,
            errors_pu=empty, limits_pu=limits_pu, cap_states=np.asarray(self.caps, dtype=float).reshape(steps, -1),
            capacitor_ids=capacitor_ids)


def write_series(path: str | Path, trace: RunTrace) -> Path:
    """Write a trace's plotted series (no estimates) to ``path`` (``.npz``); returns the path."""
    p = Path(path)
    with p.open("wb") as f:
        np.savez_compressed(f, t_ns=trace.t_ns, step_t_ns=trace.step_t_ns, v_env_max_pu=trace.v_env_max_pu,
                            v_env_min_pu=trace.v_env_min_pu, taps=trace.taps, pv_q_kvar=trace.pv_q_kvar,
                            cap_states=trace.cap_states, limits_pu=np.asarray(trace.limits_pu, dtype=float),
                            regulator_ids=np.asarray(trace.regulator_ids, dtype=str),
                            pv_ids=np.asarray(trace.pv_ids, dtype=str),
                            capacitor_ids=np.asarray(trace.capacitor_ids, dtype=str))
    return p


def read_series(path: str | Path) -> RunTrace:
    """The trace :func:`write_series` wrote (``ValueError``/``OSError``/``KeyError`` when it is not one)."""
    with np.load(Path(path), allow_pickle=False) as z:
        empty = np.zeros(0)
        lo, hi = (float(x) for x in z["limits_pu"])
        return RunTrace(
            t_ns=z["t_ns"].astype(np.int64), step_t_ns=z["step_t_ns"].astype(np.int64),
            v_env_max_pu=z["v_env_max_pu"], v_env_min_pu=z["v_env_min_pu"], taps=z["taps"],
            pv_q_kvar=z["pv_q_kvar"], regulator_ids=tuple(str(x) for x in z["regulator_ids"]),
            pv_ids=tuple(str(x) for x in z["pv_ids"]), err_t_ns=np.zeros(0, dtype=np.int64), err_max_pu=empty,
            err_min_pu=empty, err_rms_pu=empty, errors_pu=empty, limits_pu=(lo, hi), cap_states=z["cap_states"],
            capacitor_ids=tuple(str(x) for x in z["capacitor_ids"]))
