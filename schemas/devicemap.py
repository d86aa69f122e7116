"""Device map: which OpenDSS feeder, which field devices the agent controls, their limits and costs.

A device map is a TOML file beside (or pointing at) an OpenDSS master file. It is the only
configuration that makes an arbitrary OpenDSS feeder usable by the simulator, the trainer and the agent.
Paths inside it are relative to the TOML file itself. Example (IEEE 123)::

    [feeder]
    name = "ieee123"
    master = "../../shared/feeders/ieee123/IEEE123Master.dss"
    head_element = "Line.sw1"
    source_bus = "150"

    [[regulator]]
    id = "creg2a"
    regcontrol = "creg2a"

    [[pv]]
    id = "pv1"
    bus = "66"
    phases = 3
    kv_ll = 4.16
    kva = 1200.0
    pmpp_kw = 1080.0
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Annotated, Literal

import msgspec
from msgspec import Meta

from schemas.errors import CvvcError

__all__ = [
    "DeviceMap",
    "DeviceMapError",
    "FeederSection",
    "CapacitorSpec",
    "MeterSpec",
    "PvPlantSpec",
    "RegulatorSpec",
    "load_device_map",
    "resolve_device_map_path",
]

Name = Annotated[str, Meta(pattern=r"^[A-Za-z0-9_.\-]{1,64}$")]
PositiveFloat = Annotated[float, Meta(gt=0.0, le=1e7)]
Cost = Annotated[float, Meta(ge=0.0, le=1e6)]
Pu = Annotated[float, Meta(ge=0.5, le=1.5)]
V120 = Annotated[float, Meta(ge=90.0, le=150.0)]


class DeviceMapError(CvvcError):
    """A device map that cannot be read or names something that does not exist."""


class FeederSection(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The OpenDSS model and the study limits.

    ``head_element`` is the OpenDSS element (``Class.name``) whose terminal 1 the feeder-head meter
    measures; ``source_bus`` is where electrical distance is measured from.
    """

    name: Name
    master: str
    head_element: str
    source_bus: str
    extra_commands: list[str] = []
    judged_limits_pu: tuple[Pu, Pu] = (0.965, 1.05)
    optimization_limits_pu: tuple[Pu, Pu] = (0.975, 1.04)
    control_period_s: Annotated[int, Meta(ge=60, le=3600)] = 300
    step_s: Annotated[int, Meta(ge=1, le=3600)] = 60
    load_pf: Annotated[float, Meta(gt=0.5, le=1.0)] = 0.95


class RegulatorSpec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One controllable regulator controller (an OpenDSS RegControl; one tap changer).

    ``setpoint_v120`` / ``band_v120`` are its local default (on the 120 V base); when omitted, the
    values in the OpenDSS model are used.
    """

    id: Name
    regcontrol: str
    cost_per_tap: Cost = 0.14
    max_taps_per_interval: Annotated[int, Meta(ge=0, le=32)] = 4
    setpoint_v120: V120 | None = None
    band_v120: Annotated[float, Meta(gt=0.0, le=12.0)] | None = None


class CapacitorSpec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One switched capacitor bank as a field device (an OpenDSS ``Capacitor``, with its ``CapControl`` if any).

    Without a command the bank follows its local control as the model states it (its ``CapControl``; a bank
    with none stays where it is). ``capcontrol`` names that control when the model has one for the bank.
    ``cost_per_switch`` is per switching operation (one step of the bank opened or closed), on the same
    scale as ``RegulatorSpec.cost_per_tap``: a study choice, about seven tap changes, because a capacitor
    switch's contacts and the transient wear the bank more than one tap step wears a regulator.
    """

    id: Name
    capacitor: str
    capcontrol: str | None = None
    cost_per_switch: Cost = 1.0


class PvPlantSpec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One PV plant. ``create`` adds it to the model at ``bus``; otherwise ``pvsystem`` names an existing one.

    ``cost_per_kvar`` is per kvar of set point per control interval. ``q_at_night``: the inverter gives reactive
    power at zero active power (a "Q at night" or STATCOM mode, an option of many utility-scale inverters), up to
    its rating; without it, a plant gives no reactive power while it has no active power. Its frames report that
    headroom (``q_available_kvar``), and the agent takes its limits from them. Training already sweeps each plant's Q
    up to ``sqrt(kva² - P²)`` at every P, night included: the option leaves the model and the fingerprint as they
    are.
    """

    id: Name
    bus: str
    phases: Literal[1, 3] = 3
    kv_ll: PositiveFloat
    kva: PositiveFloat
    pmpp_kw: PositiveFloat
    cost_per_kvar: Cost = 0.001
    create: bool = True
    pvsystem: str | None = None
    profile_lag_min: Annotated[int, Meta(ge=0, le=120)] = 0
    q_at_night: bool = False


class MeterSpec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """An AMI meter at a customer node: beyond the paper's measurements, an explicit option.

    It reads the voltage of OpenDSS node ``node`` (``bus.phase``) every ``interval_s`` seconds of simulated time
    (at multiples of ``interval_s`` since midnight UTC) and its reading reaches the bus as a ``MeterFrame``. The
    agent corrects its estimate of that node by the reading when the node is critical (``agent.ami``).
    """

    id: Name
    node: Annotated[str, Meta(pattern=r"^[A-Za-z0-9_.\-]{1,64}$")]
    interval_s: Annotated[int, Meta(ge=60, le=86_400)] = 900


class DeviceMap(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A whole device map, as decoded from TOML. ``root`` is the folder the TOML file is in.

    ``meter``: AMI meters (explicit option); they leave the fingerprint unchanged (training does not use them).
    """

    feeder: FeederSection
    regulator: list[RegulatorSpec] = []
    capacitor: list[CapacitorSpec] = []
    pv: list[PvPlantSpec] = []
    root: str = "."
    meter: list[MeterSpec] = []

    @property
    def master_path(self) -> Path:
        """The feeder's OpenDSS master file, absolute (``feeder.master`` is relative to the map's folder)."""
        return (Path(self.root) / self.feeder.master).resolve()

    def fingerprint(self) -> str:
        """SHA-256 over the map's own content and every ``.dss`` file of the model folder.

        The agent refuses a model whose fingerprint differs from its feeder's.
        """
        h = hashlib.sha256()
        own = msgspec.to_builtins(msgspec.structs.replace(self, root="."))
        del own["meter"]  # meters do not change what training computes, nor does a plant's Q at night
        for pv in own["pv"]:
            del pv["q_at_night"]
        h.update(msgspec.json.encode(own))
        folder = self.master_path.parent
        for f in sorted(folder.rglob("*")):
            if f.is_file() and f.suffix.lower() in {".dss", ".csv", ".dat", ".txt"}:
                h.update(f.relative_to(folder).as_posix().encode())
                h.update(f.read_bytes())
        return h.hexdigest()[:16]


def load_device_map(path: str | Path) -> DeviceMap:
    """Read and validate a device map TOML file.

    Checks what can be checked without OpenDSS: unique ids, kVA >= Pmpp, the master file exists.
    Bus and RegControl names are checked by the simulator when it compiles the feeder.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise DeviceMapError(f"{path}: cannot read device map: {e}") from e
    try:
        dm = msgspec.toml.decode(raw, type=DeviceMap)
    except msgspec.ValidationError as e:
        raise DeviceMapError(f"{path}: invalid device map: {e}") from e
    except msgspec.DecodeError as e:
        raise DeviceMapError(f"{path}: not valid TOML: {e}") from e
    dm = msgspec.structs.replace(dm, root=str(path.parent.resolve()))
    for kind, ids in (("regulator", [r.id for r in dm.regulator]), ("capacitor", [c.id for c in dm.capacitor]),
                      ("pv", [p.id for p in dm.pv]), ("meter", [x.id for x in dm.meter])):
        dupes = {i for i in ids if ids.count(i) > 1}
        if dupes:
            raise DeviceMapError(f"{path}: duplicate {kind} id(s): {sorted(dupes)}")
    for p in dm.pv:
        if p.kva < p.pmpp_kw:
            raise DeviceMapError(
                f"{path}: PV plant {p.id!r}: kva {p.kva} < pmpp_kw {p.pmpp_kw}; the inverter must be "
                "rated at least at the array's maximum power"
            )
        if not p.create and not p.pvsystem:
            raise DeviceMapError(f"{path}: PV plant {p.id!r}: create = false needs pvsystem = NAME")
    if not dm.master_path.is_file():
        raise DeviceMapError(f"{path}: master file {dm.feeder.master!r} not found at {dm.master_path}")
    return dm


def resolve_device_map_path(feeder: str | Path) -> Path:
    """Turn a FEEDER argument (device map TOML, or a folder holding ``devicemap.toml``) into the TOML path.

    Raises
    ------
    DeviceMapError
        Neither a TOML file nor a folder with ``devicemap.toml``.
    """
    p = Path(feeder)
    if p.is_dir():
        p = p / "devicemap.toml"
    if not p.is_file():
        raise DeviceMapError(
            f"{feeder}: no device map there; pass a device map TOML or a folder with "
            "devicemap.toml (cvvc feeder generate writes one, cvvc feeder scaffold drafts one)"
        )
    return p
