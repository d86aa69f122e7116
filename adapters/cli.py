"""``cvvc adapter``: field-protocol adapters (``sunspec``, ``dnp3``) and a simulated SunSpec inverter to try them on
(``sim``).

Nothing heavy is imported at module level; each handler parses its flags into a typed config and calls the
runtime. SIGINT / SIGTERM end a run cleanly (token withdrawn, last status published, link closed, exit 0).
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, TypeVar

if TYPE_CHECKING:
    from schemas.messages import LinkStatus

__all__ = ["register"]

T = TypeVar("T")


def _with_stop(fn: Callable[[threading.Event], T]) -> T:
    """Run ``fn(stop)`` with SIGINT and SIGTERM setting ``stop``; the previous handlers come back after."""
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        return fn(stop)
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def _finish(status: LinkStatus, label: str, summary_out: str | None) -> int:
    """Write the last ``LinkStatus`` to ``summary_out`` (if given) and say it on stdout under ``label``; 0."""
    import msgspec

    if summary_out:  # the launcher sums the links' counts from these files, never from the bus
        from pathlib import Path

        Path(summary_out).write_bytes(msgspec.json.encode(status))
    print(f"adapter {label}: {status.state}, {status.scans} scans, {status.frames} frames, {status.commands} "
          f"commands ({status.commands_failed} failed), refused values {dict(status.refused) or 'none'}, "
          f"foreign writes {status.foreign_writes}")
    return 0


def _sunspec(args: argparse.Namespace) -> int:
    import msgspec

    from adapters.sunspec_runtime import AdapterConfig, parse_modbus_endpoint, run_adapter
    from schemas.bus import bus_config_from_args

    try:
        config = msgspec.convert(dict(
            feeder_id=args.feeder_id, device_id=args.device, modbus=args.modbus, unit=args.unit,
            scan_period_s=args.scan_period_s, control_period_s=args.control_period_s,
            status_period_s=args.status_period_s, timeout_s=args.timeout_s, local_mode=args.local_mode,
            q_at_night=args.q_at_night, clock=args.clock, set_local_mode=args.set_local_mode), AdapterConfig)
    except msgspec.ValidationError as e:
        print(f"cvvc adapter sunspec: error: {e}", file=sys.stderr)
        return 2
    parse_modbus_endpoint(config.modbus)  # a bad endpoint is refused before joining the bus
    bus = bus_config_from_args(args, role="devices")
    status = _with_stop(lambda stop: run_adapter(config, bus, stop=stop))
    return _finish(status, f"{config.device_id} ({config.modbus})", args.summary_out)


def _dnp3(args: argparse.Namespace) -> int:
    import msgspec

    from adapters.dnp3_runtime import Dnp3AdapterConfig, run_dnp3_adapter
    from schemas.bus import bus_config_from_args
    from simulator_bridge.field.dnp3_sim import Dnp3SimError, parse_dnp3_endpoint

    try:
        config = msgspec.convert(dict(
            feeder_id=args.feeder_id, device_id=args.device, kind=args.kind, dnp3=args.dnp3,
            outstation_address=args.outstation_address, master_address=args.master_address,
            scan_period_s=args.scan_period_s, control_period_s=args.control_period_s,
            status_period_s=args.status_period_s, timeout_s=args.timeout_s, phase=args.phase,
            kvar_rated=args.kvar_rated, control_type=args.control_type, clock=args.clock), Dnp3AdapterConfig)
        parse_dnp3_endpoint(config.dnp3)  # a bad endpoint is refused before joining the bus
    except (msgspec.ValidationError, Dnp3SimError) as e:
        print(f"cvvc adapter dnp3: error: {e}", file=sys.stderr)
        return 2
    bus = bus_config_from_args(args, role="devices")
    status = _with_stop(lambda stop: run_dnp3_adapter(config, bus, stop=stop))
    return _finish(status, f"{config.device_id} ({config.kind}, {config.dnp3})", args.summary_out)


def _sim(args: argparse.Namespace) -> int:
    from adapters.sunspec_runtime import parse_modbus_endpoint
    from simulator_bridge.field.sunspec_sim import SimulatedSunSpecInverter

    host, port = parse_modbus_endpoint(args.modbus)
    inv = SimulatedSunSpecInverter(plant_id=args.device, s_rated_kva=args.s_rated_kva, v_nominal_v=args.v_nominal_v,
                                   host=host, port=port, unit=args.unit)
    per_phase = args.p_kw / 3.0
    inv.set_measurements(p_kw=[per_phase] * 3, v_v=[args.v_nominal_v] * 3)

    def serve(stop: threading.Event) -> int:
        with inv:
            print(f"simulated SunSpec inverter {args.device} on {args.modbus} unit {args.unit} "
                  f"({args.s_rated_kva} kVA, {args.p_kw} kW); Ctrl-C to stop", flush=True)
            while not stop.wait(1.0):
                inv.set_measurements(p_kw=[per_phase] * 3, v_v=[args.v_nominal_v] * 3)  # Q follows the set point
        return 0

    return int(_with_stop(serve))


def _add_loop_arguments(p: argparse.ArgumentParser, *, device: str, protocol: str, timeout_s: float,
                        device_id: tuple[str, str]) -> None:
    """The flags every adapter takes (``adapters.runtime``): the feeder and device ids, the loop's periods, the
    time-out of one request, the summary file. ``device_id``: the ``--device`` flag's metavar and help.
    """
    p.add_argument("--feeder-id", required=True, help="feeder id of the keys (cvvc/<ID>/...)")
    p.add_argument("--device", required=True, metavar=device_id[0], help=device_id[1])
    p.add_argument("--summary-out", metavar="FILE",
                   help="write the link's last LinkStatus as JSON to FILE at exit (the launcher reads it)")
    p.add_argument("--scan-period-s", type=float, default=60.0,
                   help=f"read {device} at every multiple of this period (UTC) and stamp the frame with it [s]")
    p.add_argument("--control-period-s", type=float, default=300.0,
                   help="the feeder's control period: the unit of the command windows [s]")
    p.add_argument("--status-period-s", type=float, default=10.0, help="publish the link status this often [s]")
    p.add_argument("--timeout-s", type=float, default=timeout_s, help=f"time-out of one {protocol} request [s]")
    p.add_argument("--clock", choices=["wall", "head"], default="wall",
                   help="wall: scan on --scan-period-s of the UTC clock; head: scan at each new feeder-head frame and "
                        "take its time (the feeder's scan drives the adapter)")


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``adapter`` verb (sub-verbs ``sunspec``, ``dnp3`` and ``sim``) to the ``cvvc`` command line."""
    from schemas.bus_args import add_bus_arguments

    p = sub.add_parser("adapter", help="field-protocol adapters: real devices as devices of the bus")
    verbs = p.add_subparsers(dest="adapter_verb", metavar="SUBVERB", required=True)
    s = verbs.add_parser("sunspec", help="a PV inverter behind SunSpec Modbus TCP (models 701, 702, 704)",
                         description="Read the inverter's SunSpec models with pysunspec2, publish its PV frames, "
                                     "write the agent's reactive power commands as 704 set points with a revert "
                                     "timer, and acknowledge what the inverter applied. See docs/sunspec.md.")
    s.add_argument("--modbus", required=True, metavar="tcp/HOST:PORT", help="the inverter's Modbus TCP endpoint")
    s.add_argument("--unit", type=int, default=1, help="Modbus unit (slave) id [default: 1]")
    _add_loop_arguments(s, device="the inverter", protocol="Modbus", timeout_s=1.0,
                        device_id=("PV_ID", "the plant's id in the device map"))
    s.add_argument("--local-mode", choices=["unity_pf", "volt_var"], default="unity_pf",
                   help="the inverter's local default, reported in its frames")
    s.add_argument("--set-local-mode", action="store_true",
                   help="write --local-mode into the inverter's model 705 (volt-var curve enabled or not) whenever a "
                        "scan finds it otherwise; without this flag 705 is only read")
    s.add_argument("--q-at-night", action="store_true", help="the inverter gives reactive power at zero output")
    add_bus_arguments(s)
    s.set_defaults(func=_sunspec)
    dn = verbs.add_parser("dnp3", help="a regulator control or capacitor bank controller behind DNP3 (IEEE 1815)",
                          description="Poll the outstation (opendnp3 master), publish the device's frames, operate "
                                      "the agent's commands with a hold time that follows their validity, and "
                                      "acknowledge from the outstation's answer and a read back. See docs/dnp3.md.")
    dn.add_argument("--kind", choices=["vr", "cap"], default="vr",
                    help="vr: a regulator control; cap: a capacitor bank controller [default: vr]")
    dn.add_argument("--dnp3", required=True, metavar="tcp/127.0.0.1:PORT", help="the outstation's endpoint")
    dn.add_argument("--outstation-address", type=int, default=10, help="the outstation's link address")
    dn.add_argument("--master-address", type=int, default=1, help="this master's link address")
    _add_loop_arguments(dn, device="the outstation", protocol="DNP3", timeout_s=2.0,
                        device_id=("ID", "the regulator's or bank's id in the device map"))
    dn.add_argument("--phase", choices=["a", "b", "c"], default="a", help="the regulator's phase (its frames)")
    dn.add_argument("--kvar-rated", type=float, default=600.0, help="the bank's rating (its frames) [kvar]")
    dn.add_argument("--control-type", default="none",
                    help="the bank's local control type, as in its frames (none, voltage, kvar, ...)")
    add_bus_arguments(dn)
    dn.set_defaults(func=_dnp3)
    sim = verbs.add_parser("sim", help="serve a simulated SunSpec inverter (models 1, 701, 702, 704) to try on",
                           description="A pymodbus server holding SunSpec models built by pysunspec2, at a fixed "
                                       "output; its reactive power follows the 704 set point and its revert timer.")
    sim.add_argument("--modbus", required=True, metavar="tcp/HOST:PORT", help="where to serve")
    sim.add_argument("--device", default="pv1", help="its serial number (model 1 SN)")
    sim.add_argument("--unit", type=int, default=1, help="Modbus unit id it reports")
    sim.add_argument("--s-rated-kva", type=float, default=1000.0, help="rating [kVA]")
    sim.add_argument("--p-kw", type=float, default=600.0, help="active power, shared by three phases [kW]")
    sim.add_argument("--v-nominal-v", type=float, default=7200.0, help="line-to-neutral voltage [V]")
    sim.set_defaults(func=_sim)
