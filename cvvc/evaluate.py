"""``cvvc evaluate``: the paper's evaluation (section IV), reproduced through the real bus, and a robustness study.

Each (case, season, bandwidth) is one :func:`cvvc.launch.run`: bridge, agent and recorder as separate processes in
lockstep, one month per season at 1-minute resolution (paper IV: January, April, July, October, see
``simulator_bridge.simulation.profiles.season_month``), on the evaluation year (``year_seed``, 2 by default) while the
model
was trained on another year (``train_seed``, 1). Each run is a task on dask.distributed (``cvvc.cluster``): a
``LocalCluster`` of ``jobs`` worker processes on loopback, or a running cluster (``scheduler``); the feeder, the
model and the year profiles are built once here and the runs read them by path from the cache. A run that raises is
retried once, then reported (``RunFailure``) while the others go on. ``cvvc.campaign`` runs many evaluations
(feeders x variants) as tasks of one cluster.

Outputs in ``--out``: one folder per run (``summary.json``, ``session.mcap`` ...), ``results.json`` (every run's
metrics and summary) and ``results.md`` with the paper's Table II/III layout (Season | Case | MVVM | NVV | NTC |
Q cost | T cost | Total), Table IV (per-PV reactive energy) and Table V (per-regulator tap changes).

The ``opendss`` case (``--cases none,local,opendss``) is not a bus run but OpenDSS's own control loop on the same
days, loads and PV (``cvvc/reference.py``), at ``--reference-step-s`` steps, measured with the same metrics.

``--robustness`` ("beyond the paper", its stated future work) runs case D under variants instead:
measurement noise of PMU class (0.1 %, the bridge applies it to the feeder-head meter) and SCADA class (1 %, PV
plants and regulators), dropped frames (1 %, 5 %), and model error (the
simulated feeder's line lengths, hence impedances, and load kW each scaled by a factor drawn uniformly in
[0.9, 1.1], while the agent keeps the model trained on the nominal feeder).
"""

from __future__ import annotations

import calendar
import datetime as dt
import json
import math
import os
import re
import socket
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import msgspec
import numpy as np

from cvvc.cluster import ClusterError, Outcome, Task, check_scheduler, dask_client, run_tasks
from cvvc.evaluate_tables import render_results_md
from cvvc.evaluation import (
    EVALUATION_YEAR,
    ROBUSTNESS_VARIANTS,
    SEASONS,
    EvaluateConfig,
    Evaluation,
    RunFailure,
    RunResult,
    RunSpec,
    Season,
    Variant,
)
from cvvc.launch import CASES, Case, LaunchError, RunConfig, RunSummary
from cvvc.progress import progress_bar
from cvvc.reference import REFERENCE_CASE, ReferenceConfig
from schemas.errors import CvvcError

__all__ = [
    "EVALUATE_CASES",
    "EVALUATION_YEAR",
    "ROBUSTNESS_VARIANTS",
    "SEASONS",
    "EvaluateConfig",
    "EvaluateError",
    "Evaluation",
    "PreparedEvaluation",
    "RunFailure",
    "RunResult",
    "RunSpec",
    "evaluate",
    "finish",
    "parse_cases",
    "parse_seasons",
    "perturbed_device_map",
    "prepare_evaluation",
    "render_results_md",
    "run_prepared",
    "season_window",
    "write_results",
]

#: Every case ``--cases`` accepts: the bus runs (``cvvc.launch.CASES``) and OpenDSS's own loop (``opendss``).
EVALUATE_CASES: tuple[str, ...] = (*CASES, REFERENCE_CASE)
_BUS_CASES: dict[str, Case] = {c: c for c in CASES}  # the cases run through the bus (cvvc run)


class EvaluateError(LaunchError):
    """An evaluation that cannot be planned or whose run failed; the message says which and what to do."""


def longest_first(specs: list[RunSpec]) -> list[RunSpec]:
    """The order runs are started in: case A first, so that with ``--jobs`` > 1 the last run to finish is a short
    one (case A asks the bridge's oracle at every decision and takes about 3x as long as B-D, docs/results.md);
    the rest keep their order.
    """
    return sorted(specs, key=lambda s: s.case != "A")


# ---------------------------------------------------------------------------------------------------
# Planning
# ---------------------------------------------------------------------------------------------------


def parse_cases(text: str) -> tuple[str, ...]:
    """``"A,B,D"`` -> ``("A", "B", "D")``; an unknown case raises :class:`EvaluateError`."""
    cases = tuple(c.strip() for c in text.split(",") if c.strip())
    bad = [c for c in cases if c not in EVALUATE_CASES]
    if bad or not cases:
        raise EvaluateError(f"unknown case(s) {', '.join(bad) or '(none given)'}; "
                            f"choose from {','.join(EVALUATE_CASES)}")
    return cases


def parse_seasons(text: str) -> tuple[Season, ...]:
    """``"winter,summer"`` -> ``("winter", "summer")``; an unknown season raises :class:`EvaluateError`."""
    seasons = tuple(s.strip().lower() for s in text.split(",") if s.strip())
    bad = [s for s in seasons if s not in SEASONS]
    if bad or not seasons:
        raise EvaluateError(f"unknown season(s) {', '.join(bad) or '(none given)'}; choose from {','.join(SEASONS)}")
    return tuple(next(known for known in SEASONS if known == s) for s in seasons)


def season_window(season: Season, days_per_season: float | None, year: int = EVALUATION_YEAR) -> tuple[str, float]:
    """The first day and the length [days] of a season's evaluation window: its month, or its first N days."""
    from simulator_bridge.simulation.profiles import season_month

    month = season_month(season)
    month_days = calendar.monthrange(year, month)[1]
    days = float(month_days) if days_per_season is None else float(days_per_season)
    if not 0 < days <= month_days:
        raise EvaluateError(f"--days-per-season {days:g} must be in (0, {month_days}] for {season}")
    return dt.date(year, month, 1).isoformat(), days


def plan_runs(config: EvaluateConfig) -> list[RunSpec]:
    """Every run of the evaluation, in a stable order (season, case, bandwidth, variant)."""
    specs = []
    variants: tuple[Variant, ...] = ROBUSTNESS_VARIANTS if config.robustness else ("nominal",)
    for season in config.seasons:
        start, days = season_window(season, config.days_per_season)
        for case in config.cases:
            bands = config.bandwidths_v120 if case in ("C", "D") else config.bandwidths_v120[:1]
            for band in bands:
                for variant in variants:
                    specs.append(RunSpec(case=case, season=season, bandwidth_v120=band, variant=variant,
                                         start=start, days=days))
    return specs


# ---------------------------------------------------------------------------------------------------
# Model error: a derived device map
# ---------------------------------------------------------------------------------------------------

_NEW_LINE = re.compile(r"^\s*new\s+line\.(\S+)\s.*?\blength\s*=\s*([0-9.eE+-]+)", re.IGNORECASE | re.MULTILINE)
_NEW_LOAD = re.compile(r"^\s*new\s+load\.(\S+)\s.*?\bkw\s*=\s*([0-9.eE+-]+)", re.IGNORECASE | re.MULTILINE)


def perturbation_commands(dss_text: str, *, pct: float, seed: int) -> list[str]:
    """OpenDSS commands that scale every line's length (so R, X, C) and every load's kW by U(1-pct, 1+pct).

    Only ``New Line.x ... length=`` and ``New Load.x ... kW=`` statements that give the value explicitly are
    perturbed (a line without ``length`` keeps its default). Pure: the same text and seed give the same commands.
    """
    rng = np.random.default_rng(seed)
    cmds = []
    for regex, prop in ((_NEW_LINE, "length"), (_NEW_LOAD, "kW")):
        for name, value in regex.findall(dss_text):
            factor = 1.0 + rng.uniform(-pct, pct) / 100.0
            cmds.append(f"{'Line' if prop == 'length' else 'Load'}.{name}.{prop}={float(value) * factor:.6g}")
    return cmds


def perturbed_device_map(dm_path: Path, out_dir: Path, *, pct: float, seed: int) -> Path:
    """Write a device map whose feeder is ``dm_path``'s with line impedances and loads perturbed by ±``pct`` %.

    The derived map keeps the feeder name (so the bus keys match the agent's) and points at the original
    model files; the perturbation is its ``[feeder] extra_commands``, which the engine runs after compiling
    the master file. Its fingerprint differs from the original's on purpose: the agent keeps the model
    trained on the unperturbed feeder.
    """
    from schemas.devicemap import load_device_map

    dm = load_device_map(dm_path)
    folder = dm.master_path.parent
    text = "\n".join(f.read_text(errors="replace") for f in sorted(folder.rglob("*.dss")))
    cmds = perturbation_commands(text, pct=pct, seed=seed)
    if not cmds:
        raise EvaluateError(f"{dm_path}: found no 'New Line ... length=' or 'New Load ... kW=' to perturb")
    f = dm.feeder
    lines = ["[feeder]"]
    fields = {"name": f.name, "master": str(dm.master_path), "head_element": f.head_element,
              "source_bus": f.source_bus, "extra_commands": [*f.extra_commands, *cmds],
              "judged_limits_pu": list(f.judged_limits_pu), "optimization_limits_pu": list(f.optimization_limits_pu),
              "control_period_s": f.control_period_s, "step_s": f.step_s, "load_pf": f.load_pf}
    lines += [f"{k} = {json.dumps(v)}" for k, v in fields.items()]
    original = dm_path.read_text()
    rest = re.split(r"^\[feeder\]\s*$", original, maxsplit=1, flags=re.MULTILINE)[1]
    next_table = re.search(r"^\[", rest, flags=re.MULTILINE)
    rest = rest[next_table.start():] if next_table else ""
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "devicemap.toml"
    header = f"# {f.name} with line lengths and load kW x U({1 - pct / 100:g}, {1 + pct / 100:g}), seed {seed}\n"
    path.write_text(header + "\n".join(lines) + "\n\n" + rest)
    load_device_map(path)  # validate what we wrote
    return path


# ---------------------------------------------------------------------------------------------------
# Running
# ---------------------------------------------------------------------------------------------------


def _run_config(spec: RunSpec, config: EvaluateConfig, dm_path: Path, model: Path, out: Path,
                perturbed: Path | None) -> RunConfig:
    case = _BUS_CASES.get(spec.case)
    if case is None:  # the reference case is not a bus run (PreparedEvaluation.tasks runs it apart)
        raise EvaluateError(f"{spec.name}: case {spec.case!r} is not a bus run")
    return RunConfig(
        feeder=str(perturbed if spec.variant == "model-error" else dm_path), model=str(model), days=spec.days,
        start=spec.start, case=case, out=str(out / spec.name), train_seed=config.train_seed,
        year_seed=config.year_seed, cache=config.cache, baseline=False,
        agent=msgspec.structs.replace(config.agent, bandwidth_v120=spec.bandwidth_v120),
        lockstep_timeout_s=config.lockstep_timeout_s,
        progress=False, progress_label=spec.name,
        noise_pmu_pct=0.1 if spec.variant == "noise-pmu" else 0.0,
        noise_scada_pct=1.0 if spec.variant == "noise-scada" else 0.0,
        drop_prob={"drop-1": 0.01, "drop-5": 0.05}.get(spec.variant, 0.0),
        check_model_fingerprint=spec.variant != "model-error", secure=config.secure, ca_dir=config.ca_dir)


ATTEMPTS_FILE = "attempts.txt"  # in a run's folder: one line per start of the run (a failed run is retried once)


def _note_attempt(run_dir: Path) -> None:
    """Append a line to the run folder's attempts file: this run started once more (on which host, which pid)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    stamp = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    with open(run_dir / ATTEMPTS_FILE, "a") as f:
        f.write(f"{stamp} pid {os.getpid()} on {socket.gethostname()}\n")


def _attempts(run_dir: Path) -> int:
    try:
        return len((run_dir / ATTEMPTS_FILE).read_text().splitlines())
    except OSError:
        return 0


def _run_one(spec: RunSpec, run_config: RunConfig) -> RunResult:
    """Task: one run through the real bus (on a Dask worker: its own process, one thread)."""
    from cvvc.launch import run

    _note_attempt(Path(str(run_config.out)))
    s = run(run_config)
    return _result(spec, s)


def _result(spec: RunSpec, s: RunSummary) -> RunResult:
    """A run's result from its summary."""
    return RunResult(spec=spec, metrics=s.metrics, wall_s=s.wall_s, steps=s.steps, decisions=s.decisions,
                     lockstep_misses=s.lockstep_misses, out_dir=s.out_dir, recording=s.recording, soft=s.soft,
                     tolerated=s.tolerated,
                     holds=s.holds, reasons=dict(s.reasons), decision_ms=dict(s.decision_ms),
                     live=s.live)


def _run_reference(spec: RunSpec, config: EvaluateConfig, dm_path: Path, out: Path) -> RunResult:
    """Task: the ``opendss`` reference case (OpenDSS's own control loop, no bus) on the spec's window."""
    from cvvc.reference import run_reference
    from schemas.cache import profiles_dir

    _note_attempt(out / spec.name)
    s = run_reference(ReferenceConfig(feeder=str(dm_path), start=spec.start, days=spec.days,
                                      year_seed=config.year_seed, cache=str(profiles_dir(config.cache)),
                                      out=str(out / spec.name), step_s=config.reference_step_s))
    return RunResult(spec=spec, metrics=s.metrics, wall_s=s.wall_s, steps=s.steps, decisions=0, lockstep_misses=0,
                     out_dir=s.out_dir, recording=None)


def _finished(spec: RunSpec, run_dir: Path) -> RunResult | None:
    """The result of a run already finished in ``run_dir`` with the same case and window (``--resume``)."""
    path = run_dir / "summary.json"
    if not path.is_file():
        return None
    try:
        s = msgspec.json.decode(path.read_bytes(), type=RunSummary)
    except (OSError, msgspec.DecodeError, msgspec.ValidationError) as e:
        _log(f"{spec.name}: {path} is not a summary of this version ({e}): running it again")
        return None
    if (s.case, s.start[:10], s.days) != (spec.case, spec.start, spec.days):
        return None
    return _result(spec, s)


@dataclass
class PreparedEvaluation:
    """An evaluation ready to run: the feeder, model and year profiles built once, the runs still to do.

    Filled as its runs finish (:meth:`record`); :meth:`snapshot` is the :class:`Evaluation` so far.
    """

    config: EvaluateConfig
    dm_path: Path
    model: Path
    feeder_id: str
    control_period_s: int
    perturbed: Path | None
    specs: list[RunSpec]
    todo: list[RunSpec]
    t0: float
    label: str = ""  # prefixes the log lines (a campaign names the feeder and variant)
    results: list[RunResult] = field(default_factory=list)
    failures: list[RunFailure] = field(default_factory=list)

    @property
    def out(self) -> Path:
        """The evaluation's output folder (``config.out``)."""
        return Path(self.config.out)

    def tasks(self) -> list[Task]:
        """One task per run still to do, case A first (:func:`longest_first`)."""
        tasks = []
        for spec in longest_first(self.todo):
            label, tag = f"{self.label}{spec.name}", (self, spec)
            if spec.case == REFERENCE_CASE:
                tasks.append(Task(label=label, fn=_run_reference, args=(spec, self.config, self.dm_path, self.out),
                                  tag=tag))
            else:
                rc = _run_config(spec, self.config, self.dm_path, self.model, self.out, self.perturbed)
                tasks.append(Task(label=label, fn=_run_one, args=(spec, rc), tag=tag))
        return tasks

    def record(self, spec: RunSpec, outcome: Outcome, count: str = "") -> None:
        """Keep a finished run's result or failure, log one line, and rewrite results.json/results.md."""
        run_dir = self.out / spec.name
        if outcome.error is None:
            r: RunResult = msgspec.structs.replace(outcome.result, attempts=max(1, _attempts(run_dir)))
            self.results.append(r)
            mt = r.metrics
            missed = (f"; {r.lockstep_misses} LOCKSTEP MISSES: steps under local control, not the method's figures"
                      if r.lockstep_misses else "")
            soft = f", soft {r.soft} of {r.decisions}" if r.decisions else ""
            _log(f"{count}{self.label}{spec.name}: NVV {mt.nvv}, NTC {mt.ntc}, total cost {mt.total_cost:.1f}{soft} "
                 f"({r.wall_s:.0f} s){missed}")
        else:
            e = outcome.error
            error = str(e) if isinstance(e, CvvcError) else f"{type(e).__name__}: {e}"
            tries = _attempts(run_dir)
            self.failures.append(RunFailure(spec=spec, error=error, out_dir=str(run_dir), attempts=tries))
            _log(f"{count}{self.label}{spec.name}: FAILED after {tries} attempt(s) (logs in {run_dir}): {error}")
        _write(self.out, self.snapshot())

    def snapshot(self) -> Evaluation:
        """The evaluation so far: the finished runs and the failures in plan order, the wall time since prepared."""
        order = {s.name: i for i, s in enumerate(self.specs)}
        return Evaluation(config=self.config, feeder_id=self.feeder_id, feeder=str(self.dm_path),
                          model=str(self.model), control_period_s=self.control_period_s,
                          runs=tuple(sorted(self.results, key=lambda r: order[r.spec.name])),
                          wall_s=round(time.monotonic() - self.t0, 1),
                          failures=tuple(sorted(self.failures, key=lambda f: order[f.spec.name])))


def _write(out: Path, ev: Evaluation) -> None:
    """Write ``results.json`` and ``results.md``; :class:`EvaluateError` when they cannot be written (a full disk):
    the runs already finished stay in their folders for ``--resume``.
    """
    path = out / "results.json"
    try:
        path.write_bytes(msgspec.json.format(msgspec.json.encode(ev), indent=2))
        path = out / "results.md"
        path.write_text(render_results_md(ev))
    except OSError as e:
        raise EvaluateError(f"cannot write {path}: {e.strerror or e}; the {len(ev.runs)} finished run(s) are kept "
                            f"in their folders under {out}; free the space, then rerun with --resume") from e


def _check(config: EvaluateConfig) -> None:
    for c in config.cases:
        if c not in EVALUATE_CASES:
            raise EvaluateError(f"unknown case {c!r}; choose from {','.join(EVALUATE_CASES)}")
    if not (config.reference_step_s > 0 and abs(60.0 / config.reference_step_s
                                                 - round(60.0 / config.reference_step_s)) < 1e-9):
        raise EvaluateError(f"--reference-step-s {config.reference_step_s:g} must divide 60 s")
    if config.robustness and REFERENCE_CASE in config.cases:
        raise EvaluateError(f"--robustness studies case D under noise and model error; the {REFERENCE_CASE} case "
                            "has no bus to add them to: run it without --robustness")
    for s in config.seasons:
        if s not in SEASONS:
            raise EvaluateError(f"unknown season {s!r}; choose from {','.join(SEASONS)}")
    if config.jobs < 1:
        raise EvaluateError(f"--jobs {config.jobs} must be at least 1")
    if not (config.lockstep_timeout_s > 0 and math.isfinite(config.lockstep_timeout_s)):
        raise EvaluateError(f"--lockstep-timeout-s {config.lockstep_timeout_s:g} must be a positive number of seconds")
    if config.scheduler is not None:  # before any training: a wrong address is told at once
        try:
            check_scheduler(config.scheduler)
        except ClusterError as e:
            raise EvaluateError(str(e)) from e


def _ensure_year_profiles(dm_paths: list[Path], config: EvaluateConfig) -> None:
    """The evaluation year's profiles of each map, made once here into the shared cache (the runs read them)."""
    from schemas.cache import profiles_dir
    from schemas.devicemap import load_device_map
    from simulator_bridge.opendss.engine import FeederEngine
    from simulator_bridge.simulation.profiles import feeder_profiles, profiles_cache_path

    cache = profiles_dir(config.cache)
    for path in dm_paths:
        dm = load_device_map(path)
        if profiles_cache_path(dm, config.year_seed, cache).is_file():
            continue
        engine = FeederEngine(dm)
        try:
            feeder_profiles(dm, engine, seed=config.year_seed, cache_dir=cache)
        finally:
            engine.close()


def prepare_evaluation(config: EvaluateConfig, label: str = "") -> PreparedEvaluation:
    """Check ``config``, plan its runs, and build once (in this process) what every run needs.

    The device map, the trained model (cached) and the evaluation year's profiles (cached) are made here, so
    parallel runs never train or generate the same thing twice; the runs get them by path. With ``resume``, runs
    already finished in the output folder are kept and not planned again.
    """
    from cvvc.launch import prepare_feeder_and_model
    from schemas.devicemap import load_device_map

    _check(config)
    specs = plan_runs(config)
    t0 = time.monotonic()
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    # no model when no case runs an agent (none, local, opendss: e.g. epri-ckt5, which has no regulator to train for)
    agent_case = any(c not in ("none", "local", REFERENCE_CASE) for c in config.cases)
    dm_path, model = prepare_feeder_and_model(RunConfig(feeder=config.feeder, model=config.model,
                                                        train_seed=config.train_seed, cache=config.cache,
                                                        case="D" if agent_case else "none",
                                                        progress=config.progress))
    dm = load_device_map(dm_path)
    perturbed = None
    if config.robustness:
        perturbed = perturbed_device_map(dm_path, out / "model-error-feeder", pct=config.perturbation_pct,
                                         seed=config.perturbation_seed)
    _ensure_year_profiles([dm_path] + ([perturbed] if perturbed else []), config)
    prep = PreparedEvaluation(config=config, dm_path=dm_path, model=model, feeder_id=dm.feeder.name,
                              control_period_s=dm.feeder.control_period_s, perturbed=perturbed, specs=specs,
                              todo=[], t0=t0, label=label)
    for spec in specs:
        done = _finished(spec, out / spec.name) if config.resume else None
        if done is not None:
            _log(f"{label}{spec.name}: reusing the finished run in {out / spec.name} (--resume)")
            prep.results.append(done)
        else:
            (out / spec.name / ATTEMPTS_FILE).unlink(missing_ok=True)  # count this evaluation's attempts only
            prep.todo.append(spec)
    return prep


def run_prepared(preps: list[PreparedEvaluation], config: EvaluateConfig) -> None:
    """Run every prepared evaluation's runs as tasks of one Dask cluster (``config.jobs``, ``config.scheduler``).

    Case A's runs start first over all evaluations; each finished run is logged and written at once.
    """
    tasks = sorted((t for p in preps for t in p.tasks()), key=lambda t: t.tag[1].case != "A")
    if not tasks:
        return
    where = (f"the Dask cluster at {config.scheduler}" if config.scheduler
             else f"a local Dask cluster of {config.jobs} worker(s)")
    _log(f"{len(tasks)} run(s) on {where}")
    done = 0
    # one bar over every run, in simulated minutes (a month's run weighs 30 days' runs), time left from the runs done;
    # the runs' own bars are off (RunConfig.progress): workers of several runs would draw over each other
    bar = progress_bar(sum(round(t.tag[1].days * 1440) for t in tasks), enabled=config.progress,
                       desc="evaluation (simulated)", unit="min")

    def on_done(outcome: Outcome) -> None:
        nonlocal done
        done += 1
        prep, spec = outcome.task.tag
        with bar.external_write_mode(file=sys.stderr):  # the run's line above the bar, not through it
            prep.record(spec, outcome, f"[{done}/{len(tasks)}] ")
        bar.update(round(spec.days * 1440))

    try:
        with dask_client(config.jobs, config.scheduler) as client:
            run_tasks(client, tasks, on_done)
    except ClusterError as e:
        raise EvaluateError(str(e)) from e
    finally:
        bar.close()


def evaluate(config: EvaluateConfig) -> Evaluation:
    """Run every planned run (see the module docstring) and write ``results.json`` and ``results.md``.

    A run that fails (after one retry) does not stop the others: the results of the finished runs are written
    (after every run, so a long evaluation can be watched), the failures listed, and then :class:`EvaluateError`
    raised.
    """
    prep = prepare_evaluation(config)
    _log(f"{len(prep.specs)} run(s) of {prep.feeder_id}; output in {prep.out}")
    run_prepared([prep], config)
    return finish(prep)


def write_results(prep: PreparedEvaluation) -> Evaluation:
    """The evaluation as it stands, written to ``results.json`` and ``results.md`` in its folder."""
    evaluation = prep.snapshot()
    _write(prep.out, evaluation)
    return evaluation


def finish(prep: PreparedEvaluation) -> Evaluation:
    """Write the evaluation's final results; :class:`EvaluateError` if a run failed."""
    evaluation = write_results(prep)
    if evaluation.failures:
        names = ", ".join(f.spec.name for f in evaluation.failures)
        raise EvaluateError(f"{len(evaluation.failures)} of {len(prep.specs)} run(s) failed ({names}); the others "
                            f"are in {prep.out / 'results.md'}; see each failed run's folder for its logs, fix, "
                            "then rerun with --resume to run only what is missing")
    return evaluation


def _log(msg: str) -> None:
    try:
        print(f"[cvvc evaluate] {msg}", file=sys.stderr, flush=True)
    except OSError:  # stderr on a full disk: the line is lost, results.json (or the error it raises) still tells
        pass
