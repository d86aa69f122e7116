"""``cvvc adapter dnp3``'s process: one regulator control or capacitor bank controller behind DNP3 on the bus.

The outstation and its device, run by the adapters' loop (``adapters.runtime``: one thread reads the outstation
on the scan period and handles commands between reads, in their order of arrival). On the bus, for feeder ``F``,
kind ``K`` (``vr`` or ``cap``) and device ``D``, as the simulated devices (so the agent cannot tell the difference):

* ``cvvc/F/meas/K/D`` ``RegFrame`` / ``CapFrame`` at every read with valid values, stamped with the scan's time
  (a multiple of the scan period on the adapter's clock, UTC); or, with the head clock, at each newer feeder-head
  frame, stamped with its ``t_ns``;
* ``cvvc/F/cmd/K/D`` ``RegCommand`` / ``CapCommand`` in, ``cvvc/F/ack/K/D`` ``Ack`` out
  (``adapters.dnp3_device``);
* ``cvvc/F/link/K/D`` ``LinkStatus`` when the link's state changes and on the status period;
* the liveliness token ``cvvc/F/alive/K/D``; an agent's token withdrawn makes the device forget that sender's
  command sequence.

A lost link: no frames (state ``down``), commands ``rejected`` (``link_down``); the DNP3 channel reconnects by
itself. Nothing raises out of the loop but a bus that cannot be opened.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Annotated, Literal

from msgspec import Meta

from adapters.dnp3 import Dnp3Master
from adapters.dnp3_device import Dnp3Device, Dnp3DeviceSettings
from adapters.runtime import LoopConfig, run_device
from schemas import keys
from schemas import messages as m
from schemas.bus import BusConfig

__all__ = ["Dnp3AdapterConfig", "run_dnp3_adapter"]


class Dnp3AdapterConfig(LoopConfig, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """What ``cvvc adapter dnp3`` runs: the loop's settings (``LoopConfig``), which outstation and as which device.

    ``dnp3`` is ``tcp/127.0.0.1:PORT``; ``kind`` ``vr`` (regulator control) or ``cap`` (bank);
    ``outstation_address`` / ``master_address`` the DNP3 link addresses; ``timeout_s`` [s]: one DNP3 request.
    ``phase`` (regulator), ``kvar_rated`` and ``control_type`` (bank): what the frames say of the device beyond its
    points. With ``clock`` ``head`` the outstation is read when a newer feeder-head frame arrives.
    """

    kind: Literal["vr", "cap"]
    dnp3: str
    outstation_address: Annotated[int, Meta(ge=0, le=65519)] = 10
    master_address: Annotated[int, Meta(ge=0, le=65519)] = 1
    timeout_s: Annotated[float, Meta(gt=0.0, le=60.0)] = 2.0
    phase: m.Phase = "a"
    kvar_rated: Annotated[float, Meta(gt=0.0, le=1e6)] = 600.0
    control_type: m.CapControlType = "none"


def run_dnp3_adapter(config: Dnp3AdapterConfig, bus: BusConfig, *, stop: threading.Event,
                     clock_ns: Callable[[], int] = time.time_ns,
                     ready: threading.Event | None = None) -> m.LinkStatus:
    """Run the outstation as ``config`` says until ``stop`` is set; returns the last ``LinkStatus``.

    ``bus``, ``stop``, ``clock_ns`` (frame times, command windows, hold times) and ``ready`` are
    :func:`adapters.runtime.run_device`'s.
    """
    master = Dnp3Master(config.dnp3, address=config.master_address, outstation_address=config.outstation_address,
                        timeout_s=config.timeout_s)
    f, d, k = config.feeder_id, config.device_id, config.kind
    device = Dnp3Device(Dnp3DeviceSettings(feeder_id=f, device_id=d, kind=k,
                                           control_period_ns=int(config.control_period_s * 1e9), phase=config.phase,
                                           kvar_rated=config.kvar_rated, control_type=config.control_type), master)
    return run_device(device, bus, feeder_id=f, device_id=d, kind=k,
                      frame_key=keys.meas_vr(f, d) if k == "vr" else keys.meas_cap(f, d),
                      frame_type=m.RegFrame if k == "vr" else m.CapFrame,
                      cmd_type=m.RegCommand if k == "vr" else m.CapCommand, scan_period_s=config.scan_period_s,
                      status_period_s=config.status_period_s, stop=stop, clock_ns=clock_ns, ready=ready,
                      open_link=master.open, close_link=master.close, head_clock=config.clock == "head")
