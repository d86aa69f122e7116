"""What the controller takes and gives: one control step's measurements in, one decision out (array form).

``MeasurementSnapshot`` is the runtime's aligned frames of a step in the model's device order;
``Decision`` is the controller's answer before it becomes bus messages (``agent.runtime``).
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass, field, fields
from typing import Literal

import numpy as np

from agent.solve import CvvcSolution
from schemas.messages import Timings

__all__ = ["Decision", "MeasurementSnapshot", "SolveRole", "decision_time_ms", "reason_kind"]

#: Why a decision solved: the decision itself, again without the tap reversal locks, with every tap held, or with
#: every tap held and the nodes' limits widened by the tap deadband (the Q of a decision whose taps the deadband held).
SolveRole = Literal["main", "unlocked", "deadband", "tolerated", "buy"]

_DECIMAL = re.compile(r"\d+\.\d+")


@dataclass(frozen=True)
class MeasurementSnapshot:
    """The aligned measurements of one control step, as arrays (index order = the model's).

    Attributes
    ----------
    t_ns : measurement time [ns since epoch].
    head_p_kw, head_q_kvar : (3,) feeder-head power per phase a, b, c, into the feeder [kW], [kvar].
    pv_p_kw, pv_q_kvar : (K,) plant output, generator convention [kW], [kvar].
    pv_kva_available : (K,) apparent power the plant can deliver now [kVA]; Q headroom is
        ``sqrt(kva^2 - p^2)``.
    pv_q_setpoint_kvar : (K,) present Q set point [kvar], NaN when the plant is on its local default.
        Informational: eq. (13) uses the measured Q, which is what the estimate reflects.
    reg_v120 : (R,) raw secondary voltage [V on 120 V base] (for the correction, eq. 6).
    reg_v120_compared : (R,) voltage the controller compares with its band (line-drop compensation
        included) [V on 120 V base] (for eq. 8).
    reg_tap : (R,) present tap [steps].
    head_valid : the head frame arrived and passed the runtime's checks.
    pv_valid : (K,) bool, same per plant.
    reg_valid : (R,) bool, same per regulator.
    cap_steps : (C,) closed steps of each capacitor bank (the model's ``capacitors`` order).
    cap_valid : (C,) bool, the bank's frame arrived and passed the checks.
    cap_v_v : (C,) the bank's bus voltage [V] (a regressor of models with readings); NaN where missing.
    cap_control_value : (C,) what the bank's local control compares with its ON/OFF settings, in its unit
        (``CapFrame.control_value``), NaN where missing or when the bank is held by a command (not on local control);
        empty: unknown.
    reg_v120_noise : (R,) the noise of the regulator's readings at its present tap over the reading window [V on 120
        V base] (``agent.snapshot.reading_noise_v120``), NaN with too few; None: unknown.
    reg_fresh : (R,) bool, the regulator's reading is this step's own frame (not a last-good one standing in for
        a lost frame); None: every reading is.
    head_fresh : the head frame is this step's own.
    pv_fresh : (K,) bool, the plant's frame is this step's own (not a last-good one); None: every frame is.
    reg_v120_now : (R,) the raw secondary voltage of the regulator's own frame of this step [V on 120 V base] (NaN
        without one), before any averaging: what the calibrated bounds assume eq. (6) starts from; None: unknown.
    pv_age_s : (K,) how old each plant's frame is at the step [s] (0 for its own); None: unknown (a stand-in is
        then taken as old).
    reg_steps_seen : per regulator, the single-tap moves in its recent frames that no coupled regulator's move
        blurs, as (time of the frame after the move [ns], change of its compared reading per tap up [V on 120 V
        base]) (``agent.snapshot.steps_seen_v120``); None: unknown.
    """

    t_ns: int
    head_p_kw: np.ndarray
    head_q_kvar: np.ndarray
    pv_p_kw: np.ndarray
    pv_q_kvar: np.ndarray
    pv_kva_available: np.ndarray
    pv_q_setpoint_kvar: np.ndarray
    reg_v120: np.ndarray
    reg_v120_compared: np.ndarray
    reg_tap: np.ndarray
    head_valid: bool
    pv_valid: np.ndarray
    reg_valid: np.ndarray
    cap_steps: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    cap_valid: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    cap_v_v: np.ndarray = field(default_factory=lambda: np.zeros(0))
    reg_fresh: np.ndarray | None = None
    head_fresh: bool = True
    pv_fresh: np.ndarray | None = None
    reg_v120_now: np.ndarray | None = None
    cap_control_value: np.ndarray = field(default_factory=lambda: np.zeros(0))
    reg_v120_noise: np.ndarray | None = None
    pv_age_s: np.ndarray | None = None
    reg_steps_seen: tuple[tuple[tuple[int, float], ...], ...] | None = None


@dataclass(frozen=True)
class Decision:
    """What the controller decided for one snapshot.

    Attributes
    ----------
    t_ns : the snapshot's time [ns].
    status : ``optimal`` / ``soft`` / ``hold`` (no commands; see ``reason``).
    reason : why ``soft`` or ``hold`` (empty when optimal).
    pv_q_kvar : (K,) new Q set points [kvar], or None on hold.
    pv_command : (K,) bool, plants to command (False for missing plants and on hold).
    reg_tap : (R,) int, taps the decision aims at [steps], or None on hold. In ``taps`` mode these are
        the commands; in ``setpoints`` mode the set points below are.
    reg_setpoint_v120, reg_band_v120 : (R,) eq. (8) set points and bands [V on 120 V base] in
        ``setpoints`` mode; None in ``taps`` mode and on hold.
    reg_command : (R,) bool, regulators to command.
    v_pu : (N,) critical-node voltage estimates [pu] (corrected when ``corrected``), None without a head frame.
    v_pred_pu : (N,) predicted voltages after the actions (linear model) [pu], None on hold.
    corrected : eq. (7) correction applied (from at least one regulator).
    dv_dq_pu_per_kvar : (N, K) sensitivities used [pu/kvar], None without a head frame.
    missing : ids of devices whose frame was missing or invalid.
    iterations, objective : solver iterations and eq. (9) cost of the actions [cost units].
    solver_status : the solver's status (``optimal``/``soft``/``hold``), ``not run`` when it was not called.
    timings : per-stage wall time [s] (not deterministic; excluded from ``same_content``): the message's
        ``Timings`` without the aligner's ``align_s``, which the runtime adds.
    v_bound_low_pu, v_bound_high_pu : (N,) the estimate's calibrated bounds as applied (widened out of the
        envelope): the true voltage is expected within ``[v_pu - low, v_pu + high]``; None without bounds.
    out_of_envelope : the features outside what training covered ("" when inside, or without bounds).
    cap_steps : (C,) int, closed steps decided for each capacitor bank, or None on hold.
    cap_command : (C,) bool, banks to command.
    solves : every solve the decision made, by its role: ``main`` (the decision), ``unlocked`` (again without the
        tap reversal locks, when the first is not optimal), ``deadband`` (every tap held, ``tap_deadband_pu``); what
        the stage benchmark reads (``benchmarks.bench_stages``). Not part of ``same_content`` (their stage times
        are wall times).
    tolerated : a soft decision of the tap deadband: every tap held for a predicted violation of the tightened limits
        within ``tap_deadband_pu``, Q for the limits widened by it (met); False for the soft form (eq. 17).
    """

    t_ns: int
    status: Literal["optimal", "soft", "hold"]
    reason: str
    pv_q_kvar: np.ndarray | None
    pv_command: np.ndarray
    reg_tap: np.ndarray | None
    reg_setpoint_v120: np.ndarray | None
    reg_band_v120: np.ndarray | None
    reg_command: np.ndarray
    v_pu: np.ndarray | None
    v_pred_pu: np.ndarray | None
    corrected: bool
    dv_dq_pu_per_kvar: np.ndarray | None
    missing: tuple[str, ...]
    iterations: int
    objective: float
    solver_status: str
    timings: Timings
    v_bound_low_pu: np.ndarray | None = None
    v_bound_high_pu: np.ndarray | None = None
    out_of_envelope: str = ""
    cap_steps: np.ndarray | None = None
    cap_command: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    solves: tuple[tuple[SolveRole, CvvcSolution], ...] = ()
    tolerated: bool = False

    def same_content(self, other: Decision) -> bool:
        """Bit-identical in every field but ``timings`` and ``solves`` (what replay compares)."""
        for f in fields(self):
            if f.name in ("timings", "solves"):
                continue
            a, b = getattr(self, f.name), getattr(other, f.name)
            if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
                if not (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)):
                    return False
                if a.shape != b.shape or a.dtype != b.dtype or a.tobytes() != b.tobytes():
                    return False
            elif a != b:
                return False
        return True


def decision_time_ms(seconds: Iterable[float]) -> dict[str, float]:
    """p50, p99 and max of decision wall times given in seconds, in ms (rounded to 0.01 ms); empty for none.

    A decision's time runs from its frames' alignment to its message (``m.Timings.total_s``): what the agent adds
    to a control step, measured in every run rather than only by the benchmarks' replayed states.
    """
    t = np.asarray(list(seconds), float) * 1e3
    if t.size == 0:
        return {}
    p50, p99 = np.percentile(t, [50, 99])
    return {"p50": round(float(p50), 2), "p99": round(float(p99), 2), "max": round(float(t.max()), 2)}


def reason_kind(reason: str) -> str:
    """A soft or hold decision's reason with its decimal figures masked as ``#`` (the first 120 characters): what
    the summary counts, so that one cause with a different figure at each step is one line, not twenty.
    """
    return _DECIMAL.sub("#", reason)[:120]
