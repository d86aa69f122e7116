"""The feeder engine: one OpenDSS context per feeder object (made by ``dss_context.py``, the only importer of OpenDSS).

One :class:`FeederEngine` holds one OpenDSS context (:func:`new_context`), compiled from a device map.
It sets loads, PV plants, regulator taps and capacitor banks, solves one power flow, and reads what field
devices would measure (:class:`FieldReadings`), what every RegControl and CapControl of the model samples
(:meth:`FeederEngine.sense`) and the truth (every node's voltage). Device physics that spans time (the local
controls' event clock, volt-var, night behaviour) lives in ``qsts.py`` and ``controls.py``; this module is one
snapshot. :meth:`FeederEngine.start_time_control` and :meth:`FeederEngine.time_control_solve` hand the controls
to OpenDSS's own time-driven loop instead, the reference ``opendss_loop.py`` steps.

Every OpenDSS name and unit is translated to ours here:

==========================  ==========================================================================
ours                        OpenDSS
==========================  ==========================================================================
``node_names``              ``Circuit.AllNodeNames`` lower case, ``"bus.phase"``
``v_pu``                    ``Circuit.AllBusVmagPu`` (each node on its own bus ``kVBase``, L-N)
``head_p_kw`` (load conv.)  ``CktElement.Powers`` of terminal 1 of ``head_element``
``pv_p_kw`` (gen. conv.)    minus ``CktElement.Powers`` of the ``PVSystem``
``reg_v120``                ``|V(winding, PTphase)| / PTratio`` (``RegControl`` properties)
``reg_v120_compared``       ``|V/PTratio + (R + jX)·I/CTprim|``, ``I`` into the controlled winding
``reg_tap``                 ``RegControls.TapNumber``
==========================  ==========================================================================

Conventions (see ``docs/simulation.md``): voltages are line-to-neutral; ``q_kvar > 0`` injects reactive
power at PV plants (generator convention); at the feeder head P and Q are positive into the feeder.
OpenDSS's own controls are off (``set controlmode=off``); every control's behaviour is ``controls.py``'s (but for
an engine handed to OpenDSS's loop with ``start_time_control``).

The engine's helpers, each a plain module: ``dss_context.py`` (the context's lifecycle, compiling, the load batch),
``circuit_tables.py`` (what setup reads from the model: names, RegControl and CapControl wiring, distances),
``readout.py`` (the per-solve batch read and :class:`FieldReadings`) and ``sensitivities.py`` (the perturbation
sensitivities of :meth:`FeederEngine.perturbation_sensitivities`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from schemas.devicemap import DeviceMap
from schemas.messages import CapControlType
from simulator_bridge.errors import EngineError
from simulator_bridge.opendss.circuit_tables import (
    add_pv_plants,
    bus_distance_ohm,
    check_names,
    disable_meters,
    pv_name,
    read_capacitors,
    read_regulators,
)
from simulator_bridge.opendss.controls import CapControlSettings, RegControlSettings
from simulator_bridge.opendss.dss_context import (
    DSS_LIFECYCLE,
    DssException,
    LoadBatch,
    command,
    compile_feeder,
    new_context,
)
from simulator_bridge.opendss.readout import FieldReadings, Readout
from simulator_bridge.opendss.sensitivities import Sensitivities, perturbation_sensitivities

__all__ = [
    "EngineError",
    "EngineState",
    "FeederEngine",
]


@dataclass(frozen=True)
class EngineState:
    """Everything a power flow of an engine depends on besides its circuit (``FeederEngine.state``).

    Attributes
    ----------
    load_kw : (n_loads,) every load's active power, ``load_names`` order [kW].
    pv_p_kw, pv_q_kvar : (K,) each plant's available active power [kW] and applied reactive power [kvar].
    control_taps : (NR,) tap of every RegControl of the model, ``reg_controls`` order (the map's first).
    bank_states : (NB,) closed steps of every capacitor bank of the model (the map's first).
    """

    load_kw: np.ndarray
    pv_p_kw: np.ndarray
    pv_q_kvar: np.ndarray
    control_taps: np.ndarray
    bank_states: np.ndarray


class FeederEngine:
    """One OpenDSS feeder in its own context: set, solve, read.

    Parameters
    ----------
    device_map : DeviceMap
        The feeder and its field devices (``schemas.devicemap.load_device_map``).
    tolerance : float
        OpenDSS solution tolerance [pu of voltage change between iterations]. Finite-difference
        sensitivities need 1e-6 or smaller.

    Raises
    ------
    EngineError
        The master file or an ``extra_commands`` entry does not compile, or the base case does not solve.
    DeviceMapError
        The map names a bus, element or RegControl that the model does not have.

    Attributes
    ----------
    node_names : OpenDSS ``AllNodeNames``, lower case ``"bus.phase"``; the order of every node vector.
    node_in_feeder : (n_nodes,) bool, the node is on the feeder side of the head meter (or at it).
    head_node_index : (n,) int, the nodes of the bus where the feeder-head meter measures.
    node_distance_ohm : (n_nodes,) electrical distance from ``feeder.source_bus`` [ohm] (see
        ``docs/simulation.md``).
    load_names, load_kw_nominal, load_distance_ohm : every load, its model kW [kW] and distance [ohm].
    pv_ids, pv_node_index, pv_distance_ohm, pv_kva, pv_pmpp_kw : the map's PV plants, their nodes
        (indices into ``node_names``), distance [ohm], ratings [kVA], [kW].
    regulator_ids, reg_primary_node, reg_secondary_node : the map's regulators and the nodes of their PT
        phase on each side.
    reg_pu_per_v120 : (R,) pu of the secondary node per volt on the 120 V base (``ptratio / V_base``).
    reg_default_setpoint_v120, reg_default_band_v120 : (R,) local-control defaults: the map's, else the
        model's ``vreg`` and ``band`` [V on the 120 V base].
    reg_tap_max : (R,) highest tap position (taps run ``-reg_tap_max..reg_tap_max``).
    capacitor_ids : the map's ``[[capacitor]]`` ids, map order.
    cap_kvar : (C,) rated kvar of each bank, all steps [kvar].
    cap_steps : (C,) int, number of steps of each bank.
    cap_control_type : per bank, its CapControl's type: ``"voltage"``, ``"kvar"``, ``"current"``, ``"pf"``,
        ``"time"``, ``"follow"``, or ``"none"`` (no CapControl).
    reg_controls : every RegControl of the model with its own settings (the map's regulators first, map order).
    cap_controls : every CapControl of the model with its own settings (model order).
    cap_control_index : (C,) each map bank's CapControl (index into ``cap_controls``), -1 without one.
    cap_control_bank : (NC,) each CapControl's bank (the map's banks are 0..C-1).
    """

    def __init__(self, device_map: DeviceMap, *, tolerance: float = 1e-6) -> None:
        self.device_map = device_map
        self.tolerance = float(tolerance)
        self._where = f"device map of feeder {device_map.feeder.name!r} (in {device_map.root})"
        self._dss = new_context()
        with DSS_LIFECYCLE:
            compile_feeder(self._dss, device_map.master_path)
            for cmd in device_map.feeder.extra_commands:
                command(self._dss, cmd, what=f"{self._where}: extra command")
        check_names(self._dss, device_map, self._where)
        add_pv_plants(self._dss, device_map, self._where)
        command(self._dss, "set controlmode=off", what="engine setup")
        command(self._dss, f"set tolerance={self.tolerance:.3g}", what="engine setup")
        command(self._dss, "set maxiterations=100", what="engine setup")
        # The circuit's structure never changes after setup (only values: loads, PV, taps), so KLU may
        # keep its symbolic factorisation across Y rebuilds (a tap change): ~1.5x faster re-solve.
        self._dss.YMatrix.SolverOptions(2)  # SolverOptions_ReuseSymbolicFactorization
        disable_meters(self._dss)
        self._api = self._dss.to_dss_python()
        self._circuit = self._api.ActiveCircuit
        self._solve()  # builds the node lists that the element readers below need (no readout yet)

        self.node_names: tuple[str, ...] = tuple(n.lower() for n in self._dss.Circuit.AllNodeNames())
        self._node_index = {n: i for i, n in enumerate(self.node_names)}
        self._init_loads()
        self._init_pv()
        self._init_regulators()
        self._init_capacitors()
        self._readout = Readout(self._dss, self.node_names, self._node_index, device_map.feeder.head_element,
                                self._pv_names, self._regs, self._cap_names, self._cc_monitored, self.cap_controls,
                                self._where)
        bus_distance, feeder_buses, head_bus = bus_distance_ohm(self._dss, device_map.feeder.source_bus,
                                                                 device_map.feeder.head_element)
        self.node_in_feeder = np.array([n.split(".")[0] in feeder_buses for n in self.node_names])
        self.head_node_index = np.array([i for i, n in enumerate(self.node_names) if n.split(".")[0] == head_bus])
        self.node_distance_ohm = np.array([bus_distance.get(n.split(".")[0], np.inf) for n in self.node_names])
        self.load_distance_ohm = np.array([bus_distance.get(b, np.inf) for b in self._load_buses])
        self.pv_distance_ohm = np.array([bus_distance.get(p.bus.split(".")[0].lower(), np.inf)
                                         for p in device_map.pv])
        self.solve()

    # ------------------------------------------------------------------ setup
    def _init_loads(self) -> None:
        d = self._dss
        names, kw, buses = [], [], []
        i = d.Loads.First()
        while i > 0:
            names.append(d.Loads.Name().lower())
            kw.append(d.Loads.kW())
            buses.append(d.CktElement.BusNames()[0].split(".")[0].lower())
            i = d.Loads.Next()
        self.load_names: tuple[str, ...] = tuple(names)
        self.load_kw_nominal = np.array(kw, dtype=float)
        self._load_kw = self.load_kw_nominal.copy()  # as last set (``state``)
        self._load_buses = tuple(buses)
        self._tan_phi = float(np.tan(np.arccos(self.device_map.feeder.load_pf)))
        self._loads = LoadBatch(d, self.load_names)

    def _init_pv(self) -> None:
        pvs = self.device_map.pv
        self.pv_ids: tuple[str, ...] = tuple(p.id for p in pvs)
        self._pv_names = tuple(pv_name(self.device_map, p.id) for p in pvs)
        self.pv_kva = np.array([p.kva for p in pvs], dtype=float)
        self.pv_pmpp_kw = np.array([p.pmpp_kw for p in pvs], dtype=float)
        node_index = []
        for name in self._pv_names:
            self._dss.Circuit.SetActiveElement(f"PVSystem.{name}")
            bus = self._dss.CktElement.BusNames()[0].split(".")[0].lower()
            n_phases = int(self._dss.CktElement.NumPhases())
            phases = list(self._dss.CktElement.NodeOrder())[:n_phases]
            node_index.append(tuple(self._node_index[f"{bus}.{ph}"] for ph in sorted(phases)))
        self.pv_node_index: tuple[tuple[int, ...], ...] = tuple(node_index)
        self._pv_p_kw = np.zeros(len(pvs))
        self._pv_q_kvar = np.zeros(len(pvs))

    def _init_regulators(self) -> None:
        """Every RegControl of the model: the map's first (map order), then the others (model order)."""
        d = self._dss
        regs, settings = read_regulators(d, self.device_map, self._node_index, self._where)
        self._regs = regs
        self.reg_controls: tuple[RegControlSettings, ...] = settings
        n = len(self.device_map.regulator)
        self.regulator_ids: tuple[str, ...] = tuple(r.id for r in self.device_map.regulator)
        self.reg_primary_node = np.array([r.primary_node for r in regs[:n]], dtype=int)
        self.reg_secondary_node = np.array([r.secondary_node for r in regs[:n]], dtype=int)
        self.reg_pu_per_v120 = np.array([r.pu_per_v120 for r in regs[:n]], dtype=float)
        self.reg_default_setpoint_v120 = np.array(
            [s.setpoint_v120 if s.setpoint_v120 is not None else c.vreg_v120
             for s, c in zip(self.device_map.regulator, settings, strict=False)], dtype=float)
        self.reg_default_band_v120 = np.array(
            [s.band_v120 if s.band_v120 is not None else c.band_v120
             for s, c in zip(self.device_map.regulator, settings, strict=False)], dtype=float)
        self.reg_tap_max = np.array([r.tap_max for r in regs[:n]], dtype=int)
        rc = d.RegControls
        self._all_taps = np.empty(len(regs), dtype=int)
        for r, reg in enumerate(regs):
            rc.Name(reg.regcontrol)
            self._all_taps[r] = rc.TapNumber()
        self._taps = self._all_taps[:n]  # a view: the map's regulators

    def _init_capacitors(self) -> None:
        """The map's banks (map order), then every other bank a CapControl of the model switches."""
        t = read_capacitors(self._dss, self.device_map, self._where)
        specs = self.device_map.capacitor
        banks, controls = t.banks, t.controls
        n = len(specs)
        self._banks = banks
        self._bank_kvar = np.array(t.kvar, dtype=float)
        self._bank_steps = np.array(t.steps, dtype=int)
        self._bank_states = np.array(t.states, dtype=int)
        self.capacitor_ids: tuple[str, ...] = tuple(c.id for c in specs)
        self._cap_names = tuple(banks[:n])
        self.cap_kvar = self._bank_kvar[:n].copy()
        self.cap_steps = self._bank_steps[:n].copy()
        self._cap_states = self._bank_states[:n]  # a view: the map's banks
        self.cap_controls: tuple[CapControlSettings, ...] = controls
        self._cc_monitored = t.monitored
        self.cap_control_bank = np.array(t.bank_of, dtype=int)
        # each map bank's control (index into cap_controls), -1 without one
        by_name = {c.name: j for j, c in enumerate(controls)}
        self.cap_control_index = np.array([by_name[c.capcontrol.lower()] if c.capcontrol else -1 for c in specs],
                                          dtype=int)
        self.cap_control_type: tuple[CapControlType, ...] = tuple(
            controls[j].kind if j >= 0 else "none" for j in self.cap_control_index)

    # ------------------------------------------------------------------ set
    def set_loads_kw(self, p_kw: np.ndarray) -> None:
        """Set every load's active power; reactive power follows the feeder's ``load_pf``.

        Parameters
        ----------
        p_kw : (n_loads,) active power per load, in ``load_names`` order [kW].
        """
        p = np.ascontiguousarray(p_kw, dtype=float)
        if p.shape != (self._loads.n_loads,):
            raise EngineError(f"set_loads_kw: expected {self._loads.n_loads} loads, got shape {p.shape}")
        if not np.all(np.isfinite(p)):
            raise EngineError("set_loads_kw: non-finite load power; check the profiles")
        q = np.ascontiguousarray(p * self._tan_phi)
        self._load_kw[:] = p
        self._loads.set(p, q)

    def set_pv(self, p_kw: np.ndarray, q_kvar: np.ndarray) -> np.ndarray:
        """Set each PV plant's available active power and its reactive power set point.

        ``p_kw`` is clipped to ``[0, pmpp_kw]``; ``q_kvar`` to the inverter headroom
        ``±sqrt(kva² - p²)`` (watt priority). Night behaviour is the caller's (``qsts.py``).

        Parameters
        ----------
        p_kw : (K,) available AC power [kW].
        q_kvar : (K,) reactive power set point, generator convention [kvar].

        Returns
        -------
        (K,) the reactive power actually applied [kvar].
        """
        # np.minimum/np.maximum rather than np.clip: the same result, a few µs less per call
        p = np.minimum(np.maximum(np.asarray(p_kw, dtype=float), 0.0), self.pv_pmpp_kw)
        headroom = np.sqrt(np.maximum(self.pv_kva**2 - p**2, 0.0))
        q = np.minimum(np.maximum(np.asarray(q_kvar, dtype=float), -headroom), headroom)
        if p.shape != self.pv_kva.shape or q.shape != self.pv_kva.shape or not np.all(np.isfinite(q)):
            raise EngineError(f"set_pv: expected {len(self.pv_ids)} finite values, got {p_kw!r}, {q_kvar!r}")
        # Through the PVSystems interface: a property edit (text or batch) rebuilds the PV's Yprim and
        # makes the next solve ~5x slower on IEEE 8500.
        pv = self._dss.PVsystems
        for k in np.flatnonzero((p != self._pv_p_kw) | (q != self._pv_q_kvar)):
            pv.Name(self._pv_names[k])
            pv.Irradiance(p[k] / self.pv_pmpp_kw[k])
            pv.kvar(q[k])
        self._pv_p_kw, self._pv_q_kvar = p, q
        return q.copy()

    def pv_setpoints(self) -> tuple[np.ndarray, np.ndarray]:
        """The present (available P [kW], applied Q [kvar]) of every plant, each (K,)."""
        return self._pv_p_kw.copy(), self._pv_q_kvar.copy()

    def set_taps(self, taps: np.ndarray) -> None:
        """Set every map regulator's tap position (integers within ``±reg_tap_max``)."""
        t = np.asarray(taps)
        n = len(self._taps)
        if t.shape != (n,) or np.any(t != np.round(t)) or np.any(np.abs(t) > self.reg_tap_max):
            raise EngineError(f"set_taps: expected {n} integer taps within ±{self.reg_tap_max}, got {taps!r}")
        for r in np.flatnonzero(t != self._taps).tolist():
            self._set_tap(r, int(t[r]))

    def _set_tap(self, r: int, tap: int) -> None:
        # Through the transformer, not RegControls.TapNumber: that setter makes OpenDSS reprocess the
        # whole bus list (~2.5x slower solve after it on IEEE 8500); the voltages are the same.
        reg = self._regs[r]
        xf = self._dss.Transformers
        xf.Name(reg.transformer)
        xf.Wdg(reg.tap_winding)
        xf.Tap(reg.tap_center + tap * reg.tap_step)
        self._all_taps[r] = tap

    def taps(self) -> np.ndarray:
        """(R,) present tap positions of the map's regulators (only this engine's setters move them)."""
        return self._taps.copy()

    def control_taps(self) -> np.ndarray:
        """(NR,) present tap of every RegControl of the model, ``reg_controls`` order (the map's first)."""
        return self._all_taps.copy()

    def set_control_tap(self, r: int, tap: int) -> None:
        """Set RegControl ``r``'s (``reg_controls`` order) tap position, clipped to its range."""
        t = max(-self._regs[r].tap_max, min(self._regs[r].tap_max, int(tap)))
        if t != self._all_taps[r]:
            self._set_tap(r, t)

    def set_cap_states(self, states: np.ndarray) -> None:
        """Set every map capacitor bank's number of closed steps (integers within ``0..cap_steps``).

        Steps close in order (step 1 first), as OpenDSS's CapControl switches them.
        """
        st = np.asarray(states)
        if st.shape != self.cap_steps.shape or np.any(st != np.round(st)) or np.any(st < 0) \
                or np.any(st > self.cap_steps):
            raise EngineError(f"set_cap_states: expected {len(self.cap_steps)} integer states within "
                              f"0..{self.cap_steps.tolist()}, got {states!r}")
        for c in np.flatnonzero(st != self._cap_states).tolist():
            self._set_bank(c, int(st[c]))

    def _set_bank(self, b: int, n: int) -> None:
        # The steps' states and the terminal's switch, as OpenDSS's CapControl moves them: a bank its own
        # control opened at compile time has an open terminal, and closing steps alone would leave it open.
        cap = self._dss.Capacitors
        cap.Name(self._banks[b])
        cap.States([1] * n + [0] * (int(self._bank_steps[b]) - n))
        self._dss.Circuit.SetActiveElement(f"Capacitor.{self._banks[b]}")
        if n > 0:
            self._dss.CktElement.Close(1, 0)
        else:
            self._dss.CktElement.Open(1, 0)
        self._bank_states[b] = n

    @property
    def cap_phases(self) -> list[list[int]]:
        """Each map bank's phases (1-3), from its terminal's conductors (all three when none is known)."""
        cond = self._readout.cap_conductors
        return [[ph + 1 for ph in range(3) if row[ph] >= 0] or [1, 2, 3] for row in cond[: len(self.cap_steps)]]

    def cap_states(self) -> np.ndarray:
        """(C,) closed steps of each map capacitor bank."""
        return self._cap_states.copy()

    def control_cap_states(self) -> np.ndarray:
        """(NC,) closed steps of the bank of every CapControl of the model, ``cap_controls`` order."""
        return self._bank_states[self.cap_control_bank]

    def set_control_cap_state(self, j: int, n: int) -> None:
        """Set the bank of CapControl ``j`` (``cap_controls`` order) to ``n`` closed steps."""
        b = int(self.cap_control_bank[j])
        n = max(0, min(int(self._bank_steps[b]), int(n)))
        if n != self._bank_states[b]:
            self._set_bank(b, n)

    def state(self) -> EngineState:
        """A copy of everything the next power flow depends on besides the circuit (loads, PV, taps, banks)."""
        return EngineState(load_kw=self._load_kw.copy(), pv_p_kw=self._pv_p_kw.copy(),
                           pv_q_kvar=self._pv_q_kvar.copy(), control_taps=self._all_taps.copy(),
                           bank_states=self._bank_states.copy())

    def set_state(self, state: EngineState) -> None:
        """Put this engine in ``state`` (another engine's of the same device map, see :meth:`state`); only what
        differs is set. The next :meth:`solve` then solves what the other engine's did.
        """
        if state.control_taps.shape != self._all_taps.shape or state.bank_states.shape != self._bank_states.shape:
            raise EngineError("set_state: the state is of another circuit "
                              f"({state.control_taps.size} RegControls, {state.bank_states.size} banks; this one has "
                              f"{self._all_taps.size}, {self._bank_states.size})")
        if not np.array_equal(state.load_kw, self._load_kw):
            self.set_loads_kw(state.load_kw)
        self.set_pv(state.pv_p_kw, state.pv_q_kvar)
        for r in np.flatnonzero(state.control_taps != self._all_taps):
            self._set_tap(int(r), int(state.control_taps[r]))
        for b in np.flatnonzero(state.bank_states != self._bank_states):
            self._set_bank(int(b), int(state.bank_states[b]))

    # ------------------------------------------------------------------ solve and read
    def solve(self) -> None:
        """Solve one power flow at the present loads, PV and taps.

        Raises
        ------
        EngineError
            OpenDSS did not converge.
        """
        self._readout.invalidate()
        self._solve()

    def _solve(self) -> None:
        try:
            self._dss.Solution.Solve()
        except DssException as e:
            raise EngineError(f"{self.device_map.feeder.name}: power flow failed: {e}") from e
        if not self._dss.Solution.Converged():
            raise EngineError(f"{self.device_map.feeder.name}: power flow did not converge; check loads/PV "
                              "for unrealistic values")

    # ------------------------------------------------------------------ OpenDSS's own control loop
    def start_time_control(self, step_s: float, start_tod_s: float) -> None:
        """Hand every RegControl and CapControl to OpenDSS's own time-driven control loop from now on.

        ``set controlmode=time`` and ``set mode=daily stepsize=step_s number=1``: each
        :meth:`time_control_solve` then moves OpenDSS's clock by ``step_s`` [s] and solves, its controls acting
        with their own delays on its time-stamped queue. The clock is set so that the first solve is at
        ``start_tod_s`` [s of the day]. Loads and PV keep the values this engine sets (no model here gives a
        load or PV system a ``daily`` shape, the only one daily mode applies; ``tests/simulator_bridge/
        test_opendss_loop.py`` checks the first solve against a snapshot).
        The engine's own taps and bank states follow OpenDSS's after every :meth:`time_control_solve`; its
        setters must not be used any more (a tap set through the transformer bypasses the RegControl).
        """
        for cmd in ("set controlmode=time", "set maxcontroliter=100", f"set mode=daily stepsize={step_s:g}s number=1"):
            command(self._dss, cmd, what=f"{self.device_map.feeder.name}: OpenDSS control loop")
        self.set_time_control_clock(start_tod_s - step_s)  # the clock moves by one step before each solve

    def set_time_control_clock(self, t_s: float) -> None:
        """Set OpenDSS's clock to ``t_s`` [s from the first day's midnight; beyond a day as OpenDSS counts, hours
        past 24; below 0 in the first hour]: the next :meth:`time_control_solve` is one step later.
        """
        t = float(t_s)
        hour = max(int(t // 3600), 0)
        self._dss.Solution.Hour(hour)
        self._dss.Solution.Seconds(t - 3600.0 * hour)

    def time_control_pending(self) -> int:
        """Control actions on OpenDSS's queue (armed, due later) after the last :meth:`time_control_solve`."""
        return int(self._dss.CtrlQueue.QueueSize())

    def time_control_solve(self) -> None:
        """One step of OpenDSS's own control loop (after :meth:`start_time_control`): move its clock, solve with
        its controls, and read every RegControl's tap and every bank's closed steps back from OpenDSS.

        Raises
        ------
        EngineError
            OpenDSS failed or did not converge.
        """
        self._readout.invalidate()
        d = self._dss
        try:
            d.Solution.Solve()
        except DssException as e:
            raise EngineError(f"{self.device_map.feeder.name}: OpenDSS control loop failed: {e}") from e
        if not d.Solution.Converged():
            raise EngineError(f"{self.device_map.feeder.name}: OpenDSS control loop did not converge")
        rc, cap = d.RegControls, d.Capacitors
        for r, reg in enumerate(self._regs):
            rc.Name(reg.regcontrol)
            self._all_taps[r] = rc.TapNumber()
        for b, name in enumerate(self._banks):
            cap.Name(name)
            self._bank_states[b] = sum(cap.States())

    def node_voltages_pu(self) -> np.ndarray:
        """(n_nodes,) voltage magnitude of every node, in ``node_names`` order [pu of its bus's L-N base]."""
        return np.array(self._circuit.AllBusVmagPu, dtype=float)

    def sense(self, tod_h: float = float("nan")) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What every RegControl and CapControl of the model samples at the present solution.

        Parameters
        ----------
        tod_h : time of day [h]: the time-type CapControls' quantity (kept for :meth:`readings`).

        Returns
        -------
        reg_v120 : (NR,) each RegControl's compared voltage (``reg_controls`` order) [V on the 120 V base].
        cap_value : (NC,) each CapControl's quantity in its type's unit (``cap_controls`` order): V on its PT
            base, A on its CT base, kvar, PF on OpenDSS's 0..2 scale, hour of day.
        cap_v : (NC,) the voltage its ``VoltOverride`` tests [V on the PT base].
        cap_q_kvar : (NC,) reactive power into its monitored terminal [kvar].
        """
        return self._readout.sense(tod_h)

    def readings(self) -> FieldReadings:
        """What the field devices measure at the present solution (call after :meth:`solve`).

        Powers are ``V·conj(I)`` per conductor with ``I`` into the element (OpenDSS's convention): into
        the feeder at the head, negated at PV plants (generator convention). ``cap_control_value`` is what
        :meth:`sense` last computed (NaN before the first call, and for a bank without a CapControl).
        """
        return self._readout.readings(self._taps, self._cap_states, self.cap_control_index)

    # ------------------------------------------------------------------ oracle
    def perturbation_sensitivities(self, dq_kvar: float = 100.0, dp_kw: float = 100.0, *,
                                   restore: bool = True) -> Sensitivities:
        """Voltage sensitivities by perturbation from the present state (the case-A oracle): each plant's Q by
        ``dq_kvar`` [kvar], its available P by ``dp_kw`` [kW] and each regulator by one tap, one at a time; see
        :func:`simulator_bridge.opendss.sensitivities.perturbation_sensitivities`.
        """
        return perturbation_sensitivities(self, dq_kvar, dp_kw, restore=restore)

    # ------------------------------------------------------------------ bench support
    def bare_steps_s(self, load_kw: np.ndarray, pv_kw: np.ndarray, taps: np.ndarray | None = None,
                     cap_states: np.ndarray | None = None) -> float:
        """Wall time of bare OpenDSS steps [s]: per row set loads, PV output (and taps, banks), solve; nothing else.

        The reference for the QSTS overhead ratio (``benchmarks.bench_qsts``). ``taps`` (n_rows, NR) and ``cap_states``
        (n_rows, NC), when given, replay the positions of every RegControl / CapControl bank of the model
        (``control_taps`` / ``control_cap_states`` order): a row's positions are set before its solve where
        they differ from the previous row's. Leaves the last row applied.
        """
        pv = self._dss.PVsystems
        solve = self._dss.Solution.Solve
        n_rows = len(load_kw)
        tap_rows = np.asarray(taps, dtype=int) if taps is not None else np.tile(self._all_taps, (n_rows, 1))
        cap_rows = np.asarray(cap_states, dtype=int) if cap_states is not None else np.tile(
            self.control_cap_states(), (n_rows, 1))
        for r, tap in enumerate(tap_rows[0]):
            self.set_control_tap(r, int(tap))
        for j, n in enumerate(cap_rows[0]):
            self.set_control_cap_state(j, int(n))
        prev, prev_cap = tap_rows[0].copy(), cap_rows[0].copy()
        pv_kw = np.clip(np.asarray(pv_kw, dtype=float), 0.0, self.pv_pmpp_kw)
        t = time.perf_counter()
        for row, pv_row, tap_row, cap_row in zip(load_kw, pv_kw, tap_rows, cap_rows, strict=True):
            self.set_loads_kw(row)
            for k, name in enumerate(self._pv_names):
                pv.Name(name)
                pv.Irradiance(pv_row[k] / self.pv_pmpp_kw[k])
            for r in np.flatnonzero(tap_row != prev).tolist():
                self._set_tap(r, int(tap_row[r]))
            for j in np.flatnonzero(cap_row != prev_cap).tolist():
                self.set_control_cap_state(j, int(cap_row[j]))
            prev, prev_cap = tap_row, cap_row
            solve()
        elapsed = time.perf_counter() - t
        self._readout.invalidate()
        if len(pv_kw):
            self._pv_p_kw = pv_kw[-1].copy()  # keep set_pv's record of what OpenDSS holds
        return elapsed

    def close(self) -> None:
        """Release the load batch handle (the context itself is freed with the object)."""
        if getattr(self, "_loads", None) is not None:
            self._loads.close()
        if getattr(self, "_readout", None) is not None:
            self._readout.close()

    # ------------------------------------------------------------------ the feeder zone
    @property
    def load_in_feeder(self) -> np.ndarray:
        """(n_loads,) bool, in ``load_names`` order: the load is downstream of the head meter.

        A load on the meter's own bus (beside the meter, e.g. the aggregate of the substation's other feeders)
        or upstream of it is not the feeder's: it keeps its profile in the simulation but is left out of the
        feeder's peak load and PV sizing (``simulator_bridge.survey.zone``, ``docs/feeders.md``).
        """
        zone = {n.split(".")[0] for n, inside in zip(self.node_names, self.node_in_feeder, strict=True) if inside}
        head = {self.node_names[i].split(".")[0] for i in self.head_node_index}
        return np.array([b in zone and b not in head for b in self._load_buses], dtype=bool)

    @property
    def zone_peak_load_kw(self) -> float:
        """Sum of the nominal ``kW=`` of the loads downstream of the head meter [kW]."""
        return float(self.load_kw_nominal[self.load_in_feeder].sum())
