"""``cvvc feeder advise-meters``: where a few AMI meters would pay (``training.meter_advice``).

Registered under the ``feeder`` verb (``simulator_bridge.bus.cli``), which may not import training itself.
"""

from __future__ import annotations

import argparse
import sys

from schemas.cache import CACHE_HELP

__all__ = ["register"]


def _feeder_verbs(subparsers: argparse._SubParsersAction) -> argparse._SubParsersAction:
    feeder = subparsers.choices["feeder"]
    return next(a for a in feeder._actions if isinstance(a, argparse._SubParsersAction))


def _months(text: str) -> list[int]:
    try:
        months = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: months as comma-separated numbers, e.g. 1,7") from None
    if not months or any(not 1 <= m <= 12 for m in months):
        raise argparse.ArgumentTypeError(f"{text!r}: months in 1..12")
    return months


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``advise-meters`` to the ``feeder`` verb."""
    p = _feeder_verbs(subparsers).add_parser(
        "advise-meters", help="rank critical nodes as AMI meter sites by the error a meter there removes")
    p.add_argument("map", help="device map TOML of the feeder")
    p.add_argument("--model", required=True, help="the feeder's trained model")
    p.add_argument("--k", type=int, required=True, help="how many meters to advise")
    p.add_argument("--months", type=_months, default=[1, 7], help="months simulated (default 1,7)")
    p.add_argument("--minutes", type=int, default=1440, help="minutes simulated from each month's first (default 1440)")
    p.add_argument("--year-seed", type=int, default=1,
                   help="profile year simulated (default 1, the training year: advice before any field data)")
    p.add_argument("--interval-min", type=int, default=15, help="minutes between a meter's readings (default 15)")
    p.add_argument("--noise-pu", type=float, default=0.001, help="reading noise, standard deviation [pu]")
    p.add_argument("--write-map", default=None, metavar="OUT",
                   help="write the map with the advised [[meter]] entries to OUT (beside the map)")
    p.add_argument("--cache", default=None, help=CACHE_HELP)
    p.add_argument("--json", action="store_true", help="print the advice as JSON")
    p.set_defaults(func=_advise)


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.2f} %"


def _advise(args: argparse.Namespace) -> int:
    import msgspec

    from schemas.cache import cache_root
    from schemas.devicemap import resolve_device_map_path
    from training.meter_advice import advise_meters, write_advised_map

    dm_path = resolve_device_map_path(args.map)
    advice = advise_meters(args.model, dm_path, k=args.k, months=args.months, minutes=args.minutes,
                           year_seed=args.year_seed, interval_min=args.interval_min, noise_pu=args.noise_pu,
                           cache_dir=cache_root(args.cache) / "profiles", progress=sys.stderr.isatty())
    written = None if args.write_map is None else write_advised_map(dm_path, advice, args.write_map)
    if args.json:
        print(msgspec.json.encode(advice).decode())
        return 0
    print(f"# AMI meter sites on {advice.feeder}: {advice.minutes} minutes of months {advice.months}, year seed "
          f"{advice.year_seed}, a reading every {advice.interval_min} min (noise {advice.noise_pu} pu)")
    if len(advice.sites) < advice.k:
        print(f"only {len(advice.sites)} of the {advice.k} sites asked for gain from a meter: elsewhere its noise "
              f"outweighs the estimate's error")
    if advice.already_metered:
        print(f"already metered (left out): {', '.join(advice.already_metered)}")
    print("\n| rank | node | RMSE [pu] | with a meter | share of the error removed | outside bounds | with a meter |")
    print("|---|---|---|---|---|---|---|")
    for s in advice.sites:
        print(f"| {s.rank} | {s.node} | {s.rmse_pu:.5f} | {s.rmse_metered_pu:.5f} | {100 * s.gain:.1f} % | "
              f"{_pct(s.miss_rate)} | {_pct(s.miss_rate_metered)} |")
    print(f"\nevery critical node: RMSE {advice.rmse_pu:.5f} -> {advice.rmse_with_k_pu:.5f} pu, within ±0.01 pu "
          f"{100 * advice.within:.3f} -> {100 * advice.within_with_k:.3f} %, outside the bounds "
          f"{_pct(advice.miss_rate)} -> {_pct(advice.miss_rate_with_k)}")
    if written is not None:
        print(f"advised map: {written} (run it: cvvc run --feeder {written} --model {args.model})")
    return 0
