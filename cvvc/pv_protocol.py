"""``cvvc run --pv-protocol``: how the PV plants reach the bus, ``bus`` (the bridge's own frames) or ``sunspec``.

With ``sunspec`` every PV plant of the feeder is behind a simulated SunSpec inverter that the bridge serves on a
free ``127.0.0.1`` port (``simulator_bridge.bus.sunspec_fleet``), and one ``cvvc adapter sunspec --clock head`` per
plant reads it over Modbus TCP, publishes the plant's frames and acks, and writes the agent's commands to it
(docs/sunspec.md). This module only builds the adapters' and the bridge's flags; ``cvvc.launch`` starts them.
"""

from __future__ import annotations

from cvvc.errors import CommandError
from schemas.devicemap import DeviceMap
from schemas.settings import PvProtocol

__all__ = ["PvProtocol", "adapter_args", "bridge_args", "check_pv_protocol", "sunspec_endpoints"]


def check_pv_protocol(protocol: str, *, noise_scada_pct: float, drop_prob: float, meas_delay_s: float,
                      clock_skew_s: float, secure: bool = False) -> None:
    """Raise ``CommandError`` for an unknown protocol, or ``sunspec`` with options it does not take yet.

    ``secure`` is accepted whatever the protocol: the access policy lets the ``devices`` role (bridge, adapters)
    read the head frame, the PV frames and acks the head-clocked adapters and the bridge's wait need.
    """
    if protocol not in ("bus", "sunspec"):
        raise CommandError(f"--pv-protocol {protocol!r}: choose bus or sunspec")
    if protocol == "sunspec" and (noise_scada_pct or drop_prob or meas_delay_s or clock_skew_s):
        raise CommandError("--pv-protocol sunspec takes no --noise-scada-pct, --drop-prob, --meas-delay-s or "
                           "--clock-skew-s yet (the adapters publish the PV frames, the bridge applies those); "
                           "run without them, or with --pv-protocol bus")


def sunspec_endpoints(dm: DeviceMap, free_port: object) -> dict[str, str]:
    """Plant id -> ``tcp/127.0.0.1:PORT``, a free port each (``free_port()`` gives one)."""
    return {pv.id: f"tcp/127.0.0.1:{free_port()}" for pv in dm.pv}  # type: ignore[operator]


def adapter_args(dm: DeviceMap, feeder_id: str, plant_id: str, endpoint: str, *, volt_var: bool,
                 connect: list[str], summary_out: str | None = None) -> list[str]:
    """The ``cvvc adapter sunspec`` flags of one plant: scans at each head frame (the simulation's clock) and sets
    the plant's local default (volt-var in the ``local`` case) in the inverter's model 705; ``--q-at-night`` for a
    plant whose map entry says so (``q_at_night``); ``summary_out``: where it writes its last ``LinkStatus`` at exit.
    """
    q_at_night = next(pv.q_at_night for pv in dm.pv if pv.id == plant_id)
    return ["adapter", "sunspec", "--feeder-id", feeder_id, "--device", plant_id, "--modbus", endpoint,
            "--clock", "head", "--scan-period-s", str(dm.feeder.step_s),
            "--control-period-s", str(dm.feeder.control_period_s),
            "--local-mode", "volt_var" if volt_var else "unity_pf", "--set-local-mode",
            *(["--q-at-night"] if q_at_night else []), *(["--summary-out", summary_out] if summary_out else []),
            *connect]


def bridge_args(endpoints: dict[str, str]) -> list[str]:
    """The bridge's ``--pv-sunspec`` flags."""
    return [arg for pid, ep in endpoints.items() for arg in ("--pv-sunspec", f"{pid}={ep}")]
