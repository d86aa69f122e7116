"""The feeder zone and electrical distances on a circuit survey (pure functions of ``survey.CircuitSurvey``).

The **feeder zone** is what lies downstream of the head meter element: the head element's first bus (where the
meter measures) and every bus reached from its other side without crossing it back. Loads on the head's first
bus (e.g. an aggregate load of the rest of the substation beside the meter) and everything upstream (the
transmission side, other feeders of the substation bus) are outside it: they are simulated with their own
profiles but are not this feeder's peak load, PV sizing, metrics or critical nodes. ``FeederEngine`` applies the
same rule (``node_in_feeder``, ``load_in_feeder``).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from simulator_bridge.errors import SimulatorError
from simulator_bridge.survey.survey import CircuitSurvey

__all__ = [
    "PRIMARY_MIN_KV_LL",
    "SUBTRANSMISSION_KV_LL",
    "FeederZone",
    "ZoneError",
    "bus_distance_ohm",
    "feeder_zone",
    "first_line_out",
    "longest_three_phase_path",
]

#: Buses at or above this line-to-line voltage are not distribution primaries [kV].
SUBTRANSMISSION_KV_LL = 35.0
#: Buses below this line-to-line voltage are secondaries and services, not primaries [kV].
PRIMARY_MIN_KV_LL = 1.0

class ZoneError(SimulatorError):
    """The head element is not in the circuit, or the zone cannot be found from it."""


@dataclass(frozen=True)
class FeederZone:
    """The feeder zone: ``head_bus`` (where the meter measures) and ``buses`` (all zone buses, lower case).

    ``load_names`` are the loads downstream of the meter (not on ``head_bus``); ``peak_load_kw`` their summed
    nominal ``kW=`` [kW]; ``outside_load_kw`` the rest of the circuit's loads [kW].
    """

    head_element: str
    head_bus: str
    buses: frozenset[str]
    load_names: tuple[str, ...]
    peak_load_kw: float
    outside_load_kw: float


def _adjacency(survey: CircuitSurvey) -> dict[str, list[tuple[str, int]]]:
    adj: dict[str, list[tuple[str, int]]] = {}
    for k, e in enumerate(survey.edges):
        adj.setdefault(e.bus1, []).append((e.bus2, k))
        adj.setdefault(e.bus2, []).append((e.bus1, k))
    return adj


def feeder_zone(survey: CircuitSurvey, head_element: str) -> FeederZone:
    """The zone downstream of ``head_element`` (``Class.name``, any case).

    Raises
    ------
    ZoneError
        The element is not a two-bus power-delivery element of the circuit.
    """
    head = head_element.lower()
    ends = [(e.bus1, e.bus2) for e in survey.edges if e.element == head]
    if not ends:
        raise ZoneError(f"head element {head_element!r} is not an enabled line/transformer/switch between two "
                        f"buses of {survey.master}; name the element the feeder meter measures (Class.name)")
    head_bus, far = ends[0]
    adj = _adjacency(survey)
    zone = {head_bus}
    queue = deque([far])
    while queue:
        a = queue.popleft()
        if a in zone:
            continue
        zone.add(a)
        queue.extend(b for b, k in adj.get(a, []) if survey.edges[k].element != head and b not in zone)
    inside = [ld for ld in survey.loads if ld.bus in zone and ld.bus != head_bus]
    total = sum(ld.kw for ld in survey.loads)
    peak = sum(ld.kw for ld in inside)
    return FeederZone(head_element=head, head_bus=head_bus, buses=frozenset(zone),
                      load_names=tuple(ld.name for ld in inside), peak_load_kw=peak, outside_load_kw=total - peak)


def bus_distance_ohm(survey: CircuitSurvey, from_bus: str) -> dict[str, float]:
    """Electrical distance of every reachable bus from ``from_bus``: ``|sum Z1|`` along the path [ohm, referred
    to ``from_bus``'s voltage by ``(kV_from / kV_line)^2``]; the rule of ``FeederEngine.node_distance_ohm``.
    """
    kv = {b.name: b.kv_ln for b in survey.buses}
    kv_ref = kv.get(from_bus.lower(), 0.0)
    adj = _adjacency(survey)
    total = {from_bus.lower(): 0j}
    queue = deque([from_bus.lower()])
    while queue:
        a = queue.popleft()
        for b, k in adj.get(a, []):
            if b not in total:
                e = survey.edges[k]
                z = e.z_ohm
                kv_line = kv.get(e.bus1, 0.0)
                if z and kv_line > 0 and kv_ref > 0:
                    z *= (kv_ref / kv_line) ** 2
                total[b] = total[a] + z
                queue.append(b)
    return {b: abs(z) for b, z in total.items()}


def first_line_out(survey: CircuitSurvey) -> str | None:
    """The first line (breadth first from the source bus) whose bus is below subtransmission voltage, or None."""
    kv = {b.name: b.kv_ln for b in survey.buses}
    adj = _adjacency(survey)
    seen = {survey.source_bus}
    queue = deque([survey.source_bus])
    while queue:
        a = queue.popleft()
        for b, k in sorted(adj.get(a, []), key=lambda x: x[1]):
            e = survey.edges[k]
            if e.kind == "line" and 0 < kv.get(a, 0.0) * 3**0.5 < SUBTRANSMISSION_KV_LL:
                return f"Line.{e.element.split('.', 1)[1]}"
            if b not in seen:
                seen.add(b)
                queue.append(b)
    return None


def longest_three_phase_path(survey: CircuitSurvey, zone: FeederZone) -> tuple[tuple[str, ...], tuple[float, ...]]:
    """The three-phase path from the zone's head to its electrically farthest three-phase primary bus.

    Primary: ``PRIMARY_MIN_KV_LL <= kV_LL < SUBTRANSMISSION_KV_LL``, and of the head bus's voltage class (within
    10 %), so the path does not cross a step-down transformer to another primary voltage.

    Only three-phase lines between three-phase buses of the zone below subtransmission voltage are followed
    (plus three-phase regulators and switches on the way). Returns the buses from the head on and their
    electrical distances from the head bus [ohm].
    """
    kv = {b.name: b.kv_ln for b in survey.buses}
    kv_ref = kv.get(zone.head_bus, 0.0)
    # the head's own voltage class (within 10 %): not across a step-down transformer to another primary voltage
    three = {b.name for b in survey.buses if len(b.phases) == 3 and b.name in zone.buses
             and PRIMARY_MIN_KV_LL <= b.kv_ln * 3**0.5 < SUBTRANSMISSION_KV_LL
             and (kv_ref <= 0 or abs(b.kv_ln - kv_ref) <= 0.1 * kv_ref)}
    adj = _adjacency(survey)
    dist: dict[str, complex] = {zone.head_bus: 0j}
    parent: dict[str, str] = {}
    queue = deque([zone.head_bus])
    while queue:
        a = queue.popleft()
        for b, k in adj.get(a, []):
            e = survey.edges[k]
            if b in dist or b not in three or e.phases != 3 or e.kind not in ("line", "transformer", "reactor"):
                continue
            z = e.z_ohm * ((kv_ref / kv[e.bus1]) ** 2 if kv.get(e.bus1, 0) > 0 and kv_ref > 0 else 1.0)
            dist[b] = dist[a] + z
            parent[b] = a
            queue.append(b)
    end = max(dist, key=lambda b: abs(dist[b]))
    path = [end]
    while path[-1] in parent:
        path.append(parent[path[-1]])
    path.reverse()
    return tuple(path), tuple(abs(dist[b]) for b in path)
