"""``cvvc train`` and ``cvvc report accuracy`` (registered under the launcher's ``report`` verb).

Verbs::

    cvvc train [--feeder FEEDER] --out MODEL [--year-seed S] [--selection guided|random]
               [--blocks NL NPV] [--workers N] [--no-combined] [--features paper|extended]
               [--critical-margin-pu PU] [--cache DIR] [--json]
    cvvc report accuracy --model MODEL [--model MODEL2] [--feeder FEEDER] --month M [--year-seed S]
               [--png PATH] [--max-minutes N] [--cache DIR] [--json]
               [--ami-meters K [--ami-interval-min I] [--ami-noise-pu PU] [--ami-latency-min L]]

FEEDER is a device map TOML or a folder with ``devicemap.toml``; default: the embedded rural feeder.
Nothing heavy is imported at module level.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from schemas.cache import CACHE_HELP
from schemas.settings import TrainingOptions

if TYPE_CHECKING:
    from schemas.settings import FeatureOptions

__all__ = ["register", "register_accuracy"]

_DEFAULT = TrainingOptions()


def _feeder_path(feeder: str | None, cache: str | None) -> Path:
    from schemas.cache import cache_root
    from schemas.devicemap import resolve_device_map_path
    from simulator_bridge.rural.default_feeder import ensure_default_feeder

    if feeder is None:
        return ensure_default_feeder(cache_root(cache))
    return resolve_device_map_path(feeder)


def _feature_options(args: argparse.Namespace, device_map_path: Path) -> FeatureOptions:
    """The feature options of ``--features`` (``auto``: ``training.extended.default_feature_options``)."""
    from schemas.devicemap import load_device_map
    from schemas.settings import FeatureOptions
    from training.extended import default_feature_options

    if args.features == "auto":
        return default_feature_options(load_device_map(device_map_path))
    return FeatureOptions(feature_set=args.features, calendar=args.calendar,
                          critical_margin_pu=args.critical_margin_pu, calendar_cover_per_cell=args.calendar_cover,
                          calendar_seasonal=args.seasonal, calendar_weekly=args.weekly)


def _training_options(args: argparse.Namespace, device_map_path: Path) -> TrainingOptions:
    """What ``cvvc train``'s flags ask for (their defaults are ``TrainingOptions``')."""
    return TrainingOptions(
        year_seed=args.year_seed,
        selection=args.selection,
        blocks=(args.blocks[0], args.blocks[1]),
        combined_pct=() if args.no_combined else _DEFAULT.combined_pct,
        calibration_minutes=args.calibration_minutes,
        features=_feature_options(args, device_map_path),
    )


def _train(args: argparse.Namespace) -> int:
    import msgspec

    from regression.model import write_model
    from schemas.cache import profiles_dir
    from training.train import train

    path = _feeder_path(args.feeder, args.cache)
    result = train(path, _training_options(args, path), cache_dir=profiles_dir(args.cache), workers=args.workers,
                   progress=not (args.json or args.quiet))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_model(result.model, out)
    s = result.summary
    if args.json:
        print(msgspec.json.encode(s).decode())
        return 0
    print(f"model written to {out} (feeder {s.feeder}, {s.selection} selection, year seed {s.year_seed})")
    print(f"  scenarios:       {s.scenarios} from {s.non_empty_blocks} non-empty of {s.blocks[0]}x{s.blocks[1]} blocks")
    print(
        f"  power flows:     {s.power_flows} ({s.failed_power_flows} failed) on {s.workers} process(es), "
        f"{s.seconds_power_flows:.1f} s"
    )
    if s.cover_minutes:
        print(f"  calendar cover:  {s.cover_minutes} more minutes (one base flow each)")
    print(f"  critical nodes:  {s.critical_nodes} of {s.node_count} ({100 * s.critical_share:.1f} %)")
    print(
        f"  fit residuals:   rmse {s.voltage_rmse_pu:.5f} pu, max {s.voltage_max_abs_pu:.5f} pu; held-out "
        f"rmse {s.validation_rmse_pu:.5f}, max {s.validation_max_abs_pu:.5f} pu"
    )
    print(
        f"  sensitivities:   median rel. error {100 * s.sensitivity_median_rel_err:.1f} %, forms "
        f"{s.sensitivity_forms}; c = {s.c_kvar:.0f} kvar"
    )
    if s.calibration_minutes:
        print(f"  estimate bounds: median ±{s.bound_p50_pu:.4f} pu, calibrated on {s.calibration_minutes} held-out "
              f"minutes in {s.seconds_calibration:.1f} s (level {s.bound_level:.4f}: held-out windows missed "
              f"{100 * s.bound_held_out_miss:.2f} %)")
    print(f"  seconds:         {s.seconds:.1f}")
    return 0


def _accuracy(args: argparse.Namespace) -> int:
    import msgspec

    from schemas.cache import profiles_dir
    from training.accuracy import accuracy_report

    report = accuracy_report(
        args.model,
        _feeder_path(args.feeder, args.cache),
        args.month,
        args.year_seed,
        cache_dir=profiles_dir(args.cache),
        png_path=args.png,
        max_minutes=args.max_minutes,
        progress=not (args.json or args.quiet),
        ami_meters=args.ami_meters,
        ami_interval_min=args.ami_interval_min,
        ami_noise_pu=args.ami_noise_pu,
        ami_latency_min=args.ami_latency_min,
    )
    if args.json:
        print(msgspec.json.encode(report).decode())
        return 0
    print(f"feeder {report.feeder}, month {report.month}, year seed {report.year_seed}, {report.minutes} minutes")
    print(f"{'estimator':44s} {'mean':>9s} {'rmse':>8s} {'p1':>9s} {'p99':>9s} {'max|e|':>8s} {'±0.01':>8s}")
    for e in report.errors:
        print(
            f"{e.label:44s} {e.mean_pu:+9.5f} {e.rmse_pu:8.5f} {e.p1_pu:+9.5f} {e.p99_pu:+9.5f} "
            f"{e.max_abs_pu:8.5f} {100 * e.within_001:7.3f}%"
        )
    for s in report.sensitivities:
        print(
            f"sensitivity {s.label}: median rel. error {100 * s.median_rel_err:.1f} % (p90 "
            f"{100 * s.p90_rel_err:.1f} %) over {s.pairs} pairs at {s.minutes} minutes"
        )
    for label, share in report.extreme_capture.items():
        print(
            f"true max and min node critical ({label}): {100 * share:.2f} % of minutes; worst gap between "
            f"the feeder's and the critical nodes' extremes {report.extreme_gap_max_pu[label]:.5f} pu "
            f"(p99 {report.extreme_gap_p99_pu[label]:.5f}); within 0.002 pu in "
            f"{100 * report.extreme_within_gap.get(label, float('nan')):.2f} % of minutes"
        )
    for label, alpha in report.bound_alpha.items():
        held = report.bound_miss_rate[label] <= 2.0 * alpha  # the goal the live report judges too
        print(f"calibrated bounds ({label}): {100 * report.bound_miss_rate[label]:.3f} % of node-minutes outside them "
              f"(promised at most {100 * alpha:.1f} %: {'held, within 2x' if held else 'NOT held, more than 2x'})")
    if not isinstance(report.ami_nodes, msgspec.UnsetType):
        for label, metered in report.ami_nodes.items():
            print(f"AMI meters ({label}): {', '.join(metered)}")
    if report.png:
        print(f"figure: {report.png}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``train`` to the ``cvvc`` command (``report accuracy`` comes through ``register_accuracy``)."""
    p = subparsers.add_parser("train", help="train the estimator of a feeder (scenarios, power flows, fits)")
    p.add_argument("--feeder", help="device map TOML or folder with devicemap.toml (default: rural feeder)")
    p.add_argument("--out", required=True, help="model file to write (JSON)")
    p.add_argument("--year-seed", type=int, default=_DEFAULT.year_seed,
                   help=f"seed of the training year (default {_DEFAULT.year_seed})")
    p.add_argument("--selection", choices=("guided", "random"), default=_DEFAULT.selection, help="scenario selection")
    p.add_argument("--blocks", type=int, nargs=2, default=_DEFAULT.blocks, metavar=("NL", "NPV"),
                   help="load x PV blocks (default {} {})".format(*_DEFAULT.blocks))
    p.add_argument("--workers", type=int, default=None, help="power-flow processes (default: one per core)")
    p.add_argument("--no-combined", action="store_true", help="only the paper's one-plant-at-a-time Q perturbations")
    p.add_argument("--calibration-minutes", type=int, default=_DEFAULT.calibration_minutes,
                   help="held-out minutes of the training year for the calibrated estimate bounds (0: none)")
    p.add_argument(
        "--features", choices=("auto", "paper", "extended", "extended_readings"), default="auto",
        help="auto (default): extended with --calendar, --critical-margin-pu 0.001, --calendar-cover 1, --seasonal 2 "
        "and --weekly when a bank of the device "
        "map has a capcontrol or there is no regulator, else paper; paper: eq. (5) on head and plant P, Q; "
        "extended: plus the capacitor banks' states, features mapped back to the training taps and banks; "
        "extended_readings: plus the regulators' and banks' voltage readings as regressors (docs/method.md)",
    )
    p.add_argument(
        "--critical-margin-pu", type=float, default=_DEFAULT.features.critical_margin_pu,
        help="also make critical a small cover of the nodes within this of each training flow's extremes [pu] "
        "(default 0: the paper's extremes only; ignored with --features auto)",
    )
    p.add_argument(
        "--calendar", action="store_true",
        help="extended sets: time of day and day of year among the regression features (docs/method.md; "
        "ignored with --features auto)",
    )
    p.add_argument(
        "--calendar-cover", type=int, default=_DEFAULT.features.calendar_cover_per_cell, metavar="N",
        help="also N minutes in every (month, local hour) cell of the year, one base flow each, in eq. (5)'s fit "
        "(training.scenarios.calendar_cover; default 0: the paper's scenarios only; ignored with --features auto)",
    )
    p.add_argument("--seasonal", type=int, nargs="?", const=1, default=_DEFAULT.features.calendar_seasonal,
                   choices=(0, 1, 2), metavar="H",
                   help="with a calendar: also the first H (1 or 2; no value: 1) daily harmonics times the yearly one "
                   "among the features (default 0: none; ignored with --features auto)")
    p.add_argument("--weekly", action="store_true",
                   help="with a calendar: also the weekend and its daily harmonics among the features (ignored with "
                   "--features auto)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON (no progress bar)")
    p.add_argument("--quiet", action="store_true",
                   help="no progress bars on stderr (they are off anyway when stderr is not a terminal)")
    p.add_argument("--cache", default=None, help=CACHE_HELP)
    p.set_defaults(func=_train)



def register_accuracy(report_subparsers: argparse._SubParsersAction) -> None:
    """Add ``accuracy`` under ``cvvc report`` (the launcher's ``report`` verb calls this)."""
    a = report_subparsers.add_parser("accuracy", help="estimation error of a model over a simulated month")
    a.add_argument("--model", action="append", required=True, help="model file (repeat for guided and random)")
    a.add_argument("--feeder", help="device map TOML or folder with devicemap.toml (default: rural feeder)")
    a.add_argument("--month", type=int, required=True, help="month 1..12")
    a.add_argument("--year-seed", type=int, default=2, help="seed of the simulated year (default 2)")
    a.add_argument("--png", help="write a figure like the paper's Fig. 8 here")
    a.add_argument("--max-minutes", type=int, default=None, help="only the first N minutes of the month")
    a.add_argument("--json", action="store_true", help="print the report as JSON")
    a.add_argument("--quiet", action="store_true",
                   help="no progress bars on stderr (they are off anyway when stderr is not a terminal)")
    a.add_argument("--cache", default=None, help=CACHE_HELP)
    a.add_argument("--ami-meters", type=int, default=0, metavar="K",
                   help="explicit option, not the paper's: K AMI meters at the critical nodes of widest calibrated "
                        "bounds, adds a row with them (default 0: none)")
    a.add_argument("--ami-interval-min", type=int, default=15, help="minutes between AMI readings (default 15)")
    a.add_argument("--ami-noise-pu", type=float, default=0.001,
                   help="standard deviation of the AMI reading noise [pu] (default 0.001)")
    a.add_argument("--ami-latency-min", type=int, default=0,
                   help="minutes from an AMI reading to its use (default 0)")
    a.set_defaults(func=_accuracy)
