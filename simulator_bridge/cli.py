"""``cvvc feeder``: generate the embedded rural feeder and describe any feeder.

Verbs::

    cvvc feeder generate --seed N --out DIR     # writes the rural feeder, prints its device map path
    cvvc feeder info [FEEDER] [--json]          # FEEDER: a device map TOML or a folder with devicemap.toml;
                                                # default: the embedded rural feeder (generated if absent)

Also the default-feeder cache that ``cvvc run`` uses: ``default_feeder_dir`` and ``ensure_default_feeder``.
Nothing heavy is imported at module level (OpenDSS only inside ``feeder_info``).
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
from pathlib import Path

import msgspec

__all__ = [
    "DEFAULT_CACHE_ROOT",
    "FeederInfo",
    "PvPlantInfo",
    "RegulatorInfo",
    "default_feeder_dir",
    "ensure_default_feeder",
    "feeder_info",
    "register",
    "resolve_device_map_path",
]

#: Cache of generated feeders, relative to the current directory.
DEFAULT_CACHE_ROOT = Path(".cvvc-cache")

# Bump when generator.py changes its output, so cached default feeders are regenerated.
_GENERATOR_VERSION = 1


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


class FeederInfo(msgspec.Struct, frozen=True, kw_only=True):
    """What ``cvvc feeder info`` reports, measured on the compiled OpenDSS model.

    ``nodes`` counts single-phase nodes (OpenDSS ``bus.phase`` nodes, neutrals excluded);
    ``peak_load_kw`` is the sum of the loads' nominal ``kW=`` [kW].
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


def default_feeder_dir(cache_root: Path, seed: int = 1) -> Path:
    """Folder of the embedded rural feeder for ``seed`` inside ``cache_root``."""
    return Path(cache_root) / "feeders" / f"rural-v{_GENERATOR_VERSION}-s{seed}"


def ensure_default_feeder(cache_root: Path, seed: int = 1) -> Path:
    """Return the device map path of the embedded rural feeder, generating it first if absent.

    The feeder is written into a temporary sibling folder and renamed into place, so two processes
    starting together never see a half-written feeder.
    """
    from simulator_bridge.generator import DEVICE_MAP_FILE, GeneratorError, generate_rural_feeder

    folder = default_feeder_dir(cache_root, seed)
    path = folder / DEVICE_MAP_FILE
    if path.is_file():
        return path
    try:
        folder.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}-", dir=folder.parent))
    except OSError as e:
        raise GeneratorError(f"cannot create the feeder cache under {cache_root}: {e}") from e
    try:
        generate_rural_feeder(seed, tmp)
        try:
            os.rename(tmp, folder)
        except OSError:
            if not path.is_file():  # not a concurrent writer that got there first
                raise
    except OSError as e:
        raise GeneratorError(f"cannot store the generated feeder in {folder}: {e}") from e
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return path


def resolve_device_map_path(feeder: str | Path) -> Path:
    """Turn a FEEDER argument (device map TOML, or a folder holding ``devicemap.toml``) into the TOML path."""
    from schemas.devicemap import DeviceMapError

    p = Path(feeder)
    if p.is_dir():
        p = p / "devicemap.toml"
    if not p.is_file():
        raise DeviceMapError(
            f"{feeder}: no device map there; pass a device map TOML or a folder with "
            "devicemap.toml (cvvc feeder generate writes one)"
        )
    return p


def feeder_info(device_map_path: str | Path) -> FeederInfo:
    """Compile the feeder of a device map with OpenDSS and describe it."""
    from schemas.devicemap import load_device_map
    from simulator_bridge.engine import FeederEngine

    dm = load_device_map(device_map_path)
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
        peak_kw = float(engine.load_kw_nominal.sum())
        n_loads = len(engine.load_names)
    finally:
        engine.close()
    pv = [PvPlantInfo(id=p.id, bus=p.bus, phases=p.phases, kva=p.kva, pmpp_kw=p.pmpp_kw) for p in dm.pv]
    pv_kw = float(sum(p.pmpp_kw for p in dm.pv))
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
    )


def _format_info(info: FeederInfo) -> str:
    out = [
        f"feeder {info.name}: {info.master}",
        f"  buses {info.buses}, single-phase nodes {info.nodes}, loads {info.loads}, "
        f"peak load {info.peak_load_kw:.1f} kW",
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
    return "\n".join(out)


def _generate(args: argparse.Namespace) -> int:
    from simulator_bridge.generator import generate_rural_feeder

    print(generate_rural_feeder(args.seed, Path(args.out)))
    return 0


def _info(args: argparse.Namespace) -> int:
    path = (
        ensure_default_feeder(DEFAULT_CACHE_ROOT)
        if args.feeder is None
        else resolve_device_map_path(args.feeder)
    )
    info = feeder_info(path)
    if args.json:
        print(msgspec.json.format(msgspec.json.encode(info), indent=2).decode())
    else:
        print(_format_info(info))
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``feeder`` verb and its sub-verbs to the ``cvvc`` command."""
    feeder = subparsers.add_parser("feeder", help="generate the embedded rural feeder; describe any feeder")
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
    info.set_defaults(func=_info)

    from simulator_bridge.bridge_cli import register_bridge  # the `bridge` verb (issue 4)

    register_bridge(subparsers)
