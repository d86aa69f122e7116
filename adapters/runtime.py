"""The loop every field-protocol adapter runs on the bus: one device, its frames, commands, acks and link status.

The only module of the adapters that knows Zenoh and clocks; ``adapters.sunspec_runtime`` and
``adapters.dnp3_runtime`` build the device (an ``adapters.device.LinkedDevice``) and its link and call
:func:`run_device`. One thread does everything that touches the device (the protocol clients are not thread safe):
it scans on the scan period and handles commands between scans, in their order of arrival (Zenoh's callbacks only
decode them into a bounded :class:`~schemas.bus.Inbox`). On the bus, for feeder ``F``, kind ``K`` (``pv``, ``vr``,
``cap``) and device ``D``:

* the frame key (``cvvc/F/meas/K/D``) at every scan that read valid values, stamped with the scan's time (a
  multiple of the scan period on the adapter's clock, UTC); or, with the head clock, at each newer feeder-head
  frame, stamped with its ``t_ns``;
* ``cvvc/F/cmd/K/D`` commands in, ``cvvc/F/ack/K/D`` ``Ack`` out;
* ``cvvc/F/link/K/D`` ``LinkStatus`` when the link's state changes and on the status period;
* the liveliness token ``cvvc/F/alive/K/D`` while the adapter runs; an agent's token withdrawn
  (``cvvc/F/alive/agent/A``) makes the device forget that sender's command sequence, as the bridge's devices do.

Nothing raises out of the loop but a bus that cannot be opened.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Annotated, Any, Literal

import msgspec
from msgspec import Meta

from adapters.device import LinkedDevice
from schemas import keys
from schemas import messages as m
from schemas.bus import BusConfig, Inbox, LivelinessWatcher, Received, TypedPublisher, open_session

__all__ = ["LoopConfig", "run_device"]


class LoopConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """What every adapter's bus loop takes (each protocol's config adds its device and link): the feeder and the
    device it stands for; ``scan_period_s`` [s]: frames at its multiples; ``control_period_s`` [s]: the feeder's
    control period, the unit of the command windows (as the bridge's); ``status_period_s`` [s]: ``LinkStatus`` at
    least this often; ``clock``: ``wall`` scans on the scan period of ``clock_ns``; ``head`` scans when a newer
    feeder-head frame arrives (``cvvc/F/meas/head``) and takes its ``t_ns`` as the adapter's time: frames, command
    windows and hold or revert timers then follow the feeder's scan (a simulation in lockstep, or a SCADA poll cycle).
    """

    feeder_id: Annotated[str, Meta(pattern=r"^[A-Za-z0-9_.\-]{1,64}$")]
    device_id: Annotated[str, Meta(pattern=r"^[A-Za-z0-9_.\-]{1,64}$")]
    scan_period_s: Annotated[float, Meta(gt=0.0, le=3600.0)] = 60.0
    control_period_s: Annotated[float, Meta(gt=0.0, le=86400.0)] = 300.0
    status_period_s: Annotated[float, Meta(gt=0.0, le=3600.0)] = 10.0
    clock: Literal["wall", "head"] = "wall"

_MAX_WAIT_S = 0.2  # the loop looks at its clock at least this often [s]


class _SenderGone(msgspec.Struct, frozen=True):
    """An agent's liveliness token was withdrawn: its command sequence ends."""

    source: str


def run_device(device: LinkedDevice, bus: BusConfig, *, feeder_id: str, device_id: str,
               kind: Literal["pv", "vr", "cap"], frame_key: str, frame_type: type, cmd_type: type,
               scan_period_s: float, status_period_s: float, stop: threading.Event,
               clock_ns: Callable[[], int] = time.time_ns, ready: threading.Event | None = None,
               open_link: Callable[[], object] | None = None, close_link: Callable[[], object],
               head_clock: bool = False) -> m.LinkStatus:
    """Run ``device`` on the bus until ``stop`` is set; returns the last ``LinkStatus``.

    Parameters
    ----------
    device : the device, without the bus. bus : how to join the bus.
    feeder_id, device_id, kind : the device's keys. frame_key, frame_type : where its frames go, and their type.
    cmd_type : the type of its commands. scan_period_s [s]: frames at its multiples (wall clock).
    status_period_s [s]: ``LinkStatus`` at least this often.
    stop : set it to end the run (the token is withdrawn, a last status is published, the link closed).
    clock_ns : the adapter's clock [ns since the epoch]: frame times, command windows, hold and revert times.
    ready : set once the adapter is on the bus (tests wait for it).
    open_link, close_link : called once on the bus (before the first status), and at the end.
    head_clock : scan at each newer feeder-head frame and take its ``t_ns`` as the device's time.
    """
    f, d, k = feeder_id, device_id, kind
    period_ns = int(scan_period_s * 1e9)
    with open_session(bus) as session:
        pub_frame: TypedPublisher[Any] = TypedPublisher(session, frame_key, frame_type)
        pub_ack = TypedPublisher(session, keys.ack(f, k, d), m.Ack, reliable=True)
        pub_status = TypedPublisher(session, keys.link(f, k, d), m.LinkStatus, reliable=True)
        inbox = Inbox(maxsize=256)
        inbox.subscribe(session, keys.cmd(f, k, d), cmd_type)
        token = session.liveliness().declare_token(keys.alive(f, k, d))

        def on_agent(key: str, up: bool) -> None:  # a Zenoh thread: only enqueue, in order with the commands
            if not up:
                inbox.put(Received(key, _SenderGone(key.rsplit("/", 1)[-1]), time.time_ns(), b""))

        agents = LivelinessWatcher(session, f"{keys.ROOT}/{f}/alive/agent/*", on_agent)
        head_t = [0]  # the newest feeder-head frame's time [ns] (head clock)
        if head_clock:
            inbox.subscribe(session, keys.meas_head(f), m.HeadFrame)
        if open_link is not None:
            open_link()

        def device_now() -> int:
            return head_t[0] if head_clock else clock_ns()

        def scan(t: int) -> None:
            expired = device.expired(t)
            if expired is not None:
                pub_ack.put(expired)
            frame = device.scan(t)
            if frame is not None:
                pub_frame.put(frame)

        status = device.status(device_now())
        pub_status.put(status)
        if ready is not None:
            ready.set()
        next_scan = clock_ns() // period_ns * period_ns
        last_state, status_due = device.state, time.monotonic() + status_period_s
        try:
            while not stop.is_set():
                now = clock_ns()
                if not head_clock and now >= next_scan:
                    t = max(next_scan, now // period_ns * period_ns)  # a late loop skips to the present scan
                    scan(t)
                    next_scan = t + period_ns
                if device.state != last_state or time.monotonic() >= status_due:
                    status = device.status(device_now())
                    pub_status.put(status)
                    last_state, status_due = device.state, time.monotonic() + status_period_s
                wait_s = _MAX_WAIT_S if head_clock else min(max((next_scan - clock_ns()) / 1e9, 0.0), _MAX_WAIT_S)
                item = inbox.get(timeout_s=wait_s)
                if item is None:
                    continue
                msg = item.msg
                if isinstance(msg, _SenderGone):
                    device.guard.forget_source(msg.source)
                elif isinstance(msg, m.HeadFrame):
                    if msg.t_ns > head_t[0]:  # a repeated or older head frame moves nothing
                        head_t[0] = msg.t_ns
                        scan(msg.t_ns)
                else:
                    pub_ack.put(device.command(msg, device_now()))
        finally:
            agents.undeclare()
            token.undeclare()
            inbox.undeclare()
            close_link()
            status = device.status(device_now())
            pub_status.put(status)
    return status
