"""Quasi-static time series: steps a :class:`FeederEngine` through profiles with device physics.

Each step (one profile row, 1 minute by default):

1. Loads and PV available power come from the profiles (PV clipped to ``[0, Pmpp]``).
2. PV reactive power per plant: its commanded set point if any, else the local default — unity power
   factor, or the IEEE 1547-2018 Category B volt-var curve (:func:`volt_var_q_pu`) evaluated on the
   plant's voltage measured at the *previous* step's solution (an inverter reacts to what it measured;
   within one power flow there is no time), reached through a first-order lag: each step the plant moves
   ``VOLT_VAR_RESPONSE`` (0.3) of the way from its present Q to the curve's value (a time constant of about
   2.8 min). Without the lag the one-step delay makes a plant with a high loop gain (slope × rating × dV/dQ
   above 1) overshoot and oscillate every minute, and the regulators hunt after it (measured on the rural
   feeder, local case, 10 July: 1138 tap changes in a day with the bare delay). A real inverter's open-loop
   response time (IEEE 1547-2018: 1-90 s) settles it continuously onto the curve's fixed point, which the lag
   reaches in a few steps. Q is clipped to the headroom ``sqrt(kVA² − P²)``; at night (available P = 0) it
   is 0 unless ``pv_q_at_night=True``.
3. Regulators locked at a commanded tap are set to it; then the power flow is solved.
4. Regulator local control on the others (:func:`tap_direction`): after each solve, a regulator whose
   *compared* voltage (line-drop compensation included) is outside ``set point ± band/2`` counts one more
   consecutive step out of band (the count resets when it is inside). Once the count reaches
   ``delay_steps`` it moves one tap toward the band, the feeder is re-solved, and it keeps moving one tap
   per solve while still outside, up to ``max_taps_per_step`` taps in this step, never reversing
   direction within the step (a band narrower than one tap would otherwise hunt). ``delay_steps=1``
   models a time delay shorter than one step (the regulator acts in the minute it sees the violation);
   ``delay_steps=n`` a delay between ``n−1`` and ``n`` steps. Every tap moved is counted in
   ``StepResult.tap_changes``, commanded moves included.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np

from schemas.errors import CvvcError
from simulator_bridge.engine import FeederEngine, FieldReadings

__all__ = [
    "IEEE1547_CAT_B_Q_PU",
    "IEEE1547_CAT_B_V_PU",
    "Profiles",
    "Qsts",
    "QstsError",
    "StepResult",
    "VOLT_VAR_RESPONSE",
    "tap_direction",
    "volt_var_q_pu",
]

IEEE1547_CAT_B_V_PU = (0.92, 0.98, 1.02, 1.08)
"""IEEE 1547-2018 Category B default volt-var breakpoints V1..V4 [pu]."""
IEEE1547_CAT_B_Q_PU = (0.44, 0.0, 0.0, -0.44)
"""IEEE 1547-2018 Category B default Q1..Q4 [pu of the inverter's kVA rating], + injects."""


class QstsError(CvvcError):
    """The time series cannot run: profiles that do not fit the feeder, a step past the end, a bad command."""


class Profiles(Protocol):
    """What Qsts needs from ``simulator_bridge.profiles.YearProfiles``."""

    n_steps: int
    n_loads: int
    n_pv: int

    def t_ns(self, step: int) -> int: ...
    def load_kw(self, start: int, stop: int) -> np.ndarray: ...
    def pv_kw(self, start: int, stop: int) -> np.ndarray: ...


@dataclass(frozen=True)
class StepResult:
    """One QSTS step.

    Attributes
    ----------
    step : profile step index; t_ns : its time [ns since the UTC epoch].
    readings : field measurements at the final solution of the step.
    v_pu : (n_nodes,) truth: every node's voltage [pu of its L-N base].
    taps : (R,) tap positions at the end of the step.
    tap_changes : (R,) taps moved during the step (local control and commands).
    pv_q_kvar : (K,) reactive power applied, generator convention [kvar].
    pv_p_kw : (K,) available active power applied [kW].
    cap_states : (C,) int, closed steps of each map capacitor bank at the end of the step.
    cap_switches : (C,) int, switching operations during the step (one per step closed or opened; local
        control and commands).
    """

    step: int
    t_ns: int
    readings: FieldReadings
    v_pu: np.ndarray
    taps: np.ndarray
    tap_changes: np.ndarray
    pv_q_kvar: np.ndarray
    pv_p_kw: np.ndarray
    cap_states: np.ndarray
    cap_switches: np.ndarray


#: Share of the way to the volt-var curve's value a plant moves per step (first-order lag; see above).
VOLT_VAR_RESPONSE = 0.3


def volt_var_q_pu(v_pu: np.ndarray, v_points_pu=IEEE1547_CAT_B_V_PU, q_points_pu=IEEE1547_CAT_B_Q_PU) -> np.ndarray:
    """Volt-var curve: reactive power [pu of kVA rating, + injects] at voltage ``v_pu`` [pu].

    Piecewise linear through the points, flat beyond the end points (IEEE 1547-2018 §5.3.3).
    """
    return np.interp(np.asarray(v_pu, dtype=float), v_points_pu, q_points_pu)


def tap_direction(v_compared_v120: np.ndarray, setpoint_v120: np.ndarray, band_v120: np.ndarray) -> np.ndarray:
    """Tap move a regulator wants: +1 below ``set point − band/2``, −1 above ``set point + band/2``, else 0.

    All voltages on the 120 V base [V]. Returns an int array of the same shape.
    """
    dev = np.asarray(v_compared_v120, dtype=float) - np.asarray(setpoint_v120, dtype=float)
    half = 0.5 * np.asarray(band_v120, dtype=float)
    return np.where(dev < -half, 1, np.where(dev > half, -1, 0)).astype(int)


class Qsts:
    """Steps an engine through profiles with regulator local control and PV reactive power.

    Parameters
    ----------
    engine : FeederEngine
    profiles : YearProfiles (or anything with ``n_steps``, ``n_loads``, ``n_pv``, ``t_ns``, ``load_kw``,
        ``pv_kw``), columns in ``engine.load_names`` / ``engine.pv_ids`` order.
    start_step : first profile step to simulate.
    pv_local : local default of a PV plant without a commanded Q: ``"unity"`` or ``"volt_var"``.
    pv_q_at_night : allow reactive power (commanded or volt-var) when available P is 0.
    delay_steps : consecutive out-of-band steps before a regulator starts moving (>= 1).
    max_taps_per_step : most taps one regulator moves in one step under local control.
    chunk_steps : profile rows read at a time.
    """

    def __init__(
        self,
        engine: FeederEngine,
        profiles: Profiles,
        *,
        start_step: int,
        pv_local: Literal["unity", "volt_var"] = "unity",
        pv_q_at_night: bool = False,
        delay_steps: int = 1,
        max_taps_per_step: int = 8,
        chunk_steps: int = 1440,
    ) -> None:
        if profiles.n_loads != len(engine.load_names) or profiles.n_pv != len(engine.pv_ids):
            raise QstsError(
                f"profiles have {profiles.n_loads} loads and {profiles.n_pv} PV plants, the feeder "
                f"{engine.device_map.feeder.name!r} has {len(engine.load_names)} and {len(engine.pv_ids)}; "
                "make the profiles from this feeder's engine"
            )
        if not 0 <= start_step < profiles.n_steps:
            raise QstsError(f"start_step {start_step} outside the profiles' 0..{profiles.n_steps - 1}")
        if pv_local not in ("unity", "volt_var"):
            raise QstsError(f"pv_local must be 'unity' or 'volt_var', not {pv_local!r}")
        if delay_steps < 1 or max_taps_per_step < 0:
            raise QstsError("delay_steps must be >= 1 and max_taps_per_step >= 0")
        self.engine = engine
        self.profiles = profiles
        self.pv_local = pv_local
        self.pv_q_at_night = bool(pv_q_at_night)
        self.delay_steps = int(delay_steps)
        self.max_taps_per_step = int(max_taps_per_step)
        self._chunk_steps = int(chunk_steps)
        self._chunk_start = -1
        self._staged: int | None = None  # the step whose loads are already set (stage_loads)
        self._chunk_load = np.empty((0, 0))
        self._chunk_pv = np.empty((0, 0))
        self._step = int(start_step)
        n_pv, n_reg = len(engine.pv_ids), len(engine.regulator_ids)
        self._pv_cmd: list[float | None] = [None] * n_pv
        self._locked = np.zeros(n_reg, dtype=bool)  # regulator r held at self._lock_tap[r]
        self._lock_tap = np.zeros(n_reg, dtype=int)
        self._setpoint_v120 = engine.reg_default_setpoint_v120.copy()
        self._band_v120 = engine.reg_default_band_v120.copy()
        self._out_of_band_steps = np.zeros(n_reg, dtype=int)
        n_cap = len(engine.capacitor_ids)
        self._cap_locked = np.zeros(n_cap, dtype=bool)  # bank c held at self._cap_lock_state[c]
        self._cap_lock_state = np.zeros(n_cap, dtype=int)
        # plant voltage = mean of its nodes' voltages: flat node indices and segment starts
        self._pv_nodes = np.array([i for ix in engine.pv_node_index for i in ix], dtype=int)
        self._pv_counts = np.array([len(ix) for ix in engine.pv_node_index], dtype=float)
        self._pv_starts = np.concatenate([[0], np.cumsum(self._pv_counts)[:-1]]).astype(int)
        engine.solve()
        self._pv_v_pu = self._plant_v_pu(engine.node_voltages_pu())
        self._pv_p_kw, self._pv_q_kvar = engine.pv_setpoints()

    @property
    def next_step(self) -> int:
        """The profile step the next :meth:`step` simulates."""
        return self._step

    # ------------------------------------------------------------------ commands
    def command_pv_q(self, k: int, q_kvar: float | None) -> float:
        """Command plant ``k``'s reactive power [kvar, + injects]; ``None`` returns it to its local default.

        Returns the value that would be applied at the present available power (clipped to the
        headroom; 0 at night unless ``pv_q_at_night``). The next step re-clips at its own P.
        """
        self._check_index(k, len(self._pv_cmd), "PV plant")
        if q_kvar is not None and not np.isfinite(q_kvar):
            raise QstsError(f"command_pv_q: plant {k}: non-finite set point {q_kvar!r}")
        self._pv_cmd[k] = None if q_kvar is None else float(q_kvar)
        q = self._pv_q_target(self._pv_p_kw, self._pv_v_pu)[k]
        return float(q)

    def command_tap(self, r: int, tap: int | None) -> int:
        """Lock regulator ``r`` at ``tap`` from the next step on (clipped to its range); ``None`` unlocks.

        Returns the tap it will hold (its present tap when unlocked).
        """
        self._check_index(r, len(self._locked), "regulator")
        if tap is None:
            self._locked[r] = False
            self._out_of_band_steps[r] = 0
            return int(self.engine.taps()[r])
        t = int(np.clip(int(tap), -self.engine.reg_tap_max[r], self.engine.reg_tap_max[r]))
        self._locked[r], self._lock_tap[r] = True, t
        return t

    def command_setpoint(self, r: int, setpoint_v120: float | None, band_v120: float | None) -> None:
        """Set regulator ``r``'s local-control set point and band [V on the 120 V base]; ``None``: default.

        A locked regulator keeps its tap; the set point applies once it is unlocked.
        """
        self._check_index(r, len(self._locked), "regulator")
        for name, value in (("setpoint_v120", setpoint_v120), ("band_v120", band_v120)):
            if value is not None and not (np.isfinite(value) and value > 0):
                raise QstsError(f"command_setpoint: regulator {r}: {name} {value!r} must be positive")
        self._setpoint_v120[r] = (self.engine.reg_default_setpoint_v120[r] if setpoint_v120 is None
                                  else float(setpoint_v120))
        self._band_v120[r] = self.engine.reg_default_band_v120[r] if band_v120 is None else float(band_v120)

    def command_cap(self, c: int, state_steps: int | None) -> int:
        """Hold map capacitor bank ``c`` at ``state_steps`` closed steps from the next step on (clipped to
        ``0..cap_steps``); ``None`` returns it to its local CapControl (a bank without one stays where it is).

        Returns the state it will hold (its present state when released).
        """
        self._check_index(c, len(self._cap_locked), "capacitor")
        if state_steps is None:
            self._cap_locked[c] = False
            return int(self.engine.cap_states()[c])
        st = int(np.clip(int(state_steps), 0, self.engine.cap_steps[c]))
        self._cap_locked[c], self._cap_lock_state[c] = True, st
        return st

    # ------------------------------------------------------------------ staging
    def stage_loads(self) -> None:
        """Set the next step's loads now: they come from the profiles alone, so a caller that waits between
        steps (the bridge, for the agent's decision) can do this part of the next :meth:`step` meanwhile. The
        power flow then solves exactly what it would have. Before any power flow on the present state (a
        perturbation), call :meth:`unstage_loads`.
        """
        s = self._step
        if s < self.profiles.n_steps and self._staged != s:
            self.engine.set_loads_kw(self._rows(s)[0])
            self._staged = s

    def unstage_loads(self) -> None:
        """Put back the loads of the step last simulated, if :meth:`stage_loads` moved them on."""
        if self._staged is not None:
            self.engine.set_loads_kw(self._rows(self._step - 1)[0])
            self._staged = None

    @staticmethod
    def _check_index(i: int, n: int, what: str) -> None:
        if not (isinstance(i, int | np.integer) and 0 <= i < n):
            raise QstsError(f"no {what} {i!r}: this feeder has {n} (indices 0..{n - 1})")

    # ------------------------------------------------------------------ stepping
    def _plant_v_pu(self, v_pu: np.ndarray) -> np.ndarray:
        """(K,) each plant's measured voltage: the mean of its nodes' voltages [pu]."""
        if not len(self._pv_nodes):
            return np.zeros(0)
        return np.add.reduceat(v_pu[self._pv_nodes], self._pv_starts) / self._pv_counts

    def _rows(self, step: int) -> tuple[np.ndarray, np.ndarray]:
        if not self._chunk_start <= step < self._chunk_start + len(self._chunk_load):
            stop = min(step + self._chunk_steps, self.profiles.n_steps)
            self._chunk_load = np.asarray(self.profiles.load_kw(step, stop), dtype=float)
            self._chunk_pv = np.asarray(self.profiles.pv_kw(step, stop), dtype=float)
            self._chunk_start = step
        i = step - self._chunk_start
        return self._chunk_load[i], self._chunk_pv[i]

    def _pv_q_target(self, p_kw: np.ndarray, v_pu: np.ndarray) -> np.ndarray:
        """Reactive power each plant will apply [kvar] at available power ``p_kw`` and measured ``v_pu``."""
        e = self.engine
        if self.pv_local == "volt_var":
            curve = volt_var_q_pu(v_pu) * e.pv_kva
            local = self._pv_q_kvar + VOLT_VAR_RESPONSE * (curve - self._pv_q_kvar)
        else:
            local = np.zeros(len(p_kw))
        q = np.array([local[k] if c is None else c for k, c in enumerate(self._pv_cmd)], dtype=float)
        if not self.pv_q_at_night:
            q = np.where(p_kw > 0.0, q, 0.0)
        headroom = np.sqrt(np.maximum(e.pv_kva**2 - np.minimum(p_kw, e.pv_pmpp_kw) ** 2, 0.0))
        return np.minimum(np.maximum(q, -headroom), headroom)

    def step(self) -> StepResult:
        """Advance one profile step: set loads and PV, apply locked taps, solve, run regulator control."""
        e, s = self.engine, self._step
        if s >= self.profiles.n_steps:
            raise QstsError(f"step {s} is past the end of the profiles ({self.profiles.n_steps} steps)")
        load_kw, pv_kw = self._rows(s)
        p = np.minimum(np.maximum(pv_kw, 0.0), e.pv_pmpp_kw)
        q = e.set_pv(p, self._pv_q_target(p, self._pv_v_pu))
        if self._staged != s:
            e.set_loads_kw(load_kw)
        self._staged = None

        taps0 = e.taps()  # the engine's, in case its owner moved them between steps
        locked = self._locked
        taps = np.where(locked, self._lock_tap, taps0)
        changes = np.abs(taps - taps0)
        if changes.any():
            e.set_taps(taps)
        caps0 = e.cap_states()
        caps = np.where(self._cap_locked, self._cap_lock_state, caps0)
        cap_switches = np.abs(caps - caps0)
        if cap_switches.any():
            e.set_cap_states(caps)
        e.solve()
        readings = e.readings()

        want = tap_direction(readings.reg_v120_compared, self._setpoint_v120, self._band_v120)
        want[locked] = 0
        self._out_of_band_steps = np.where(want != 0, self._out_of_band_steps + 1, 0)
        moving = self._out_of_band_steps >= self.delay_steps
        first_move = np.zeros_like(want)
        for _ in range(self.max_taps_per_step):
            # a regulator never reverses within one step (no hunting when the band is under one tap)
            moving &= (first_move == 0) | (want == first_move)
            move = np.where(moving, want, 0)
            move = np.where(np.abs(taps + move) <= e.reg_tap_max, move, 0)
            if not move.any():
                break
            first_move = np.where(first_move == 0, move, first_move)
            taps = taps + move
            changes += np.abs(move)
            e.set_taps(taps)
            e.solve()
            readings = e.readings()
            want = tap_direction(readings.reg_v120_compared, self._setpoint_v120, self._band_v120)
            want[locked] = 0
        self._out_of_band_steps = np.where(want != 0, self._out_of_band_steps, 0)

        v = e.node_voltages_pu()
        self._pv_v_pu = self._plant_v_pu(v)
        self._pv_p_kw, self._pv_q_kvar = p, np.asarray(q, dtype=float)
        self._step = s + 1
        return StepResult(
            step=s, t_ns=int(self.profiles.t_ns(s)), readings=readings, v_pu=v, taps=taps.copy(),
            tap_changes=changes, pv_q_kvar=q, pv_p_kw=p, cap_states=e.cap_states(), cap_switches=cap_switches,
        )
