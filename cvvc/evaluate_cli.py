"""``cvvc evaluate`` and ``cvvc report run|evaluate``: argument parsing only (handlers import the heavy parts)."""

from __future__ import annotations

import argparse

from cvvc.cli_options import add_agent_option_arguments
from cvvc.progress import QUIET_HELP, progress_wanted
from schemas.cache import CACHE_HELP
from schemas.settings import RunCase

__all__ = ["register_evaluate", "register_report_plots"]


def register_evaluate(sub: argparse._SubParsersAction) -> None:
    """Add the ``evaluate`` verb to ``sub``."""
    p = sub.add_parser(
        "evaluate", help="the paper's evaluation: cases x seasons through the real bus, Tables II-V",
        description="Run each (case, season, bandwidth) through bridge, agent and recorder in lockstep, one month "
                    "per season at 1-minute resolution (or --days-per-season), and write results.json and "
                    "results.md (paper Tables II-V). --robustness runs case D under noise, drops and model error.")
    p.add_argument("--feeder", default=None, help="device map TOML or folder (default: embedded rural feeder)")
    p.add_argument("--model", default=None, help="model file (default: train once on --train-seed and cache)")
    p.add_argument("--cases", default=None,
                   help="comma-separated cases among A,B,C,D,none,local and opendss (OpenDSS's own control loop on "
                        "the same days, no bus) (default: A,B,C,D,none,local; D with --robustness)")
    p.add_argument("--seasons", default="winter,spring,summer,fall", help="comma-separated seasons")
    d = RunCase()  # the settings tree's defaults
    p.add_argument("--bandwidth-v", default=f"{d.agent.bandwidth_v120:g}",
                   help="comma-separated regulator bands on 120 V for cases C/D")
    p.add_argument("--year-seed", type=int, default=d.window.year_seed,
                   help=f"profile year evaluated (default {d.window.year_seed}: out of sample)")
    p.add_argument("--train-seed", type=int, default=d.feeder.train_seed,
                   help=f"profile year of the training (default {d.feeder.train_seed})")
    p.add_argument("--days-per-season", type=float, default=None,
                   help="days from the first of each season's month (default: the whole month)")
    p.add_argument("--jobs", type=int, default=1,
                   help="runs at a time: the worker processes of the local Dask cluster (default 1)")
    p.add_argument("--scheduler", default=None,
                   help="a running Dask scheduler (tcp://HOST:PORT) to run on instead of a local cluster; its "
                        "workers must see the cache and --out at the same paths")
    p.add_argument("--campaign", default=None,
                   help="a campaign file (TOML: feeders x cases x seasons x variants, docs/results.md): writes "
                        "campaign.csv and each feeder's and variant's results.md in --out")
    p.add_argument("--reference-step-s", type=float, default=5.0,
                   help="OpenDSS's time step in the opendss case [s], a divisor of 60 (default 5; docs/simulation.md)")
    add_agent_option_arguments(p)
    p.add_argument("--robustness", action="store_true",
                   help="case D under PMU/SCADA noise, 1 %% and 5 %% dropped frames, and +-10 %% model error")
    p.add_argument("--lockstep-timeout-s", type=float, default=60.0,
                   help="how long the bridge waits for the agent's decision before going on under local control "
                        "(a lockstep miss, listed in results.md) [s] (default 60)")
    p.add_argument("--resume", action="store_true",
                   help="reuse runs already finished in --out (same case and window); run only the others")
    p.add_argument("--cache", default=None, help=CACHE_HELP)
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--quiet", action="store_true", help=QUIET_HELP)
    from cvvc.cli_options import add_security_arguments

    add_security_arguments(p)
    p.set_defaults(func=_evaluate)


def _evaluate(args: argparse.Namespace) -> int:
    from cvvc.case import agent_options_from_args
    from cvvc.errors import CliError
    from cvvc.evaluate import EvaluateConfig, EvaluateError, evaluate, parse_cases, parse_seasons
    from cvvc.launch import CASES

    if args.campaign:
        return _campaign(args)
    try:
        cases = parse_cases(args.cases) if args.cases else (("D",) if args.robustness else None)
        seasons = parse_seasons(args.seasons)
        bands = tuple(float(b) for b in args.bandwidth_v.split(",") if b.strip())
    except (EvaluateError, ValueError) as e:
        raise CliError(str(e)) from e
    config = EvaluateConfig(feeder=args.feeder, model=args.model, seasons=seasons, bandwidths_v120=bands,
                            year_seed=args.year_seed, train_seed=args.train_seed,
                            days_per_season=args.days_per_season, jobs=args.jobs, scheduler=args.scheduler,
                            out=args.out, cache=args.cache,
                            robustness=args.robustness, resume=args.resume,
                            reference_step_s=args.reference_step_s, lockstep_timeout_s=args.lockstep_timeout_s,
                            agent=agent_options_from_args(args), cases=CASES if cases is None else cases,
                            secure=not args.insecure, ca_dir=args.ca_dir, progress=progress_wanted(args))
    try:
        ev = evaluate(config)
    except EvaluateError as e:
        raise CliError(str(e)) from e
    print((__import__("pathlib").Path(args.out) / "results.md").read_text())
    print(f"output: {args.out} (results.json, results.md, one folder per run); {ev.wall_s:.0f} s")
    return 0


def _campaign(args: argparse.Namespace) -> int:
    from cvvc.campaign import run_campaign
    from cvvc.errors import CliError
    from cvvc.evaluate import EvaluateError

    given = [f for f, v in (("--feeder", args.feeder), ("--model", args.model), ("--cases", args.cases),
                            ("--days-per-season", args.days_per_season), ("--robustness", args.robustness))
             if v not in (None, False)]
    if given:
        raise CliError(f"{', '.join(given)}: with --campaign, the campaign file says the feeders, cases, seasons and "
                       "variants")
    try:
        result = run_campaign(args.campaign, args.out, jobs=args.jobs, scheduler=args.scheduler, cache=args.cache,
                              resume=args.resume, progress=progress_wanted(args))
    except EvaluateError as e:
        raise CliError(str(e)) from e
    print(f"output: {result.csv} and one folder per feeder and variant (results.md); {result.wall_s:.0f} s")
    return 0


def register_report_plots(rsub: argparse._SubParsersAction) -> None:
    """Add ``report run`` and ``report evaluate`` (PNG plots) to the ``report`` verb's ``rsub``."""
    p = rsub.add_parser("run", help="PNG plots of one cvvc run folder (voltage envelope, PV Q, taps, estimates)")
    p.add_argument("dir", help="a cvvc run output folder (with session.mcap)")
    p.add_argument("--out", default=None, help="where the PNGs go (default: DIR/plots)")
    p.set_defaults(func=_report_run)
    p = rsub.add_parser("evaluate", help="PNG plots of a cvvc evaluate folder: the cases of each season together")
    p.add_argument("dir", help="a cvvc evaluate output folder (with results.json)")
    p.add_argument("--out", default=None, help="where the PNGs go (default: DIR/plots)")
    p.set_defaults(func=_report_evaluate)
    p = rsub.add_parser("decision", help="why the agent decided what it did at one step of a recording (re-run "
                                         "offline): its solves, its rows nearest their limits and what tightened them")
    p.add_argument("dir", help="a cvvc run output folder (with session.mcap) or an MCAP recording")
    p.add_argument("--at", required=True, metavar="YYYY-MM-DDTHH:MM",
                   help="local standard time of the profiles (UTC-5); the control step at or before it")
    p.add_argument("--rows", type=int, default=6, help="rows nearest their limits to show (default 6)")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=_report_decision)


def _report_decision(args: argparse.Namespace) -> int:
    import msgspec

    from cvvc.errors import CliError
    from cvvc.explain import ExplainError, explain_decision, local_time_ns, render_explanation

    if args.rows < 1:
        raise CliError(f"--rows {args.rows}: give at least 1")
    try:
        x = explain_decision(args.dir, local_time_ns(args.at), rows=args.rows)
    except ExplainError as e:
        raise CliError(str(e)) from e
    print(msgspec.json.format(msgspec.json.encode(x)).decode() if args.json else render_explanation(x))
    return 0


def _report_run(args: argparse.Namespace) -> int:
    from cvvc.report import plot_run

    return _print_plots(plot_run, args)


def _report_evaluate(args: argparse.Namespace) -> int:
    from cvvc.report import plot_evaluation

    return _print_plots(plot_evaluation, args)


def _print_plots(plot, args: argparse.Namespace) -> int:
    """Run ``plot(args.dir, out=args.out)`` and print the PNG paths; a ``ReportError`` is a one-line CLI error."""
    from cvvc.errors import CliError
    from cvvc.report import ReportError

    try:
        paths = plot(args.dir, out=args.out)
    except ReportError as e:
        raise CliError(str(e)) from e
    for path in paths:
        print(path)
    return 0
