"""``cvvc bridge``: run the simulated feeder's field devices on the bus (lockstep or real time).

Registered by ``simulator_bridge.bus.cli.register``. Nothing heavy is imported at module level; the handler
only parses arguments into a :class:`~simulator_bridge.bus.bridge.BridgeConfig` and calls ``run_bridge``.
SIGINT / SIGTERM end the run cleanly (final metrics, tokens withdrawn, session closed, exit 0).
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from pathlib import Path

from schemas.settings import BridgeSection

__all__ = ["register_bridge"]

_REALISM = BridgeSection()  # the realism flags' defaults: a case file's [bridge] section's


def _bridge(args: argparse.Namespace) -> int:
    import msgspec

    from schemas.bus import Mode, bus_config_from_args
    from schemas.cache import cache_root, profiles_dir
    from schemas.devicemap import resolve_device_map_path
    from schemas.errors import CvvcError
    from simulator_bridge.bus.bridge import BridgeConfig, run_bridge
    from simulator_bridge.rural.default_feeder import ensure_default_feeder

    try:
        path = (ensure_default_feeder(cache_root(args.cache)) if args.feeder is None
                else resolve_device_map_path(args.feeder))
        if args.steps is not None:
            steps = args.steps
        else:
            steps = int(round(args.days * 1440))  # profiles are 1-minute steps
        config = BridgeConfig(
            device_map_path=str(path), feeder_id=args.feeder_id, start=args.start, steps=steps,
            clock="realtime" if args.realtime else "lockstep", timeout_s=args.timeout_s, speed=args.speed,
            wait_agent_s=args.wait_agent_s, year_seed=args.year_seed, pv_local=args.pv_local,
            truth_every=args.truth_every, noise_pmu_pct=args.noise_pmu_pct, noise_scada_pct=args.noise_scada_pct,
            drop_prob=args.drop_prob, latency_s=args.latency_s, noise_seed=args.noise_seed,
            drop_burst_min=args.drop_burst_min, clock_skew_s=args.clock_skew_s,
            cache_dir=(str(profiles_dir(args.cache)) if args.cache_dir is None
                       else None if args.cache_dir == "" else args.cache_dir), publisher=args.publisher,
            oracle=args.oracle, pv_sunspec=_device_endpoints("--pv-sunspec", "PV_ID", args.pv_sunspec),
            field_dnp3=_device_endpoints("--field-dnp3", "DEVICE_ID", args.field_dnp3),
            own_commands_only=args.own_commands_only,
        )
        default_mode: Mode = "router" if args.listen and not args.connect else "peer"
        bus = bus_config_from_args(args, default_mode=default_mode, role="devices")
        stop = threading.Event()
        previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            summary = run_bridge(config, bus, stop=stop)
        finally:
            for s, h in previous.items():
                signal.signal(s, h)
    except CvvcError as e:
        print(f"cvvc bridge: error: {e}", file=sys.stderr)
        return 2
    if args.summary_out:
        Path(args.summary_out).write_bytes(msgspec.json.encode(summary))
    if args.json:
        print(msgspec.json.format(msgspec.json.encode(summary), indent=2).decode())
    else:
        rt = ("" if summary.round_trip_p50_s is None
              else f", decision round trip p50 {1e3 * summary.round_trip_p50_s:.2f} ms")
        print(f"bridge {summary.feeder_id} ({summary.clock}, publisher {summary.publisher}): {summary.steps}/"
              f"{summary.steps_total} steps in {summary.wall_s:.2f} s ({summary.steps_per_s:.1f} steps/s), "
              f"{summary.decisions} decisions, {summary.lockstep_misses} lockstep misses{rt}")
    return 0


def _device_endpoints(flag: str, name: str, items: list[str] | None) -> dict[str, str]:
    """``FLAG ID=tcp/127.0.0.1:PORT`` flags -> {device: endpoint}; BridgeError when malformed."""
    from simulator_bridge.errors import BridgeError

    out: dict[str, str] = {}
    for item in items or []:
        device, sep, endpoint = item.partition("=")
        if not sep or not device or not endpoint or device in out:
            raise BridgeError(f"{flag} {item!r}: write {name}=tcp/127.0.0.1:PORT, once per device")
        out[device] = endpoint
    return out


def register_bridge(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``bridge`` verb."""
    from schemas.bus_args import add_bus_arguments
    from schemas.cache import CACHE_HELP

    p = subparsers.add_parser("bridge", help="run the simulated feeder's field devices on the bus")
    p.add_argument("--feeder", default=None,
                   help="device map TOML or a folder with devicemap.toml (default: the embedded rural feeder)")
    p.add_argument("--feeder-id", default=None, help="feeder id in the key space (default: the map's name)")
    when = p.add_argument_group("what to simulate")
    when.add_argument("--start", default="2023-07-01",
                      help="first instant, YYYY-MM-DD[THH:MM] local standard time (UTC-5) in the profile year")
    n = when.add_mutually_exclusive_group()
    n.add_argument("--days", type=float, default=1.0, help="simulated days (default 1)")
    n.add_argument("--steps", type=int, default=None, help="simulated 1-minute steps (overrides --days)")
    when.add_argument("--year-seed", type=int, default=1, help="profile seed (default 1)")
    when.add_argument("--pv-local", choices=["unity", "volt_var"], default="unity",
                      help="PV local default without a valid command (default unity power factor)")
    when.add_argument("--cache", default=None, help=CACHE_HELP)
    when.add_argument("--cache-dir", default=None,
                      help="profile cache folder ('' for none; default: profiles/ in the --cache folder)")
    clock = p.add_argument_group("clock")
    mode = clock.add_mutually_exclusive_group()
    mode.add_argument("--lockstep", action="store_true", help="wait for the agent each control step (default)")
    mode.add_argument("--realtime", action="store_true", help="step on the wall clock times --speed")
    clock.add_argument("--timeout-s", type=float, default=5.0, help="lockstep wait per control step [s]")
    clock.add_argument("--speed", type=float, default=1.0, help="real-time speed factor (default 1)")
    clock.add_argument("--wait-agent-s", type=float, default=0.0,
                       help="before the first step, wait this long for an agent liveliness token [s]")
    out = p.add_argument_group("simulation topics and measurement realism (off by default)")
    out.add_argument("--truth-every", type=int, default=_REALISM.truth_every, help="TruthFrame every N steps (0: none)")
    out.add_argument("--noise-pmu-pct", type=float, default=_REALISM.noise_pmu_pct,
                     help="PMU-class noise, e.g. 0.1 [%%]")
    out.add_argument("--noise-scada-pct", type=float, default=_REALISM.noise_scada_pct,
                     help="SCADA-class noise, e.g. 1 [%%]")
    out.add_argument("--drop-prob", type=float, default=_REALISM.drop_prob, help="probability that a frame is dropped")
    out.add_argument("--drop-burst-min", type=float, default=_REALISM.drop_burst_min,
                     help="with --drop-prob: each device loses its frames in outages of this many minutes, "
                          "--drop-prob being the share lost (default 0: each frame independently)")
    out.add_argument("--clock-skew-s", type=float, default=_REALISM.clock_skew_s,
                     help="the field devices' clocks are this far off the bridge's: frames stamped t + skew [s]")
    out.add_argument("--latency-s", type=float, default=0.0, help="fixed frame latency [s of wall time]")
    out.add_argument("--noise-seed", type=int, default=0, help="seed of noise and drops")
    p.add_argument("--publisher", choices=["auto", "inline", "process"], default="auto",
                   help="who builds and puts each step's frames, truth and metrics: the stepping thread (inline), "
                        "a publisher process with its own Zenoh session (process), or auto: the process on feeders "
                        "of 200 nodes or more, without --latency-s, with --connect/--listen and no "
                        "--zenoh-config (docs/bridge.md)")
    p.add_argument("--oracle", action="store_true", help="serve the case-A oracle on sim/oracle (true voltages "
                   "and sensitivities of every node; off unless case A needs it)")
    p.add_argument("--pv-sunspec", action="append", metavar="PV_ID=tcp/127.0.0.1:PORT",
                   help="serve this plant as a simulated SunSpec inverter on PORT and leave its frames, acks and "
                        "commands to a `cvvc adapter sunspec --clock head` (repeat per plant; docs/sunspec.md)")
    p.add_argument("--field-dnp3", action="append", metavar="DEVICE_ID=tcp/127.0.0.1:PORT",
                   help="serve this regulator or capacitor bank as a simulated DNP3 outstation on PORT and leave its "
                        "frames, acks and commands to a `cvvc adapter dnp3 --clock head` (repeat per device; "
                        "docs/dnp3.md)")
    p.add_argument("--own-commands-only", action="store_true",
                   help="subscribe to this feeder's commands only, not every feeder's (many feeders on one bus: "
                        "`cvvc fleet`); no wrong_feeder answers for commands sent to feeders without a bridge")
    p.add_argument("--json", action="store_true", help="print the run summary as JSON")
    p.add_argument("--summary-out", metavar="FILE", help="write the run summary as JSON to FILE at exit (the "
                   "launcher takes the run's final metrics from the bridge itself, not from the bus)")
    add_bus_arguments(p)
    p.set_defaults(func=_bridge)
