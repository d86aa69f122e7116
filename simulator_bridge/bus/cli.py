"""``cvvc feeder``: generate the embedded rural feeder, draft a device map for any feeder, check and describe one.

Verbs::

    cvvc feeder generate --seed N --out DIR          # writes the rural feeder, prints its device map path
    cvvc feeder scaffold MASTER.dss --out MAP.toml   # drafts a device map, every line commented for review
    cvvc feeder info [FEEDER] [--json] [--cache DIR] # FEEDER: a device map TOML or a folder with devicemap.toml;
                                                     # default: the embedded rural feeder (generated if absent)

``feeder info`` first checks the map against its circuit and prints one line per problem (what is wrong, how to
mend it), exit code 2. ``default_feeder_dir`` / ``ensure_default_feeder`` (``simulator_bridge.rural.default_feeder``)
and
``resolve_device_map_path`` (``schemas.devicemap``) are re-exported for older callers.
Nothing heavy is imported at module level (OpenDSS only inside the handlers).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import msgspec

from schemas.cache import CACHE_HELP, cache_root
from schemas.devicemap import resolve_device_map_path
from simulator_bridge.rural.default_feeder import default_feeder_dir, ensure_default_feeder

__all__ = [
    "CapacitorInfo",
    "FeederInfo",
    "PvPlantInfo",
    "RegulatorInfo",
    "default_feeder_dir",
    "ensure_default_feeder",
    "feeder_info",
    "check_feeder",
    "register",
    "resolve_device_map_path",
]



class RegulatorInfo(msgspec.Struct, frozen=True, kw_only=True):
    """One regulator (tap changer) of the device map: the phase its PT reads and its two buses."""

    id: str
    regcontrol: str
    phase: int
    primary_bus: str
    secondary_bus: str
    setpoint_v120: float
    band_v120: float


class PvPlantInfo(msgspec.Struct, frozen=True, kw_only=True):
    """One PV plant of the device map."""

    id: str
    bus: str
    phases: int
    kva: float
    pmpp_kw: float


class CapacitorInfo(msgspec.Struct, frozen=True, kw_only=True):
    """One capacitor bank of the device map: its bus, size [kvar] and CapControl (None: none)."""

    id: str
    capacitor: str
    bus: str
    kvar: float
    capcontrol: str | None


class FeederInfo(msgspec.Struct, frozen=True, kw_only=True):
    """What ``cvvc feeder info`` reports, measured on the compiled OpenDSS model.

    ``nodes`` counts OpenDSS ``bus.phase`` nodes; ``loads`` and ``peak_load_kw`` (the sum of the loads' nominal
    ``kW=`` [kW]) are the feeder zone's: the loads downstream of the head meter. ``outside_loads`` /
    ``outside_load_kw`` are the rest (other feeders on the substation bus, loads beside the meter) [kW];
    ``zone_nodes`` the nodes of the zone; ``pv_share_of_peak`` is of the zone's peak.
    """

    name: str
    master: str
    device_map: str
    buses: int
    nodes: int
    loads: int
    peak_load_kw: float
    regulators: list[RegulatorInfo]
    pv: list[PvPlantInfo]
    pv_pmpp_kw: float
    pv_share_of_peak: float
    zone_nodes: int = 0
    outside_loads: int = 0
    outside_load_kw: float = 0.0
    capacitors: list[CapacitorInfo] = []


def check_feeder(device_map_path: str | Path) -> list[str]:
    """The problems of a device map against its circuit, one line each (empty: none); see ``mapcheck``."""
    from schemas.devicemap import load_device_map
    from simulator_bridge.survey.circuit_survey import survey_circuit
    from simulator_bridge.survey.mapcheck import check_device_map

    dm = load_device_map(device_map_path)
    return check_device_map(dm, survey_circuit(dm.master_path, extra_commands=dm.feeder.extra_commands))


def feeder_info(device_map_path: str | Path) -> FeederInfo:
    """Compile the feeder of a device map with OpenDSS and describe it (the zone's loads and peak)."""
    from schemas.devicemap import load_device_map
    from simulator_bridge.opendss.engine import FeederEngine
    from simulator_bridge.survey.circuit_survey import survey_circuit

    dm = load_device_map(device_map_path)
    survey = survey_circuit(dm.master_path, extra_commands=dm.feeder.extra_commands)
    caps = {c.name: c for c in survey.capacitors}
    engine = FeederEngine(dm)
    try:
        nodes = engine.node_names
        regs = [
            RegulatorInfo(
                id=spec.id,
                regcontrol=spec.regcontrol,
                phase=int(nodes[engine.reg_secondary_node[r]].split(".")[1]),
                primary_bus=nodes[engine.reg_primary_node[r]].split(".")[0],
                secondary_bus=nodes[engine.reg_secondary_node[r]].split(".")[0],
                setpoint_v120=float(engine.reg_default_setpoint_v120[r]),
                band_v120=float(engine.reg_default_band_v120[r]),
            )
            for r, spec in enumerate(dm.regulator)
        ]
        inside = engine.load_in_feeder
        peak_kw = engine.zone_peak_load_kw
        outside_kw = float(engine.load_kw_nominal[~inside].sum())
        n_loads, n_outside = int(inside.sum()), int((~inside).sum())
        zone_nodes = int(engine.node_in_feeder.sum())
    finally:
        engine.close()
    pv = [PvPlantInfo(id=p.id, bus=p.bus, phases=p.phases, kva=p.kva, pmpp_kw=p.pmpp_kw) for p in dm.pv]
    pv_kw = float(sum(p.pmpp_kw for p in dm.pv))
    capacitors = [CapacitorInfo(id=c.id, capacitor=c.capacitor, bus=caps[c.capacitor.lower()].bus,
                                kvar=caps[c.capacitor.lower()].kvar, capcontrol=c.capcontrol) for c in dm.capacitor]
    return FeederInfo(
        name=dm.feeder.name,
        master=str(dm.master_path),
        device_map=str(Path(device_map_path).resolve()),
        buses=len({n.split(".")[0] for n in nodes}),
        nodes=len(nodes),
        loads=n_loads,
        peak_load_kw=round(peak_kw, 3),
        regulators=regs,
        pv=pv,
        pv_pmpp_kw=pv_kw,
        pv_share_of_peak=round(pv_kw / peak_kw, 4) if peak_kw > 0 else 0.0,
        zone_nodes=zone_nodes,
        outside_loads=n_outside,
        outside_load_kw=round(outside_kw, 3),
        capacitors=capacitors,
    )


def _format_info(info: FeederInfo) -> str:
    out = [
        f"feeder {info.name}: {info.master}",
        f"  buses {info.buses}, single-phase nodes {info.nodes} ({info.zone_nodes} in the feeder zone)",
        f"  feeder zone (downstream of the head meter): {info.loads} loads, peak load {info.peak_load_kw:.1f} kW; "
        f"outside it {info.outside_loads} loads, {info.outside_load_kw:.1f} kW (not this feeder's)",
        f"  regulators ({len(info.regulators)}):",
    ]
    out += [
        f"    {r.id:<10} phase {r.phase}  {r.primary_bus} -> {r.secondary_bus}  "
        f"(RegControl {r.regcontrol}, {r.setpoint_v120:.1f} V +/- {r.band_v120 / 2:.1f} V)"
        for r in info.regulators
    ]
    out.append(
        f"  PV plants ({len(info.pv)}): {info.pv_pmpp_kw:.1f} kW "
        f"= {100 * info.pv_share_of_peak:.1f} % of peak load"
    )
    out += [
        f"    {p.id:<10} bus {p.bus}  {p.phases} ph  {p.kva:.1f} kVA  {p.pmpp_kw:.1f} kW" for p in info.pv
    ]
    out.append(f"  capacitors ({len(info.capacitors)}):")
    out += [f"    {c.id:<10} bus {c.bus}  {c.kvar:.0f} kvar  "
            f"{'CapControl ' + c.capcontrol if c.capcontrol else 'no CapControl'}" for c in info.capacitors]
    return "\n".join(out)


def _generate(args: argparse.Namespace) -> int:
    from simulator_bridge.rural.generator import generate_rural_feeder

    print(generate_rural_feeder(args.seed, Path(args.out)))
    return 0


def _info(args: argparse.Namespace) -> int:
    import sys

    from schemas.errors import CvvcError

    try:
        path = (ensure_default_feeder(cache_root(args.cache)) if args.feeder is None
                else resolve_device_map_path(args.feeder))
        problems = check_feeder(path)
        if problems:
            for line in problems:
                print(f"cvvc feeder info: error: {path}: {line}", file=sys.stderr)
            return 2
        info = feeder_info(path)
    except CvvcError as e:
        print(f"cvvc feeder info: error: {e}", file=sys.stderr)
        return 2
    if args.json:
        print(msgspec.json.format(msgspec.json.encode(info), indent=2).decode())
    else:
        print(_format_info(info))
    return 0


def _scaffold(args: argparse.Namespace) -> int:
    import sys

    from schemas.errors import CvvcError
    from simulator_bridge.survey.scaffold import scaffold_device_map

    out = Path(args.out)
    if out.exists() and not args.force:
        print(f"cvvc feeder scaffold: error: {out} exists; pass --force to overwrite it", file=sys.stderr)
        return 2
    try:
        r = scaffold_device_map(args.master, out, name=args.name)
    except CvvcError as e:
        print(f"cvvc feeder scaffold: error: {e}", file=sys.stderr)
        return 2
    sites = ", ".join(f"{s.bus} ({s.pmpp_kw:.0f} kW)" for s in r.pv_sites)
    print(f"{out}: feeder {r.name}, head {r.head_element}, zone peak {r.zone.peak_load_kw:.1f} kW "
          f"({r.zone.outside_load_kw:.1f} kW of other loads outside it); PV sites {sites}; review it, then "
          f"`cvvc feeder info {out}`")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``feeder`` verb and its sub-verbs to the ``cvvc`` command."""
    feeder = subparsers.add_parser("feeder", help="generate the rural feeder; draft, check and describe device maps")
    verbs = feeder.add_subparsers(dest="feeder_verb", metavar="SUBVERB", required=True)

    gen = verbs.add_parser("generate", help="write the synthetic rural feeder (OpenDSS + devicemap.toml)")
    gen.add_argument("--seed", type=int, default=1, help="random seed (same seed, same bytes; default 1)")
    gen.add_argument("--out", required=True, help="output folder (created if absent)")
    gen.set_defaults(func=_generate)

    info = verbs.add_parser(
        "info", help="buses, nodes, loads, regulators, PV plants and peak load of a feeder"
    )
    info.add_argument(
        "feeder",
        nargs="?",
        default=None,
        help="device map TOML, or a folder with devicemap.toml (default: the embedded rural feeder, seed 1)",
    )
    info.add_argument("--json", action="store_true", help="print JSON instead of text")
    info.add_argument("--cache", default=None, help=CACHE_HELP)
    info.set_defaults(func=_info)

    scaffold = verbs.add_parser("scaffold", help="draft a device map of an OpenDSS feeder, commented for review")
    scaffold.add_argument("master", help="the feeder's OpenDSS master file")
    scaffold.add_argument("--out", required=True, help="device map TOML to write (paths in it are relative to it)")
    scaffold.add_argument("--name", default=None, help="feeder name (default: the master's folder name)")
    scaffold.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    scaffold.set_defaults(func=_scaffold)

    from simulator_bridge.bus.bridge_cli import register_bridge  # the `bridge` verb

    register_bridge(subparsers)
