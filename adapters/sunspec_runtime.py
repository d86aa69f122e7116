"""``cvvc adapter sunspec``'s process: one PV inverter behind SunSpec Modbus TCP as a device of the cvvc bus.

The inverter and its plant, run by the adapters' loop (``adapters.runtime``: one thread does everything that
touches the inverter, as pysunspec2's client is not thread safe; it scans on the scan period and handles commands
between scans, in their order of arrival).

On the bus, for feeder ``F`` and device ``D`` (as the simulated plants, so the agent cannot tell the difference):

* ``cvvc/F/meas/pv/D`` ``PvFrame`` at every scan that read valid values, stamped with the scan's time: a multiple
  of the scan period on the adapter's clock (UTC), so frames of devices scanned on the same period align; or, with
  the head clock, at each newer feeder-head frame, stamped with its ``t_ns``;
* ``cvvc/F/cmd/pv/D`` ``PvCommand`` in, ``cvvc/F/ack/pv/D`` ``Ack`` out (``adapters.sunspec_plant``);
* ``cvvc/F/link/pv/D`` ``LinkStatus`` when the link's state changes and on the status period;
* the liveliness token ``cvvc/F/alive/pv/D`` while the adapter runs; an agent's token withdrawn
  (``cvvc/F/alive/agent/A``) makes the plant forget that sender's command sequence, as the bridge's devices do
  (a restarted agent counts from 1 again).

Loss of the Modbus link: no frames (the state is ``down`` with the reason), commands are acknowledged
``rejected`` (``link_down``), and every scan tries to connect again. Nothing raises out of the loop but a bus
that cannot be opened.
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Callable
from typing import Annotated, Literal

from msgspec import Meta

from adapters.errors import AdapterError
from adapters.runtime import LoopConfig, run_device
from adapters.sunspec import SunSpecLink
from adapters.sunspec_plant import PlantSettings, SunSpecPlant
from schemas import keys
from schemas import messages as m
from schemas.bus import BusConfig

__all__ = ["AdapterConfig", "parse_modbus_endpoint", "run_adapter"]

_ENDPOINT = re.compile(r"^tcp/(?P<host>[A-Za-z0-9_.\-]+|\[[0-9A-Fa-f:.]+\]):(?P<port>[0-9]{1,5})$")


class AdapterConfig(LoopConfig, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """What ``cvvc adapter sunspec`` runs: the loop's settings (``LoopConfig``), which inverter and as which device.

    ``modbus`` is ``tcp/HOST:PORT``; ``unit`` the Modbus unit id; ``timeout_s`` [s]: one Modbus request.
    ``set_local_mode``: write ``local_mode`` into the inverter's model 705 (volt-var enabled or not) when it differs.
    """

    modbus: str
    unit: Annotated[int, Meta(ge=0, le=255)] = 1
    timeout_s: Annotated[float, Meta(gt=0.0, le=60.0)] = 1.0
    local_mode: Literal["unity_pf", "volt_var"] = "unity_pf"
    q_at_night: bool = False
    set_local_mode: bool = False


def parse_modbus_endpoint(text: str) -> tuple[str, int]:
    """``tcp/HOST:PORT`` -> (host, port); AdapterError for anything else."""
    match = _ENDPOINT.match(text)
    port = int(match.group("port")) if match else 0
    if match is None or not 0 < port < 65536:
        raise AdapterError(f"{text!r} is not a Modbus TCP endpoint: write tcp/HOST:PORT, e.g. tcp/127.0.0.1:502")
    return match.group("host").strip("[]"), port


def run_adapter(config: AdapterConfig, bus: BusConfig, *, stop: threading.Event,
                clock_ns: Callable[[], int] = time.time_ns,
                ready: threading.Event | None = None) -> m.LinkStatus:
    """Run the inverter as ``config`` says until ``stop`` is set; returns the last ``LinkStatus``.

    ``bus``, ``stop``, ``clock_ns`` (frame times, command windows, revert timers) and ``ready`` are
    :func:`adapters.runtime.run_device`'s.
    """
    host, port = parse_modbus_endpoint(config.modbus)
    link = SunSpecLink(host, port, unit=config.unit, timeout_s=config.timeout_s)
    plant = SunSpecPlant(PlantSettings(feeder_id=config.feeder_id, device_id=config.device_id,
                                       control_period_ns=int(config.control_period_s * 1e9),
                                       local_mode=config.local_mode, q_at_night=config.q_at_night,
                                       set_local_mode=config.set_local_mode), link)
    f, d = config.feeder_id, config.device_id
    return run_device(plant, bus, feeder_id=f, device_id=d, kind="pv", frame_key=keys.meas_pv(f, d),
                      frame_type=m.PvFrame, cmd_type=m.PvCommand, scan_period_s=config.scan_period_s,
                      status_period_s=config.status_period_s, stop=stop, clock_ns=clock_ns, ready=ready,
                      close_link=link.close, head_clock=config.clock == "head")
