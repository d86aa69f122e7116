"""``cvvc fleet``: the command line of several feeders on one bus (``cvvc.fleet``)."""

from __future__ import annotations

import argparse
import sys

from schemas.cache import CACHE_HELP
from schemas.settings import RunCase

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``fleet`` verb to the ``cvvc`` command line's ``sub``."""
    p = sub.add_parser("fleet", help="several feeders at once: a bridge and an agent each, one recorder, one router",
                       description="Run several feeders at once on one Zenoh router (loopback): one bridge and one "
                                   "agent per feeder, each in lockstep with its own agent, one recorder; print a "
                                   "per-feeder table. Feeders from --feeders, --rural-seeds and --fleet together.")
    p.add_argument("--feeders", default="", metavar="A.toml,B.toml",
                   help="device maps (TOML or folders), comma-separated; each feeder's id is its map's name")
    p.add_argument("--rural-seeds", default="", metavar="1,2,...",
                   help="embedded rural feeders generated with these seeds (feeder ids rural-s<seed>)")
    p.add_argument("--fleet", default=None, metavar="FILE.toml",
                   help="a fleet file: [[feeder]] tables with map or rural_seed, and optional id, model, year_seed, "
                        "train_seed, case; top-level days, start, case as defaults (docs/architecture.md)")
    p.add_argument("--days", type=float, default=None, help="simulated days per feeder (default 0.25)")
    p.add_argument("--start", default=None, help="first simulated instant, YYYY-MM-DD[THH:MM] (default 2023-01-16)")
    p.add_argument("--case", default=None, choices=["A", "B", "C", "D", "none", "local"],
                   help="every feeder's case unless its fleet entry names one (default D)")
    p.add_argument("--year-seed", type=int, default=RunCase().window.year_seed,
                   help="profile year of the --feeders/--rural-seeds feeders")
    p.add_argument("--lockstep-timeout-s", type=float, default=30.0,
                   help="how long each bridge waits for its agent's decision [s] (default 30)")
    p.add_argument("--truth-every", type=int, default=RunCase().bridge.truth_every, metavar="N",
                   help="record every feeder's truth frame every N steps (0: never; default 1)")
    p.add_argument("--out", default=None, help="output folder (default runs/fleet-<n>-<time>)")
    p.add_argument("--cache", default=None, help=CACHE_HELP)
    p.add_argument("--no-record", action="store_true", help="no recording (no decision times, no crossing check)")
    from cvvc.cli_options import add_security_arguments

    add_security_arguments(p)  # secure by default: one certificate per feeder's agent and devices, each allowed on
    # its own feeder's keys alone; a probe command across feeders is put and must be refused
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=_fleet)


def _fleet(args: argparse.Namespace) -> int:
    import msgspec

    from cvvc.fleet import FleetConfig, FleetFeeder, load_fleet_file, run_fleet
    from cvvc.fleet_report import render_fleet
    from cvvc.launch import LaunchError

    fleet = load_fleet_file(args.fleet) if args.fleet else None
    feeders = [FleetFeeder(map=path, year_seed=args.year_seed) for path in _items(args.feeders)]
    try:
        feeders += [FleetFeeder(rural_seed=int(seed), year_seed=args.year_seed) for seed in _items(args.rural_seeds)]
    except ValueError as e:
        raise LaunchError(f"--rural-seeds {args.rural_seeds!r}: {e}") from e
    feeders += fleet.feeder if fleet else []

    def pick(flag, key: str, default):
        if flag is not None:
            return flag
        value = getattr(fleet, key) if fleet else None
        return default if value is None else value

    defaults = FleetConfig(feeders=[])
    config = FleetConfig(feeders=feeders, days=pick(args.days, "days", defaults.days),
                         start=pick(args.start, "start", defaults.start), case=pick(args.case, "case", defaults.case),
                         out=args.out, cache=args.cache, record=not args.no_record, truth_every=args.truth_every,
                         lockstep_timeout_s=args.lockstep_timeout_s, secure=not args.insecure, ca_dir=args.ca_dir,
                         progress=not args.json, agent=fleet.agent if fleet and fleet.agent else defaults.agent)
    summary = run_fleet(config)
    if args.json:
        sys.stdout.write(msgspec.json.format(msgspec.json.encode(summary), indent=2).decode() + "\n")
    else:
        print(render_fleet(summary))
        print(f"output: {summary.out_dir} (fleet-summary.json, fleet.md, one folder per feeder)")
    return 0


def _items(text: str) -> list[str]:
    return [x.strip() for x in text.split(",") if x.strip()]
