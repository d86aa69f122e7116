"""The stateful CVVC controller: one aligned measurement snapshot in, one decision out (paper II.E, III).

It holds the model, the configuration, the last known value of every device and the previous solution
(for the solver's warm start), and nothing else; it knows no clock, bus or file (the runtime does).

Hold rule (what happens when frames are missing or invalid; a frame flagged valid but holding a non-finite
or impossible value is treated as invalid and listed in ``Decision.missing``):

- feeder-head frame missing/invalid -> ``hold``: no commands at all (devices keep their last valid commands
  until those expire, then local control);
- PV plant frame missing/invalid -> the plant's last known P and Q stand in for the estimate, its Q is fixed
  at that last known value in the optimization and it gets no command; never seen yet -> ``hold``;
- regulator frame missing/invalid -> its last known tap stands in for the estimate, it is not moved
  (``max_taps_per_interval`` 0), gives no correction (eq. 6) and gets no command; never seen yet -> ``hold``;
- capacitor bank frame missing/invalid (stale), or its last command refused (``refuse_bank``) -> the bank is
  held: its last known state (the training state before any frame) stands in, it is not switched and gets no
  command. A bank never blocks the decision.

Capacitor banks (beyond the paper, docs/method.md "Capacitor decisions") enter the CVVC problem as integer
devices beside the taps: closed steps within ``0..steps``, at most ``max_switches_per_interval`` switchings,
``cost_per_switch`` per step switched, their voltage effect ``dv_dcap_pu`` per step. They are relaxed and
rounded with the taps (``agent.solve``), and the decided states are sent as ``CapCommand`` s.

Determinism: same snapshots in the same order give bit-identical decisions (``Decision.same_content``),
timings aside. The solver is warm-started only from the previous decision's solution and has fixed
settings and iteration limits (``agent.solve``).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Iterable
from typing import Literal

import numpy as np
from scipy.stats import norm

from agent.ami import AmiReadings
from agent.bank_rows import local_bank_rows, predicted_banks
from agent.cvvc_qp import CvvcInputs
from agent.decision import Decision, MeasurementSnapshot, SolveRole
from agent.drift import DriftMargin
from agent.errors import AgentInputError
from agent.setpoints import (
    MeasuredSteps,
    expected_compared_v120,
    narrow_held_bands,
    setpoint_for_tap_change,
    with_measured_steps,
)
from agent.solve import CvvcSolution, WarmStart, solve_cvvc
from agent.stale_plants import StalePlants, stale_rise_pu
from agent.state import (
    CorrectionFilter,
    CorrectionNoise,
    GridState,
    OracleSource,
    estimated_state,
    filter_gap_bounds_pu,
    noise_bounds_pu,
    oracle_state,
)
from agent.tap_moves import TapMoves
from regression.estimator import SensitivityTable, dv_dp_pu_per_kw, pv_variability_margins_pu
from regression.model import CvvcModel, ModelArrays, features
from schemas.devicemap import MeterSpec
from schemas.messages import Timings
from schemas.settings import AgentOptions

__all__ = ["CvvcController", "Decision", "MeasurementSnapshot"]

#: Plausible ranges; a value outside makes its frame invalid (the schemas bound the wire values already).
_V120_RANGE = (60.0, 180.0)
_POWER_LIMIT_KW = 1e6
NOISY_READING_STEPS = 0.25  # readings noisier than this share of a tap step: the bounds' gap from their window mean
# (chosen on epri-m1's noiseless day, whose load moves the readings by up to 0.1 step between minutes, and the rural
# winter with 1 % SCADA noise, 1.6 steps: judged on epri-k1 and the noiseless rural winter)
OUT_OF_ENVELOPE_WIDEN = 2.0  # on the calibrated estimate bounds when the inputs leave the training envelope
_MIN_BAND_PU = 1e-3  # the narrowest band the estimate bounds leave between a node's limits [pu]
PRECISION_OUTLIER = 3.0  # precision_weights: bounds wider than this many times the median node's weigh less
STALE_PLANT_AGE_S = 150.0
"""A plant's stand-in frame older than this [s] (two lost 1-minute frames and more: an outage, not a dropped frame)
is treated by ``agent.stale_plants``; a younger one as it is (20 % of the frames lost at random: stand-ins of a
minute, and the rule at every one of them took the rural winter week from 20 to 144 tap changes)."""


_SHIPPED = AgentOptions()  # the shipped agent's options (``schemas.settings``), written there once


def precision_weights(bound_low_pu: np.ndarray, bound_high_pu: np.ndarray) -> np.ndarray:
    """(N,) weights of the nodes' squared violations in the soft form: ``(PRECISION_OUTLIER * median / bound)^2``,
    at most 1.

    A node's bound is the mean of its two calibrated bounds [pu]. A node whose estimate is more than
    ``PRECISION_OUTLIER`` times as uncertain as the median node's (a deep secondary that no feeder-level measurement
    sees, whose bounds close the band) weighs the square of that ratio's inverse, so it cannot move the whole feeder
    for a violation its estimate cannot confirm; every other node weighs 1, as in the paper's eq. (17).
    """
    width = 0.5 * (np.asarray(bound_low_pu, float) + np.asarray(bound_high_pu, float))
    ref = PRECISION_OUTLIER * float(np.median(width)) if width.size else 0.0
    if ref <= 0.0:
        return np.ones(width.size)
    return np.minimum(1.0, (ref / np.maximum(width, ref * 1e-3)) ** 2)


def _finite(*arrays: np.ndarray) -> bool:
    return all(bool(np.all(np.isfinite(a))) for a in arrays)


class CvvcController:
    """Estimation (eq. 5-7), sensitivities (eq. 3-4), CVVC (eq. 9-17) and eq. (8), with the hold rule.

    ``options`` are the settings tree's (``schemas.settings.AgentOptions``; the runtime passes its
    ``AgentSettings``), by default the shipped agent's; ``schemas.settings.PAPER_AGENT`` is the paper's method (every
    option beyond it off). Those the controller reads:

    Parameters
    ----------
    model : the trained model.
    options : the agent's options, below.
    mode : ``taps`` (command tap positions: cases A/B) or ``setpoints`` (command eq. 8 set points and
        bands: cases C/D).
    correction : apply the eq. (6)-(7) correction from regulator secondary voltages.
    meters : the device map's AMI meters (``AgentSettings.meters``): the only meters whose readings count
        (``agent.ami``); none by default.

    Options
    -------
    bandwidth_v120 : regulator bandwidth ``B`` sent with set points [V on 120 V base] (paper case C: 4 V).
    pv_margin_window_s : beyond the paper: tighten each node's limits by how far its voltage would move if the
        plants went back to their highest or lowest output of this many recent seconds (control steps seen);
        0 turns it off (the paper's method). See ``regression.estimator.pv_variability_margins_pu``.
    pv_margin_cap_pu : largest such margin on either side [pu].
    control_banks : beyond the paper: decide and command the model's capacitor banks (integer devices of the CVVC
        problem). Off, the banks stay on their local control; their measured state still corrects the estimate.
    setpoint_hold : beyond the paper, ``setpoints`` mode: when no tap change is decided for a regulator and the
        set point sent to it at most two control periods ago is still in force, send that set point again
        instead of eq. (8)'s re-centred one (a noisy regulator reading then cannot move the band).
    sensitivity_error : beyond the paper, soft form (eq. 17): the relative error assumed for the estimated Q
        sensitivities [-] (see ``CvvcInputs.dv_dq_rel_error``); 0: the paper's eq. (17). Case A's oracle
        sensitivities are the power flow's own and get none.
    bounds_in_margin : the optimization limits lie inside the judged ones (0.975-1.04 against 0.965-1.05): let that
        gap take the calibrated bounds first, so a node's limit is tightened only by what of its bound exceeds the
        gap, i.e. to the judged limit less the bound when that is tighter. Off: the bounds come on top of the gap.
    filtered_setpoints : beyond the paper, ``setpoints`` mode with the correction and its filter (case D; case C keeps
        the paper's eq. 8 on the reading): eq. (8)'s ``V_s^1`` starts
        from the corrected estimate at the regulator's secondary plus the filtered difference between the raw
        reading and that estimate (a second ``CorrectionFilter``), instead of the compared reading itself: the
        reading's noise then moves the band by a fraction of itself. Line-drop compensation (the compared minus the
        raw reading) is added as read where the readings are quiet (``NOISY_READING_STEPS``), filtered where noisy.
    stale_plants : beyond the paper: a plant behind a stand-in frame older than ``STALE_PLANT_AGE_S`` is taken as
        ``agent.stale_plants`` says (P projected from the fresh plants, Q our command in force and not raised, its
        P's own variability margin).
    valid_intervals : how many control periods a command stays in force after its step (the runtime's too): how
        long ``stale_plants`` takes our last Q command as the plant's Q.
    correction_window_s, bounds_cover_filter, predict_banks, tap_reversal_lockout_s, drift_margin,
    tap_deadband_hold_s : see ``schemas.settings.AgentOptions``.
    """

    def __init__(
        self,
        model: CvvcModel,
        options: AgentOptions = _SHIPPED,
        *,
        mode: Literal["taps", "setpoints"],
        correction: bool,
        meters: Iterable[MeterSpec] = (),
    ) -> None:
        o = options
        if mode not in ("taps", "setpoints"):
            raise AgentInputError(f"mode must be 'taps' or 'setpoints', not {mode!r}")
        steps = np.array([r.step_v120 for r in model.regulators], float)
        if mode == "setpoints" and not (np.isfinite(o.bandwidth_v120) and np.all(o.bandwidth_v120 > steps)):
            raise AgentInputError(
                f"bandwidth {o.bandwidth_v120} V must exceed one tap step ({steps.max(initial=0.0)} V); use e.g. 4"
            )
        if not (np.isfinite(o.pv_margin_window_s) and o.pv_margin_window_s >= 0.0):
            raise AgentInputError(f"pv_margin_window_s must be >= 0, not {o.pv_margin_window_s}")
        if not (np.isfinite(o.pv_margin_cap_pu) and 0.0 <= o.pv_margin_cap_pu <= 0.05):
            raise AgentInputError(f"pv_margin_cap_pu must be within 0 to 0.05 pu, not {o.pv_margin_cap_pu}")
        if not (np.isfinite(o.correction_window_s) and o.correction_window_s >= 0.0):
            raise AgentInputError(f"correction_window_s must be >= 0, not {o.correction_window_s}")
        if not (np.isfinite(o.sensitivity_error) and 0.0 <= o.sensitivity_error <= 1.0):
            raise AgentInputError(f"sensitivity_error must be within 0 to 1, not {o.sensitivity_error}")
        self.sensitivity_error = float(o.sensitivity_error)
        self.bounds_in_margin = bool(o.bounds_in_margin)
        self.bounds_cover_filter = bool(o.bounds_cover_filter)
        self.predict_banks = bool(o.predict_banks)
        self.soft_precision = bool(o.soft_precision)
        self.setpoint_safety = bool(o.setpoint_safety)
        # the latest decision's problem as solved and the arguments it was built from: (inputs, snapshot, state, out of
        # envelope, plants); read by ``cvvc.explain`` to take the problem apart, never by the decisions
        self.last_problem: tuple[CvvcInputs, MeasurementSnapshot, GridState, bool, tuple] | None = None
        self.model = model
        self.mode = mode
        # eq. (6)'s corrections, and eq. (8)'s residual and line-drop compensation, averaged over about an hour
        weight = min(1.0, float(model.control_period_s) / o.correction_window_s) if o.correction_window_s > 0 else 0.0
        self._eps_filter = CorrectionFilter(len(model.regulators), weight) if weight > 0 else None
        setpoint_filters = correction and weight > 0 and o.filtered_setpoints
        self._cmp_filter = CorrectionFilter(len(model.regulators), weight) if setpoint_filters else None
        self._ldc_filter = CorrectionFilter(len(model.regulators), weight) if setpoint_filters else None
        self.correction = correction
        self.bandwidth_v120 = float(o.bandwidth_v120)
        self._arrays = ModelArrays.of(model)
        self._margin_window_ns = int(o.pv_margin_window_s * 1e9)
        self._margin_cap_pu = float(o.pv_margin_cap_pu)
        self._dv_dp = dv_dp_pu_per_kw(self._arrays, model.feature_names, len(model.pv))
        self._recent_pv_p: deque[tuple[int, np.ndarray]] = deque()  # (t_ns, (K,) P) at recent decisions
        self._drift = DriftMargin(int(model.control_period_s) * 1_000_000_000, o.pv_margin_cap_pu) \
            if o.drift_margin else None
        self._drift_pu: tuple[np.ndarray, np.ndarray] | None = None  # this decision's (fall, rise) drift margins
        self._sens = SensitivityTable.of(model.sens_q)
        self._pv_ids = tuple(p.id for p in model.pv)
        self._reg_ids = tuple(r.id for r in model.regulators)
        self._pv_rating_kva = np.array([p.kva for p in model.pv], float)
        self._pv_cost = np.array([p.cost_per_kvar for p in model.pv], float)
        regs = model.regulators
        self._tap_min = np.array([r.tap_min for r in regs], int)
        self._tap_max = np.array([r.tap_max for r in regs], int)
        self.tap_moves = TapMoves(o, self._tap_min, self._tap_max)  # reversal locks, tap deadband, rent or buy
        self._max_taps = np.array([r.max_taps_per_interval for r in regs], int)
        self._tap_cost = np.array([r.cost_per_tap for r in regs], float)
        self._step_v120 = steps
        # each regulator's step on its compared reading, measured at its own moves (eq. 8 lands with it)
        self._measured_steps = MeasuredSteps(steps) if o.measured_tap_step else None
        # Last known values (None until first seen) and the previous solution.
        n_pv, n_reg = len(model.pv), len(regs)
        self._pv_last_p_kw: list[float | None] = [None] * n_pv
        self._pv_last_q_kvar: list[float | None] = [None] * n_pv
        self._reg_last_tap: list[int | None] = [None] * n_reg
        self._warm: WarmStart | None = None
        self.setpoint_hold = bool(o.setpoint_hold)
        self.control_banks = bool(o.control_banks)
        self._setpoint_hold_ns = 2 * int(model.control_period_s) * 1_000_000_000  # commands' validity
        self._last_setpoint: list[tuple[int, float] | None] = [None] * n_reg  # (t_ns, V on 120 V) last sent
        b = model.bounds  # calibrated estimate bounds and the training envelope (training.calibration)
        self._bound_lo = None if b is None else np.asarray(b.lower_pu, float)
        self._bound_hi = None if b is None else np.asarray(b.upper_pu, float)
        self._env = None if b is None else (np.asarray(b.envelope_lo, float), np.asarray(b.envelope_hi, float))
        # this decision's eq. (6) correction as computed minus as applied through the filter, per regulator [pu]
        self._filter_gap_pu = np.zeros(len(model.regulators))
        # noisy readings: the filtered correction's own noise, from the mean square of that gap (``noise_bounds_pu``)
        self._noise_z = float(norm.ppf(1.0 - b.alpha / 2.0)) if b is not None and 0.0 < b.alpha < 1.0 else 0.0
        self._noise_pu = np.zeros(len(model.regulators))  # this decision's filtered-correction noise [pu]
        self._correction_noise = (CorrectionNoise(len(model.regulators), self._eps_filter.weight)
                                  if self._eps_filter is not None else None)
        self.ami = AmiReadings(model, meters)  # AMI meter readings (explicit option): the map's meters only
        banks = model.capacitors
        self._cap_ids = tuple(c.id for c in banks)
        self._cap_steps_max = np.array([c.steps for c in banks], int)
        self._cap_max_sw = np.array([c.max_switches_per_interval for c in banks], int)
        self._cap_cost = np.array([c.cost_per_switch for c in banks], float)
        self._cap_last = np.array([c.closed0 for c in banks], int)  # last known state (training state at first)
        self._cap_refused_until = np.full(len(banks), -1, dtype=np.int64)  # t_ns until which a bank is held
        self._period_ns = int(model.control_period_s) * 1_000_000_000
        self.stale_plants = bool(o.stale_plants)
        # our Q command is in force as long as the runtime's commands are valid (``AgentSettings.valid_intervals``)
        self._stale = StalePlants(self._pv_rating_kva, int(o.valid_intervals * self._period_ns))

    def measured_steps_v120(self) -> dict[str, float]:
        """Each regulator's tap step as its compared reading measured it, by id, those measured so far [V on 120 V]."""
        if self._measured_steps is None:
            return {}
        return {rid: round(float(v), 4) for rid, v in zip(self._reg_ids, self._measured_steps.step_v120(), strict=True)
                if np.isfinite(v)}

    # ------------------------------------------------------------------------------------------ bounds
    def bounds_pu(self, out_of_envelope: bool) -> tuple[np.ndarray, np.ndarray] | None:
        """``(low, high)`` bounds [pu] of the critical-node estimates as applied: the calibrated ones, widened by
        :data:`OUT_OF_ENVELOPE_WIDEN` when the inputs are outside the training envelope; None without bounds.
        """
        if self._bound_lo is None or self._bound_hi is None:
            return None
        widen = OUT_OF_ENVELOPE_WIDEN if out_of_envelope else 1.0
        lo, hi = widen * self._bound_lo, widen * self._bound_hi
        if self.bounds_cover_filter:
            lo, hi = filter_gap_bounds_pu(lo, hi, self._filter_gap_pu, self._arrays.upstream_regulator)
            lo, hi = noise_bounds_pu(lo, hi, self._noise_z * self._noise_pu, self._arrays.upstream_regulator)
        return self.ami.bounds(lo, hi)

    def envelope_problem(self, x: np.ndarray) -> str:
        """The features of ``x`` (M,) outside the training envelope, as text ("" when inside or no envelope)."""
        if self._env is None:
            return ""
        lo, hi = self._env
        out = np.flatnonzero((x < lo) | (x > hi))
        return ", ".join(f"{self.model.feature_names[i]} {x[i]:.0f} outside [{lo[i]:.0f}, {hi[i]:.0f}]"
                         for i in out[:4]) + (f" and {out.size - 4} more" if out.size > 4 else "")

    def refuse_bank(self, capacitor_id: str, t_ns: int) -> bool:
        """A bank refused the command of step ``t_ns``: hold it (no switching, no command) for two periods.

        Returns False for an id the model does not know (nothing changes).
        """
        if capacitor_id not in self._cap_ids:
            return False
        c = self._cap_ids.index(capacitor_id)
        self._cap_refused_until[c] = max(int(self._cap_refused_until[c]), int(t_ns) + 2 * self._period_ns)
        return True

    def _hold(
        self,
        snap: MeasurementSnapshot,
        reason: str,
        missing: tuple[str, ...],
        started: tuple[float, float],
        *,
        state: GridState | None = None,
        solution: CvvcSolution | None = None,
        solves: tuple[tuple[SolveRole, CvvcSolution], ...] = (),
        estimate_s: float = 0.0,
    ) -> Decision:
        """The one constructor of a ``hold``: no commands; the state and solver figures reached, if any.

        ``state`` (when the grid state was built) gives the reported estimates (critical nodes only),
        ``solution`` (when the solver ran) its iterations, status and stage times, ``solves`` every solve the
        decision made; ``started`` is ``(time.perf_counter(), time.thread_time())`` at the start of the decision
        (``decide``'s).
        """
        if self._drift is not None:
            self._drift.forget()
        n_pv, n_reg = len(self._pv_ids), len(self._reg_ids)
        report = state is not None and state.critical
        sec = solution.seconds if solution is not None else None
        return Decision(
            t_ns=int(snap.t_ns),
            status="hold",
            reason=reason,
            pv_q_kvar=None,
            pv_command=np.zeros(n_pv, bool),
            reg_tap=None,
            reg_setpoint_v120=None,
            reg_band_v120=None,
            reg_command=np.zeros(n_reg, bool),
            v_pu=state.v0_pu if report and state is not None else None,
            v_pred_pu=None,
            corrected=state.corrected if state is not None else False,
            dv_dq_pu_per_kvar=state.dv_dq_pu_per_kvar if report and state is not None else None,
            missing=missing,
            iterations=solution.iterations if solution is not None else 0,
            objective=0.0,
            solver_status=solution.status if solution is not None else "not run",
            cap_command=np.zeros(len(self._cap_ids), bool),
            solves=solves,
            timings=Timings(
                estimate_s=float(estimate_s),
                solve_s=sec.build_s + sec.relaxed_s if sec is not None else 0.0,
                round_s=sec.rounding_s if sec is not None else 0.0,
                total_s=time.perf_counter() - started[0],
                cpu_s=time.thread_time() - started[1],
            ),
        )

    def _usable(self, snap: MeasurementSnapshot) -> tuple[bool, np.ndarray, np.ndarray]:
        """Which frames are usable: valid flag set and values finite and plausible (a NaN fails every comparison)."""
        head_p, head_q = np.asarray(snap.head_p_kw, float), np.asarray(snap.head_q_kvar, float)
        head_ok = bool(snap.head_valid) and bool((np.abs(head_p) < _POWER_LIMIT_KW).all()
                                                 and (np.abs(head_q) < _POWER_LIMIT_KW).all())
        pv_p, pv_q = np.asarray(snap.pv_p_kw, float), np.asarray(snap.pv_q_kvar, float)
        kva = np.asarray(snap.pv_kva_available, float)
        pv_ok = (np.asarray(snap.pv_valid, bool) & np.isfinite(kva) & (kva >= 0.0)
                 & (np.abs(pv_p) < _POWER_LIMIT_KW) & (np.abs(pv_q) < _POWER_LIMIT_KW))
        lo, hi = _V120_RANGE
        v, vc = np.asarray(snap.reg_v120, float), np.asarray(snap.reg_v120_compared, float)
        tap = np.asarray(snap.reg_tap, float)
        reg_ok = (np.asarray(snap.reg_valid, bool) & (lo < v) & (v < hi) & (lo < vc) & (vc < hi)
                  & (tap == np.round(tap)) & (self._tap_min <= tap) & (tap <= self._tap_max))
        return head_ok, pv_ok, reg_ok

    def _reading_noise(self, snap: MeasurementSnapshot) -> tuple[np.ndarray, np.ndarray]:
        """(R,) bool each: the regulators whose readings are quiet, and those whose readings are noisy (above
        ``NOISY_READING_STEPS`` of a tap step); neither where the noise cannot be told (too few readings at the tap).
        """
        if snap.reg_v120_noise is None:
            none = np.zeros(len(self._reg_ids), bool)
            return none, none.copy()
        noise = np.asarray(snap.reg_v120_noise, float)
        limit = NOISY_READING_STEPS * self._step_v120
        return noise <= limit, noise > limit

    def _freshness(self, snap: MeasurementSnapshot) -> tuple[np.ndarray, bool]:
        """(R,) bool the regulators whose frame is this step's own, and whether the head's and every plant's are."""
        fresh = np.full(len(self._reg_ids), True) if snap.reg_fresh is None else np.asarray(snap.reg_fresh, bool)
        return fresh, bool(snap.head_fresh) and (snap.pv_fresh is None or bool(np.all(snap.pv_fresh)))

    def _correction_filter(self, snap: MeasurementSnapshot) -> Callable[[np.ndarray, np.ndarray], np.ndarray] | None:
        """The correction filter for this step (None without a filter): only this step's own readings, with its
        own head and plant frames, enter the mean; with a head or plant frame standing in for a lost one, this
        step's own readings are applied as they are (``CorrectionFilter``).
        """
        filt = self._eps_filter
        self._filter_gap_pu = np.zeros(len(self._reg_ids))
        self._noise_pu = np.zeros(len(self._reg_ids))
        if filt is None:
            return None
        fresh, inputs_fresh = self._freshness(snap)

        # eq. (6) from this step's own reading differs from eq. (6) from the averaged one by the readings' difference
        now = (np.full(len(self._reg_ids), np.nan) if snap.reg_v120_now is None
               else np.asarray(snap.reg_v120_now, float))
        to_now_pu = (now - np.asarray(snap.reg_v120, float)) * self._arrays.reg_pu_per_v120
        # noisy readings: the reading window's mean (noise / sqrt(n)) instead of the last reading (its noise would
        # widen and narrow the bounds at random, every decision)
        quiet, loud = self._reading_noise(snap)
        to_now_pu = np.where(quiet & np.isfinite(to_now_pu), to_now_pu, np.where(np.isfinite(to_now_pu), 0.0, np.nan))

        def apply(eps: np.ndarray, ok: np.ndarray) -> np.ndarray:
            applied = filt(eps, ok, fresh, inputs_fresh=inputs_fresh)
            inst = np.asarray(eps, float) + to_now_pu
            own = np.asarray(ok, bool) & fresh & np.isfinite(inst)
            self._filter_gap_pu = np.where(own, inst - applied, 0.0)
            if self._correction_noise is not None:
                self._noise_pu = self._correction_noise.observe(self._filter_gap_pu, own, loud, quiet | loud)
            return applied

        return apply

    def _compared_v120(self, snap: MeasurementSnapshot, state: GridState, reg_ok: np.ndarray) -> np.ndarray:
        """(R,) the compared voltages eq. (8) starts from [V on the 120 V base]: the readings, or with
        ``filtered_setpoints`` the estimate at each secondary plus the filtered difference between the raw reading and
        that estimate, plus the line-drop compensation (compared minus raw reading): as it is where the readings are
        quiet, filtered where they are noisy.

        Line-drop compensation moves with the load current, and an hour's mean of it lags: on IEEE 123's substation
        regulator (R = 3, X = 7.5) a winter morning's mean was 0.45 V below the reading, and eq. (8) lowered the
        regulator two steps for the one decided. Without compensation the compared reading is the raw one, and
        nothing changes.
        """
        compared = np.asarray(snap.reg_v120_compared, float)
        filt = self._cmp_filter
        if filt is None or self._ldc_filter is None or not state.critical:
            return compared
        raw = np.asarray(snap.reg_v120, float)
        per_v = self._arrays.reg_pu_per_v120
        est_v120 = state.v0_pu[self._arrays.reg_secondary_node] / per_v
        fresh, inputs_fresh = self._freshness(snap)
        residual_pu = filt((raw - est_v120) * per_v, reg_ok, fresh, inputs_fresh=inputs_fresh)
        ldc_pu = self._ldc_filter((compared - raw) * per_v, reg_ok, fresh, inputs_fresh=inputs_fresh)
        quiet, _ = self._reading_noise(snap)  # too few readings at the tap to tell: filtered
        ldc_v120 = np.where(quiet, compared - raw, ldc_pu / per_v)
        return np.where(reg_ok, est_v120 + residual_pu / per_v + ldc_v120, compared)

    def _pv_fresh(self, snap: MeasurementSnapshot) -> np.ndarray:
        """(K,) bool: the plants whose frame is this step's own."""
        n_pv = len(self._pv_ids)
        return np.full(n_pv, True) if snap.pv_fresh is None else np.asarray(snap.pv_fresh, bool).reshape(n_pv)

    def _pv_old(self, snap: MeasurementSnapshot, pv_ok: np.ndarray) -> np.ndarray:
        """(K,) bool: usable plants whose frame is a stand-in older than ``STALE_PLANT_AGE_S`` (or of unknown age)."""
        stand_in = pv_ok & ~self._pv_fresh(snap)
        if snap.pv_age_s is None:
            return stand_in
        return stand_in & (np.asarray(snap.pv_age_s, float).reshape(stand_in.shape) > STALE_PLANT_AGE_S)

    def _plant_inputs(self, snap: MeasurementSnapshot,
                      pv_ok: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The plants as the decision takes them: ``(p_kw, q_kvar, kva, q_max_kvar)``, (K,) each.

        Last known P [kW] and Q [kvar], apparent power available [kVA] and the highest Q the decision may give
        [kvar] (inf: the headroom); with ``stale_plants``, a plant behind a stale frame as ``agent.stale_plants``
        says: P projected from the fresh plants, Q our command in force, not raised from it. No state changes.
        """
        p = np.array(self._pv_last_p_kw, float)
        q = np.array(self._pv_last_q_kvar, float)
        kva = np.asarray(snap.pv_kva_available, float).copy()
        fresh_ok = pv_ok & self._pv_fresh(snap)
        stale = self._pv_old(snap, pv_ok)
        if not (self.stale_plants and np.any(stale)):
            return p, q, kva, np.full(p.size, np.inf)
        p = self._stale.projected_p_kw(p, fresh_ok, stale)
        kva = np.where(stale, np.minimum(np.maximum(kva, p), self._pv_rating_kva), kva)
        headroom = np.sqrt(np.maximum(kva**2 - p**2, 0.0))
        cmd = self._stale.commanded_q_kvar(int(snap.t_ns))
        q = np.where(stale & np.isfinite(cmd), np.clip(np.nan_to_num(cmd), -headroom, headroom), q)
        return p, q, kva, np.where(stale, q, np.inf)

    def _cap_usable(self, snap: MeasurementSnapshot) -> np.ndarray:
        """(C,) bool: banks whose frame is valid with a whole number of closed steps within the bank's."""
        steps = np.asarray(snap.cap_steps, float)
        ok = np.asarray(snap.cap_valid, bool) & np.isfinite(steps)
        ok &= (steps == np.round(steps)) & (steps >= 0) & (steps <= self._cap_steps_max)
        return ok

    def _cap_readings(self, snap: MeasurementSnapshot, cap_ok: np.ndarray) -> np.ndarray:
        """(C,) the usable banks' bus voltage readings [V], NaN elsewhere (and where the snapshot has none)."""
        v = np.asarray(snap.cap_v_v, float)
        if v.shape != cap_ok.shape:
            return np.full(cap_ok.shape, np.nan)
        return np.where(cap_ok, v, np.nan)

    def _cap_movable(self, snap: MeasurementSnapshot, state: GridState) -> np.ndarray:
        """(C,) bool: banks the decision may switch and command (usable, not refused lately, estimator state)."""
        ok = self._cap_usable(snap) & (self._cap_refused_until < int(snap.t_ns))
        return ok & bool(state.critical) & self.control_banks

    def _remember_pv_p(self, t_ns: int, pv_p_kw: np.ndarray) -> None:
        """Record the plants' output of this step in the PV variability margin's window [kW]."""
        if self._margin_window_ns <= 0:
            return
        recent = self._recent_pv_p
        if recent and recent[-1][0] >= t_ns:
            recent.clear()  # a step out of order (the aligner prevents it): start the window again
        while recent and recent[0][0] < t_ns - self._margin_window_ns:
            recent.popleft()
        recent.append((t_ns, pv_p_kw.copy()))

    def problem(self, snap: MeasurementSnapshot, state: GridState, *, out_of_envelope: bool = False,
                plants: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
                locks: Literal["reversals", "none", "all"] = "reversals", margins: bool = True) -> CvvcInputs:
        """The CVVC problem (eq. 9-17) of a snapshot the controller has taken in, over ``state``'s nodes.

        The one inputs builder, whichever the state's source: missing plants fixed at their last Q, missing
        regulators frozen; the optimization limits tightened by the PV variability margin of ``state``'s
        dV/dP over the window recorded so far (or, for estimated critical nodes, by the drift margin where larger,
        ``drift_margin``) and, for estimated critical nodes, by the estimate's calibrated bounds (widened
        ``out_of_envelope``). ``plants``: ``_plant_inputs``'s result for ``snap`` if the caller has it.
        ``locks``: which tap moves are not offered: the reverse of recent moves (``TapMoves.reversal_locks``), none,
        or every one (the taps held). ``margins=False``: without the PV variability and drift margins (what they take
        from the limits, for explanations). No state changes. Raises ``AgentInputError`` on unusable inputs.
        """
        _, pv_ok, reg_ok = self._usable(snap)
        pv_p, pv_q, kva, q_hi = self._plant_inputs(snap, pv_ok) if plants is None else plants
        headroom = np.sqrt(np.maximum(kva**2 - pv_p**2, 0.0))
        lo_pu, hi_pu = self.model.optimization_limits_pu
        v_min_pu: np.ndarray | float = lo_pu
        v_max_pu: np.ndarray | float = hi_pu
        if self._margin_window_ns > 0 and margins:
            rise, fall = self.pv_margins_pu(state.dv_dp_pu_per_kw, pv_p)
            if self.stale_plants and self._recent_pv_p:
                recent = np.array([x for _, x in self._recent_pv_p])
                rise = stale_rise_pu(rise, state.dv_dp_pu_per_kw, pv_p, recent, self._pv_old(snap, pv_ok),
                                     self._margin_cap_pu)
            v_min_pu, v_max_pu = lo_pu + fall, hi_pu - rise
        drift = self._drift_pu if state.critical and margins else None
        if drift is not None and drift[0].shape == state.v0_pu.shape:
            v_min_pu = lo_pu + np.maximum(np.asarray(v_min_pu, float) - lo_pu, drift[0])
            v_max_pu = hi_pu - np.maximum(hi_pu - np.asarray(v_max_pu, float), drift[1])
        bounds = self.bounds_pu(out_of_envelope) if state.critical else None
        soft_weight = None if bounds is None or not self.soft_precision else precision_weights(*bounds)
        if bounds is not None and self.bounds_in_margin:
            (judged_lo, judged_hi), (lo_b, hi_b) = self.model.judged_limits_pu, bounds
            bounds = (np.maximum(lo_b - max(lo_pu - judged_lo, 0.0), 0.0),
                      np.maximum(hi_b - max(judged_hi - hi_pu, 0.0), 0.0))
        if bounds is not None:
            # never past an empty band: a node whose limits are closer than its bounds keeps half its gap (or
            # 1 mV/V) between them, and the soft form then says the hard limits cannot be met
            gap = np.asarray(v_max_pu, float) - np.asarray(v_min_pu, float)
            room = gap - np.minimum(_MIN_BAND_PU, gap / 2.0)
            total = bounds[0] + bounds[1]
            scale = np.where(total > room, room / np.maximum(total, 1e-12), 1.0)
            v_min_pu, v_max_pu = v_min_pu + scale * bounds[0], v_max_pu - scale * bounds[1]
        # Capacitor banks are integer devices after the regulators: closed steps 0..steps, cost per switching.
        movable = self._cap_movable(snap, state)
        n = state.v0_pu.shape[0]
        dv_dcap = self._arrays.dv_dcap_pu if state.critical else np.zeros((n, len(self._cap_ids)))
        v0, dv_dq = state.v0_pu, state.dv_dq_pu_per_kvar
        dv_dtap = np.hstack([np.reshape(state.dv_dtap_pu, (n, -1)), dv_dcap])
        if self.predict_banks and predicted_banks(self.model.capacitors).size:
            # the banks on their local control, predicted: rows after the nodes (agent.bank_rows)
            rows = local_bank_rows(self.model.capacitors, snap.cap_control_value, self._cap_last, movable,
                                   len(self._pv_ids), len(self._reg_ids), v_v=snap.cap_v_v)
            v0, dv_dq = np.concatenate([v0, rows.u0]), np.vstack([dv_dq, rows.du_dq])
            dv_dtap = np.vstack([dv_dtap, rows.du_dtap])
            v_min_pu = np.concatenate([np.broadcast_to(np.asarray(v_min_pu, float), (n,)), rows.lo])
            v_max_pu = np.concatenate([np.broadcast_to(np.asarray(v_max_pu, float), (n,)), rows.hi])
            if soft_weight is not None:
                soft_weight = np.concatenate([soft_weight, np.ones(rows.lo.size)])
        inputs = CvvcInputs(
            v0_pu=v0,
            dv_dq_pu_per_kvar=dv_dq,
            dv_dtap_pu=dv_dtap,
            q0_kvar=pv_q,
            q_min_kvar=np.where(pv_ok, -headroom, pv_q),
            q_max_kvar=np.where(pv_ok, np.minimum(headroom, np.maximum(q_hi, -headroom)), pv_q),
            q_rating_kvar=np.maximum(self._pv_rating_kva, 1.0),
            taps=np.concatenate([state.taps, self._cap_last]).astype(int),
            tap_min=np.concatenate([self._tap_min, np.zeros(len(self._cap_ids), int)]),
            tap_max=np.concatenate([self._tap_max, self._cap_steps_max]),
            max_taps_per_interval=np.concatenate([np.where(reg_ok, self._max_taps, 0),
                                                  np.where(movable, self._cap_max_sw, 0)]),
            cost_per_tap=np.concatenate([self._tap_cost, self._cap_cost]),
            cost_per_kvar=self._pv_cost,
            v_min_pu=v_min_pu,
            v_max_pu=v_max_pu,
            dv_dq_rel_error=self.sensitivity_error if state.critical else 0.0,
            soft_weight=soft_weight,
        )
        return inputs if locks == "none" else self.tap_moves.relocked(inputs, locks, int(snap.t_ns))

    def pv_margins_pu(self, dv_dp_pu_per_kw: np.ndarray, pv_p_kw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(rise, fall)`` PV variability margins [pu] of nodes with these sensitivities (N, K) [pu/kW].

        Over the plants' outputs recorded by ``decide`` in the margin window (this step's included once it has
        decided); zeros when the margin is off. Case A applies it to every node with the oracle's dV/dP.
        """
        n = np.shape(dv_dp_pu_per_kw)[0]
        if self._margin_window_ns <= 0 or not self._recent_pv_p:
            return np.zeros(n), np.zeros(n)
        recent = np.array([p for _, p in self._recent_pv_p])
        return pv_variability_margins_pu(dv_dp_pu_per_kw, pv_p_kw, recent, self._margin_cap_pu)

    def decide(self, snap: MeasurementSnapshot, oracle: OracleSource | None = None, *,
               cpu_started: float | None = None) -> Decision:
        """Decide the actions for one snapshot (see the module docstring for the hold rule).

        ``oracle`` (case A) is asked for the true state of every node at the snapshot's time once the hold
        rule lets the step be decided; without it the estimator gives the state of the critical nodes.
        ``cpu_started``: the thread's CPU clock (``time.thread_time()``) when the step's work began, the snapshot
        included (the runtime's); ``Timings.cpu_s`` counts from it (default: from this call).
        """
        t0 = time.perf_counter()
        started = (t0, time.thread_time() if cpu_started is None else cpu_started)
        n_pv, n_reg = len(self._pv_ids), len(self._reg_ids)
        shapes = {
            "head_p_kw": (snap.head_p_kw, 3), "head_q_kvar": (snap.head_q_kvar, 3),
            "pv_p_kw": (snap.pv_p_kw, n_pv), "pv_q_kvar": (snap.pv_q_kvar, n_pv),
            "pv_kva_available": (snap.pv_kva_available, n_pv), "pv_valid": (snap.pv_valid, n_pv),
            "reg_v120": (snap.reg_v120, n_reg), "reg_v120_compared": (snap.reg_v120_compared, n_reg),
            "reg_tap": (snap.reg_tap, n_reg), "reg_valid": (snap.reg_valid, n_reg),
            "cap_steps": (snap.cap_steps, len(self._cap_ids)), "cap_valid": (snap.cap_valid, len(self._cap_ids)),
        }  # fmt: skip
        for name, (arr, size) in shapes.items():
            if np.shape(arr) != (size,):
                return self._hold(snap, f"snapshot.{name} has shape {np.shape(arr)}, expected ({size},)", (), started)

        head_ok, pv_ok, reg_ok = self._usable(snap)
        cap_ok = self._cap_usable(snap)
        missing = tuple(
            (["head"] if not head_ok else [])
            + [self._pv_ids[k] for k in range(n_pv) if not pv_ok[k]]
            + [self._reg_ids[r] for r in range(n_reg) if not reg_ok[r]]
            + [self._cap_ids[c] for c in range(len(self._cap_ids)) if not cap_ok[c]]
        )
        # Remember what is usable now (before any hold: last known values are facts, not decisions).
        for k in np.flatnonzero(pv_ok):
            self._pv_last_p_kw[k] = float(snap.pv_p_kw[k])
            self._pv_last_q_kvar[k] = float(snap.pv_q_kvar[k])
        for r in np.flatnonzero(reg_ok):
            self._reg_last_tap[r] = int(snap.reg_tap[r])
        if self._measured_steps is not None and snap.reg_steps_seen is not None:
            _, noisy = self._reading_noise(snap)
            self._measured_steps.observe(snap.reg_steps_seen, reg_ok & ~noisy)
        for c in np.flatnonzero(cap_ok):
            self._cap_last[c] = int(snap.cap_steps[c])
        self._stale.observe(snap.pv_p_kw, pv_ok & self._pv_fresh(snap))
        if not head_ok:
            return self._hold(snap, "no valid feeder-head frame: holding (no commands)", missing, started)
        never_pv = [self._pv_ids[k] for k in range(n_pv) if self._pv_last_p_kw[k] is None]
        never_reg = [self._reg_ids[r] for r in range(n_reg) if self._reg_last_tap[r] is None]
        if never_pv or never_reg:
            return self._hold(snap, f"no valid frame yet from {', '.join(never_pv + never_reg)}: holding", missing,
                              started)

        # The grid state: the estimator's (eq. 5-7, eq. 3) or, in case A, the bridge's oracle (every node).
        plants = self._plant_inputs(snap, pv_ok)
        pv_p, pv_q = plants[0], plants[1]
        taps = np.array(self._reg_last_tap, int)
        prefix = "" if oracle is None else "case A: "
        if oracle is None:
            state = estimated_state(
                self._arrays, self._sens, self._dv_dp, t_ns=int(snap.t_ns), head_p_kw=snap.head_p_kw,
                head_q_kvar=snap.head_q_kvar, pv_p_kw=pv_p, pv_q_kvar=pv_q, taps=taps, caps=self._cap_last,
                reg_v120=snap.reg_v120 if self.correction else None, reg_ok=reg_ok,
                cap_v_v=self._cap_readings(snap, cap_ok), eps_filter=self._correction_filter(snap))
            state = self.ami.correct(int(snap.t_ns), state)  # AMI readings (explicit option; none: unchanged)
        else:
            reply = oracle(int(snap.t_ns))
            if reply is None:
                return self._hold(snap, "case A: no oracle reply from the bridge", missing, started)
            try:
                state = oracle_state(self.model, reply, taps)
            except AgentInputError as e:
                return self._hold(snap, f"case A: {e}", missing, started)
        t_est = time.perf_counter()
        if not _finite(state.v0_pu, state.dv_dq_pu_per_kvar):
            return self._hold(snap, f"{prefix}estimate is not finite: check the model", missing, started,
                              estimate_s=t_est - t0)

        self._remember_pv_p(int(snap.t_ns), pv_p)
        self._drift_pu = (self._drift.margins(int(snap.t_ns), state.v0_pu)
                          if self._drift is not None and state.critical and oracle is None else None)
        outside = "" if not state.critical else self.envelope_problem(
            features(np.asarray(snap.head_p_kw, float), np.asarray(snap.head_q_kvar, float), pv_p, pv_q))
        try:
            inputs = self.problem(snap, state, out_of_envelope=bool(outside), plants=plants)
            self.last_problem = (inputs, snap, state, bool(outside), plants)
        except AgentInputError as e:
            return self._hold(snap, f"{prefix}unusable optimization inputs: {e}", missing, started, state=state,
                              estimate_s=t_est - t0)
        # Case A solves cold (as it always has): its rows are every live node, not the critical nodes.
        solution = solve_cvvc(inputs, warm_start=self._warm if oracle is None else None)
        solves: list[tuple[SolveRole, CvvcSolution]] = [("main", solution)]
        if solution.status != "optimal" and any(lock.any() for lock in self.tap_moves.reversal_locks(int(snap.t_ns))):
            # the limits are not met with the locks: the soft form trades every lever, the reverse moves included
            # (keeping the locks there distorted every decision of a feeder always in the soft form: epri-ckt24
            # winter day, NVV 54,765 against 413)
            solution = solve_cvvc(self.tap_moves.relocked(inputs, "none", int(snap.t_ns)),
                                  warm_start=self._warm if oracle is None else None)
            solves.append(("unlocked", solution))
        settled = self.tap_moves.settle(inputs, solution, state.taps, state.v0_pu.shape[0], int(snap.t_ns),
                                   lambda problem: solve_cvvc(problem, warm_start=self._warm), estimated=oracle is None)
        solution = settled.solution
        solves.extend(settled.solves)
        sec = solution.seconds
        if solution.status == "hold":
            return self._hold(snap, prefix + solution.reason, missing, started, state=state, solution=solution,
                              solves=tuple(solves),
                              estimate_s=t_est - t0)
        if oracle is None:
            self._warm = solution.warm_start

        # Commands.
        setpoints = bands = None
        if self.mode == "setpoints":
            sec_node = self._arrays.reg_secondary_node
            dv_sec = solution.v_pred_pu[sec_node] - state.v0_pu[sec_node]
            v_s1 = expected_compared_v120(self._compared_v120(snap, state, reg_ok), dv_sec,
                                          self._arrays.reg_pu_per_v120)
            d_tap = solution.taps_new[:n_reg] - state.taps
            band, step = self.bandwidth_v120, self._step_v120
            dv_dtap = np.reshape(state.dv_dtap_pu, (state.v0_pu.shape[0], -1))  # (N, R)
            if self._measured_steps is not None:  # beyond the paper: each regulator's step as it measured it
                own = dv_dtap[sec_node, np.arange(n_reg)]
                v_s1, step = with_measured_steps(v_s1, d_tap, step, own / self._arrays.reg_pu_per_v120,
                                                 self._measured_steps.step_v120())
            setpoints = np.array(
                [setpoint_for_tap_change(float(v_s1[r]), int(d_tap[r]), band, float(step[r])) for r in range(n_reg)]
            )
            if self.setpoint_hold:
                # No tap change decided and our last set point still in force: send it again unchanged instead of
                # re-centring the band on a (possibly noisy) reading.
                t_now = int(snap.t_ns)
                for r in np.flatnonzero((d_tap == 0) & reg_ok):
                    last = self._last_setpoint[r]
                    if last is not None and 0 < t_now - last[0] <= self._setpoint_hold_ns:
                        setpoints[r] = last[1]
                for r in np.flatnonzero(reg_ok):
                    self._last_setpoint[r] = (t_now, float(setpoints[r]))
            bands = np.full(n_reg, self.bandwidth_v120)
            if self.setpoint_safety and state.critical:
                narrow_held_bands(setpoints, bands, (d_tap == 0) & reg_ok, v_s1, step, solution.v_pred_pu, dv_dtap,
                                  self._arrays.reg_secondary_node, self._arrays.reg_pu_per_v120)
        self._stale.commanded(int(snap.t_ns), solution.q_new_kvar, pv_ok)
        moved = reg_ok & (solution.taps_new[:n_reg] != state.taps)
        self.tap_moves.moved(moved, solution.taps_new[:n_reg] - state.taps, int(snap.t_ns))
        applied = self.bounds_pu(bool(outside)) if state.critical else None
        if self._drift is not None:
            if state.critical and oracle is None:
                self._drift.predicted(int(snap.t_ns), solution.v_pred_pu[: state.v0_pu.shape[0]])
            else:
                self._drift.forget()
        reason = solution.reason
        if outside:
            note = (f"inputs outside the training envelope ({outside}): estimate bounds widened "
                    f"x{OUT_OF_ENVELOPE_WIDEN:g}")
            reason = f"{reason}; {note}" if reason else note
        return Decision(
            t_ns=int(snap.t_ns),
            status=solution.status,
            reason=reason,
            pv_q_kvar=solution.q_new_kvar.copy(),
            pv_command=pv_ok.copy(),
            reg_tap=solution.taps_new[:n_reg].copy(),
            reg_setpoint_v120=setpoints,
            reg_band_v120=bands,
            reg_command=reg_ok.copy(),
            v_pu=state.v0_pu if state.critical else None,
            v_pred_pu=solution.v_pred_pu[: state.v0_pu.shape[0]].copy() if state.critical else None,
            corrected=state.corrected,
            dv_dq_pu_per_kvar=state.dv_dq_pu_per_kvar if state.critical else None,
            missing=missing,
            iterations=solution.iterations,
            objective=solution.cost,
            solver_status=solution.status,
            cap_steps=solution.taps_new[n_reg:].copy(),
            cap_command=self._cap_movable(snap, state),
            timings=Timings(
                estimate_s=t_est - t0,
                solve_s=sec.build_s + sec.relaxed_s,
                round_s=sec.rounding_s,
                total_s=time.perf_counter() - t0,
                cpu_s=time.thread_time() - started[1],
            ),
            v_bound_low_pu=None if applied is None else applied[0],
            v_bound_high_pu=None if applied is None else applied[1],
            out_of_envelope=outside,
            solves=tuple(solves),
            tolerated=settled.tolerated,
        )
