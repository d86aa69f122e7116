"""``cvvc feeder scaffold``: draft a device map from an OpenDSS circuit, every line commented for review.

What the draft holds (``docs/feeders.md``, "Scaffold"):

- ``[feeder]``: the name from the master's folder, the master path relative to the map, the head element from the
  circuit's ``EnergyMeter`` (else the first line out of the substation), the Vsource's bus as source bus;
- every ``RegControl`` as a ``[[regulator]]`` and every ``Capacitor`` as a ``[[capacitor]]`` (with its
  ``CapControl`` when it has one), existing ``PVSystem`` s as ``create = false`` plants;
- three suggested three-phase PV plants sized together to 100 % of the feeder zone's peak load, at about 1/3, 2/3
  and 19/20 of the electrical distance along the zone's longest three-phase primary path, ``kva = 1.1 pmpp_kw``
  (as the rural generator rates them).

The draft is checked before it is returned: it decodes with ``load_device_map`` and passes ``check_device_map``.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

from schemas.devicemap import DeviceMapError, load_device_map
from simulator_bridge.survey.circuit_survey import survey_circuit
from simulator_bridge.survey.mapcheck import check_device_map, suggested_head_element
from simulator_bridge.survey.survey import CircuitSurvey
from simulator_bridge.survey.zone import (
    PRIMARY_MIN_KV_LL,
    SUBTRANSMISSION_KV_LL,
    FeederZone,
    feeder_zone,
    longest_three_phase_path,
)

__all__ = ["PV_KVA_PER_KW", "PV_SITE_FRACTIONS", "ScaffoldResult", "draft_device_map", "scaffold_device_map"]

#: Where the suggested plants go, as fractions of the longest three-phase path's electrical length.
PV_SITE_FRACTIONS = (1 / 3, 2 / 3, 0.95)
#: Inverter rating per kW of array (the rural generator's rule).
PV_KVA_PER_KW = 1.1


@dataclass(frozen=True)
class PvSite:
    """One suggested plant: bus, line-to-line kV, distance from the head [ohm] and share of the path [-]."""

    bus: str
    kv_ll: float
    distance_ohm: float
    fraction: float
    pmpp_kw: float


@dataclass(frozen=True)
class ScaffoldResult:
    """A drafted device map: its TOML text, the zone it was sized on and the suggested PV sites."""

    toml: str
    name: str
    head_element: str
    zone: FeederZone
    pv_sites: tuple[PvSite, ...]


def _ident(text: str) -> str:
    s = re.sub(r"[^A-Za-z0-9_.\-]", "_", text)[:64]
    return s or "x"


def _q(text: str) -> str:
    return json.dumps(text)


def _pv_sites(survey: CircuitSurvey, zone: FeederZone) -> tuple[PvSite, ...]:
    path, dist = longest_three_phase_path(survey, zone)
    kv = {b.name: b.kv_ln * 3**0.5 for b in survey.buses}
    length = dist[-1] if dist else 0.0
    total_kw = round(zone.peak_load_kw)
    each = [round(total_kw / 3 / 10) * 10] * 2
    sizes = [*each, total_kw - sum(each)]
    sites: list[PvSite] = []
    used: set[str] = set()
    for frac, kw in zip(PV_SITE_FRACTIONS, sizes, strict=True):
        order = sorted(range(len(path)), key=lambda i: abs(dist[i] - frac * length))
        for i in order:
            primary = PRIMARY_MIN_KV_LL <= kv[path[i]] < SUBTRANSMISSION_KV_LL
            if path[i] not in used and path[i] != zone.head_bus and primary:
                used.add(path[i])
                sites.append(PvSite(path[i], round(kv[path[i]], 4), dist[i], dist[i] / length if length else 0.0,
                                    float(kw)))
                break
    return tuple(sites)


def draft_device_map(survey: CircuitSurvey, out_path: str | Path, *, name: str | None = None) -> ScaffoldResult:
    """Draft the device map of ``survey`` as it would be written at ``out_path`` (paths relative to it).

    Raises
    ------
    DeviceMapError
        No head element can be found (no ``EnergyMeter`` and no line out of the substation), or the zone has
        no three-phase primary bus for PV plants.
    """
    master = Path(survey.master)
    out_path = Path(out_path).resolve()
    feeder_name = _ident(name or master.parent.name or survey.circuit)
    head = suggested_head_element(survey)
    if head is None:
        raise DeviceMapError(f"{master}: no EnergyMeter and no line out of the substation; add an EnergyMeter at "
                             "the feeder head (New EnergyMeter.head element=Line.X terminal=1) and scaffold again")
    zone = feeder_zone(survey, head)
    sites = _pv_sites(survey, zone)
    if len(sites) < 3:
        raise DeviceMapError(f"{master}: the feeder zone below {head} has fewer than three three-phase primary "
                             "buses on its longest three-phase path; write the [[pv]] entries by hand")
    rel = Path(os.path.relpath(master, out_path.parent)).as_posix()
    bus_kv = {b.name: b.kv_ln * 3**0.5 for b in survey.buses}
    how_head = (f"metered by EnergyMeter.{survey.meters[0].name} (terminal {survey.meters[0].terminal})"
                if survey.meters else "no EnergyMeter: the first line out of the substation")
    lines = [
        f"# Device map of {master.name} drafted by `cvvc feeder scaffold`: review every line before use.",
        f"# Circuit {survey.circuit!r}: {len(survey.buses)} buses, {survey.node_count} nodes, {len(survey.loads)} "
        f"loads; source {survey.source_kv_ll:g} kV at {survey.source_pu:g} pu.",
        f"# Feeder zone (downstream of {head}): {len(zone.buses)} buses, {len(zone.load_names)} loads, peak "
        f"{zone.peak_load_kw:.1f} kW; outside it {zone.outside_load_kw:.1f} kW of other loads (not this feeder's).",
        "[feeder]",
        f"name = {_q(feeder_name)}",
        f"master = {_q(rel)}",
        f"head_element = {_q(head)}   # {how_head}; head bus {zone.head_bus}",
        f"source_bus = {_q(survey.source_bus)}   # the Vsource's bus ({survey.source_kv_ll:g} kV)",
    ]
    for r in survey.regcontrols:
        where = "in the zone" if r.bus in zone.buses else "upstream of the feeder meter (substation)"
        remote = (f"; senses remote bus {r.monitored_bus!r}: needs remote-sensing support in the simulator"
                  if r.monitored_bus else "")
        lines += ["", f"# RegControl {r.name}: Transformer.{r.transformer} winding {r.winding}, {r.other_bus} -> "
                      f"{r.bus} ({r.phases} ph, {bus_kv.get(r.bus, 0):.4g} kV), {where}; vreg {r.vreg_v120:g} V band "
                      f"{r.band_v120:g} V, delay {r.delay_s:g} s, tapdelay {r.tapdelay_s:g} s{remote}",
                  "[[regulator]]", f"id = {_q(_ident(r.name))}", f"regcontrol = {_q(r.name)}"]
    for c in survey.capacitors:
        where = "in the zone" if c.bus in zone.buses else "OUTSIDE the zone: remove unless it is this feeder's"
        ctl = (f"CapControl {c.capcontrol} ({c.control_mode} mode)" if c.capcontrol
               else "no CapControl (stays as compiled unless commanded)")
        lines += ["", f"# Capacitor {c.name}: {c.kvar:g} kvar at {c.kv:g} kV, bus {c.bus} ({c.phases} ph), {where}; "
                      f"{ctl}", "[[capacitor]]", f"id = {_q(_ident(c.name))}", f"capacitor = {_q(c.name)}"]
        if c.capcontrol:
            lines.append(f"capcontrol = {_q(c.capcontrol)}")
    for p in survey.pvsystems:
        kv_ll = p.kv if p.phases == 3 else p.kv * 3**0.5
        lines += ["", f"# existing PVSystem {p.name} at bus {p.bus} ({p.phases} ph)", "[[pv]]",
                  f"id = {_q(_ident('pv_' + p.name))}", f"bus = {_q(p.bus)}", f"phases = {1 if p.phases == 1 else 3}",
                  f"kv_ll = {kv_ll:.6g}", f"kva = {max(p.kva, p.pmpp_kw):.6g}", f"pmpp_kw = {p.pmpp_kw:.6g}",
                  "create = false", f"pvsystem = {_q(p.name)}"]
    total = sum(s.pmpp_kw for s in sites)
    lines += ["", f"# Suggested PV plants: three three-phase plants, {total:.0f} kW together = 100 % of the zone's "
                  f"peak load,", "# spread along the longest three-phase primary path (electrical distance from "
                  f"{zone.head_bus}); kva = {PV_KVA_PER_KW} x pmpp_kw."]
    for k, s in enumerate(sites, start=1):
        lines += ["", f"# {100 * s.fraction:.0f} % along the path, {s.distance_ohm:.3f} ohm from the head, "
                      f"{s.kv_ll:g} kV three-phase primary bus",
                  "[[pv]]", f"id = \"pv{k}\"", f"bus = {_q(s.bus)}", "phases = 3", f"kv_ll = {s.kv_ll:g}",
                  f"kva = {PV_KVA_PER_KW * s.pmpp_kw:.1f}", f"pmpp_kw = {s.pmpp_kw:.1f}"]
    return ScaffoldResult(toml="\n".join(lines) + "\n", name=feeder_name, head_element=head, zone=zone,
                          pv_sites=sites)


def scaffold_device_map(master: str | Path, out_path: str | Path, *, name: str | None = None) -> ScaffoldResult:
    """Survey ``master``, draft its device map, write it to ``out_path`` and check it loads and fits the circuit.

    Raises
    ------
    EngineError
        The master does not compile.
    DeviceMapError
        No head element could be found, or the draft does not pass its own checks (a bug: please report it).
    """
    survey = survey_circuit(master)
    result = draft_device_map(survey, out_path, name=name)
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_path.with_suffix(out_path.suffix + ".tmp")
    tmp.write_text(result.toml)
    try:
        dm = load_device_map(tmp)
        problems = check_device_map(dm, survey)
        if problems:
            raise DeviceMapError(f"{out_path}: the draft does not fit its circuit: {problems[0]}")
        os.replace(tmp, out_path)
    finally:
        tmp.unlink(missing_ok=True)
    return result
