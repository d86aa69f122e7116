"""What the engine reads from a compiled OpenDSS model once, at setup: names checked, PV plants added, the wiring and
settings of every RegControl and CapControl, where each measured terminal's conductors are, and the electrical
distance of every bus.

Plain functions of an OpenDSS context ``d`` (made by ``dss_context.new_context``) and the device map; they leave
OpenDSS's active element wherever they last put it (the engine never relies on it). Used by ``engine.py``.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from schemas.devicemap import DeviceMap, DeviceMapError
from simulator_bridge.opendss.controls import CapControlSettings, CapKind, RegControlSettings
from simulator_bridge.opendss.dss_context import command

__all__ = [
    "BankTable",
    "RegulatorWiring",
    "TerminalIndex",
    "add_pv_plants",
    "bus_distance_ohm",
    "check_names",
    "conductor_range",
    "disable_meters",
    "phase_mode",
    "pv_name",
    "read_capacitors",
    "read_regulators",
    "terminal_index",
]

_PHASES = (1, 2, 3)
# OpenDSS CapControl types -> ours
_CAP_KINDS: dict[str, CapKind] = {"current": "current", "voltage": "voltage", "kvar": "kvar", "pf": "pf",
                                  "powerfactor": "pf", "time": "time", "follow": "follow"}


@dataclass(frozen=True)
class TerminalIndex:
    """Where to find one terminal of one measured element in the per-step read-outs.

    Indices are into the batch vectors of conductor voltages and currents (every conductor of every
    measured element, in batch order), extended with a trailing 0 so that index -1 reads 0.
    """

    element: str
    node: tuple[int, int, int]  # per phase a, b, c: node index into node_names, -1 if absent
    conductor: tuple[int, int, int]  # per phase a, b, c: index into the batch vectors, -1 if absent
    neutral: int  # index of the terminal's neutral conductor in the batch vectors, -1 if none


@dataclass(frozen=True)
class RegulatorWiring:
    """How one RegControl of the model is wired: its transformer, winding, PT and CT, line-drop compensation and
    tap range, and the nodes it reads (indices into the engine's ``node_names``).
    """

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


def phase_mode(text: str, what: str) -> int:
    """A CapControl's PTphase/CTphase: 1..3, or -1 (AVG), -2 (MAX), -3 (MIN).

    Raises
    ------
    DeviceMapError
        ``text`` is none of these; ``what`` names the control in the message.
    """
    t = text.strip().lower()
    if t.isdigit():
        return int(t)
    modes = {"avg": -1, "max": -2, "min": -3}
    if t not in modes:
        raise DeviceMapError(f"{what}: phase selection {text!r} is not understood")
    return modes[t]


@dataclass(frozen=True)
class BankTable:
    """Every capacitor bank the engine sets (the map's first, map order; then the others a CapControl switches) and
    every CapControl of the model (model order).

    Attributes
    ----------
    banks : OpenDSS Capacitor names, lower case. kvar : each bank's rated kvar, all steps [kvar].
    steps : each bank's number of steps. states : closed steps at compile time (0 with an open terminal).
    controls : each CapControl's own settings. bank_of : each CapControl's bank (index into ``banks``).
    monitored : per CapControl (monitored element, terminal, PT phase mode, CT phase mode, PT ratio, CT ratio, the
        bank is delta-connected); phase modes as :func:`phase_mode`.
    """

    banks: tuple[str, ...]
    kvar: tuple[float, ...]
    steps: tuple[int, ...]
    states: tuple[int, ...]
    controls: tuple[CapControlSettings, ...]
    monitored: tuple[tuple[str, int, int, int, float, float, bool], ...]
    bank_of: tuple[int, ...]


def check_names(d, dm: DeviceMap, where: str) -> None:
    """Raise ``DeviceMapError`` for a bus, element, RegControl, Capacitor, CapControl or PVSystem the map names
    and the model compiled in ``d`` does not have (``where`` names the map in the message).
    """
    buses = {b.lower() for b in d.Circuit.AllBusNames()}
    elements = {e.lower() for e in d.Circuit.AllElementNames()}
    regcontrols = {r.lower() for r in d.RegControls.AllNames()}
    master = dm.master_path.name
    if dm.feeder.source_bus.lower() not in buses:
        raise DeviceMapError(f"{where}: feeder.source_bus {dm.feeder.source_bus!r} is not a bus "
                             f"of {master}")
    if dm.feeder.head_element.lower() not in elements:
        raise DeviceMapError(f"{where}: feeder.head_element {dm.feeder.head_element!r} is not an "
                             f"element of {master} (write it as Class.name, e.g. Line.sw1)")
    for r in dm.regulator:
        if r.regcontrol.lower() not in regcontrols:
            raise DeviceMapError(f"{where}: regulator {r.id!r}: RegControl {r.regcontrol!r} not "
                                 f"found in {master}; known: {sorted(regcontrols)}")
    capacitors = {c.lower() for c in d.Capacitors.AllNames()}
    capcontrols = {c.lower() for c in d.CapControls.AllNames()}
    for c in dm.capacitor:
        if c.capacitor.lower() not in capacitors:
            raise DeviceMapError(f"{where}: capacitor {c.id!r}: Capacitor {c.capacitor!r} not found in "
                                 f"{master}; known: {sorted(capacitors)}")
        if c.capcontrol is None:
            continue
        if c.capcontrol.lower() not in capcontrols:
            raise DeviceMapError(f"{where}: capacitor {c.id!r}: CapControl {c.capcontrol!r} not found "
                                 f"in {master}; known: {sorted(capcontrols)}")
        d.CapControls.Name(c.capcontrol)
        controlled = d.CapControls.Capacitor().lower()
        if controlled != c.capacitor.lower():
            raise DeviceMapError(f"{where}: capacitor {c.id!r}: CapControl {c.capcontrol!r} switches "
                                 f"Capacitor {controlled!r}, not {c.capacitor!r}; name the bank's own control")
    for p in dm.pv:
        if p.bus.split(".")[0].lower() not in buses:
            raise DeviceMapError(f"{where}: PV plant {p.id!r}: bus {p.bus!r} not found in {master}")
        if not p.create and f"pvsystem.{p.pvsystem}".lower() not in elements:
            raise DeviceMapError(f"{where}: PV plant {p.id!r}: PVSystem {p.pvsystem!r} not found "
                                 f"in {master}")


def add_pv_plants(d, dm: DeviceMap, where: str) -> None:
    """Create the map's new PV plants in ``d`` (``create = true``) and set up its existing ones, all dark."""
    for p in dm.pv:
        name = pv_name(dm, p.id)
        if p.create:
            kv = p.kv_ll if p.phases == 3 else p.kv_ll / np.sqrt(3.0)  # 1-phase: kV across the terminals
            command(d,
                f"new pvsystem.{name} phases={p.phases} bus1={p.bus} kv={kv:.6g} kva={p.kva:.6g} "
                f"pmpp={p.pmpp_kw:.6g} irradiance=0 %cutin=0.01 %cutout=0.01 kvar=0 "
                "wattpriority=yes varfollowinverter=no",
                what=f"{where}: PV plant {p.id!r}",
            )
        else:
            command(d, f"edit pvsystem.{name} kva={p.kva:.6g} pmpp={p.pmpp_kw:.6g} irradiance=0 kvar=0 "
                          "wattpriority=yes varfollowinverter=no",
                          what=f"{where}: PV plant {p.id!r}")


def pv_name(dm: DeviceMap, pv_id: str) -> str:
    """The OpenDSS PVSystem name (lower case) of the map's plant ``pv_id``."""
    spec = next(p for p in dm.pv if p.id == pv_id)
    return (spec.pvsystem if not spec.create and spec.pvsystem else f"cvvc_{spec.id}").lower()


def disable_meters(d) -> None:
    """Disable every EnergyMeter and Monitor of the model (they would sample every solve)."""
    for name in d.Meters.AllNames():
        if name and name.upper() != "NONE":
            command(d, f"disable energymeter.{name}", what="engine setup")
    for name in d.Monitors.AllNames():
        if name and name.upper() != "NONE":
            command(d, f"disable monitor.{name}", what="engine setup")


def read_regulators(d, dm: DeviceMap, node_index: dict[str, int],
                    where: str) -> tuple[tuple[RegulatorWiring, ...], tuple[RegControlSettings, ...]]:
    """Every RegControl of the model: the map's first (map order), then the others (model order); its wiring
    and its own settings.

    Raises
    ------
    DeviceMapError
        A RegControl uses a mode that is not modelled, a PT phase that is not understood, or a monitored bus
        that is not a node of the model.
    """
    map_names = [s.regcontrol.lower() for s in dm.regulator]
    others = [n.lower() for n in d.RegControls.AllNames() if n and n.upper() != "NONE"
              and n.lower() not in map_names]
    regs, settings = [], []
    for name in map_names + others:
        d.RegControls.Name(name)
        what = f"{where}: RegControl {name!r}"
        xf, winding = d.RegControls.Transformer().lower(), int(d.RegControls.Winding())
        pt_ratio, ct = float(d.RegControls.PTRatio()), float(d.RegControls.CTPrimary())
        r_v, x_v = float(d.RegControls.ForwardR()), float(d.RegControls.ForwardX())
        vreg, bandw = float(d.RegControls.ForwardVreg()), float(d.RegControls.ForwardBand())
        remote_bus = d.RegControls.MonitoredBus().strip().lower()
        prop = {p: command(d, f"? regcontrol.{name}.{p}", what=what).strip().lower()
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
            if key not in node_index:
                raise DeviceMapError(f"{what}: monitored bus {remote_bus!r} is not a node of the model")
            remote_node = node_index[key]
        tap_step = (tap_hi - tap_lo) / (2 * tap_max)
        regs.append(RegulatorWiring(
            regcontrol=name, transformer=xf, winding=winding, pt_phase=pt_phase_number, pt_mode=pt_mode,
            pt_ratio=pt_ratio, ct_primary_a=ct, ldc_r_v=r_v, ldc_x_v=x_v, tap_winding=tap_winding,
            tap_center=(tap_lo + tap_hi) / 2, tap_step=tap_step, tap_max=tap_max,
            primary_node=node_index[pri_node], secondary_node=node_index[sec_node],
            pu_per_v120=pt_ratio / base_v, remote_node=remote_node,
            remote_pt_ratio=float(prop["remoteptratio"] or pt_ratio)))
        max_change = int(d.RegControls.MaxTapChange())
        settings.append(RegControlSettings(
            name=name, vreg_v120=vreg, band_v120=bandw, delay_s=float(d.RegControls.Delay()),
            tap_delay_s=float(d.RegControls.TapDelay()), inverse_time=bool(d.RegControls.IsInverseTime()),
            enabled=prop["enabled"] in ("yes", "true") and max_change > 0, tap_max=tap_max,
            taps_per_v120=pt_ratio / (v_base_wdg * tap_step) * (1.0 if tap_winding == winding else -1.0)))
    return tuple(regs), tuple(settings)


def read_capacitors(d, dm: DeviceMap, where: str) -> BankTable:
    """The map's banks (map order), then every other bank a CapControl of the model switches, and every
    CapControl of the model (model order).

    Raises
    ------
    DeviceMapError
        A CapControl's type or phase selection is not modelled.
    """
    specs = dm.capacitor
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
    controls, monitored, bank_of = [], [], []
    for name in cc_names:
        d.CapControls.Name(name)
        what = f"{where}: CapControl {name!r}"
        prop = {p: command(d, f"? capcontrol.{name}.{p}", what=what).strip().lower()
                for p in ("type", "ptphase", "ctphase", "pctminkvar", "enabled", "voltoverride")}
        kind = _CAP_KINDS.get(prop["type"])
        if kind is None:
            raise DeviceMapError(f"{what}: type {prop['type']!r} is not modelled (current, voltage, kvar, pf, time, "
                                 "follow)")
        on, off = float(d.CapControls.ONSetting()), float(d.CapControls.OFFSetting())
        if kind == "pf":  # OpenDSS's 0..2 scale: a leading (negative) PF setting is 2 + PF
            on, off = (2.0 + on if on < 0 else on), (2.0 + off if off < 0 else off)
        bank = banks.index(cc_cap[name])
        bank_of.append(bank)
        controls.append(CapControlSettings(
            name=name, kind=kind, on=on, off=off, delay_s=float(d.CapControls.Delay()),
            delay_off_s=float(d.CapControls.DelayOff()), dead_time_s=float(d.CapControls.DeadTime()),
            volt_override=prop["voltoverride"] in ("yes", "true"), vmin_v=float(d.CapControls.Vmin()),
            vmax_v=float(d.CapControls.Vmax()), n_steps=steps[bank], total_kvar=kvar[bank],
            pct_min_kvar=float(prop["pctminkvar"] or 50.0), enabled=prop["enabled"] in ("yes", "true")))
        monitored.append((d.CapControls.MonitoredObj(), int(d.CapControls.MonitoredTerm()),
                          phase_mode(prop["ptphase"], what), phase_mode(prop["ctphase"], what),
                          float(d.CapControls.PTRatio()), float(d.CapControls.CTRatio()), conn_delta[bank]))
    return BankTable(banks=tuple(banks), kvar=tuple(kvar), steps=tuple(steps), states=tuple(states),
                     controls=tuple(controls), monitored=tuple(monitored), bank_of=tuple(bank_of))


def conductor_range(d, element: str, terminal: int, offset: int, *, with_conductors: bool = False):
    """(first batch index of ``terminal``'s conductors, number of phases[, number of conductors])."""
    d.Circuit.SetActiveElement(element)
    n_cond, n_phases = int(d.CktElement.NumConductors()), int(d.CktElement.NumPhases())
    first = offset + (terminal - 1) * n_cond
    return (first, n_phases, n_cond) if with_conductors else (first, n_phases)


def terminal_index(d, node_index: dict[str, int], element: str, terminal: int, offset: int,
                   where: str) -> tuple[TerminalIndex, int]:
    """Index tables for ``terminal`` of ``element``; also its number of currents (all terminals)."""
    if d.Circuit.SetActiveElement(element) < 0:
        raise DeviceMapError(f"{where}: element {element!r} not found")
    n_cond = int(d.CktElement.NumConductors())
    n_phases = int(d.CktElement.NumPhases())
    n_term = int(d.CktElement.NumTerminals())
    bus = d.CktElement.BusNames()[terminal - 1].split(".")[0].lower()
    order = list(d.CktElement.NodeOrder())[(terminal - 1) * n_cond: terminal * n_cond]
    node, conductor = [-1, -1, -1], [-1, -1, -1]
    first = offset + (terminal - 1) * n_cond
    for c, ph in enumerate(order[:n_phases]):
        if ph in _PHASES:
            node[ph - 1] = node_index[f"{bus}.{ph}"]
            conductor[ph - 1] = first + c
    neutral = first + n_phases if n_cond > n_phases else -1
    return (TerminalIndex(d.CktElement.Name(), (node[0], node[1], node[2]), (conductor[0], conductor[1], conductor[2]),
                          neutral), n_term * n_cond)


def bus_distance_ohm(d, source_bus: str, head_element: str) -> tuple[dict[str, float], set[str], str]:
    """Electrical distance of every bus from ``source_bus`` [ohm, referred to the source bus voltage],
    and the buses of the feeder proper: the head element's first bus and everything reached from its
    other side without crossing it back (the transmission side of the substation is not the feeder).

    Breadth-first over power-delivery elements from the source bus; each line adds its positive-
    sequence series impedance ``Z1 = mean(Z_self) - mean(Z_mutual)`` (from its phase impedance
    matrix, = R1 + jX1 for a transposed line) times its length, referred to the source bus voltage
    by ``(kV_source / kV_line)^2``; transformers, regulators and switches-as-elements add 0. The
    distance is ``|sum Z1|`` along the path.
    """
    kv_base: dict[str, float] = {}
    for bus in d.Circuit.AllBusNames():
        d.Circuit.SetActiveBus(bus)
        kv_base[bus.lower()] = d.Bus.kVBase()
    src = source_bus.lower()
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
            z_edge = line_z.get(name, 0j)
            kv = kv_base.get(buses[0], 0.0)
            if z_edge and kv > 0 and kv_src > 0:
                z_edge *= (kv_src / kv) ** 2
            for a in buses:
                for b in buses:
                    if a != b:
                        edges.setdefault(a, []).append((b, z_edge))
                        named_edges.setdefault(a, []).append((b, name))
        i = d.PDElements.Next()
    total: dict[str, complex] = {src: 0j}
    queue = deque([src])
    while queue:
        a = queue.popleft()
        for b, z_ab in edges.get(a, []):
            if b not in total:
                total[b] = total[a] + z_ab
                queue.append(b)
    head = head_element.lower()
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
