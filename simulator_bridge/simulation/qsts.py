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
   is 0 unless the plant gives Q at night (its device map entry's ``q_at_night``, or ``pv_q_at_night``).
3. Devices held by a command are set (a locked regulator's tap, a held capacitor bank's state); then the
   power flow is solved.
4. Local control of every RegControl and CapControl of the model, with its own settings, on an event clock
   inside the step (``controls.py`` states OpenDSS's semantics): each control samples the solution at the
   step's start time ``t``; an out-of-band regulator or a capacitor control whose condition holds arms an
   action at ``t + delay``. While the next queued action falls inside the step (before ``t + step``), the
   clock moves to it: controls sample again (no new power flow: loads and PV are constant within the step),
   the actions due then are done, the feeder is re-solved and every control samples the new solution. An
   action due later stays queued into the next step, where the first sample after the new loads may disarm
   it. A quiet step costs one power flow. So the number of taps a regulator moves in a step follows from its
   own ``delay`` and ``tapdelay``. Every tap moved and every capacitor step switched is counted
   (``StepResult.tap_changes``, ``cap_switches``), commanded moves included.

Before the first step the local controls run for ``SETTLE_S`` (30 minutes) on the first step's loads and PV, and
their moves are not counted: a simulation starts from a feeder whose regulators and banks have settled, as a real
feeder is found at any hour, not from the taps and bank states the model file leaves them in. Without it the first
minutes of a run count the model's own start-up (IEEE 8500: every bank closed at 00:00, six of them opening in the
first minute while case D's first decision moved the regulators 1-8 steps), and every case's tap and bank counts and
1-minute minima carry it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np

from simulator_bridge.errors import SimulatorError
from simulator_bridge.opendss.controls import LocalControls
from simulator_bridge.opendss.engine import FeederEngine
from simulator_bridge.opendss.readout import FieldReadings

__all__ = [
    "IEEE1547_CAT_B_Q_PU",
    "IEEE1547_CAT_B_V_PU",
    "Profiles",
    "Qsts",
    "QstsError",
    "SETTLE_S",
    "StepResult",
    "VOLT_VAR_RESPONSE",
    "tap_direction",
    "volt_var_q_pu",
]

IEEE1547_CAT_B_V_PU = (0.92, 0.98, 1.02, 1.08)
"""IEEE 1547-2018 Category B default volt-var breakpoints V1..V4 [pu]."""
IEEE1547_CAT_B_Q_PU = (0.44, 0.0, 0.0, -0.44)
"""IEEE 1547-2018 Category B default Q1..Q4 [pu of the inverter's kVA rating], + injects."""


class QstsError(SimulatorError):
    """The time series cannot run: profiles that do not fit the feeder, a step past the end, a bad command."""


class Profiles(Protocol):
    """What Qsts needs from ``simulator_bridge.simulation.profiles.YearProfiles``."""

    n_steps: int
    n_loads: int
    n_pv: int
    step_s: int  # a row's length [s]

    def t_ns(self, step: int) -> int:
        """Time of row ``step`` [ns since the UTC epoch]."""
        ...

    def load_kw(self, start: int, stop: int) -> np.ndarray:
        """(stop - start, n_loads) every load's active power [kW]."""
        ...

    def pv_kw(self, start: int, stop: int) -> np.ndarray:
        """(stop - start, n_pv) every plant's available AC power [kW]."""
        ...


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


_MAX_INSTANTS = 10_000  # event times within one step (a runaway control loop is an error, not a hang)
_MAX_ROUNDS = 100  # action rounds at one instant (OpenDSS's maxcontroliter)

#: Local control run before the first step on its loads, uncounted (module docstring) [s].
SETTLE_S = 1800.0

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
    """Steps an engine through profiles with every RegControl's and CapControl's local control (an event
    clock inside each step, ``controls.py``) and PV reactive power.

    Parameters
    ----------
    engine : FeederEngine
    profiles : YearProfiles (or anything with ``n_steps``, ``n_loads``, ``n_pv``, ``step_s``, ``t_ns``, ``load_kw``,
        ``pv_kw``), columns in ``engine.load_names`` / ``engine.pv_ids`` order; its ``step_s`` is the step's
        length [s] for the event clock.
    start_step : first profile step to simulate.
    pv_local : local default of a PV plant without a commanded Q: ``"unity"`` or ``"volt_var"``.
    pv_q_at_night : allow reactive power (commanded or volt-var) when available P is 0: for every plant (a bool),
        or, ``None``, for the plants whose device map entry says so (``q_at_night``). Kept as ``self.pv_q_at_night``,
        (K,) bool in ``engine.pv_ids`` order.
    chunk_steps : profile rows read at a time.
    settle_s : local control run, uncounted, on the first step's loads before it (module docstring); 0 starts
        from the model's own taps and bank states (as OpenDSS's own control loop does, for comparing with it).
    """

    def __init__(
        self,
        engine: FeederEngine,
        profiles: Profiles,
        *,
        start_step: int,
        pv_local: Literal["unity", "volt_var"] = "unity",
        pv_q_at_night: bool | None = None,
        chunk_steps: int = 1440,
        settle_s: float = SETTLE_S,
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
        if not (np.isfinite(settle_s) and settle_s >= 0):
            raise QstsError(f"settle_s must be a finite number of seconds >= 0, not {settle_s!r}")
        self.engine = engine
        self.profiles = profiles
        self.pv_local = pv_local
        by_id = {p.id: p.q_at_night for p in engine.device_map.pv}
        self.pv_q_at_night = np.array([by_id[pid] if pv_q_at_night is None else bool(pv_q_at_night)
                                       for pid in engine.pv_ids], bool)
        self._chunk_steps = int(chunk_steps)
        self._chunk_start = -1
        self._staged: int | None = None  # the step whose loads are already set (stage_loads)
        self._chunk_load = np.empty((0, 0))
        self._chunk_pv = np.empty((0, 0))
        self._step = int(start_step)
        n_pv, n_reg = len(engine.pv_ids), len(engine.regulator_ids)
        self._pv_cmd: list[float | None] = [None] * n_pv
        self._pv_volt_var: np.ndarray | None = None  # per plant, volt-var as its local default; None: pv_local's
        self._locked = np.zeros(n_reg, dtype=bool)  # regulator r held at self._lock_tap[r]
        self._lock_tap = np.zeros(n_reg, dtype=int)
        self.controls = LocalControls(engine.reg_controls, engine.cap_controls)
        for r in range(n_reg):  # the map's set point and band, where it gives them, replace the model's
            self.controls.set_reg_band(r, engine.reg_default_setpoint_v120[r], engine.reg_default_band_v120[r])
        n_cap = len(engine.capacitor_ids)
        self._cap_locked = np.zeros(n_cap, dtype=bool)  # bank c held at self._cap_lock_state[c]
        self._cap_lock_state = np.zeros(n_cap, dtype=int)
        self._cap_control = engine.cap_control_index  # each map bank's CapControl, -1 without one
        self._cap_bank = engine.cap_control_bank  # each CapControl's bank (map banks first)
        self._step_s = float(profiles.step_s)
        self._has_time_caps = any(c.kind == "time" for c in engine.cap_controls)
        # plant voltage = mean of its nodes' voltages: flat node indices and segment starts
        self._pv_nodes = np.array([i for ix in engine.pv_node_index for i in ix], dtype=int)
        self._pv_counts = np.array([len(ix) for ix in engine.pv_node_index], dtype=float)
        self._pv_starts = np.concatenate([[0], np.cumsum(self._pv_counts)[:-1]]).astype(int)
        engine.solve()
        self._pv_v_pu = self._plant_v_pu(engine.node_voltages_pu())
        self._pv_p_kw, self._pv_q_kvar = engine.pv_setpoints()
        if settle_s > 0:
            self._settle(float(settle_s))

    def _settle(self, settle_s: float) -> None:
        """Run the local controls for ``settle_s`` before the first step, on its loads and PV; count nothing."""
        e, s = self.engine, self._step
        p, q = self._set_injections(s)
        e.solve()
        t0 = self.profiles.t_ns(s) / 1e9
        self._run_controls(t0 - settle_s, t0, np.zeros(len(self._locked), int), np.zeros(len(self._cap_locked), int))
        self._pv_v_pu = self._plant_v_pu(e.node_voltages_pu())
        self._pv_p_kw, self._pv_q_kvar = p, q

    @property
    def next_step(self) -> int:
        """The profile step the next :meth:`step` simulates."""
        return self._step

    # ------------------------------------------------------------------ commands
    def command_pv_q(self, k: int, q_kvar: float | None) -> float:
        """Command plant ``k``'s reactive power [kvar, + injects]; ``None`` returns it to its local default.

        Returns the value that would be applied at the present available power (clipped to the
        headroom; 0 at night unless the plant gives Q at night). The next step re-clips at its own P.
        """
        self._check_index(k, len(self._pv_cmd), "PV plant")
        if q_kvar is not None and not np.isfinite(q_kvar):
            raise QstsError(f"command_pv_q: plant {k}: non-finite set point {q_kvar!r}")
        self._pv_cmd[k] = None if q_kvar is None else float(q_kvar)
        q = self._pv_q_target(self._pv_p_kw, self._pv_v_pu)[k]
        return float(q)

    def set_pv_local(self, k: int, volt_var: bool) -> None:
        """Plant ``k``'s local default from the next step on: the volt-var curve (True) or unity power factor
        (False), in place of ``pv_local`` for that plant (a plant's inverter may be set either way on its own, e.g.
        through SunSpec model 705). The other plants keep ``pv_local`` until set.
        """
        self._check_index(k, len(self._pv_cmd), "PV plant")
        if self._pv_volt_var is None:
            self._pv_volt_var = np.full(len(self._pv_cmd), self.pv_local == "volt_var")
        self._pv_volt_var[k] = bool(volt_var)

    def command_tap(self, r: int, tap: int | None) -> int:
        """Lock regulator ``r`` at ``tap`` from the next step on (clipped to its range); ``None`` unlocks (back
        to its local control, which starts unarmed).

        Returns the tap it will hold (its present tap when unlocked).
        """
        self._check_index(r, len(self._locked), "regulator")
        if tap is None:
            self._locked[r] = False
            self.controls.block_reg(r, False)
            return int(self.engine.taps()[r])
        t = int(np.clip(int(tap), -self.engine.reg_tap_max[r], self.engine.reg_tap_max[r]))
        self._locked[r], self._lock_tap[r] = True, t
        self.controls.block_reg(r, True)
        return t

    def command_setpoint(self, r: int, setpoint_v120: float | None, band_v120: float | None) -> None:
        """Set regulator ``r``'s local-control set point and band [V on the 120 V base]; ``None``: default.

        Its own delays still apply. A locked regulator keeps its tap; the set point applies once it is unlocked.
        """
        self._check_index(r, len(self._locked), "regulator")
        for name, value in (("setpoint_v120", setpoint_v120), ("band_v120", band_v120)):
            if value is not None and not (np.isfinite(value) and value > 0):
                raise QstsError(f"command_setpoint: regulator {r}: {name} {value!r} must be positive")
        e = self.engine
        self.controls.set_reg_band(
            r, e.reg_default_setpoint_v120[r] if setpoint_v120 is None else float(setpoint_v120),
            e.reg_default_band_v120[r] if band_v120 is None else float(band_v120))

    @property
    def setpoint_v120(self) -> np.ndarray:
        """(R,) the map regulators' present local-control set points [V on the 120 V base]."""
        return self.controls.vreg_v120[:len(self._locked)].copy()

    @property
    def band_v120(self) -> np.ndarray:
        """(R,) the map regulators' present local-control bands [V on the 120 V base]."""
        return self.controls.band_v120[:len(self._locked)].copy()

    def command_cap(self, c: int, state_steps: int | None) -> int:
        """Hold map capacitor bank ``c`` at ``state_steps`` closed steps from the next step on (clipped to
        ``0..cap_steps``); ``None`` returns it to its local CapControl (a bank without one stays where it is).

        Returns the state it will hold (its present state when released).
        """
        self._check_index(c, len(self._cap_locked), "capacitor")
        if state_steps is None:
            self._cap_locked[c] = False
            if self._cap_control[c] >= 0:
                self.controls.block_cap(int(self._cap_control[c]), False)
            return int(self.engine.cap_states()[c])
        st = int(np.clip(int(state_steps), 0, self.engine.cap_steps[c]))
        self._cap_locked[c], self._cap_lock_state[c] = True, st
        if self._cap_control[c] >= 0:
            self.controls.block_cap(int(self._cap_control[c]), True)
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
        if self._pv_volt_var is not None:  # set per plant (set_pv_local)
            curve = volt_var_q_pu(v_pu) * e.pv_kva
            local = np.where(self._pv_volt_var, self._pv_q_kvar + VOLT_VAR_RESPONSE * (curve - self._pv_q_kvar), 0.0)
        elif self.pv_local == "volt_var":
            curve = volt_var_q_pu(v_pu) * e.pv_kva
            local = self._pv_q_kvar + VOLT_VAR_RESPONSE * (curve - self._pv_q_kvar)
        else:
            local = np.zeros(len(p_kw))
        q = np.array([local[k] if c is None else c for k, c in enumerate(self._pv_cmd)], dtype=float)
        q = np.where((p_kw > 0.0) | self.pv_q_at_night, q, 0.0)
        headroom = np.sqrt(np.maximum(e.pv_kva**2 - np.minimum(p_kw, e.pv_pmpp_kw) ** 2, 0.0))
        return np.minimum(np.maximum(q, -headroom), headroom)

    def _set_injections(self, s: int) -> tuple[np.ndarray, np.ndarray]:
        """Set step ``s``'s loads (unless staged) and PV, available P clipped to ``[0, Pmpp]`` and Q as each plant
        applies it; returns (P [kW], Q [kvar]).
        """
        e = self.engine
        load_kw, pv_kw = self._rows(s)
        p = np.minimum(np.maximum(pv_kw, 0.0), e.pv_pmpp_kw)
        q = e.set_pv(p, self._pv_q_target(p, self._pv_v_pu))
        if self._staged != s:
            e.set_loads_kw(load_kw)
        self._staged = None
        return p, np.asarray(q, dtype=float)

    def step(self) -> StepResult:
        """Advance one profile step: set loads and PV, apply held devices, solve, run local control."""
        e, s = self.engine, self._step
        if s >= self.profiles.n_steps:
            raise QstsError(f"step {s} is past the end of the profiles ({self.profiles.n_steps} steps)")
        p, q = self._set_injections(s)

        taps0 = e.taps()  # the engine's, in case its owner moved them between steps
        taps = np.where(self._locked, self._lock_tap, taps0)
        changes = np.abs(taps - taps0)
        if changes.any():
            e.set_taps(taps)
        caps0 = e.cap_states()
        caps = np.where(self._cap_locked, self._cap_lock_state, caps0)
        cap_switches = np.abs(caps - caps0)
        if cap_switches.any():
            e.set_cap_states(caps)
        e.solve()
        t0 = self.profiles.t_ns(s) / 1e9
        self._run_controls(t0, t0 + self._step_s, changes, cap_switches)
        readings = e.readings()

        v = e.node_voltages_pu()
        self._pv_v_pu = self._plant_v_pu(v)
        self._pv_p_kw, self._pv_q_kvar = p, q
        self._step = s + 1
        return StepResult(
            step=s, t_ns=int(self.profiles.t_ns(s)), readings=readings, v_pu=v, taps=e.taps(),
            tap_changes=changes, pv_q_kvar=q, pv_p_kw=p, cap_states=e.cap_states(), cap_switches=cap_switches,
        )

    def _run_controls(self, t0_s: float, t1_s: float, tap_changes: np.ndarray, cap_switches: np.ndarray) -> None:
        """The event clock over ``[t0_s, t1_s)`` on the solved feeder; counts moves into the arrays given."""
        e, ctl = self.engine, self.controls
        n_reg, n_cap = len(tap_changes), len(cap_switches)
        now = t0_s
        sensed = e.sense((now % 86400.0) / 3600.0)
        for _ in range(_MAX_INSTANTS):
            ctl.sample(now, sensed[0], e.control_taps(), sensed[1], sensed[2], e.control_cap_states(), sensed[3])
            for _ in range(_MAX_ROUNDS):  # actions due now, a power flow, the controls sample again
                done = ctl.pop_due(now, e.control_taps(), e.control_cap_states())
                if not (done.taps or done.cap_states):
                    break
                all_taps = e.control_taps()
                for r, tap in done.taps.items():
                    if r < n_reg:
                        tap_changes[r] += abs(tap - all_taps[r])
                    e.set_control_tap(r, tap)
                states = e.control_cap_states()
                for j, n in done.cap_states.items():
                    b = int(self._cap_bank[j])
                    if b < n_cap:
                        cap_switches[b] += abs(n - int(states[j]))
                    e.set_control_cap_state(j, n)
                e.solve()
                sensed = e.sense((now % 86400.0) / 3600.0)
                ctl.sample(now, sensed[0], e.control_taps(), sensed[1], sensed[2], e.control_cap_states(),
                           sensed[3])
            nxt = ctl.next_time_s(now)
            if nxt >= t1_s:
                return
            now = nxt
            if self._has_time_caps:
                sensed = (sensed[0], e.sense((now % 86400.0) / 3600.0)[1], sensed[2], sensed[3])
        raise QstsError(f"step {self._step}: local controls did not settle within {_MAX_INSTANTS} instants")
