"""What a compiled OpenDSS model holds, as plain typed data (``circuit_survey.survey_circuit`` reads it; no OpenDSS
here).

Used by ``zone.py`` (the feeder zone, distances), ``mapcheck.py`` (``cvvc feeder info``'s checks) and
``scaffold.py`` (``cvvc feeder scaffold``). Names are OpenDSS's, lower case; buses without their node suffixes.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = [
    "CircuitSurvey",
    "SurveyBus",
    "SurveyCapacitor",
    "SurveyEdge",
    "SurveyLoad",
    "SurveyMeter",
    "SurveyPvSystem",
    "SurveyRegControl",
]


@dataclass(frozen=True)
class SurveyBus:
    """One bus: its name (lower case), line-to-neutral base [kV] and the phases (1-3) it has."""

    name: str
    kv_ln: float
    phases: tuple[int, ...]


@dataclass(frozen=True)
class SurveyEdge:
    """One enabled power-delivery element between two buses (lines, transformers, regulators, reactors).

    ``z_ohm`` is a line's positive-sequence series impedance times its length, on its own voltage [ohm]
    (0 for every other element); ``phases`` its number of phases; ``kind`` its OpenDSS class, lower case.
    A transformer with more than two windings gives one edge per winding pair.
    """

    element: str
    kind: str
    bus1: str
    bus2: str
    phases: int
    z_ohm: complex


@dataclass(frozen=True)
class SurveyRegControl:
    """One OpenDSS ``RegControl``: its transformer and winding, the buses of the winding, and its settings.

    ``vreg_v120``/``band_v120`` [V on the 120 V base], ``delay_s``/``tapdelay_s`` [s]; ``monitored_bus`` is ``""``
    for local sensing.
    """

    name: str
    transformer: str
    winding: int
    bus: str
    other_bus: str
    phases: int
    vreg_v120: float
    band_v120: float
    delay_s: float
    tapdelay_s: float
    monitored_bus: str


@dataclass(frozen=True)
class SurveyCapacitor:
    """One OpenDSS ``Capacitor`` [kvar at rated kV, kV as rated] and its ``CapControl`` (None when it has none)."""

    name: str
    bus: str
    phases: int
    kvar: float
    kv: float
    capcontrol: str | None
    control_mode: str | None


@dataclass(frozen=True)
class SurveyPvSystem:
    """One existing OpenDSS ``PVSystem`` [kVA, kW, kV as in the model]."""

    name: str
    bus: str
    phases: int
    kva: float
    pmpp_kw: float
    kv: float


@dataclass(frozen=True)
class SurveyLoad:
    """One load: its bus and nominal ``kW=`` [kW]."""

    name: str
    bus: str
    kw: float


@dataclass(frozen=True)
class SurveyMeter:
    """One ``EnergyMeter``: the element (``Class.name``, lower case) and terminal it meters."""

    name: str
    element: str
    terminal: int


@dataclass(frozen=True)
class CircuitSurvey:
    """What a compiled OpenDSS model holds, read once (``survey_circuit``); no OpenDSS object outlives it.

    ``source_bus`` is the bus of ``Vsource.source`` (``source_kv_ll`` [kV], ``source_pu`` [pu]); ``elements``
    every element name (``class.name``, lower case); ``node_count`` the single-phase nodes (``AllNodeNames``).
    """

    master: str
    circuit: str
    source_bus: str
    source_kv_ll: float
    source_pu: float
    buses: tuple[SurveyBus, ...]
    edges: tuple[SurveyEdge, ...]
    elements: frozenset[str]
    regcontrols: tuple[SurveyRegControl, ...]
    capacitors: tuple[SurveyCapacitor, ...]
    pvsystems: tuple[SurveyPvSystem, ...]
    loads: tuple[SurveyLoad, ...]
    meters: tuple[SurveyMeter, ...]
    node_count: int
