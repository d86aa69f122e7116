"""``cvvc run`` (and later ``evaluate``, ``report``): the launchers' command line."""

from __future__ import annotations

import argparse
import sys

from cvvc.cli_options import add_agent_option_arguments, add_security_arguments
from cvvc.progress import QUIET_HELP, progress_wanted
from schemas.cache import CACHE_HELP

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``run`` and ``report`` verbs to the ``cvvc`` command line's ``sub``."""
    p = sub.add_parser("run", help="the main job: bridge + agent + recorder on one simulated day (case D)",
                       description="Generate or reuse the feeder and model, then run bridge, agent and recorder "
                                   "as separate processes on loopback and print a summary.")
    p.add_argument("--feeder", default=None, help="device map TOML or folder (default: embedded rural feeder)")
    p.add_argument("--model", default=None, help="model file (default: train once and cache)")
    p.add_argument("--days", type=float, default=1.0, help="simulated days (default 1; 1/24 = one hour)")
    p.add_argument("--start", default="2023-01-16",
                   help="first simulated instant, YYYY-MM-DD[THH:MM], local standard time (default 2023-01-16)")
    p.add_argument("--case", default="D", choices=["A", "B", "C", "D", "none", "local"],
                   help="paper case A-D, or a baseline: none (no central control), local (+ IEEE 1547 volt-var)")
    p.add_argument("--realtime", action="store_true", help="step on the wall clock instead of lockstep")
    p.add_argument("--speed", type=float, default=60.0, help="with --realtime: simulated s per wall s")
    p.add_argument("--out", default=None, help="output folder (default runs/<feeder>-<case>-<time>)")
    p.add_argument("--year-seed", type=int, default=2, help="profile year of the run (default 2: out of sample)")
    p.add_argument("--train-seed", type=int, default=1, help="profile year used for training (default 1)")
    p.add_argument("--bandwidth-v", type=float, default=4.0, help="regulator band on 120 V in cases C/D")
    add_agent_option_arguments(p)
    p.add_argument("--drop-prob", type=float, default=0.0, metavar="P",
                   help="the bridge drops each measurement frame with probability P (robustness runs; default 0)")
    p.add_argument("--drop-burst-min", type=float, default=0.0, metavar="MIN",
                   help="with --drop-prob: each device loses its frames in outages of MIN minutes, P being the "
                        "share of frames lost (default 0: each frame independently)")
    p.add_argument("--meas-delay-s", type=float, default=0.0, metavar="S",
                   help="with --realtime: every measurement frame reaches the agent S simulated seconds late")
    p.add_argument("--clock-skew-s", type=float, default=0.0, metavar="S",
                   help="the field devices' clocks are S seconds off the bridge's and the agent's: frames "
                        "stamped t + S (default 0)")
    p.add_argument("--noise-scada-pct", type=float, default=0.0, metavar="PCT",
                   help="SCADA-class noise on PV, regulator and capacitor readings [%%] (default 0)")
    p.add_argument("--noise-pmu-pct", type=float, default=0.0, metavar="PCT",
                   help="PMU-class noise on the feeder-head meter [%%] (default 0)")
    p.add_argument("--pv-protocol", choices=["bus", "sunspec"], default="bus",
                   help="how the PV plants reach the bus: bus (the simulator's own frames, default) or sunspec "
                        "(each plant behind a simulated SunSpec Modbus inverter and a `cvvc adapter sunspec`; "
                        "docs/sunspec.md)")
    p.add_argument("--no-record", action="store_true", help="do not record the session to MCAP")
    p.add_argument("--no-baseline", action="store_true", help="skip the no-control baseline")
    p.add_argument("--cache", default=None, help=CACHE_HELP)
    p.add_argument("--json", action="store_true", help="print the summary as JSON (no progress bars)")
    p.add_argument("--quiet", action="store_true", help=QUIET_HELP)
    add_security_arguments(p)
    p.set_defaults(func=_run)
    register_report(sub)
    from cvvc.evaluate_cli import register_evaluate

    register_evaluate(sub)


def _run(args: argparse.Namespace) -> int:
    import msgspec

    from cvvc.launch import RunConfig, run
    from cvvc.run_report import render_summary

    config = RunConfig(feeder=args.feeder, model=args.model, days=args.days, start=args.start, case=args.case,
                       realtime=args.realtime, speed=args.speed, out=args.out, train_seed=args.train_seed,
                       year_seed=args.year_seed, bandwidth_v120=args.bandwidth_v, record=not args.no_record,
                       pv_margin_window_s=args.pv_margin_window_s, setpoint_hold=args.setpoint_hold,
                       control_banks=args.control_banks,
                       baseline=not args.no_baseline, cache=args.cache, progress=progress_wanted(args),
                       secure=not args.insecure, ca_dir=args.ca_dir, drop_prob=args.drop_prob,
                       noise_scada_pct=args.noise_scada_pct, noise_pmu_pct=args.noise_pmu_pct,
                       drop_burst_min=args.drop_burst_min, meas_delay_s=args.meas_delay_s,
                       clock_skew_s=args.clock_skew_s, pv_protocol=args.pv_protocol)
    summary = run(config)
    if args.json:
        sys.stdout.write(msgspec.json.format(msgspec.json.encode(summary), indent=2).decode() + "\n")
    else:
        print(render_summary(summary))
        print(f"output: {summary.out_dir} (summary.json, report.md{', session.mcap' if summary.recording else ''})")
    return 0


def register_report(sub: argparse._SubParsersAction) -> None:
    from training.cli import register_accuracy

    p = sub.add_parser("report", help="reports: estimation accuracy, plots of a run or an evaluation")
    rsub = p.add_subparsers(dest="report_verb", metavar="SUBVERB")
    register_accuracy(rsub)
    from cvvc.evaluate_cli import register_report_plots

    register_report_plots(rsub)
