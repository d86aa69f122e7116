"""``cvvc run --field-protocol``: how the regulators and capacitor banks reach the bus, ``bus`` (the bridge's own
frames) or ``dnp3``.

With ``dnp3`` every regulator and capacitor bank of the device map is behind a simulated DNP3 outstation that the
bridge serves on a free ``127.0.0.1`` port (``simulator_bridge.bus.dnp3_fleet``), and one
``cvvc adapter dnp3 --clock head`` per device polls it, publishes the device's frames and acks, and operates the
agent's commands on it (docs/dnp3.md). This module only checks the option, describes the devices for their adapters
and builds the adapters' and the bridge's flags; ``cvvc.launch`` starts them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from cvvc.errors import CommandError
from schemas.devicemap import DeviceMap
from schemas.settings import Case, FieldProtocol

__all__ = ["Dnp3Device", "FieldProtocol", "adapter_args", "bridge_args", "check_field_protocol", "dnp3_devices",
           "dnp3_endpoints"]

_TAP_CASES = ("A", "B")  # the cases whose agent commands taps (paper Table I)


@dataclass(frozen=True)
class Dnp3Device:
    """One regulator or bank behind DNP3, as its adapter's frames describe it.

    ``kind``: ``vr`` or ``cap``; ``phase``: a regulator's phase; ``kvar_rated`` [kvar] and ``control_type``: a bank's
    rating and local control (the simulated feeder's, so the frames are the bridge's own).
    """

    device_id: str
    kind: Literal["vr", "cap"]
    phase: str = "a"
    kvar_rated: float = 0.0
    control_type: str = "none"


def check_field_protocol(protocol: str, *, case: Case, noise_scada_pct: float, drop_prob: float,
                         meas_delay_s: float, clock_skew_s: float) -> None:
    """Raise ``CommandError`` for an unknown protocol, or ``dnp3`` with a case or options it does not take.

    Cases A and B command taps, for which the DNP3 map has no point (docs/dnp3.md); the realism options act on the
    bridge's own frames, and the adapters publish these devices' frames.
    """
    if protocol not in ("bus", "dnp3"):
        raise CommandError(f"--field-protocol {protocol!r}: choose bus or dnp3")
    if protocol != "dnp3":
        return
    if case in _TAP_CASES:
        raise CommandError(f"--field-protocol dnp3 does not take case {case}: its agent commands taps, and the DNP3 "
                           "regulator control takes a voltage set point and band only (docs/dnp3.md); run case C "
                           "or D, or with --field-protocol bus")
    if noise_scada_pct or drop_prob or meas_delay_s or clock_skew_s:
        raise CommandError("--field-protocol dnp3 takes no --noise-scada-pct, --drop-prob, --meas-delay-s or "
                           "--clock-skew-s yet (the adapters publish the regulators' and banks' frames, the bridge "
                           "applies those); run without them, or with --field-protocol bus")


def dnp3_devices(dm_path: Path) -> tuple[Dnp3Device, ...]:
    """Every regulator and bank of the feeder at ``dm_path`` (compiled once, to read their phases, ratings and
    controls as the bridge will); ``CommandError`` for a bank of several steps (the DNP3 map serves one).
    """
    from schemas.devicemap import load_device_map
    from simulator_bridge.bus.dnp3_fleet import regulator_phases
    from simulator_bridge.opendss.engine import FeederEngine

    engine = FeederEngine(load_device_map(dm_path))
    try:
        several = [c for k, c in enumerate(engine.capacitor_ids) if int(engine.cap_steps[k]) != 1]
        if several:
            raise CommandError(f"--field-protocol dnp3: banks {several} have several steps; the DNP3 bank map serves "
                               "banks of one step (docs/dnp3.md); run with --field-protocol bus")
        shared = sorted(set(engine.regulator_ids) & set(engine.capacitor_ids))
        if shared:
            raise CommandError(f"--field-protocol dnp3: {shared} name both a regulator and a bank; each DNP3 adapter "
                               "is named by its device's id: rename one in the device map")
        regs = [Dnp3Device(rid, "vr", phase=phase)
                for rid, phase in zip(engine.regulator_ids, regulator_phases(engine), strict=True)]
        caps = [Dnp3Device(cid, "cap", kvar_rated=float(engine.cap_kvar[k]),
                           control_type=str(engine.cap_control_type[k]))
                for k, cid in enumerate(engine.capacitor_ids)]
    finally:
        engine.close()
    return (*regs, *caps)


def dnp3_endpoints(devices: tuple[Dnp3Device, ...], free_port: object) -> dict[str, str]:
    """Device id -> ``tcp/127.0.0.1:PORT``, a free port each (``free_port()`` gives one)."""
    return {d.device_id: f"tcp/127.0.0.1:{free_port()}" for d in devices}  # type: ignore[operator]


def adapter_args(dm: DeviceMap, feeder_id: str, device: Dnp3Device, endpoint: str, *, connect: list[str],
                 summary_out: str | None = None) -> list[str]:
    """The ``cvvc adapter dnp3`` flags of one device: reads at each head frame (the simulation's clock);
    ``summary_out``: where it writes its last ``LinkStatus`` at exit.
    """
    described = (["--phase", device.phase] if device.kind == "vr"
                 else ["--kvar-rated", repr(device.kvar_rated), "--control-type", device.control_type])
    return ["adapter", "dnp3", "--feeder-id", feeder_id, "--device", device.device_id, "--kind", device.kind,
            "--dnp3", endpoint, "--clock", "head", "--scan-period-s", str(dm.feeder.step_s),
            "--control-period-s", str(dm.feeder.control_period_s), *described,
            *(["--summary-out", summary_out] if summary_out else []), *connect]


def bridge_args(endpoints: dict[str, str]) -> list[str]:
    """The bridge's ``--field-dnp3`` flags."""
    return [arg for did, ep in endpoints.items() for arg in ("--field-dnp3", f"{did}={ep}")]
