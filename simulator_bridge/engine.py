"""The feeder engine: the only module that imports ``opendssdirect``.

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
"""

from __future__ import annotations

import gc
import logging
import os
import tempfile
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import opendssdirect as dss

from schemas.devicemap import DeviceMap, DeviceMapError
from simulator_bridge.controls import CapControlSettings, RegControlSettings
from simulator_bridge.errors import SimulatorError

log = logging.getLogger(__name__)

__all__ = [
    "EngineError",
    "EngineState",
    "FeederEngine",
    "FieldReadings",
    "OpenDssSnapshot",
    "Sensitivities",
    "opendss_snapshot",
    "survey_circuit",
]

_PHASES = (1, 2, 3)
_LOAD_SETTER_FLAGS = 2  # SetterFlags_AvoidFullRecalc: a kW change does not rebuild the load's Yprim
_BATCH_SET = 0  # BatchOperation_Set


class EngineError(SimulatorError):
    """OpenDSS could not compile or solve the feeder, or was asked for something impossible."""


@dataclass(frozen=True)
class FieldReadings:
    """What the field devices measure at one solved state.

    Attributes
    ----------
    head_v_mag_v, head_v_ang_deg : (3,) line-to-neutral voltage phasor on terminal 1 of the head
        element, phases a, b, c [V], [deg]; 0 on absent phases.
    head_i_mag_a, head_i_ang_deg : (3,) current phasor into the feeder through the head element [A], [deg].
    head_p_kw, head_q_kvar : (3,) active / reactive power into the feeder per phase [kW], [kvar].
    pv_p_kw, pv_q_kvar : (K, 3) output per phase of each PV plant, generator convention [kW], [kvar].
    pv_v_v : (K, 3) line-to-neutral voltage magnitude at each PV plant per phase [V].
    reg_v120 : (R,) raw secondary line-to-neutral voltage / PT ratio [V on the 120 V base].
    reg_v120_compared : (R,) the voltage the controller compares with its band: ``reg_v120`` with
        line-drop compensation applied [V on the 120 V base].
    reg_tap : (R,) tap positions, -16..16 for a 32-step regulator.
    cap_states : (C,) int, closed steps of each map capacitor bank (0..its ``numsteps``).
    cap_v_v : (C,) mean line-to-neutral voltage magnitude at the bank's bus [V].
    cap_control_value : (C,) the quantity the bank's CapControl compares with its ON/OFF settings, in the
        control's own unit (V on its PT base, kvar, A, PF, hour of day); NaN when the bank has none.
    """

    head_v_mag_v: np.ndarray
    head_v_ang_deg: np.ndarray
    head_i_mag_a: np.ndarray
    head_i_ang_deg: np.ndarray
    head_p_kw: np.ndarray
    head_q_kvar: np.ndarray
    pv_p_kw: np.ndarray
    pv_q_kvar: np.ndarray
    pv_v_v: np.ndarray
    reg_v120: np.ndarray
    reg_v120_compared: np.ndarray
    reg_tap: np.ndarray
    cap_states: np.ndarray
    cap_v_v: np.ndarray
    cap_control_value: np.ndarray


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


@dataclass(frozen=True)
class _Terminal:
    """Where to find one terminal of one measured element in the per-step read-outs.

    Indices are into the batch vectors of conductor voltages and currents (every conductor of every
    measured element, in batch order), extended with a trailing 0 so that index -1 reads 0.
    """

    element: str
    node: tuple[int, int, int]  # per phase a, b, c: node index into node_names, -1 if absent
    conductor: tuple[int, int, int]  # per phase a, b, c: index into the batch vectors, -1 if absent
    neutral: int  # index of the terminal's neutral conductor in the batch vectors, -1 if none


@dataclass(frozen=True)
class _Regulator:
    regcontrol: str
    transformer: str
    winding: int  # the monitored winding (OpenDSS's ``winding``: the element terminal)
    pt_phase: int  # phase number (1, 2, 3) of the controlled winding's conductor the PT reads (MAX/MIN: 1st)
    pt_mode: int  # PT phase 1..3 of the winding, or -2 (MAX) / -3 (MIN)
    pt_ratio: float
    ct_primary_a: float
    ldc_r_v: float
    ldc_x_v: float
    tap_winding: int
    tap_center: float  # [pu] tap of position 0
    tap_step: float  # [pu] per position
    tap_max: int
    primary_node: int
    secondary_node: int
    pu_per_v120: float
    remote_node: int  # node index of the monitored remote bus (``bus=``), -1 if none
    remote_pt_ratio: float


def _phase_mode(text: str, what: str) -> int:
    """A CapControl's PTphase/CTphase: 1..3, or -1 (AVG), -2 (MAX), -3 (MIN)."""
    t = text.strip().lower()
    if t.isdigit():
        return int(t)
    modes = {"avg": -1, "max": -2, "min": -3}
    if t not in modes:
        raise DeviceMapError(f"{what}: phase selection {text!r} is not understood")
    return modes[t]


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
            self._compile(device_map.master_path)
            for cmd in device_map.feeder.extra_commands:
                self._command(cmd, what=f"{self._where}: extra command")
        self._check_names()
        self._add_pv_plants()
        self._command("set controlmode=off", what="engine setup")
        self._command(f"set tolerance={self.tolerance:.3g}", what="engine setup")
        self._command("set maxiterations=100", what="engine setup")
        # The circuit's structure never changes after setup (only values: loads, PV, taps), so KLU may
        # keep its symbolic factorisation across Y rebuilds (a tap change): ~1.5x faster re-solve.
        self._dss.YMatrix.SolverOptions(2)  # SolverOptions_ReuseSymbolicFactorization
        self._disable_meters()
        self._api = self._dss.to_dss_python()
        self._circuit = self._api.ActiveCircuit
        self.solve()  # builds the node lists that the element readers below need

        self.node_names: tuple[str, ...] = tuple(n.lower() for n in self._dss.Circuit.AllNodeNames())
        self._node_index = {n: i for i, n in enumerate(self.node_names)}
        self._init_loads()
        self._init_pv()
        self._init_regulators()
        self._init_capacitors()
        self._init_measurements()
        bus_distance, feeder_buses, head_bus = self._bus_distance_ohm()
        self.node_in_feeder = np.array([n.split(".")[0] in feeder_buses for n in self.node_names])
        self.head_node_index = np.array([i for i, n in enumerate(self.node_names) if n.split(".")[0] == head_bus])
        self.node_distance_ohm = np.array([bus_distance.get(n.split(".")[0], np.inf) for n in self.node_names])
        self.load_distance_ohm = np.array([bus_distance.get(b, np.inf) for b in self._load_buses])
        self.pv_distance_ohm = np.array([bus_distance.get(p.bus.split(".")[0].lower(), np.inf)
                                         for p in device_map.pv])
        self.solve()

    # ------------------------------------------------------------------ setup
    def _command(self, cmd: str, *, what: str) -> str:
        try:
            self._dss.Text.Command(cmd)
        except dss.DSSException as e:
            raise EngineError(f"{what}: OpenDSS rejected {cmd!r}: {e}; fix the command or the model") from e
        return self._dss.Text.Result()

    def _compile(self, master: Path) -> None:
        cwd = os.getcwd()
        try:
            _compile_read_only(self._dss, master)
        except dss.DSSException as e:
            raise EngineError(f"{master}: the feeder does not compile: {e}; fix the OpenDSS model") from e
        finally:
            os.chdir(cwd)
        if self._dss.Circuit.NumBuses() == 0:
            raise EngineError(f"{master}: compiled to an empty circuit; is this an OpenDSS master file?")
        _close_debug_traces(self._dss)

    def _check_names(self) -> None:
        dm = self.device_map
        buses = {b.lower() for b in self._dss.Circuit.AllBusNames()}
        elements = {e.lower() for e in self._dss.Circuit.AllElementNames()}
        regcontrols = {r.lower() for r in self._dss.RegControls.AllNames()}
        master = dm.master_path.name
        if dm.feeder.source_bus.lower() not in buses:
            raise DeviceMapError(f"{self._where}: feeder.source_bus {dm.feeder.source_bus!r} is not a bus "
                                 f"of {master}")
        if dm.feeder.head_element.lower() not in elements:
            raise DeviceMapError(f"{self._where}: feeder.head_element {dm.feeder.head_element!r} is not an "
                                 f"element of {master} (write it as Class.name, e.g. Line.sw1)")
        for r in dm.regulator:
            if r.regcontrol.lower() not in regcontrols:
                raise DeviceMapError(f"{self._where}: regulator {r.id!r}: RegControl {r.regcontrol!r} not "
                                     f"found in {master}; known: {sorted(regcontrols)}")
        capacitors = {c.lower() for c in self._dss.Capacitors.AllNames()}
        capcontrols = {c.lower() for c in self._dss.CapControls.AllNames()}
        for c in dm.capacitor:
            if c.capacitor.lower() not in capacitors:
                raise DeviceMapError(f"{self._where}: capacitor {c.id!r}: Capacitor {c.capacitor!r} not found in "
                                     f"{master}; known: {sorted(capacitors)}")
            if c.capcontrol is None:
                continue
            if c.capcontrol.lower() not in capcontrols:
                raise DeviceMapError(f"{self._where}: capacitor {c.id!r}: CapControl {c.capcontrol!r} not found "
                                     f"in {master}; known: {sorted(capcontrols)}")
            self._dss.CapControls.Name(c.capcontrol)
            controlled = self._dss.CapControls.Capacitor().lower()
            if controlled != c.capacitor.lower():
                raise DeviceMapError(f"{self._where}: capacitor {c.id!r}: CapControl {c.capcontrol!r} switches "
                                     f"Capacitor {controlled!r}, not {c.capacitor!r}; name the bank's own control")
        for p in dm.pv:
            if p.bus.split(".")[0].lower() not in buses:
                raise DeviceMapError(f"{self._where}: PV plant {p.id!r}: bus {p.bus!r} not found in {master}")
            if not p.create and f"pvsystem.{p.pvsystem}".lower() not in elements:
                raise DeviceMapError(f"{self._where}: PV plant {p.id!r}: PVSystem {p.pvsystem!r} not found "
                                     f"in {master}")

    def _add_pv_plants(self) -> None:
        for p in self.device_map.pv:
            name = self._pv_name(p.id)
            if p.create:
                kv = p.kv_ll if p.phases == 3 else p.kv_ll / np.sqrt(3.0)  # 1-phase: kV across the terminals
                self._command(
                    f"new pvsystem.{name} phases={p.phases} bus1={p.bus} kv={kv:.6g} kva={p.kva:.6g} "
                    f"pmpp={p.pmpp_kw:.6g} irradiance=0 %cutin=0.01 %cutout=0.01 kvar=0 "
                    "wattpriority=yes varfollowinverter=no",
                    what=f"{self._where}: PV plant {p.id!r}",
                )
            else:
                self._command(f"edit pvsystem.{name} kva={p.kva:.6g} pmpp={p.pmpp_kw:.6g} irradiance=0 kvar=0 "
                              "wattpriority=yes varfollowinverter=no",
                              what=f"{self._where}: PV plant {p.id!r}")

    def _pv_name(self, pv_id: str) -> str:
        spec = next(p for p in self.device_map.pv if p.id == pv_id)
        return (spec.pvsystem if not spec.create and spec.pvsystem else f"cvvc_{spec.id}").lower()

    def _disable_meters(self) -> None:
        for name in self._dss.Meters.AllNames():
            if name and name.upper() != "NONE":
                self._command(f"disable energymeter.{name}", what="engine setup")
        for name in self._dss.Monitors.AllNames():
            if name and name.upper() != "NONE":
                self._command(f"disable monitor.{name}", what="engine setup")

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
        # Batch handle over every load, in the same order as Loads.First/Next (class order).
        ffi, lib = d.dss_ffi, d.dss_lib
        self._ffi, self._lib = ffi, lib
        self._load_batch_ptr = ffi.new("void***")
        dims = ffi.new("int32_t[4]")
        lib.Batch_CreateByClassS(self._load_batch_ptr, dims, b"Load")
        self._n_batch = int(dims[0])
        if self._n_batch != len(names):
            raise EngineError(f"internal: load batch has {self._n_batch} loads, Loads has {len(names)}")
        if names:
            d.Circuit.SetActiveElement(f"Load.{names[0]}")
            props = [p.lower() for p in d.Element.AllPropertyNames()]
            self._kw_prop, self._kvar_prop = props.index("kw") + 1, props.index("kvar") + 1

    def _init_pv(self) -> None:
        pvs = self.device_map.pv
        self.pv_ids: tuple[str, ...] = tuple(p.id for p in pvs)
        self._pv_names = tuple(self._pv_name(p.id) for p in pvs)
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
        map_names = [s.regcontrol.lower() for s in self.device_map.regulator]
        others = [n.lower() for n in d.RegControls.AllNames() if n and n.upper() != "NONE"
                  and n.lower() not in map_names]
        regs, settings = [], []
        for name in map_names + others:
            d.RegControls.Name(name)
            what = f"{self._where}: RegControl {name!r}"
            xf, winding = d.RegControls.Transformer().lower(), int(d.RegControls.Winding())
            pt_ratio, ct = float(d.RegControls.PTRatio()), float(d.RegControls.CTPrimary())
            r_v, x_v = float(d.RegControls.ForwardR()), float(d.RegControls.ForwardX())
            vreg, bandw = float(d.RegControls.ForwardVreg()), float(d.RegControls.ForwardBand())
            remote_bus = d.RegControls.MonitoredBus().strip().lower()
            prop = {p: self._command(f"? regcontrol.{name}.{p}", what=what).strip().lower()
                    for p in ("ptphase", "remoteptratio", "enabled", "vlimit", "reversible", "ldc_z", "cogen")}
            if prop["reversible"] in ("yes", "true") or prop["cogen"] in ("yes", "true") \
                    or float(prop["vlimit"] or 0) > 0 or float(prop["ldc_z"] or 0) > 0:
                raise DeviceMapError(f"{what}: reversible/cogen modes, vlimit and LDC_Z are not modelled (forward "
                                     "mode with R/X line-drop compensation only); remove them from the model")
            tap_winding = int(d.RegControls.TapWinding())
            d.Transformers.Name(xf)
            d.Transformers.Wdg(tap_winding)
            tap_max = int(d.Transformers.NumTaps()) // 2
            tap_lo, tap_hi = float(d.Transformers.MinTap()), float(d.Transformers.MaxTap())
            d.Transformers.Wdg(winding)
            kv_wdg, delta = float(d.Transformers.kV()), bool(d.Transformers.IsDelta())
            d.Circuit.SetActiveElement(f"Transformer.{xf}")
            n_phases = int(d.CktElement.NumPhases())
            # OpenDSS's winding base voltage: L-N for more than one phase or a delta winding, else kV [V]
            v_base_wdg = kv_wdg * 1000.0 / (np.sqrt(3.0) if (n_phases > 1 or delta) else 1.0)
            buses = [b.split(".") for b in d.CktElement.BusNames()]
            n_cond = int(d.CktElement.NumConductors())
            order = list(d.CktElement.NodeOrder())
            if prop["ptphase"].isdigit():
                pt_mode = int(prop["ptphase"]) if int(prop["ptphase"]) <= n_phases else 1
            elif prop["ptphase"] in ("max", "min"):
                pt_mode = -2 if prop["ptphase"] == "max" else -3
            else:
                raise DeviceMapError(f"{what}: PTphase={prop['ptphase']} is not understood")
            ph = (pt_mode if pt_mode > 0 else 1) - 1
            other = 1 if winding != 1 else 2
            pt_phase_number = order[(winding - 1) * n_cond + ph]
            sec_node = f"{buses[winding - 1][0].lower()}.{pt_phase_number}"
            pri_node = f"{buses[other - 1][0].lower()}.{order[(other - 1) * n_cond + ph]}"
            d.Circuit.SetActiveBus(buses[winding - 1][0])
            base_v = d.Bus.kVBase() * 1000.0
            remote_node = -1
            if remote_bus:
                bus, *node = remote_bus.split(".")
                key = f"{bus}.{node[0] if node else 1}"
                if key not in self._node_index:
                    raise DeviceMapError(f"{what}: monitored bus {remote_bus!r} is not a node of the model")
                remote_node = self._node_index[key]
            tap_step = (tap_hi - tap_lo) / (2 * tap_max)
            regs.append(_Regulator(
                regcontrol=name, transformer=xf, winding=winding, pt_phase=pt_phase_number, pt_mode=pt_mode,
                pt_ratio=pt_ratio, ct_primary_a=ct, ldc_r_v=r_v, ldc_x_v=x_v, tap_winding=tap_winding,
                tap_center=(tap_lo + tap_hi) / 2, tap_step=tap_step, tap_max=tap_max,
                primary_node=self._node_index[pri_node], secondary_node=self._node_index[sec_node],
                pu_per_v120=pt_ratio / base_v, remote_node=remote_node,
                remote_pt_ratio=float(prop["remoteptratio"] or pt_ratio)))
            max_change = int(d.RegControls.MaxTapChange())
            settings.append(RegControlSettings(
                name=name, vreg_v120=vreg, band_v120=bandw, delay_s=float(d.RegControls.Delay()),
                tap_delay_s=float(d.RegControls.TapDelay()), inverse_time=bool(d.RegControls.IsInverseTime()),
                enabled=prop["enabled"] in ("yes", "true") and max_change > 0, tap_max=tap_max,
                taps_per_v120=pt_ratio / (v_base_wdg * tap_step) * (1.0 if tap_winding == winding else -1.0)))
        self._regs = tuple(regs)
        self.reg_controls: tuple[RegControlSettings, ...] = tuple(settings)
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
        d = self._dss
        specs = self.device_map.capacitor
        cc_names = [n.lower() for n in d.CapControls.AllNames() if n and n.upper() != "NONE"]
        cc_cap = {}
        for name in cc_names:
            d.CapControls.Name(name)
            cc_cap[name] = d.CapControls.Capacitor().lower()
        banks = [c.capacitor.lower() for c in specs]
        banks += [b for b in dict.fromkeys(cc_cap.values()) if b not in banks]
        kvar, steps, states, conn_delta = [], [], [], []
        for b in banks:
            d.Capacitors.Name(b)
            kvar.append(float(d.Capacitors.kvar()))
            steps.append(int(d.Capacitors.NumSteps()))
            closed_steps = int(sum(d.Capacitors.States()))
            d.Circuit.SetActiveElement(f"Capacitor.{b}")
            states.append(0 if d.CktElement.IsOpen(1, 0) else closed_steps)  # an open terminal: no step in
            conn_delta.append(bool(d.Capacitors.IsDelta()))
        n = len(specs)
        self._banks = tuple(banks)
        self._bank_kvar = np.array(kvar, dtype=float)
        self._bank_steps = np.array(steps, dtype=int)
        self._bank_states = np.array(states, dtype=int)
        self.capacitor_ids: tuple[str, ...] = tuple(c.id for c in specs)
        self._cap_names = tuple(banks[:n])
        self.cap_kvar = self._bank_kvar[:n].copy()
        self.cap_steps = self._bank_steps[:n].copy()
        self._cap_states = self._bank_states[:n]  # a view: the map's banks
        controls, monitored, bank_of = [], [], []
        for name in cc_names:
            d.CapControls.Name(name)
            what = f"{self._where}: CapControl {name!r}"
            prop = {p: self._command(f"? capcontrol.{name}.{p}", what=what).strip().lower()
                    for p in ("type", "ptphase", "ctphase", "pctminkvar", "enabled", "voltoverride")}
            kind = {"powerfactor": "pf"}.get(prop["type"], prop["type"])
            if kind not in ("current", "voltage", "kvar", "pf", "time", "follow"):
                raise DeviceMapError(f"{what}: type {kind!r} is not modelled (current, voltage, kvar, pf, time, "
                                     "follow)")
            on, off = float(d.CapControls.ONSetting()), float(d.CapControls.OFFSetting())
            if kind == "pf":  # OpenDSS's 0..2 scale: a leading (negative) PF setting is 2 + PF
                on, off = (2.0 + on if on < 0 else on), (2.0 + off if off < 0 else off)
            b = banks.index(cc_cap[name])
            bank_of.append(b)
            controls.append(CapControlSettings(
                name=name, kind=kind, on=on, off=off, delay_s=float(d.CapControls.Delay()),
                delay_off_s=float(d.CapControls.DelayOff()), dead_time_s=float(d.CapControls.DeadTime()),
                volt_override=prop["voltoverride"] in ("yes", "true"), vmin_v=float(d.CapControls.Vmin()),
                vmax_v=float(d.CapControls.Vmax()), n_steps=steps[b], total_kvar=kvar[b],
                pct_min_kvar=float(prop["pctminkvar"] or 50.0), enabled=prop["enabled"] in ("yes", "true")))
            monitored.append((d.CapControls.MonitoredObj(), int(d.CapControls.MonitoredTerm()),
                              _phase_mode(prop["ptphase"], what), _phase_mode(prop["ctphase"], what),
                              float(d.CapControls.PTRatio()), float(d.CapControls.CTRatio()), conn_delta[b]))
        self.cap_controls: tuple[CapControlSettings, ...] = tuple(controls)
        self._cc_monitored = tuple(monitored)
        self.cap_control_bank = np.array(bank_of, dtype=int)
        # each map bank's control (index into cap_controls), -1 without one
        by_name = {c.name: j for j, c in enumerate(controls)}
        self.cap_control_index = np.array([by_name[c.capcontrol.lower()] if c.capcontrol else -1 for c in specs],
                                          dtype=int)
        self.cap_control_type: tuple[str, ...] = tuple(
            controls[j].kind if j >= 0 else "none" for j in self.cap_control_index)
        self._cap_value = np.full(len(controls), np.nan)  # last sensed, for readings

    def _init_measurements(self) -> None:
        """Batch the measured elements (head, PV plants, regulator transformers, banks, CapControls'
        monitored elements) for one current read.

        Also builds the index tables that turn the node voltages and those currents into readings.
        """
        lib, ffi = self._lib, self._ffi
        cc_elements = [m[0] for m in self._cc_monitored]
        elements = [self.device_map.feeder.head_element] + [f"PVSystem.{n}" for n in self._pv_names] + [
            f"Transformer.{r.transformer}" for r in self._regs] + [f"Capacitor.{c}" for c in self._cap_names] \
            + cc_elements
        terminals = [1] * (1 + len(self._pv_names)) + [r.winding for r in self._regs] + [1] * len(
            self._cap_names) + [m[1] for m in self._cc_monitored]
        handles, terms, offsets, offset = [], [], [], 0
        for element, terminal in zip(elements, terminals, strict=True):
            cls, name = element.split(".", 1)
            handle = lib.Obj_GetHandleByName(lib._ctx, lib.DSS_SetActiveClass(cls.encode()), name.encode())
            if handle == ffi.NULL:
                raise DeviceMapError(f"{self._where}: element {element!r} not found")
            handles.append(handle)
            t, size = self._terminal(element, terminal, offset)
            terms.append(t)
            offsets.append(offset)
            offset += size
        self._ce_handles = ffi.new("void*[]", handles)
        self._n_ce = len(handles)
        self._ce_result = ffi.new("double**")
        self._ce_dims = ffi.new("int32_t[4]")
        n_pv, n_reg, n_cap = len(self._pv_names), len(self._regs), len(self._cap_names)
        head, pvs = terms[0], terms[1:1 + n_pv]
        regs = terms[1 + n_pv:1 + n_pv + n_reg]
        caps = terms[1 + n_pv + n_reg:1 + n_pv + n_reg + n_cap]
        self._head_cond, self._head_neutral = np.array(head.conductor), head.neutral
        self._pv_cond = np.array([t.conductor for t in pvs], dtype=int).reshape(-1, 3)
        self._pv_neutral = np.array([t.neutral for t in pvs], dtype=int)
        # regulators: the winding's phase conductors in the transformer's own order (PT phase 1..n)
        reg_cond = np.full((n_reg, 3), -1, dtype=int)
        for r, (reg, off) in enumerate(zip(self._regs, offsets[1 + n_pv:1 + n_pv + n_reg], strict=True)):
            first, nph = self._conductor_range(f"Transformer.{reg.transformer}", reg.winding, off)
            reg_cond[r, :nph] = np.arange(first, first + nph)
        self._reg_cond_all = reg_cond
        self._reg_phase_mask = reg_cond >= 0
        self._reg_neutral = np.array([t.neutral for t in regs], dtype=int)
        self._reg_ratio = np.array([r.pt_ratio for r in self._regs], dtype=float)
        self._reg_ldc = np.array([complex(r.ldc_r_v, r.ldc_x_v) / r.ct_primary_a if r.remote_node < 0 else 0j
                                  for r in self._regs])
        self._reg_pt_mode = np.array([r.pt_mode for r in self._regs], dtype=int)
        self._reg_rows = np.arange(n_reg)
        self._reg_sel_fixed = self._reg_pt_mode - 1 if np.all(self._reg_pt_mode > 0) else None
        self._reg_v: tuple[np.ndarray, np.ndarray] | None = None  # this solution's, once computed
        self._reg_fixed = np.flatnonzero(self._reg_pt_mode > 0)
        self._reg_remote = np.flatnonzero(np.array([r.remote_node >= 0 for r in self._regs], dtype=bool))
        # a bank's voltage: mean over its phases of |V(phase) - V(neutral)|; absent phases are masked out
        self._cap_cond = np.array([t.conductor for t in caps], dtype=int).reshape(-1, 3)
        self._cap_neutral = np.array([t.neutral for t in caps], dtype=int)
        self._cap_phase_mask = self._cap_cond >= 0
        self._cap_n_phases = np.maximum(self._cap_phase_mask.sum(axis=1), 1)
        # CapControls: the monitored terminal's phase conductors (PT/CT phase 1..n) and all its conductors
        n_cc = len(self._cc_monitored)
        cc_ph = np.full((n_cc, 3), -1, dtype=int)
        cc_all = np.full((n_cc, 8), -1, dtype=int)
        for j, (m, off) in enumerate(zip(self._cc_monitored, offsets[1 + n_pv + n_reg + n_cap:], strict=True)):
            first, nph, ncond = self._conductor_range(m[0], m[1], off, with_conductors=True)
            cc_ph[j, :min(nph, 3)] = np.arange(first, first + min(nph, 3))
            cc_all[j, :min(ncond, 8)] = np.arange(first, first + min(ncond, 8))
        self._cc_ph, self._cc_all, self._cc_mask = cc_ph, cc_all, cc_ph >= 0
        self._cc_nph = np.maximum(self._cc_mask.sum(axis=1), 1)
        self._cc_pt = np.array([m[2] for m in self._cc_monitored], dtype=int)
        self._cc_ct = np.array([m[3] for m in self._cc_monitored], dtype=int)
        self._cc_ptratio = np.array([m[4] for m in self._cc_monitored], dtype=float)
        self._cc_ctratio = np.array([m[5] for m in self._cc_monitored], dtype=float)
        self._cc_delta = np.array([m[6] for m in self._cc_monitored], dtype=bool)
        kinds = [c.kind for c in self.cap_controls]
        self._cc_kind = {k: np.array([x == k for x in kinds], dtype=bool) for k in ("current", "voltage", "kvar",
                                                                                      "pf", "time")}
        self._cc_is_v = self._cc_kind["voltage"]
        self._cc_any = {k: bool(m.any()) for k, m in self._cc_kind.items()}
        self._batch: tuple[np.ndarray, np.ndarray] | None = None

    def _conductor_range(self, element: str, terminal: int, offset: int, *, with_conductors: bool = False):
        """(first batch index of ``terminal``'s conductors, number of phases[, number of conductors])."""
        d = self._dss
        d.Circuit.SetActiveElement(element)
        n_cond, n_phases = int(d.CktElement.NumConductors()), int(d.CktElement.NumPhases())
        first = offset + (terminal - 1) * n_cond
        return (first, n_phases, n_cond) if with_conductors else (first, n_phases)

    def _terminal(self, element: str, terminal: int, offset: int) -> tuple[_Terminal, int]:
        """Index tables for ``terminal`` of ``element``; also its number of currents (all terminals)."""
        d = self._dss
        if d.Circuit.SetActiveElement(element) < 0:
            raise DeviceMapError(f"{self._where}: element {element!r} not found")
        n_cond = int(d.CktElement.NumConductors())
        n_phases = int(d.CktElement.NumPhases())
        n_term = int(d.CktElement.NumTerminals())
        bus = d.CktElement.BusNames()[terminal - 1].split(".")[0].lower()
        order = list(d.CktElement.NodeOrder())[(terminal - 1) * n_cond: terminal * n_cond]
        node, conductor = [-1, -1, -1], [-1, -1, -1]
        first = offset + (terminal - 1) * n_cond
        for c, ph in enumerate(order[:n_phases]):
            if ph in _PHASES:
                node[ph - 1] = self._node_index[f"{bus}.{ph}"]
                conductor[ph - 1] = first + c
        neutral = first + n_phases if n_cond > n_phases else -1
        return _Terminal(d.CktElement.Name(), tuple(node), tuple(conductor), neutral), n_term * n_cond

    def _bus_distance_ohm(self) -> tuple[dict[str, float], set[str], str]:
        """Electrical distance of every bus from ``source_bus`` [ohm, referred to the source bus voltage],
        and the buses of the feeder proper: the head element's first bus and everything reached from its
        other side without crossing it back (the transmission side of the substation is not the feeder).

        Breadth-first over power-delivery elements from the source bus; each line adds its positive-
        sequence series impedance ``Z1 = mean(Z_self) - mean(Z_mutual)`` (from its phase impedance
        matrix, = R1 + jX1 for a transposed line) times its length, referred to the source bus voltage
        by ``(kV_source / kV_line)^2``; transformers, regulators and switches-as-elements add 0. The
        distance is ``|sum Z1|`` along the path.
        """
        d = self._dss
        kv_base: dict[str, float] = {}
        for bus in d.Circuit.AllBusNames():
            d.Circuit.SetActiveBus(bus)
            kv_base[bus.lower()] = d.Bus.kVBase()
        src = self.device_map.feeder.source_bus.lower()
        kv_src = kv_base.get(src, 0.0)
        edges: dict[str, list[tuple[str, complex]]] = {}
        named_edges: dict[str, list[tuple[str, str]]] = {}
        line_z: dict[str, complex] = {}
        i = d.Lines.First()
        while i > 0:
            n = int(d.Lines.Phases())
            r = np.asarray(d.Lines.RMatrix(), dtype=float).reshape(n, n)
            x = np.asarray(d.Lines.XMatrix(), dtype=float).reshape(n, n)
            z = r + 1j * x
            z1 = np.mean(np.diag(z)) - (np.mean(z[~np.eye(n, dtype=bool)]) if n > 1 else 0.0)
            line_z[f"line.{d.Lines.Name().lower()}"] = complex(z1 * d.Lines.Length())
            i = d.Lines.Next()
        i = d.PDElements.First()
        while i > 0:
            name = d.CktElement.Name().lower()
            buses = [b.split(".")[0].lower() for b in d.CktElement.BusNames()]
            if d.CktElement.Enabled() and len(set(buses)) > 1 and not name.startswith("capacitor."):
                z = line_z.get(name, 0j)
                kv = kv_base.get(buses[0], 0.0)
                if z and kv > 0 and kv_src > 0:
                    z *= (kv_src / kv) ** 2
                for a in buses:
                    for b in buses:
                        if a != b:
                            edges.setdefault(a, []).append((b, z))
                            named_edges.setdefault(a, []).append((b, name))
            i = d.PDElements.Next()
        total: dict[str, complex] = {src: 0j}
        queue = deque([src])
        while queue:
            a = queue.popleft()
            for b, z in edges.get(a, []):
                if b not in total:
                    total[b] = total[a] + z
                    queue.append(b)
        head = self.device_map.feeder.head_element.lower()
        d.Circuit.SetActiveElement(head)
        head_buses = [b.split(".")[0].lower() for b in d.CktElement.BusNames()]
        feeder = {head_buses[0]}
        queue = deque(head_buses[1:])
        while queue:
            a = queue.popleft()
            if a in feeder:
                continue
            feeder.add(a)
            queue.extend(b for b, name in named_edges.get(a, []) if name != head and b not in feeder)
        return {b: abs(z) for b, z in total.items()}, feeder, head_buses[0]

    # ------------------------------------------------------------------ set
    def set_loads_kw(self, p_kw: np.ndarray) -> None:
        """Set every load's active power; reactive power follows the feeder's ``load_pf``.

        Parameters
        ----------
        p_kw : (n_loads,) active power per load, in ``load_names`` order [kW].
        """
        p = np.ascontiguousarray(p_kw, dtype=float)
        if p.shape != (self._n_batch,):
            raise EngineError(f"set_loads_kw: expected {self._n_batch} loads, got shape {p.shape}")
        if not np.all(np.isfinite(p)):
            raise EngineError("set_loads_kw: non-finite load power; check the profiles")
        q = np.ascontiguousarray(p * self._tan_phi)
        self._load_kw[:] = p
        batch = self._load_batch_ptr[0]
        self._lib.Batch_Float64Array(batch, self._n_batch, self._kw_prop, _BATCH_SET,
                                     self._ffi.from_buffer("double[]", p), _LOAD_SETTER_FLAGS)
        self._lib.Batch_Float64Array(batch, self._n_batch, self._kvar_prop, _BATCH_SET,
                                     self._ffi.from_buffer("double[]", q), _LOAD_SETTER_FLAGS)

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
        for r in np.flatnonzero(t != self._taps):
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
        for c in np.flatnonzero(st != self._cap_states):
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
        self._batch = self._reg_v = None
        try:
            self._dss.Solution.Solve()
        except dss.DSSException as e:
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
            self._command(cmd, what=f"{self.device_map.feeder.name}: OpenDSS control loop")
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
        self._batch = self._reg_v = None
        d = self._dss
        try:
            d.Solution.Solve()
        except dss.DSSException as e:
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

    def _batch_read(self, func) -> np.ndarray:
        """One batch read (voltages [V] or currents into the element [A]) of every conductor of every
        measured element, as complex, plus a trailing 0.
        """
        func(self._ce_result, self._ce_dims, self._ce_handles, self._n_ce)
        n = int(self._ce_dims[0])
        out = np.zeros(n // 2 + 1, dtype=complex)
        out[:-1] = np.frombuffer(self._ffi.buffer(self._ce_result[0], n * 8), dtype=complex)  # (re, im) pairs
        return out

    def _read(self) -> tuple[np.ndarray, np.ndarray]:
        """The batch voltages and currents of the present solution (read once per solve)."""
        if self._batch is None:
            self._batch = (self._batch_read(self._lib.Alt_CEBatch_Get_Voltages),
                           self._batch_read(self._lib.Alt_CEBatch_Get_Currents))
        return self._batch

    def _reg_voltages(self, v: np.ndarray, i: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(raw, compared) voltage of every RegControl [V on the 120 V base], as its ``Sample`` computes it:
        the PT phase's winding voltage (MAX/MIN: the highest/lowest phase) over PTratio plus ``(R + jX)·I/CTprim``
        (current into the winding, same phase); a remote bus: that node's voltage over its PT ratio, no LDC.
        """
        if self._reg_v is not None:
            return self._reg_v
        rows = self._reg_rows
        if self._reg_sel_fixed is not None:  # every PT reads one fixed phase: no phase comparison needed
            sel = self._reg_sel_fixed
            cond = self._reg_cond_all[rows, sel]
            v_sec = (v[cond] - v[self._reg_neutral]) / self._reg_ratio
        else:
            w = (v[self._reg_cond_all] - v[self._reg_neutral][:, None]) * self._reg_phase_mask
            sel = _select_phase_index(np.abs(w), self._reg_phase_mask, self._reg_pt_mode)
            cond = self._reg_cond_all[rows, sel]
            v_sec = w[rows, sel] / self._reg_ratio
        compared = np.abs(v_sec + self._reg_ldc * i[cond])
        raw = np.abs(v_sec)
        for r in self._reg_remote:
            reg = self._regs[r]
            bus, node = self.node_names[reg.remote_node].split(".")
            self._dss.Circuit.SetActiveBus(bus)
            pos = list(self._dss.Bus.Nodes()).index(int(node))
            raw[r] = compared[r] = self._dss.Bus.VMagAngle()[2 * pos] / reg.remote_pt_ratio
        self._reg_v = (raw, compared)
        return raw, compared

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
        v, i = self._read()
        reg = self._reg_voltages(v, i)[1]
        if not len(self._cc_ph):
            z = np.zeros(0)
            return reg, z, z, z
        vph = v[self._cc_ph] * self._cc_mask
        vm = np.abs(vph)
        volts = _select_phase(vm, self._cc_mask, self._cc_pt, self._cc_nph)
        if self._cc_delta.any():  # a delta bank with one PT phase reads the line-to-line voltage
            for j in np.flatnonzero(self._cc_delta & (self._cc_pt > 0)):
                k = self._cc_pt[j] - 1
                volts[j] = abs(vph[j, k] - vph[j, (k + 1) % self._cc_nph[j]])
        volts = volts / self._cc_ptratio
        amps = _select_phase(np.abs(i[self._cc_ph]) * self._cc_mask, self._cc_mask, self._cc_ct, self._cc_nph)
        amps = amps / self._cc_ctratio
        s = (v[self._cc_all] * np.conj(i[self._cc_all])).sum(axis=1)
        q_kvar = s.imag / 1000.0
        s_abs = np.abs(s)
        pf = np.where(s_abs > 0, np.abs(s.real) / np.where(s_abs > 0, s_abs, 1.0), 1.0)
        pf = np.where(s.imag < 0, 2.0 - pf, pf)  # OpenDSS's 0..2 scale: above 1 is leading
        value = np.where(self._cc_is_v, volts, np.nan)
        for kind, x in (("current", amps), ("kvar", q_kvar), ("pf", pf)):
            if self._cc_any[kind]:
                value = np.where(self._cc_kind[kind], x, value)
        if self._cc_any["time"]:
            value = np.where(self._cc_kind["time"], tod_h, value)
        self._cap_value = value
        return reg, value, volts, q_kvar

    def readings(self) -> FieldReadings:
        """What the field devices measure at the present solution (call after :meth:`solve`).

        Powers are ``V·conj(I)`` per conductor with ``I`` into the element (OpenDSS's convention): into
        the feeder at the head, negated at PV plants (generator convention). ``cap_control_value`` is what
        :meth:`sense` last computed (NaN before the first call, and for a bank without a CapControl).
        """
        v, i = self._read()
        hv = v[self._head_cond] - v[self._head_neutral]  # index -1 reads the trailing 0
        hi = i[self._head_cond]
        hs = hv * np.conj(hi) / 1000.0
        pv_v = np.where(self._pv_cond >= 0, v[self._pv_cond] - v[self._pv_neutral][:, None], 0)  # absent: 0
        pv_s = -pv_v * np.conj(i[self._pv_cond]) / 1000.0
        n = len(self._taps)
        raw, compared = self._reg_voltages(v, i)
        cap_v = np.abs(v[self._cap_cond] - v[self._cap_neutral][:, None]) * self._cap_phase_mask
        cap_v_v = cap_v.sum(axis=1) / self._cap_n_phases
        cc = self.cap_control_index
        value = np.where(cc >= 0, self._cap_value[cc] if len(self._cap_value) else np.nan, np.nan)
        return FieldReadings(
            head_v_mag_v=np.abs(hv), head_v_ang_deg=np.degrees(np.angle(hv)),
            head_i_mag_a=np.abs(hi), head_i_ang_deg=np.degrees(np.angle(hi)),
            head_p_kw=hs.real, head_q_kvar=hs.imag,
            pv_p_kw=pv_s.real, pv_q_kvar=pv_s.imag, pv_v_v=np.abs(pv_v),
            reg_v120=raw[:n], reg_v120_compared=compared[:n], reg_tap=self._taps.copy(),
            cap_states=self._cap_states.copy(), cap_v_v=cap_v_v, cap_control_value=value,
        )

    # ------------------------------------------------------------------ oracle
    def perturbation_sensitivities(self, dq_kvar: float = 100.0, dp_kw: float = 100.0, *,
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
        self.solve()
        v0 = self.node_voltages_pu()
        p0, q0 = self.pv_setpoints()
        t0 = self.taps()
        headroom = np.sqrt(np.maximum(self.pv_kva**2 - p0**2, 0.0))
        dv_dq = np.full((len(v0), len(q0)), np.nan)
        for k in range(len(q0)):
            up, down = headroom[k] - q0[k], headroom[k] + q0[k]
            dq = min(dq_kvar, up) if up >= down else -min(dq_kvar, down)
            if abs(dq) < 1.0:
                continue
            q = q0.copy()
            q[k] += dq
            applied = self.set_pv(p0, q)
            self.solve()
            dv_dq[:, k] = (self.node_voltages_pu() - v0) / (applied[k] - q0[k])
        self.set_pv(p0, q0)
        dv_dp = np.full((len(v0), len(p0)), np.nan)
        out0 = self.readings().pv_p_kw.sum(axis=1)
        for k in range(len(p0)):
            p = p0.copy()
            p[k] += -dp_kw if p0[k] >= dp_kw else min(dp_kw, self.pv_pmpp_kw[k] - p0[k])
            applied = self.set_pv(p, q0)
            self.solve()
            moved = float(self.readings().pv_p_kw[k].sum() - out0[k])
            dv = self.node_voltages_pu() - v0
            if applied[k] != q0[k]:
                dv = dv - dv_dq[:, k] * (applied[k] - q0[k])  # NaN when Q cannot be moved either
            if abs(moved) >= 1.0:
                dv_dp[:, k] = dv / moved
        self.set_pv(p0, q0)
        dv_dtap = np.zeros((len(v0), len(t0)))
        for r in range(len(t0)):
            step = 1 if t0[r] < self.reg_tap_max[r] else -1
            t = t0.copy()
            t[r] += step
            self.set_taps(t)
            self.solve()
            dv_dtap[:, r] = (self.node_voltages_pu() - v0) / step
        if not restore:
            return Sensitivities(dv_dq=dv_dq, dv_dtap=dv_dtap, dv_dp=dv_dp)
        self.set_taps(t0)
        self.solve()
        drift = float(np.max(np.abs(self.node_voltages_pu() - v0))) if len(v0) else 0.0
        p1, q1 = self.pv_setpoints()
        if not (np.array_equal(self.taps(), t0) and np.array_equal(q1, q0) and np.array_equal(p1, p0)):
            raise EngineError("perturbation_sensitivities: set points or taps not restored")
        if drift >= 100 * self.tolerance:
            log.info("perturbation_sensitivities: the restored state solved %.2e pu away from before", drift)
        return Sensitivities(dv_dq=dv_dq, dv_dtap=dv_dtap, dv_dp=dv_dp, restore_drift_pu=drift)

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
            for r in np.flatnonzero(tap_row != prev):
                self._set_tap(r, int(tap_row[r]))
            for j in np.flatnonzero(cap_row != prev_cap):
                self.set_control_cap_state(j, int(cap_row[j]))
            prev, prev_cap = tap_row, cap_row
            solve()
        elapsed = time.perf_counter() - t
        self._batch = self._reg_v = None
        if len(pv_kw):
            self._pv_p_kw = pv_kw[-1].copy()  # keep set_pv's record of what OpenDSS holds
        return elapsed

    def close(self) -> None:
        """Release the load batch handle (the context itself is freed with the object)."""
        if getattr(self, "_load_batch_ptr", None) is not None and self._load_batch_ptr[0] != self._ffi.NULL:
            self._lib.Batch_Dispose(self._load_batch_ptr[0])
            self._load_batch_ptr = None
        if getattr(self, "_ce_result", None) is not None and self._ce_result[0] != self._ffi.NULL:
            self._lib.DSS_Dispose_PDouble(self._ce_result)
            self._ce_result = None

    # ------------------------------------------------------------------ the feeder zone
    @property
    def load_in_feeder(self) -> np.ndarray:
        """(n_loads,) bool, in ``load_names`` order: the load is downstream of the head meter.

        A load on the meter's own bus (beside the meter, e.g. the aggregate of the substation's other feeders)
        or upstream of it is not the feeder's: it keeps its profile in the simulation but is left out of the
        feeder's peak load and PV sizing (``simulator_bridge.zone``, ``docs/feeders.md``).
        """
        zone = {n.split(".")[0] for n, inside in zip(self.node_names, self.node_in_feeder, strict=True) if inside}
        head = {self.node_names[i].split(".")[0] for i in self.head_node_index}
        return np.array([b in zone and b not in head for b in self._load_buses], dtype=bool)

    @property
    def zone_peak_load_kw(self) -> float:
        """Sum of the nominal ``kW=`` of the loads downstream of the head meter [kW]."""
        return float(self.load_kw_nominal[self.load_in_feeder].sum())


def _select_phase_index(mag: np.ndarray, mask: np.ndarray, mode: np.ndarray) -> np.ndarray:
    """(n,) column of each row: the fixed phase ``mode`` (1..3), the highest (-2) or lowest (-3) present one."""
    fixed = np.clip(mode - 1, 0, 2)
    hi = np.argmax(np.where(mask, mag, -np.inf), axis=1)
    lo = np.argmin(np.where(mask, mag, np.inf), axis=1)
    return np.where(mode > 0, fixed, np.where(mode == -2, hi, lo))


def _select_phase(mag: np.ndarray, mask: np.ndarray, mode: np.ndarray, n_phases: np.ndarray) -> np.ndarray:
    """(n,) per row: a fixed phase (``mode`` 1..3), the average (-1), maximum (-2) or minimum (-3) over phases."""
    if not len(mag):
        return np.zeros(0)
    rows = np.arange(len(mag))
    avg = (mag * mask).sum(axis=1) / n_phases
    pick = mag[rows, _select_phase_index(mag, mask, np.where(mode == -1, 1, mode))]
    return np.where(mode == -1, avg, pick)


@dataclass(frozen=True)
class OpenDssSnapshot:
    """OpenDSS's own solution of a plain model (its own controls on), for golden comparisons.

    Attributes
    ----------
    node_names : OpenDSS ``AllNodeNames``, lower case.
    v_pu : (n_nodes,) node voltage magnitudes [pu of each bus's L-N base].
    taps : {regcontrol name (lower case): tap position} after OpenDSS's control iterations.
    """

    node_names: tuple[str, ...]
    v_pu: np.ndarray
    taps: dict[str, int]


def opendss_snapshot(master: str | Path, *, tolerance: float = 1e-8) -> OpenDssSnapshot:
    """Compile ``master`` as it is, solve one snapshot with OpenDSS's own (static) controls, and read it.

    Raises
    ------
    EngineError
        The model does not compile or the snapshot does not converge.
    """
    ctx = new_context()
    cwd = os.getcwd()
    try:
        with DSS_LIFECYCLE:
            ctx.Text.Command(f'compile "{Path(master).resolve()}"')
        ctx.Text.Command(f"set tolerance={tolerance:.3g}")
        ctx.Text.Command("set maxcontroliter=100")
        ctx.Text.Command("set maxiterations=100")
        ctx.Solution.Solve()
    except dss.DSSException as e:
        raise EngineError(f"{master}: OpenDSS snapshot failed: {e}") from e
    finally:
        os.chdir(cwd)
    if not ctx.Solution.Converged():
        raise EngineError(f"{master}: OpenDSS snapshot did not converge")
    taps = {}
    i = ctx.RegControls.First()
    while i > 0:
        taps[ctx.RegControls.Name().lower()] = int(ctx.RegControls.TapNumber())
        i = ctx.RegControls.Next()
    return OpenDssSnapshot(
        node_names=tuple(n.lower() for n in ctx.Circuit.AllNodeNames()),
        v_pu=np.asarray(ctx.Circuit.AllBusMagPu(), dtype=float),
        taps=taps,
    )


# ---------------------------------------------------------------------------------------------------------------
# Circuit survey: a read-only description of a compiled model, for ``cvvc feeder scaffold`` and ``feeder info``
# (the result types are in survey.py).
# ---------------------------------------------------------------------------------------------------------------


_CAPCONTROL_MODES = {0: "current", 1: "voltage", 2: "kvar", 3: "time", 4: "pf"}  # CapControls.Mode()

if TYPE_CHECKING:
    from simulator_bridge.survey import CircuitSurvey


def survey_circuit(master: str | Path, *, extra_commands: tuple[str, ...] | list[str] = ()) -> CircuitSurvey:
    """Compile ``master`` in a context of its own (plus ``extra_commands``) and read what it holds.

    Read only: nothing is solved, nothing is changed; the context is dropped on return.

    Raises
    ------
    EngineError
        The model does not compile, an extra command is rejected, or the circuit is empty.
    """
    from simulator_bridge.survey import (
        CircuitSurvey,
        SurveyBus,
        SurveyCapacitor,
        SurveyEdge,
        SurveyLoad,
        SurveyMeter,
        SurveyPvSystem,
        SurveyRegControl,
    )

    master = Path(master).resolve()
    d = new_context()
    cwd = os.getcwd()
    try:
        with DSS_LIFECYCLE:
            _compile_read_only(d, master)
            for cmd in extra_commands:
                d.Text.Command(cmd)
    except dss.DSSException as e:
        raise EngineError(f"{master}: the feeder does not compile: {e}; fix the OpenDSS model") from e
    finally:
        os.chdir(cwd)
    if d.Circuit.NumBuses() == 0:
        raise EngineError(f"{master}: compiled to an empty circuit; is this an OpenDSS master file?")
    _close_debug_traces(d)

    def bus_of(spec: str) -> str:
        return spec.split(".")[0].lower()

    def phases_of(spec: str, n: int) -> int:
        parts = [p for p in spec.split(".")[1:] if p.isdigit() and 1 <= int(p) <= 3]
        return len(parts) if parts else n

    buses = []
    for name in d.Circuit.AllBusNames():
        d.Circuit.SetActiveBus(name)
        buses.append(SurveyBus(name.lower(), float(d.Bus.kVBase()),
                               tuple(sorted(int(n) for n in d.Bus.Nodes() if 1 <= int(n) <= 3))))
    line_z: dict[str, complex] = {}
    i = d.Lines.First()
    while i > 0:
        n = int(d.Lines.Phases())
        z = (np.asarray(d.Lines.RMatrix(), float) + 1j * np.asarray(d.Lines.XMatrix(), float)).reshape(n, n)
        z1 = np.mean(np.diag(z)) - (np.mean(z[~np.eye(n, dtype=bool)]) if n > 1 else 0.0)
        line_z[f"line.{d.Lines.Name().lower()}"] = complex(z1 * d.Lines.Length())
        i = d.Lines.Next()
    edges = []
    i = d.PDElements.First()
    while i > 0:
        name = d.CktElement.Name().lower()
        specs = list(d.CktElement.BusNames())
        kind = name.split(".")[0]
        if d.CktElement.Enabled() and kind != "capacitor":
            n_ph = int(d.CktElement.NumPhases())
            for a in range(len(specs)):
                for b in range(a + 1, len(specs)):
                    if bus_of(specs[a]) != bus_of(specs[b]):
                        edges.append(SurveyEdge(name, kind, bus_of(specs[a]), bus_of(specs[b]),
                                                min(phases_of(specs[a], n_ph), phases_of(specs[b], n_ph)),
                                                line_z.get(name, 0j)))
        i = d.PDElements.Next()
    d.Circuit.SetActiveElement("Vsource.source")
    source_bus = bus_of(d.CktElement.BusNames()[0])
    d.Vsources.Name("source")
    source_kv, source_pu = float(d.Vsources.BasekV()), float(d.Vsources.PU())

    regs = []
    i = d.RegControls.First()
    while i > 0:
        name, xf, w = d.RegControls.Name().lower(), d.RegControls.Transformer().lower(), int(d.RegControls.Winding())
        vreg, band = float(d.RegControls.ForwardVreg()), float(d.RegControls.ForwardBand())
        delay, tapdelay = float(d.RegControls.Delay()), float(d.RegControls.TapDelay())
        monitored = d.RegControls.MonitoredBus().strip().lower()
        d.Circuit.SetActiveElement(f"Transformer.{xf}")
        specs = list(d.CktElement.BusNames())
        n_ph = int(d.CktElement.NumPhases())
        other = specs[1] if w == 1 and len(specs) > 1 else specs[0]
        regs.append(SurveyRegControl(name, xf, w, bus_of(specs[w - 1]), bus_of(other), phases_of(specs[w - 1], n_ph),
                                     vreg, band, delay, tapdelay, monitored))
        i = d.RegControls.Next()
    controls: dict[str, tuple[str, str]] = {}
    i = d.CapControls.First()
    while i > 0:
        controls[d.CapControls.Capacitor().lower()] = (
            d.CapControls.Name().lower(), _CAPCONTROL_MODES.get(int(d.CapControls.Mode()), "unknown"))
        i = d.CapControls.Next()
    caps = []
    i = d.Capacitors.First()
    while i > 0:
        name = d.Capacitors.Name().lower()
        spec = d.CktElement.BusNames()[0]
        ctl = controls.get(name)
        caps.append(SurveyCapacitor(name, bus_of(spec), phases_of(spec, int(d.CktElement.NumPhases())),
                                    float(d.Capacitors.kvar()), float(d.Capacitors.kV()),
                                    ctl[0] if ctl else None, ctl[1] if ctl else None))
        i = d.Capacitors.Next()
    pvs = []
    i = d.PVsystems.First()
    while i > 0:
        spec = d.CktElement.BusNames()[0]
        name = d.PVsystems.Name().lower()
        d.Text.Command(f"? pvsystem.{name}.kv")
        try:
            kv = float(d.Text.Result())
        except ValueError:
            kv = 0.0
        pvs.append(SurveyPvSystem(name, bus_of(spec), phases_of(spec, int(d.CktElement.NumPhases())),
                                  float(d.PVsystems.kVARated()), float(d.PVsystems.Pmpp()), kv))
        i = d.PVsystems.Next()
    loads = []
    i = d.Loads.First()
    while i > 0:
        loads.append(SurveyLoad(d.Loads.Name().lower(), bus_of(d.CktElement.BusNames()[0]), float(d.Loads.kW())))
        i = d.Loads.Next()
    meters = []
    i = d.Meters.First()
    while i > 0:
        meters.append(SurveyMeter(d.Meters.Name().lower(), d.Meters.MeteredElement().lower(),
                                  int(d.Meters.MeteredTerminal())))
        i = d.Meters.Next()
    return CircuitSurvey(
        master=str(master), circuit=d.Circuit.Name().lower(), source_bus=source_bus, source_kv_ll=source_kv,
        source_pu=source_pu, buses=tuple(buses), edges=tuple(edges),
        elements=frozenset(e.lower() for e in d.Circuit.AllElementNames()), regcontrols=tuple(regs),
        capacitors=tuple(caps), pvsystems=tuple(pvs), loads=tuple(loads), meters=tuple(meters),
        node_count=len(d.Circuit.AllNodeNames()),
    )


DSS_LIFECYCLE = threading.RLock()
"""Held while an OpenDSS context is created, compiled or disposed.

Contexts solve in parallel threads, but their birth and death are not safe to overlap: ``ctx_New`` segfaulted
once in CI in a bridge thread while the test's main thread let go of an earlier engine (cffi disposes a context
from whichever thread drops the last reference), and ``compile``/``redirect`` change the process's working
directory, so two compiles at once read each other's relative ``redirect`` files ("Redirect file not found",
reproduced with two threads compiling IEEE 13). Re-entrant: a disposal that the garbage collector starts inside
a locked section of the same thread goes through.
"""


def new_context():
    """A fresh OpenDSS context whose creation and disposal hold :data:`DSS_LIFECYCLE`.

    ``dss.NewContext()`` attaches ``ctx_Dispose`` to the context pointer as a bare cffi destructor; it is
    replaced by one that takes the lock, owned by the context's own API object (so it runs after that object's
    callbacks are unregistered, as before).

    Make, use and drop an engine in a thread that lives as long as it does (a process's main thread, a worker's
    pool thread): DSS C-API is FreePascal, which sets up a foreign thread's own state and heap the first time the
    thread calls in; ``ctx_New`` segfaulted in a fresh, short-lived test thread (tests/simulator_bridge/dssthread.py).
    """
    with DSS_LIFECYCLE:
        # The cyclic garbage collector disposes contexts left in reference cycles from whichever thread it runs
        # in; inside this section that is this thread, which holds the (re-entrant) lock, so a collection
        # triggered by the wrapper's own allocations would dispose an old context in the middle of creating the
        # new one (the segfault in ctx_New seen twice in test_bridge, right after a fixture dropped an engine).
        # Collect first, then keep the collector off while the context is made.
        gc.collect()
        enabled = gc.isenabled()
        gc.disable()
        try:
            d = dss.NewContext()
        finally:
            if enabled:
                gc.enable()
    util = d._api_util
    ffi, lib = util.ffi, util.lib_unpatched
    ffi.gc(util.ctx, None)  # detach the unlocked destructor
    util._cvvc_disposer = ffi.gc(util.ctx, _locked_dispose(lib))
    return d


def _locked_dispose(lib):
    def dispose(ctx) -> None:
        with DSS_LIFECYCLE:
            lib.ctx_Dispose(ctx)
    return dispose


def _compile_read_only(d, master: Path) -> None:
    """Compile ``master`` without writing into its folder, then make its folder the data path as ``compile`` does.

    ``compile`` makes the master's folder OpenDSS's output folder while the model is read, so a model that opens
    an output file as it is defined (epri-ckt24's LTC has ``debugtrace=yes``: ``REG_<name>.csv``) writes into the
    shared, read-in-place model folder, and FreePascal's exclusive lock on that file makes every other process that
    compiles the model meanwhile fail ("Unable to create file"). Here the model is read with ``redirect`` (which
    resolves its files as ``compile`` does) while the data path is a private temporary folder, removed afterwards.
    """
    with tempfile.TemporaryDirectory(prefix="cvvc-dss-") as scratch:
        d.Text.Command(f'set datapath="{scratch}"')
        d.Text.Command(f'redirect "{master}"')
        _close_debug_traces(d)  # closes the trace files, which live in scratch
        d.Text.Command(f'set datapath="{master.parent}"')


def _close_debug_traces(d) -> None:
    """Turn off every RegControl's ``debugtrace``, which closes its trace file.

    A model compiled with ``debugtrace=yes`` (epri-ckt24's LTC) keeps ``REG_<name>.csv`` open in the model's
    folder; a second context in the same process then fails to compile it ("Unable to create file").
    """
    i = d.RegControls.First()
    while i > 0:
        d.Text.Command(f"edit regcontrol.{d.RegControls.Name()} debugtrace=no")
        i = d.RegControls.Next()
