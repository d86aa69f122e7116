"""The embedded default feeder: a synthetic rural distribution feeder generated from a seed.

``generate_rural_feeder(seed, out_dir)`` writes an OpenDSS model (text files) and its device map
(``devicemap.toml``), byte for byte the same for the same seed. The feeder matches the rural circuit
of the paper (section IV): about 1003 buses and 1284 single-phase nodes, 2 three-phase and
2 single-phase regulators, 3 PV plants totalling 100 % of peak load. ``docs/feeders.md`` describes the
construction; the steps are:

1. topology: a 12.47 kV three-phase backbone (17-22 km), two three-phase branches, and single-phase
   laterals (trees of #2 / #4 ACSR) tapped off at points drawn with a density that decreases along
   the backbone;
2. loads: mostly single-phase service-transformer loads, a few single-phase small commercial and
   three-phase loads, denser and larger near the substation, scaled to a total peak of 3.8-4.6 MW;
   laterals are assigned to phases heaviest first to balance the backbone;
3. conductors: line impedance matrices from Kersting's modified Carson equations with the neutral
   Kron-reduced (``phase_impedance_ohm_per_mile``, ``phase_capacitance_uf_per_mile``);
4. regulators where the voltage drop needs them: a linear per-phase drop estimate
   (``(R P + X Q) / V^2`` summed along the path) puts the two three-phase banks where the backbone drop
   reaches one and two thirds of its end value, and the two single-phase regulators on the two laterals
   with the largest drop;
5. PV plants (created by the simulator from the device map) on a mid-feeder backbone bus, near the
   backbone's end and at the end of a three-phase branch.

Randomness comes from ``numpy.random.default_rng(seed)`` only; numbers are written with fixed
precision so that the files do not depend on the last bit of a floating-point operation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from simulator_bridge.errors import SimulatorError
from simulator_bridge.rural.linecodes import (
    CONDUCTORS,
    LINECODES,
    Conductor,
    phase_capacitance_uf_per_mile,
    phase_impedance_ohm_per_mile,
)

__all__ = [
    "CONDUCTORS",
    "Conductor",
    "GeneratorError",
    "generate_rural_feeder",
    "phase_capacitance_uf_per_mile",
    "phase_impedance_ohm_per_mile",
]

MASTER_FILE = "master.dss"
DEVICE_MAP_FILE = "devicemap.toml"

_KV_LL = 12.47
_KV_LN = 7.2  # nominal line-to-neutral kV written on single-phase elements
_V_LN_V = _KV_LL * 1000.0 / math.sqrt(3.0)
_PT_RATIO = 60.0  # 7200 V / 120 V
_VREG_V120 = 123.0
_BAND_V120 = 2.0
_LOAD_PF = 0.95
_OMEGA = 2.0 * math.pi * 60.0


class GeneratorError(SimulatorError):
    """The rural feeder could not be generated (bad arguments or an unwritable output folder)."""


# --------------------------------------------------------------------------------------------------
# Topology
# --------------------------------------------------------------------------------------------------


@dataclass
class _Bus:
    """One bus while the feeder is built; ``parent`` is the upstream bus index (-1 for the root)."""

    parent: int
    phase: int  # 0: three-phase; 1, 2, 3: single-phase on that phase
    length_km: float
    linecode: str
    x_m: float
    y_m: float
    u: float  # position of the backbone point the bus hangs off, 0 at the substation, 1 at the end
    kind: str  # "backbone", "branch", "lateral"
    lateral: int = -1
    heading_rad: float = 0.0
    load_kw: float = 0.0
    reg: str = ""  # the element feeding this bus is a regulator (bank id) instead of a line
    name: str = ""
    children: list[int] = field(default_factory=list)


@dataclass(frozen=True)
class _Plant:
    id: str
    bus: int
    pmpp_kw: float


def _sample_counts(rng: np.random.Generator) -> tuple[int, int]:
    """Draw the number of buses and of three-phase buses (the paper: 1003 buses, 1284 single-phase nodes)."""
    n_buses = 1003 + int(rng.integers(-8, 9))
    n_three_phase = 140 + int(rng.integers(-4, 5))
    return n_buses, n_three_phase


def _add(buses: list[_Bus], bus: _Bus) -> int:
    buses.append(bus)
    if bus.parent >= 0:
        buses[bus.parent].children.append(len(buses) - 1)
    return len(buses) - 1


def _step(buses: list[_Bus], parent: int, length_km: float, heading_rad: float) -> tuple[float, float]:
    p = buses[parent]
    return p.x_m + 1000.0 * length_km * math.cos(heading_rad), p.y_m + 1000.0 * length_km * math.sin(
        heading_rad
    )


def _nearest(buses: list[_Bus], candidates: list[int], u: float) -> int:
    """Return the candidate bus whose backbone position is closest to ``u`` (first one on ties)."""
    return min(candidates, key=lambda b: abs(buses[b].u - u))


def _build_three_phase(
    rng: np.random.Generator, n_three_phase: int
) -> tuple[list[_Bus], list[int], list[list[int]]]:
    """Substation, backbone and two three-phase branches. Returns buses, backbone and branch indices."""
    buses: list[_Bus] = []
    _add(buses, _Bus(-1, 0, 0.0, "", -200.0, 0.0, 0.0, "source"))  # 115 kV source bus
    sub = _add(buses, _Bus(0, 0, 0.0, "", 0.0, 0.0, 0.0, "substation"))
    n_branch = [int(rng.integers(10, 17)) for _ in range(2)]
    n_backbone = n_three_phase - 4 - sum(n_branch)  # 4: source, substation, two regulator secondaries
    length_km = float(rng.uniform(17.0, 22.0))
    spans = rng.gamma(4.0, 1.0, n_backbone - 1)
    spans = spans / spans.sum() * (length_km - 0.05)
    backbone = [sub]
    heading = 0.0
    distance = 0.0
    for i in range(n_backbone):
        span = 0.05 if i == 0 else float(spans[i - 1])
        distance += span
        heading = float(np.clip(heading + rng.normal(0.0, 0.25), -0.7, 0.7))
        u = distance / length_km
        x, y = _step(buses, backbone[-1], span, heading)
        code = "ph3_336" if u <= 0.8 else "ph3_1_0"
        backbone.append(
            _add(buses, _Bus(backbone[-1], 0, span, code, x, y, u, "backbone", heading_rad=heading))
        )
    branches = []
    for k, n in enumerate(n_branch):
        lo, hi = (0.25, 0.45) if k == 0 else (0.5, 0.7)
        tap = _nearest(buses, backbone[1:], float(rng.uniform(lo, hi)))
        heading = buses[tap].heading_rad + (math.pi / 2 if k == 0 else -math.pi / 2)
        parent, members = tap, []
        for _ in range(n):
            span = float(rng.uniform(0.2, 0.45))
            heading += float(rng.normal(0.0, 0.2))
            x, y = _step(buses, parent, span, heading)
            parent = _add(
                buses, _Bus(parent, 0, span, "ph3_1_0", x, y, buses[tap].u, "branch", heading_rad=heading)
            )
            members.append(parent)
        branches.append(members)
    return buses, backbone[1:], branches


def _grow_laterals(
    rng: np.random.Generator, buses: list[_Bus], taps_3ph: list[int], n_lateral_buses: int
) -> int:
    """Single-phase laterals: trees tapped off three-phase buses, more of them near the substation."""
    sizes: list[int] = []
    while sum(sizes) < n_lateral_buses:
        sizes.append(int(np.clip(round(rng.lognormal(math.log(7.0), 1.0)), 2, 90)))
    sizes[-1] -= sum(sizes) - n_lateral_buses
    if sizes[-1] < 2:
        sizes[-2] += sizes.pop()
    # tap position: density proportional to (1 - 0.5 u) on the backbone/branch position u
    u_of = np.array([buses[b].u for b in taps_3ph])
    weight = (1.0 - 0.5 * u_of) * np.array([0.6 if buses[b].kind == "branch" else 1.0 for b in taps_3ph])
    weight = weight / weight.sum()
    for lat, size in enumerate(sizes):
        tap = taps_3ph[int(rng.choice(len(taps_3ph), p=weight))]
        side = 1.0 if rng.random() < 0.5 else -1.0
        base_heading = buses[tap].heading_rad + side * float(rng.uniform(1.2, 1.9))
        members: list[int] = []
        tip = -1
        for _ in range(size):
            if tip >= 0 and rng.random() < 0.7:
                parent, heading = tip, buses[tip].heading_rad + float(rng.normal(0.0, 0.3))
            elif members:
                parent = members[int(rng.integers(len(members)))]
                heading = buses[parent].heading_rad + float(rng.choice([-1.0, 1.0]) * rng.uniform(0.8, 1.6))
            else:
                parent, heading = tap, base_heading
            span = float(np.clip(rng.lognormal(math.log(0.14), 0.5), 0.03, 0.8))
            x, y = _step(buses, parent, span, heading)
            tip = _add(buses, _Bus(parent, 0, span, "", x, y, buses[tap].u, "lateral", lat, heading))
            members.append(tip)
    return len(sizes)


def _assign_loads(rng: np.random.Generator, buses: list[_Bus], target_kw: float) -> None:
    """Draw loads: density and size fall off along the feeder; totals scaled to ``target_kw`` [kW]."""
    for b in buses:
        g = 1.2 - 0.4 * b.u
        if b.kind == "lateral" and rng.random() < 0.35 + 0.1 * g:
            if rng.random() < 0.06:
                b.load_kw = float(rng.uniform(20.0, 60.0)) * g  # small commercial
            else:
                b.load_kw = float(np.clip(rng.lognormal(math.log(7.0), 0.5), 2.0, 40.0)) * g
        elif b.kind in ("backbone", "branch") and rng.random() < 0.06:
            b.load_kw = float(rng.uniform(50.0, 250.0)) * g  # three-phase commercial / pumping
    total = sum(b.load_kw for b in buses)
    for b in buses:
        b.load_kw = round(b.load_kw * target_kw / total, 1)


def _subtree_kw(buses: list[_Bus]) -> np.ndarray:
    """Load downstream of each bus, itself included [kW] (children always come after parents)."""
    kw = np.array([b.load_kw for b in buses])
    for i in range(len(buses) - 1, 0, -1):
        kw[buses[i].parent] += kw[i]
    return kw


def _assign_phases(buses: list[_Bus], n_laterals: int) -> None:
    """Laterals go to phases heaviest first, each to the phase with the least load so far."""
    lat_kw = np.zeros(n_laterals)
    for b in buses:
        if b.lateral >= 0:
            lat_kw[b.lateral] += b.load_kw
    phase_kw = [0.0, 0.0, 0.0]
    phase_of = np.zeros(n_laterals, dtype=int)
    for lat in np.argsort(-lat_kw, kind="stable"):
        p = int(np.argmin(phase_kw))
        phase_of[lat] = p + 1
        phase_kw[p] += float(lat_kw[lat])
    for b in buses:
        if b.lateral >= 0:
            b.phase = int(phase_of[b.lateral])


def _size_conductors(buses: list[_Bus], kw_down: np.ndarray) -> None:
    """Single-phase spans carrying more than 60 kW get #2 ACSR, lighter ones #4 ACSR."""
    for i, b in enumerate(buses):
        if b.kind == "lateral":
            b.linecode = "ph1_2" if kw_down[i] > 60.0 else "ph1_4"


def _drop_pu(buses: list[_Bus], kw_down: np.ndarray) -> np.ndarray:
    """Linear estimate of the voltage drop from the substation to each bus [pu of 7.2 kV].

    ``sum (R P + X Q) / V_ln^2`` along the path, with the per-phase power through each span (three-phase
    spans carry a third of their downstream load) at the load power factor.
    """
    tan_phi = math.tan(math.acos(_LOAD_PF))
    drop = np.zeros(len(buses))
    for i in range(2, len(buses)):
        b = buses[i]
        z = LINECODES[b.linecode].z1_ohm_per_km * b.length_km
        p_w = kw_down[i] * 1000.0 / (3.0 if b.phase == 0 else 1.0)
        drop[i] = drop[b.parent] + (z.real * p_w + z.imag * p_w * tan_phi) / _V_LN_V**2
    return drop


def _insert_regulator(buses: list[_Bus], at: int, reg_id: str) -> int:
    """Put a regulator in the span feeding bus ``at``: parent -> regulator -> new bus -> line -> ``at``."""
    b = buses[at]
    parent = b.parent
    new = _add(buses, _Bus(parent, b.phase, 0.0, "", b.x_m, b.y_m, b.u, b.kind, b.lateral, b.heading_rad))
    buses[new].reg = reg_id
    siblings = buses[parent].children
    siblings.remove(new)  # _add appended it; it takes the place of ``at`` instead
    siblings[siblings.index(at)] = new
    b.parent = new
    buses[new].children.append(at)
    # place the regulator a few metres past its primary pole on the drawing
    p = buses[parent]
    buses[new].x_m, buses[new].y_m = p.x_m + 0.02 * (b.x_m - p.x_m), p.y_m + 0.02 * (b.y_m - p.y_m)
    return new


def _path_to_root(buses: list[_Bus], i: int) -> list[int]:
    path = []
    while i > 0:
        path.append(i)
        i = buses[i].parent
    return path[::-1]


def _place_regulators(buses: list[_Bus], backbone: list[int]) -> list[tuple[str, int]]:
    """Two three-phase banks at 1/3 and 2/3 of the backbone drop; two single-phase units on laterals."""
    kw_down = _subtree_kw(buses)
    drop = _drop_pu(buses, kw_down)
    end_drop = drop[backbone[-1]]
    regs = []
    for k, frac in ((1, 0.4), (2, 0.7)):
        at = next(b for b in backbone if drop[b] >= frac * end_drop)
        regs.append((f"reg{k}", _insert_regulator(buses, at, f"reg{k}")))
    # single-phase: the two laterals with the largest drop from their tap (each at most once)
    lateral_drop: dict[int, tuple[float, int]] = {}
    for i, b in enumerate(buses):
        if b.lateral >= 0 and not b.reg:
            tap = b.parent
            while buses[tap].lateral >= 0:
                tap = buses[tap].parent
            d = drop[i] - drop[tap]
            if d > lateral_drop.get(b.lateral, (-1.0, -1))[0]:
                lateral_drop[b.lateral] = (d, i)
    worst = sorted(lateral_drop.items(), key=lambda kv: (-kv[1][0], kv[0]))[:2]
    for k, (_, (d_max, far)) in enumerate(worst, start=3):
        path = [i for i in _path_to_root(buses, far) if buses[i].lateral >= 0]
        tap_drop = drop[buses[path[0]].parent]
        at = next(i for i in path if drop[i] - tap_drop >= 0.3 * d_max)
        regs.append((f"reg{k}", _insert_regulator(buses, at, f"reg{k}")))
    return regs


def _name_buses(buses: list[_Bus], backbone: list[int], branches: list[list[int]]) -> None:
    """Stable short names: backbone first, then branches, then laterals, each depth first."""
    buses[0].name, buses[1].name = "src", "sub"
    counter = 0

    def visit(i: int, kinds: tuple[str, ...]) -> None:
        nonlocal counter
        stack = [i]
        while stack:
            j = stack.pop()
            if buses[j].name or buses[j].kind not in kinds:
                continue
            counter += 1
            buses[j].name = f"b{counter:04d}"
            stack.extend(reversed(buses[j].children))

    for i in backbone:
        chain = _path_to_root(buses, i)
        for j in chain:
            if buses[j].kind == "backbone" and not buses[j].name:
                counter += 1
                buses[j].name = f"b{counter:04d}"
    for members in branches:
        for i in members:
            for j in _path_to_root(buses, i):
                if buses[j].kind == "branch" and not buses[j].name:
                    counter += 1
                    buses[j].name = f"b{counter:04d}"
    for i in range(len(buses)):
        if buses[i].kind == "lateral" and not buses[buses[i].parent].kind == "lateral":
            visit(i, ("lateral",))


def _place_pv(
    rng: np.random.Generator,
    buses: list[_Bus],
    backbone: list[int],
    branches: list[list[int]],
    peak_kw: float,
) -> list[_Plant]:
    """Three plants: mid-backbone, near the backbone end, end of the second branch; sum = peak load."""
    bb = [b for b in backbone if not buses[b].reg]
    mid = _nearest(buses, bb, float(rng.uniform(0.45, 0.6)))
    far = _nearest(buses, bb, float(rng.uniform(0.85, 0.97)))
    share = rng.dirichlet([6.0, 6.0, 6.0])
    sites = (mid, far, branches[1][-1])
    sizes = [round(float(s) * peak_kw, -1) for s in share]
    sizes[-1] = round(peak_kw - sum(sizes[:-1]), -1)
    return [_Plant(f"pv{k + 1}", site, size) for k, (site, size) in enumerate(zip(sites, sizes, strict=True))]


# --------------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------------


def _matrix_text(m: np.ndarray, fmt: str) -> str:
    rows = [" ".join(format(float(m[i, j]), fmt) for j in range(i + 1)) for i in range(m.shape[0])]
    return "(" + " | ".join(rows) + ")"


def _linecodes_text() -> str:
    lines = [
        "! Overhead line codes: Kersting's modified Carson equations, neutral Kron-reduced,",
        "! 60 Hz, earth resistivity 100 ohm-m.",
        "! ph3_336: 336,400 26/7 ACSR phases, 4/0 6/1 ACSR neutral, ID-500 crossarm.",
        "! ph3_1_0: 1/0 ACSR phases and neutral, ID-500 crossarm.",
        "! ph1_2 / ph1_4: #2 / #4 ACSR phase and neutral, single-phase pole (neutral 4 ft below).",
    ]
    for lc in LINECODES.values():
        lines.append(
            f"New LineCode.{lc.name} nphases={lc.n_phases} units=km normamps={lc.ampacity_a:.0f} "
            f"emergamps={1.3 * lc.ampacity_a:.0f}\n"
            f"~ rmatrix={_matrix_text(lc.z_ohm_per_km.real, '.6f')}\n"
            f"~ xmatrix={_matrix_text(lc.z_ohm_per_km.imag, '.6f')}\n"
            f"~ cmatrix={_matrix_text(lc.c_nf_per_km, '.4f')}"
        )
    return "\n".join(lines) + "\n"


def _terminal(b: _Bus, phase: int) -> str:
    """``bus`` for three-phase (``phase`` 0), ``bus.phase`` for single-phase connections."""
    return b.name if phase == 0 else f"{b.name}.{phase}"


def _feeder_text(buses: list[_Bus]) -> tuple[str, str, str]:
    """(lines.dss, regulators.dss, loads.dss) texts."""
    lines, regs, loads = [], [], []
    ordered = sorted(buses[2:], key=lambda b: b.name)
    for b in ordered:
        up = buses[b.parent]
        if b.reg:
            units = ("a", "b", "c") if b.phase == 0 else ("",)
            phases = (1, 2, 3) if b.phase == 0 else (b.phase,)
            kva, ct = (1666, 300) if b.phase == 0 else (500, 100)
            for unit, ph in zip(units, phases, strict=True):
                name = f"{b.reg}{unit}"
                regs.append(
                    f"New Transformer.{name} phases=1 windings=2 bank={b.reg} xhl=0.01 %loadloss=0.01\n"
                    f"~ wdg=1 bus={up.name}.{ph} conn=wye kv={_KV_LN} kva={kva}\n"
                    f"~ wdg=2 bus={b.name}.{ph} conn=wye kv={_KV_LN} kva={kva}\n"
                    "~ maxtap=1.1 mintap=0.9 numtaps=32\n"
                    f"New RegControl.c{name} transformer={name} winding=2 vreg={_VREG_V120:.1f} "
                    f"band={_BAND_V120:.1f} ptratio={_PT_RATIO:.0f} ctprim={ct} R=0 X=0 delay=30 tapdelay=2"
                )
            continue
        name = "head" if up.name == "sub" else f"l{b.name[1:]}"
        lines.append(
            f"New Line.{name} phases={1 if b.phase else 3} "
            f"bus1={_terminal(up, b.phase)} bus2={_terminal(b, b.phase)} "
            f"linecode={b.linecode} length={b.length_km:.4f} units=km"
        )
    for b in ordered:
        if b.load_kw > 0:
            if b.phase:
                spec = f"phases=1 bus1={_terminal(b, b.phase)} kv={_KV_LN}"
            else:
                spec = f"phases=3 bus1={b.name} kv={_KV_LL}"
            loads.append(
                f"New Load.d{b.name[1:]} {spec} kw={b.load_kw:.1f} pf={_LOAD_PF} "
                "model=1 vminpu=0.8 vmaxpu=1.2"
            )
    return "\n".join(lines) + "\n", "\n".join(regs) + "\n", "\n".join(loads) + "\n"


def _master_text(seed: int) -> str:
    return (
        f"! Synthetic rural 12.47 kV feeder from cvvc-edge simulator_bridge/rural/generator.py, seed {seed}.\n"
        "Clear\n"
        f"New Circuit.rural_s{seed} basekv=115 pu=1.045 phases=3 bus1=src mvasc3=2000 mvasc1=2100\n"
        "Redirect linecodes.dss\n"
        "! substation transformer 115 kV delta / 12.47 kV grounded wye, no load tap changer\n"
        "New Transformer.sub phases=3 windings=2 xhl=7 %loadloss=0.5\n"
        "~ wdg=1 bus=src conn=delta kv=115 kva=10000\n"
        f"~ wdg=2 bus=sub conn=wye kv={_KV_LL} kva=10000\n"
        "Redirect lines.dss\n"
        "Redirect regulators.dss\n"
        "Redirect loads.dss\n"
        f"Set voltagebases=[115, {_KV_LL}]\n"
        "Calcvoltagebases\n"
        "Buscoords buscoords.csv\n"
    )


def _devicemap_text(seed: int, buses: list[_Bus], regs: list[tuple[str, int]], plants: list[_Plant]) -> str:
    out = [
        f"# Device map of the synthetic rural feeder, seed {seed} (cvvc feeder generate).",
        "[feeder]",
        f'name = "rural-s{seed}"',
        f'master = "{MASTER_FILE}"',
        'head_element = "Line.head"',
        'source_bus = "sub"',
        f"load_pf = {_LOAD_PF}",
    ]
    for reg_id, i in regs:
        units = ("a", "b", "c") if buses[i].phase == 0 else ("",)
        for unit in units:
            out += [
                "",
                "[[regulator]]",
                f'id = "{reg_id}{unit}"',
                f'regcontrol = "c{reg_id}{unit}"',
                f"setpoint_v120 = {_VREG_V120:.1f}",
                f"band_v120 = {_BAND_V120:.1f}",
            ]
    for p in plants:
        out += [
            "",
            "[[pv]]",
            f'id = "{p.id}"',
            f'bus = "{buses[p.bus].name}"',
            "phases = 3",
            f"kv_ll = {_KV_LL}",
            f"kva = {round(1.1 * p.pmpp_kw, -1):.1f}",
            f"pmpp_kw = {p.pmpp_kw:.1f}",
            "create = true",
        ]
    return "\n".join(out) + "\n"


def generate_rural_feeder(seed: int, out_dir: Path) -> Path:
    """Write the synthetic rural feeder for ``seed`` into ``out_dir``; return the device map path.

    Writes ``master.dss``, ``linecodes.dss``, ``lines.dss``, ``regulators.dss``, ``loads.dss``,
    ``buscoords.csv`` [m] and ``devicemap.toml``. The same seed gives the same bytes.

    Parameters
    ----------
    seed : non-negative integer seed.
    out_dir : folder to write into (created if absent; files of the same names are overwritten).

    Returns
    -------
    Path of ``devicemap.toml``.
    """
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise GeneratorError(f"seed must be a non-negative integer, got {seed!r}")
    rng = np.random.default_rng(seed)
    n_buses, n_three_phase = _sample_counts(rng)
    buses, backbone, branches = _build_three_phase(rng, n_three_phase)
    taps_3ph = backbone + [b for members in branches for b in members]
    n_laterals = _grow_laterals(rng, buses, taps_3ph, n_buses - n_three_phase - 2)
    peak_kw = round(float(rng.uniform(3800.0, 4600.0)), -1)
    _assign_loads(rng, buses, peak_kw)
    _assign_phases(buses, n_laterals)
    _size_conductors(buses, _subtree_kw(buses))
    regs = _place_regulators(buses, backbone)
    _name_buses(buses, backbone, branches)
    plants = _place_pv(rng, buses, backbone, branches, sum(b.load_kw for b in buses))
    lines, reg_text, loads = _feeder_text(buses)
    coords = "".join(f"{b.name},{b.x_m:.1f},{b.y_m:.1f}\n" for b in buses)
    files = {
        MASTER_FILE: _master_text(seed),
        "linecodes.dss": _linecodes_text(),
        "lines.dss": lines,
        "regulators.dss": reg_text,
        "loads.dss": loads,
        "buscoords.csv": coords,
        DEVICE_MAP_FILE: _devicemap_text(seed, buses, regs, plants),
    }
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        for name, text in files.items():
            (out_dir / name).write_bytes(text.encode("ascii"))
    except OSError as e:
        raise GeneratorError(
            f"cannot write the rural feeder into {out_dir}: {e}; choose a writable --out"
        ) from e
    return out_dir / DEVICE_MAP_FILE
