"""OpenDSS's own time-driven control loop over per-minute loads and PV: the reference our device physics and
the baselines are set beside.

Two uses:

- :func:`opendss_control_loop`: per-minute loads (PV at zero) through OpenDSS's loop, the taps and bank states at
  the end of each minute; ``control_check.py`` compares it with :class:`~simulator_bridge.simulation.qsts.Qsts`.
- :class:`OpenDssLoop` and :func:`reference_metrics`: the ``opendss`` reference case of ``cvvc evaluate``: the
  feeder's year profiles (loads *and* PV, PV at unity power factor as in the ``none`` case) stepped minute by
  minute through OpenDSS's own RegControls and CapControls (``set controlmode=time``, their own ``delay``,
  ``tapdelay``, ``Delay``, ``DelayOFF``, ``DeadTime``), with the paper's IV.F metrics computed by the same
  :class:`~simulator_bridge.simulation.metrics_stream.MetricsAccumulator` as every bus run (``for_feeder``: the zone's
  nodes).

Within a minute the loads and PV are held and OpenDSS solves ``60 / step_s`` times at ``start + 60 m + k step_s``
[s]; the minute's voltages are those of its last solve (as a QSTS step reports the solution after its controls
acted), and every tap and capacitor step moved between two solves is counted (|change| per solve, so a regulator
that moves twice within a minute counts two). The clock's time of day is the profiles' ``t_ns`` modulo a day,
the same clock :class:`~simulator_bridge.simulation.qsts.Qsts` gives the time-type CapControls.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from simulator_bridge.opendss.engine import EngineError, FeederEngine

if TYPE_CHECKING:
    from schemas.devicemap import DeviceMap
    from simulator_bridge.simulation.metrics import Metrics
    from simulator_bridge.simulation.qsts import Profiles

__all__ = ["MinuteResult", "OpenDssControlRun", "OpenDssLoop", "opendss_control_loop", "reference_metrics"]

_DAY_S = 86_400.0


@dataclass(frozen=True)
class MinuteResult:
    """One minute of OpenDSS's own loop.

    Attributes
    ----------
    v_pu : (n_nodes,) every node's voltage after the minute's last solve [pu of its L-N base].
    tap_changes : (R,) int, taps each map regulator moved during the minute.
    cap_switches : (C,) int, steps each map capacitor bank opened or closed during the minute.
    pv_q_kvar : (K,) each plant's reactive power [kvar] (0: unity power factor).
    taps : (NR,) int, every RegControl's tap at the end of the minute (``reg_controls`` order).
    cap_states : (NC,) int, the bank of every CapControl's closed steps at the end (``cap_controls`` order).
    """

    v_pu: np.ndarray
    tap_changes: np.ndarray
    cap_switches: np.ndarray
    pv_q_kvar: np.ndarray
    taps: np.ndarray
    cap_states: np.ndarray


class OpenDssLoop:
    """A feeder engine handed to OpenDSS's own control loop, stepped one minute at a time.

    Parameters
    ----------
    engine : a fresh :class:`FeederEngine` (its setters must not be used afterwards; this object owns it).
    step_s : OpenDSS's time step [s], a divisor of 60.
    start_tod_s : time of day of the first minute [s].
    skip_quiet : skip the rest of a minute's solves once OpenDSS's control queue is empty (see below).

    Quiet minutes: loads and PV are held within a minute, so once a solve leaves OpenDSS's control queue empty
    (no RegControl or CapControl armed; an armed control, a ``DeadTime`` included, is an action on the queue) the
    minute's remaining solves would each find the same solution and arm nothing; they are skipped and the clock
    set to the minute's last step. Not with a time-type CapControl (its condition is the clock itself). The
    counts equal the unskipped loop's, the voltages within the solver's tolerance (a repeated solve only refines
    the solution; ``tests/simulator_bridge/test_opendss_loop.py``).
    """

    def __init__(self, engine: FeederEngine, *, step_s: float, start_tod_s: float, skip_quiet: bool = True) -> None:
        if step_s <= 0 or abs(60.0 / step_s - round(60.0 / step_s)) > 1e-9:
            raise EngineError(f"OpenDSS control loop: step_s {step_s} must divide 60 s")
        self.engine = engine
        self.step_s = float(step_s)
        self._n_sub = int(round(60.0 / step_s))
        self._zero_q = np.zeros(len(engine.pv_ids))
        engine.start_time_control(self.step_s, start_tod_s)
        self._minute = 0
        self._tod0_s = float(start_tod_s)
        # a time-type CapControl acts on the clock alone: every solve counts there
        self.skip_quiet = bool(skip_quiet) and not any(c.kind == "time" for c in engine.cap_controls)
        self.skipped = 0  # solves skipped so far

    def step(self, load_kw: np.ndarray, pv_kw: np.ndarray) -> MinuteResult:
        """Hold ``load_kw`` (n_loads,) [kW] and PV available power ``pv_kw`` (K,) [kW] at unity power factor
        for one minute of OpenDSS's solves; count every move of the map's devices.
        """
        e = self.engine
        e.set_loads_kw(load_kw)
        q = e.set_pv(pv_kw, self._zero_q)
        n_reg, n_cap = len(e.regulator_ids), len(e.capacitor_ids)
        taps, caps = e.taps(), e.cap_states()
        tap_changes = np.zeros(n_reg, dtype=np.int64)
        cap_switches = np.zeros(n_cap, dtype=np.int64)
        for k in range(self._n_sub):
            try:
                e.time_control_solve()
            except EngineError as err:
                raise EngineError(f"{err} (minute {self._minute} of the loop)") from err
            new_taps, new_caps = e.taps(), e.cap_states()
            tap_changes += np.abs(new_taps - taps)
            cap_switches += np.abs(new_caps - caps)
            taps, caps = new_taps, new_caps
            if self.skip_quiet and k < self._n_sub - 1 and e.time_control_pending() == 0:
                # nothing armed and nothing changes until the next minute's loads: the rest of the minute's
                # solves would find this solution again; the clock goes to the minute's last step
                e.set_time_control_clock(self._tod0_s + 60.0 * self._minute + 60.0 - self.step_s)
                self.skipped += self._n_sub - 1 - k
                break
        self._minute += 1
        return MinuteResult(v_pu=e.node_voltages_pu(), tap_changes=tap_changes, cap_switches=cap_switches,
                            pv_q_kvar=q, taps=e.control_taps(), cap_states=e.control_cap_states())

    def close(self) -> None:
        """Dispose of the engine's OpenDSS context."""
        self.engine.close()


def reference_metrics(device_map: DeviceMap, profiles: Profiles, *, start_step: int, steps: int,
                      step_s: float, skip_quiet: bool = True) -> Metrics:
    """The ``opendss`` reference case: ``steps`` minutes of ``profiles`` from ``start_step`` through OpenDSS's own
    control loop at ``step_s`` [s], measured with the same IV.F metrics as every run (``MetricsAccumulator``).

    ``profiles`` must be the feeder's (columns in the engine's load and plant order) at 60 s per row;
    ``skip_quiet``: see :class:`OpenDssLoop`. As every QSTS run, the loop first runs ``SETTLE_S`` on the first
    minute's loads and PV, uncounted (``simulator_bridge.simulation.qsts``: the feeder starts settled).
    """
    from simulator_bridge.simulation.metrics_stream import MetricsAccumulator
    from simulator_bridge.simulation.qsts import SETTLE_S

    if profiles.step_s != 60:
        raise EngineError(f"the OpenDSS reference steps minutes; the profiles have {profiles.step_s} s rows")
    if not (0 <= start_step and start_step + steps <= profiles.n_steps and steps > 0):
        raise EngineError(f"steps {start_step}..{start_step + steps} outside the profiles' 0..{profiles.n_steps}")
    engine = FeederEngine(device_map)
    try:
        acc = MetricsAccumulator.for_feeder(device_map, engine, step_s=60)
        settle_min = int(round(SETTLE_S / 60.0))
        loop = OpenDssLoop(engine, step_s=step_s,
                           start_tod_s=(profiles.t_ns(start_step) / 1e9 - 60.0 * settle_min) % _DAY_S,
                           skip_quiet=skip_quiet)
        load, pv = profiles.load_kw(start_step, start_step + steps), profiles.pv_kw(start_step, start_step + steps)
        for _ in range(settle_min):
            loop.step(load[0], pv[0])
        for m in range(steps):
            r = loop.step(load[m], pv[m])
            acc.update(r.v_pu, r.tap_changes, r.pv_q_kvar, r.cap_switches)
    finally:
        engine.close()
    return acc.result()


@dataclass(frozen=True)
class OpenDssControlRun:
    """OpenDSS's own time-driven control loop over per-minute loads (:func:`opendss_control_loop`).

    Attributes
    ----------
    regcontrol_names : every RegControl of the model, ``FeederEngine.reg_controls`` order (the map's first).
    capcontrol_names : every CapControl of the model, ``FeederEngine.cap_controls`` order.
    taps : (n_minutes, NR) int, each RegControl's tap at the end of each minute.
    cap_states : (n_minutes, NC) int, closed steps of each CapControl's bank at the end of each minute.
    step_s : OpenDSS's time step [s]. elapsed_s : wall time of the loop [s].
    """

    regcontrol_names: tuple[str, ...]
    capcontrol_names: tuple[str, ...]
    taps: np.ndarray
    cap_states: np.ndarray
    step_s: float
    elapsed_s: float


def opendss_control_loop(device_map: DeviceMap, load_kw: np.ndarray, *, step_s: float = 60.0,
                         start_tod_s: float = 0.0, tolerance: float = 1e-6) -> OpenDssControlRun:
    """Run OpenDSS's own control loop over per-minute loads, PV plants at zero output: the reference that
    ``qsts.py``'s local device physics is checked against (``control_check.py``).

    Parameters
    ----------
    load_kw : (n_minutes, n_loads) every load's kW per minute (``FeederEngine.load_names`` order).
    step_s : OpenDSS's step [s], a divisor of 60. start_tod_s : time of day of the first minute [s].
    """
    eng = FeederEngine(device_map, tolerance=tolerance)
    try:
        loop = OpenDssLoop(eng, step_s=step_s, start_tod_s=start_tod_s)
        zero_pv = np.zeros(len(eng.pv_ids))
        rows = np.asarray(load_kw, dtype=float)
        taps = np.zeros((len(rows), len(eng.reg_controls)), dtype=int)
        states = np.zeros((len(rows), len(eng.cap_controls)), dtype=int)
        t = time.perf_counter()
        for m, row in enumerate(rows):
            r = loop.step(row, zero_pv)
            taps[m], states[m] = r.taps, r.cap_states
        elapsed = time.perf_counter() - t
    finally:
        eng.close()
    return OpenDssControlRun(regcontrol_names=tuple(r.name for r in eng.reg_controls),
                             capcontrol_names=tuple(c.name for c in eng.cap_controls),
                             taps=taps, cap_states=states, step_s=float(step_s), elapsed_s=elapsed)
