"""``cvvc agent``: the volt-var control agent as a process on the bus."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from schemas.settings import AgentSettings

__all__ = ["register"]

_SHIPPED = AgentSettings()  # the flags' defaults: the settings tree's (schemas.settings)


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``agent`` verb to the ``cvvc`` command line."""
    from schemas.bus_args import add_bus_arguments

    p = sub.add_parser("agent", help="run the CVVC agent on the bus",
                       description="Subscribe to the feeder's measurement frames, decide every control step "
                                   "and publish PV Q set points and regulator commands.")
    p.add_argument("--model", required=True, help="model file from `cvvc train`")
    p.add_argument("--feeder-id", required=True, help="feeder id of the keys (cvvc/<ID>/...)")
    p.add_argument("--settings", default=None, metavar="JSON",
                   help="every decision setting as encoded AgentSettings (how `cvvc run` hands a case over); "
                        "the flags below that shape decisions are then ignored")
    p.add_argument("--feeder", default=None,
                   help="device map of the feeder: refuse the model if its fingerprint differs; its AMI meters "
                        "([[meter]]) are the only ones whose readings count (none without it)")
    p.add_argument("--mode", choices=["taps", "setpoints"], default=_SHIPPED.mode,
                   help="command tap positions (cases A/B) or eq. 8 voltage set points (cases C/D)")
    p.add_argument("--correction", choices=["on", "off"], default="on" if _SHIPPED.correction else "off",
                   help="eq. 6-7 correction (case D)")
    p.add_argument("--bandwidth-v", type=float, default=_SHIPPED.bandwidth_v120,
                   help="regulator band sent with set points [V on 120 V]")
    p.add_argument("--pv-margin-window-s", type=float, default=None,
                   help="beyond the paper: tighten each node's limits by the voltage change if the plants went back "
                        "to their highest/lowest output of this many recent seconds; 0 = off (the paper's method) "
                        f"[default {_SHIPPED.pv_margin_window_s:g}]")
    p.add_argument("--pv-margin-cap-pu", type=float, default=None,
                   help=f"largest PV variability margin on either side [pu] [default {_SHIPPED.pv_margin_cap_pu:g}]")
    p.add_argument("--setpoint-hold", choices=["on", "off"], default=None,
                   help="beyond the paper (setpoints mode): re-send the last set point unchanged when no tap change is "
                        "decided, instead of re-centring the band on the reading "
                        f"[default: {'on' if _SHIPPED.setpoint_hold else 'off'}]")
    p.add_argument("--setpoint-recentre", choices=["on", "off"], default=None,
                   help="beyond the paper (setpoints mode): once a regulator told to step has stepped, send its band "
                        "again centred on its reading, at the next step; off: eq. (8) alone "
                        f"[default: {'on' if _SHIPPED.setpoint_recentre else 'off'}]")
    p.add_argument("--control-banks", choices=["on", "off"], default=None,
                   help="beyond the paper: decide and command the capacitor banks (else they stay on their local "
                        "control) "
                        f"[default: {'on' if _SHIPPED.control_banks else 'off'}]")
    p.add_argument("--reading-window-s", type=float, default=None,
                   help="regulator readings averaged over this many seconds at the present tap (robust to "
                        f"SCADA-class noise); 0: the last reading alone [default {_SHIPPED.reading_window_s:g}]")
    p.add_argument("--reading-fit-s", type=float, default=None,
                   help="beyond the paper, opt-in: regulator readings of this many seconds regressed on the head's "
                        "P, Q and voltage and evaluated now (agent/readings.py); 0: off "
                        f"[default {_SHIPPED.reading_fit_s:g}]")
    p.add_argument("--filtered-setpoints", choices=["on", "off"], default=None,
                   help="beyond the paper (setpoints mode, with the correction filter): eq. (8) starts from the "
                        "estimate plus the filtered reading-minus-estimate, not the noisy reading "
                        f"[default: {'on' if _SHIPPED.filtered_setpoints else 'off'}]")
    p.add_argument("--full-visibility", action="store_true",
                   help="case A: true voltages and sensitivities of every node from the bridge's oracle")
    p.add_argument("--agent-id", default=_SHIPPED.agent_id)
    p.add_argument("--stale-after-s", type=float, default=_SHIPPED.stale_after_s)
    p.add_argument("--json", action="store_true", help="print a JSON summary at exit")
    p.add_argument("--summary-out", metavar="FILE", help="write the JSON summary at exit to FILE (the launcher "
                   "reads the run's decision counts from the agent itself, not from the bus)")
    add_bus_arguments(p)
    p.set_defaults(func=_agent)


def settings_from_args(args: argparse.Namespace):
    """The agent's settings: decoded from ``--settings`` when given, else from the flags."""
    import msgspec

    from agent.errors import AgentError
    from agent.runtime import AgentSettings

    if args.settings is not None:
        try:
            settings = msgspec.json.decode(args.settings, type=AgentSettings)
        except (msgspec.DecodeError, msgspec.ValidationError) as e:
            raise AgentError(f"--settings is not valid AgentSettings JSON: {e}") from e
        if settings.feeder_id != args.feeder_id:
            raise AgentError(f"--settings is for feeder {settings.feeder_id!r}, --feeder-id is {args.feeder_id!r}")
        return settings

    given = {"pv_margin_window_s": args.pv_margin_window_s, "pv_margin_cap_pu": args.pv_margin_cap_pu,
             "setpoint_hold": None if args.setpoint_hold is None else args.setpoint_hold == "on",
             "setpoint_recentre": None if args.setpoint_recentre is None else args.setpoint_recentre == "on",
             "control_banks": None if args.control_banks is None else args.control_banks == "on",
             "reading_window_s": args.reading_window_s, "reading_fit_s": args.reading_fit_s,
             "filtered_setpoints": None if args.filtered_setpoints is None else args.filtered_setpoints == "on"}
    optional: dict[str, Any] = {name: value for name, value in given.items() if value is not None}
    return AgentSettings(feeder_id=args.feeder_id, agent_id=args.agent_id, mode=args.mode,
                         correction=args.correction == "on", bandwidth_v120=args.bandwidth_v,
                         full_visibility=args.full_visibility, stale_after_s=args.stale_after_s, **optional)


def _agent(args: argparse.Namespace) -> int:
    import logging

    import msgspec

    from agent.runtime import run_agent
    from regression.model import read_model
    from schemas.bus import bus_config_from_args

    expect = None
    settings = settings_from_args(args)
    if args.feeder:
        from schemas.devicemap import load_device_map, resolve_device_map_path

        dm = load_device_map(resolve_device_map_path(args.feeder))
        expect = dm.fingerprint()
        if dm.meter and not settings.meters:  # the map's meters: the only ones whose readings count
            settings = msgspec.structs.replace(settings, meters=tuple(dm.meter))
    model = read_model(args.model, expect_fingerprint=expect)
    if settings.mode == "taps" and settings.correction and not settings.full_visibility:
        logging.getLogger("agent").info("taps mode with correction: not one of the paper's cases, allowed")
    summary = run_agent(model, settings, bus_config_from_args(args, role="agent"))
    if args.json:
        print(json.dumps(msgspec.to_builtins(summary)))
    if args.summary_out:
        Path(args.summary_out).write_bytes(msgspec.json.encode(summary))
    return 0
