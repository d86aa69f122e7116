"""``cvvc init``, ``cvvc run`` (and ``evaluate``, ``report``): the launchers' command line."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from cvvc.cli_options import add_agent_option_arguments, add_security_arguments
from cvvc.progress import QUIET_HELP, progress_wanted
from schemas.cache import CACHE_HELP
from schemas.settings import CASES, RunCase

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``init``, ``run`` and ``report`` verbs to the ``cvvc`` command line's ``sub``."""
    i = sub.add_parser("init", help="write a case file with every setting of a run and its default",
                       description="Write a commented TOML case file (docs/case-file.md) with every setting of "
                                   "`cvvc run`, its description and its default; edit it, then `cvvc run FILE`.")
    i.add_argument("case_file", metavar="FILE", help="the case file to write (e.g. case.toml)")
    i.add_argument("--force", action="store_true", help="overwrite FILE if it exists")
    i.set_defaults(func=_init)
    d = RunCase()  # the defaults the help texts name: every flag's default is the settings tree's
    p = sub.add_parser("run", help="the main job: bridge + agent + recorder on one simulated day (case D)",
                       description="Generate or reuse the feeder and model, then run bridge, agent and recorder "
                                   "as separate processes on loopback and print a summary. The settings come from "
                                   "the defaults, then the case file FILE (`cvvc init FILE`), then the flags given. "
                                   "Exit status: 0 a clean run, 2 an error, 3 a run in which the agent lost control "
                                   "for more than one control period (summary.json's 'integrity' says what was "
                                   "refused, missed or overwritten).")
    p.add_argument("case_file", nargs="?", metavar="FILE", default=None,
                   help="a case file (`cvvc init FILE` writes one); flags given override it")
    p.add_argument("--print-case", action="store_true",
                   help="print the resolved case (defaults, FILE, flags) as TOML and exit without running")
    p.add_argument("--feeder", default=None, help="device map TOML or folder (default: embedded rural feeder)")
    p.add_argument("--model", default=None, help="model file (default: train once and cache)")
    p.add_argument("--days", type=float, default=None, help=f"simulated days (default {d.window.days:g}; 1/24 = one "
                   "hour)")
    p.add_argument("--start", default=None, help=f"first simulated instant, YYYY-MM-DD[THH:MM], local standard time "
                   f"(default {d.window.start})")
    p.add_argument("--case", default=None, choices=list(CASES),
                   help=f"paper case A-D, or a baseline: none (no central control), local (+ IEEE 1547 volt-var) "
                        f"(default {d.case})")
    p.add_argument("--realtime", action="store_true", help="step on the wall clock instead of lockstep")
    p.add_argument("--speed", type=float, default=None,
                   help=f"with --realtime: simulated s per wall s (default {d.bridge.speed:g})")
    p.add_argument("--lockstep-timeout-s", type=float, default=None, metavar="S",
                   help=f"in lockstep, how long the bridge waits for a decision [s] "
                        f"(default {d.bridge.lockstep_timeout_s:g})")
    p.add_argument("--out", default=None, help="output folder (default runs/<feeder>-<case>-<time>)")
    p.add_argument("--year-seed", type=int, default=None,
                   help=f"profile year of the run (default {d.window.year_seed}: out of sample)")
    p.add_argument("--train-seed", type=int, default=None,
                   help=f"profile year used for training (default {d.feeder.train_seed})")
    p.add_argument("--bandwidth-v", type=float, default=None,
                   help=f"regulator band on 120 V in cases C/D (default {d.agent.bandwidth_v120:g})")
    add_agent_option_arguments(p)
    p.add_argument("--drop-prob", type=float, default=None, metavar="P",
                   help="the bridge drops each measurement frame with probability P (robustness runs; default 0)")
    p.add_argument("--drop-burst-min", type=float, default=None, metavar="MIN",
                   help="with --drop-prob: each device loses its frames in outages of MIN minutes, P being the "
                        "share of frames lost (default 0: each frame independently)")
    p.add_argument("--meas-delay-s", type=float, default=None, metavar="S",
                   help="with --realtime: every measurement frame reaches the agent S simulated seconds late")
    p.add_argument("--clock-skew-s", type=float, default=None, metavar="S",
                   help="the field devices' clocks are S seconds off the bridge's and the agent's: frames "
                        "stamped t + S (default 0)")
    p.add_argument("--noise-scada-pct", type=float, default=None, metavar="PCT",
                   help="SCADA-class noise on PV, regulator and capacitor readings [%%] (default 0)")
    p.add_argument("--noise-pmu-pct", type=float, default=None, metavar="PCT",
                   help="PMU-class noise on the feeder-head meter [%%] (default 0)")
    p.add_argument("--pv-protocol", choices=["bus", "sunspec"], default=None,
                   help="how the PV plants reach the bus: bus (the simulator's own frames, default) or sunspec "
                        "(each plant behind a simulated SunSpec Modbus inverter and a `cvvc adapter sunspec`; "
                        "docs/sunspec.md)")
    p.add_argument("--field-protocol", choices=["bus", "dnp3"], default=None,
                   help="how the regulators and capacitor banks reach the bus: bus (the simulator's own frames, "
                        "default) or dnp3 (each behind a simulated DNP3 outstation and a `cvvc adapter dnp3`; cases "
                        "C, D, none and local; docs/dnp3.md)")
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


def _init(args: argparse.Namespace) -> int:
    from cvvc.case import write_case

    path = write_case(args.case_file, force=args.force)
    print(f"wrote {path}: every setting of a run with its default; edit it, then `cvvc run {path}`")
    return 0


def _run(args: argparse.Namespace) -> int:
    import msgspec

    from cvvc.case import absolute_paths, apply_flags, case_toml, load_case
    from cvvc.launch import RunConfig, run

    case = apply_flags(load_case(args.case_file) if args.case_file else RunCase(), args)
    if args.print_case:
        given = f"resolved from {args.case_file} and the flags given" if args.case_file else \
            "resolved from the defaults and the flags given"
        sys.stdout.write(case_toml(absolute_paths(case), header=f"the case `cvvc run` would run, {given}"))
        return 0
    summary = run(RunConfig.of_case(case, progress=progress_wanted(args), case_file=args.case_file))
    if args.json:
        sys.stdout.write(msgspec.json.format(msgspec.json.encode(summary), indent=2).decode() + "\n")
    else:
        print(Path(summary.out_dir, "report.md").read_text())  # the report the run wrote
        print(f"output: {summary.out_dir} (summary.json, report.md{', session.mcap' if summary.recording else ''})")
    if summary.integrity.degraded:  # the run finished, but the agent did not control the feeder all along
        from cvvc.integrity import EXIT_DEGRADED

        print(f"cvvc run: degraded for more than one control period: {summary.integrity.degraded} (exit "
              f"{EXIT_DEGRADED}; {summary.out_dir}/summary.json, 'integrity')", file=sys.stderr)
        return EXIT_DEGRADED
    return 0


def register_report(sub: argparse._SubParsersAction) -> None:
    from training.cli import register_accuracy

    p = sub.add_parser("report", help="reports: estimation accuracy, plots of a run or an evaluation")
    rsub = p.add_subparsers(dest="report_verb", metavar="SUBVERB")
    register_accuracy(rsub)
    from cvvc.evaluate_cli import register_report_plots

    register_report_plots(rsub)
