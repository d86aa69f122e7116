"""Check a device map against its circuit (``cvvc feeder info``): one line per problem, saying how to mend it.

Pure: works on a :class:`~simulator_bridge.survey.survey.CircuitSurvey` (``circuit_survey.survey_circuit``), so it
needs no
``FeederEngine`` and finds every problem at once instead of stopping at the first.
"""

from __future__ import annotations

from schemas.devicemap import DeviceMap
from simulator_bridge.survey.survey import CircuitSurvey
from simulator_bridge.survey.zone import ZoneError, feeder_zone, first_line_out

__all__ = ["KV_TOLERANCE", "check_device_map", "suggested_head_element"]

#: Largest relative difference between a PV plant's ``kv_ll`` and its bus's base voltage.
KV_TOLERANCE = 0.05


def suggested_head_element(survey: CircuitSurvey) -> str | None:
    """The element an ``EnergyMeter`` meters (``Class.name``), else the first line out of the substation."""
    if survey.meters:
        cls, name = survey.meters[0].element.split(".", 1)
        return f"{cls.capitalize()}.{name}"
    return first_line_out(survey)


def _close(names, what: str, limit: int = 8) -> str:
    names = sorted(names)
    if not names:
        return f"the model has no {what}"
    more = f" (+{len(names) - limit} more)" if len(names) > limit else ""
    return f"known: {', '.join(names[:limit])}{more}"


def check_device_map(dm: DeviceMap, survey: CircuitSurvey) -> list[str]:
    """Every problem of ``dm`` against ``survey``, one line each (empty: the map fits its circuit).

    Checked: source bus, head element (and its zone), RegControls, Capacitors and their CapControls, PV buses
    (existence, three phases for a three-phase plant, inside the zone, ``kv_ll`` against the bus base voltage),
    existing PVSystems and AMI meters' nodes (``bus.phase`` of the circuit, inside the zone).
    """
    out: list[str] = []
    master = survey.master.rsplit("/", 1)[-1]
    bus = {b.name: b for b in survey.buses}
    f = dm.feeder
    if f.source_bus.lower() not in bus:
        out.append(f"feeder.source_bus {f.source_bus!r} is not a bus of {master}; set source_bus = "
                   f"{survey.source_bus!r} (the Vsource's bus)")
    zone = None
    suggestion = suggested_head_element(survey)
    hint = f"; set head_element = {suggestion!r} (the feeder meter's element)" if suggestion else ""
    if f.head_element.lower() not in survey.elements:
        out.append(f"feeder.head_element {f.head_element!r} is not an element of {master}{hint}")
    else:
        try:
            zone = feeder_zone(survey, f.head_element)
        except ZoneError as e:
            out.append(f"feeder.head_element {f.head_element!r}: not a two-bus line/transformer/switch{hint} ({e})")
    regcontrols = {r.name for r in survey.regcontrols}
    for r in dm.regulator:
        if r.regcontrol.lower() not in regcontrols:
            out.append(f"regulator {r.id!r}: RegControl {r.regcontrol!r} not found in {master}; "
                       f"{_close(regcontrols, 'RegControl')}")
    caps = {c.name: c for c in survey.capacitors}
    for c in dm.capacitor:
        cap = caps.get(c.capacitor.lower())
        if cap is None:
            out.append(f"capacitor {c.id!r}: Capacitor {c.capacitor!r} not found in {master}; "
                       f"{_close(caps, 'Capacitor')}")
            continue
        if c.capcontrol is not None and c.capcontrol.lower() != (cap.capcontrol or ""):
            fix = (f"set capcontrol = {cap.capcontrol!r}" if cap.capcontrol
                   else "remove capcontrol (the bank has no CapControl)")
            out.append(f"capacitor {c.id!r}: CapControl {c.capcontrol!r} does not control Capacitor {c.capacitor!r} "
                       f"in {master}; {fix}")
        if zone is not None and cap.bus not in zone.buses:
            out.append(f"capacitor {c.id!r}: bus {cap.bus!r} is outside the feeder zone (upstream of "
                       f"{f.head_element}); remove the entry or move head_element upstream of it")
    pvsystems = {p.name for p in survey.pvsystems}
    for p in dm.pv:
        name = p.bus.split(".")[0].lower()
        b = bus.get(name)
        if b is None:
            out.append(f"pv {p.id!r}: bus {p.bus!r} not found in {master}; name an existing bus "
                       "(cvvc feeder scaffold suggests three-phase primary buses)")
            continue
        if p.phases == 3 and len(b.phases) < 3:
            out.append(f"pv {p.id!r}: phases = 3 but bus {name!r} has phase(s) {list(b.phases)}; pick a three-phase "
                       "bus or set phases = 1")
        if zone is not None and name not in zone.buses:
            out.append(f"pv {p.id!r}: bus {name!r} is outside the feeder zone (not downstream of {f.head_element}); "
                       "pick a bus downstream of the feeder meter")
        kv_ll = b.kv_ln * 3**0.5
        if p.create and kv_ll > 0 and abs(p.kv_ll - kv_ll) > KV_TOLERANCE * kv_ll:
            out.append(f"pv {p.id!r}: kv_ll = {p.kv_ll:g} but bus {name!r} has a base of {kv_ll:.4g} kV line to "
                       f"line; set kv_ll = {kv_ll:.4g}")
        if not p.create and (p.pvsystem or "").lower() not in pvsystems:
            out.append(f"pv {p.id!r}: PVSystem {p.pvsystem!r} not found in {master}; {_close(pvsystems, 'PVSystem')}"
                       " (or set create = true to add the plant)")
    for meter in dm.meter:  # AMI meters (explicit option): a node is ``bus.phase``
        name, _, phase = meter.node.lower().rpartition(".")
        b = bus.get(name)
        if b is None or not phase.isdigit() or int(phase) not in b.phases:
            where = (f"bus {name!r} not found" if b is None else
                     f"bus {name!r} has phase(s) {list(b.phases)}, not {phase!r}")
            out.append(f"meter {meter.id!r}: node {meter.node!r} is not a node of {master} ({where}); name it "
                       "bus.phase")
        elif zone is not None and name not in zone.buses:
            out.append(f"meter {meter.id!r}: node {meter.node!r} is outside the feeder zone (not downstream of "
                       f"{f.head_element}); the agent only corrects its critical nodes, which are inside")
    return out
