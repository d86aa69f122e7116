"""``cvvc evaluate``: the paper's evaluation (section IV), reproduced through the real bus, and a robustness study.

Each (case, season, bandwidth) is one :func:`cvvc.launch.run`: bridge, agent and recorder as separate processes in
lockstep, one month per season at 1-minute resolution (paper IV: January, April, July, October, see
``simulator_bridge.profiles.season_month``), on the evaluation year (``year_seed``, 2 by default) while the model
was trained on another year (``train_seed``, 1). Independent runs go to a process pool (spawn context).

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
import concurrent.futures as cf
import datetime as dt
import json
import multiprocessing
import re
import sys
import time
from pathlib import Path
from typing import Literal

import msgspec
import numpy as np

from cvvc.launch import CASES, Case, LaunchError, RunConfig, RunSummary
from cvvc.reference import REFERENCE_CASE, ReferenceConfig
from schemas import messages as m
from schemas.errors import CvvcError

__all__ = [
    "EVALUATE_CASES",
    "EVALUATION_YEAR",
    "ROBUSTNESS_VARIANTS",
    "SEASONS",
    "EvaluateConfig",
    "EvaluateError",
    "Evaluation",
    "RunFailure",
    "RunResult",
    "RunSpec",
    "evaluate",
    "parse_cases",
    "parse_seasons",
    "perturbed_device_map",
    "render_results_md",
    "season_window",
]

#: Every case ``--cases`` accepts: the bus runs (``cvvc.launch.CASES``) and OpenDSS's own loop (``opendss``).
EVALUATE_CASES: tuple[str, ...] = (*CASES, REFERENCE_CASE)
_BUS_CASES: dict[str, Case] = {c: c for c in CASES}  # the cases run through the bus (cvvc run)
Season = Literal["winter", "spring", "summer", "fall"]
SEASONS: tuple[Season, ...] = ("winter", "spring", "summer", "fall")
EVALUATION_YEAR = 2023  # the calendar year of the generated profiles (``make_profiles`` default)
Variant = Literal["nominal", "noise-pmu", "noise-scada", "drop-1", "drop-5", "model-error"]
ROBUSTNESS_VARIANTS: tuple[Variant, ...] = ("nominal", "noise-pmu", "noise-scada", "drop-1", "drop-5", "model-error")
_VARIANT_LABEL = {
    "nominal": "nominal (no noise, no drops, exact model)",
    "noise-pmu": "PMU-class noise 0.1 % (feeder head)",
    "noise-scada": "SCADA-class noise 1 % (PV plants, regulators)",
    "drop-1": "1 % of measurement frames dropped",
    "drop-5": "5 % of measurement frames dropped",
    "model-error": "model error: line impedances and loads x U(0.9, 1.1)",
}


class EvaluateError(LaunchError):
    """An evaluation that cannot be planned or whose run failed; the message says which and what to do."""


class EvaluateConfig(msgspec.Struct, frozen=True, kw_only=True):
    """Everything ``cvvc evaluate`` needs; built from the command line."""

    feeder: str | None = None  # None: the embedded rural feeder
    model: str | None = None
    cases: tuple[str, ...] = CASES
    seasons: tuple[Season, ...] = SEASONS
    bandwidths_v120: tuple[float, ...] = (4.0,)
    year_seed: int = 2
    train_seed: int = 1
    days_per_season: float | None = None  # None: the whole month
    jobs: int = 1
    out: str = "runs/evaluate"
    cache: str | None = None  # cache root; None: schemas.cache.default_cache_root()
    robustness: bool = False
    pv_margin_window_s: float | None = None  # the agent's PV variability margin window; None: its default, 0: off
    setpoint_hold: bool = False  # the agent's opt-in set-point hold (cases C/D)
    control_banks: bool = False  # the agent's opt-in capacitor-bank decisions
    resume: bool = False  # reuse a run whose folder already holds a finished summary.json of the same spec
    perturbation_pct: float = 10.0
    perturbation_seed: int = 7
    progress: bool = True
    reference_step_s: float = 5.0  # OpenDSS's time step in the ``opendss`` case [s] (docs/simulation.md)


def longest_first(specs: list[RunSpec]) -> list[RunSpec]:
    """The order runs are started in: case A first, so that with ``--jobs`` > 1 the last run to finish is a short
    one (case A asks the bridge's oracle at every decision and takes about 3x as long as B-D, docs/results.md);
    the rest keep their order.
    """
    return sorted(specs, key=lambda s: s.case != "A")


class RunSpec(msgspec.Struct, frozen=True, kw_only=True):
    """One run of the evaluation: a case on a season's window, with a bandwidth and a robustness variant."""

    case: str
    season: Season
    bandwidth_v120: float
    variant: Variant = "nominal"
    start: str  # YYYY-MM-DD, the first day of the season's month
    days: float

    @property
    def name(self) -> str:
        """The run's folder name: season, case, the band on the 120 V base [V] in cases C/D, and the variant."""
        band = f"-bw{self.bandwidth_v120:g}" if self.case in ("C", "D") else ""
        var = "" if self.variant == "nominal" else f"-{self.variant}"
        return f"{self.season}-{self.case}{band}{var}"


class RunResult(msgspec.Struct, frozen=True, kw_only=True):
    """What one run measured: its spec, the final metrics frame (paper IV.F) and the run's summary."""

    spec: RunSpec
    metrics: m.MetricsFrame  # the bridge's final metrics frame
    wall_s: float
    steps: int
    decisions: int
    lockstep_misses: int
    out_dir: str
    recording: str | None


class RunFailure(msgspec.Struct, frozen=True, kw_only=True):
    """A run that did not finish: its spec and why (the run folder keeps the processes' logs)."""

    spec: RunSpec
    error: str
    out_dir: str


class Evaluation(msgspec.Struct, frozen=True, kw_only=True):
    """A whole evaluation: its configuration, every run's result, the failed runs and the total wall time."""

    config: EvaluateConfig
    feeder_id: str
    feeder: str
    model: str
    control_period_s: int
    runs: tuple[RunResult, ...]
    wall_s: float
    failures: tuple[RunFailure, ...] = ()


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
    from simulator_bridge.profiles import season_month

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
    if case is None:  # the reference case is not a bus run (_submit runs it apart)
        raise EvaluateError(f"{spec.name}: case {spec.case!r} is not a bus run")
    return RunConfig(
        feeder=str(perturbed if spec.variant == "model-error" else dm_path), model=str(model), days=spec.days,
        start=spec.start, case=case, out=str(out / spec.name), train_seed=config.train_seed,
        year_seed=config.year_seed, bandwidth_v120=spec.bandwidth_v120, cache=config.cache, baseline=False,
        pv_margin_window_s=config.pv_margin_window_s, setpoint_hold=config.setpoint_hold,
        control_banks=config.control_banks,
        progress=config.progress, progress_label=spec.name,
        noise_pmu_pct=0.1 if spec.variant == "noise-pmu" else 0.0,
        noise_scada_pct=1.0 if spec.variant == "noise-scada" else 0.0,
        drop_prob={"drop-1": 0.01, "drop-5": 0.05}.get(spec.variant, 0.0),
        check_model_fingerprint=spec.variant != "model-error")


def _run_one(spec: RunSpec, run_config: RunConfig) -> RunResult:
    """Worker: one run through the real bus (a fresh spawned interpreter runs this)."""
    from cvvc.launch import run

    s = run(run_config)
    return RunResult(spec=spec, metrics=s.metrics, wall_s=s.wall_s, steps=s.steps, decisions=s.decisions,
                     lockstep_misses=s.lockstep_misses, out_dir=s.out_dir, recording=s.recording)


def _run_reference(spec: RunSpec, config: EvaluateConfig, dm_path: Path, out: Path) -> RunResult:
    """Worker: the ``opendss`` reference case (OpenDSS's own control loop, no bus) on the spec's window."""
    from cvvc.reference import run_reference
    from schemas.cache import profiles_dir

    s = run_reference(ReferenceConfig(feeder=str(dm_path), start=spec.start, days=spec.days,
                                      year_seed=config.year_seed, cache=str(profiles_dir(config.cache)),
                                      out=str(out / spec.name), step_s=config.reference_step_s))
    return RunResult(spec=spec, metrics=s.metrics, wall_s=s.wall_s, steps=s.steps, decisions=0, lockstep_misses=0,
                     out_dir=s.out_dir, recording=None)


def _submit(pool: cf.Executor, spec: RunSpec, config: EvaluateConfig, dm_path: Path, model: Path, out: Path,
            perturbed: Path | None) -> cf.Future:
    if spec.case == REFERENCE_CASE:
        return pool.submit(_run_reference, spec, config, dm_path, out)
    return pool.submit(_run_one, spec, _run_config(spec, config, dm_path, model, out, perturbed))


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
    return RunResult(spec=spec, metrics=s.metrics, wall_s=s.wall_s, steps=s.steps, decisions=s.decisions,
                     lockstep_misses=s.lockstep_misses, out_dir=s.out_dir, recording=s.recording)


def _write(out: Path, ev: Evaluation) -> None:
    (out / "results.json").write_bytes(msgspec.json.format(msgspec.json.encode(ev), indent=2))
    (out / "results.md").write_text(render_results_md(ev))


def evaluate(config: EvaluateConfig) -> Evaluation:
    """Run every planned run (see the module docstring) and write ``results.json`` and ``results.md``.

    A run that fails does not stop the others: the results of the finished runs are written (after every
    run, so a long evaluation can be watched), the failures listed, and then :class:`EvaluateError` raised.
    """
    from cvvc.launch import prepare_feeder_and_model
    from schemas.devicemap import load_device_map

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
    specs = plan_runs(config)
    t0 = time.monotonic()
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    # the feeder and model once, here, so parallel runs never train the same model twice; none when no case runs
    # an agent (none, local, opendss: e.g. epri-ckt5, which has no regulator to train for)
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
    _log(f"{len(specs)} run(s) of {dm.feeder.name}, {config.jobs} at a time; output in {out}")
    results: list[RunResult] = []
    failures: list[RunFailure] = []
    order = {s.name: i for i, s in enumerate(specs)}

    def snapshot() -> Evaluation:
        return Evaluation(config=config, feeder_id=dm.feeder.name, feeder=str(dm_path), model=str(model),
                          control_period_s=dm.feeder.control_period_s,
                          runs=tuple(sorted(results, key=lambda r: order[r.spec.name])),
                          wall_s=round(time.monotonic() - t0, 1),
                          failures=tuple(sorted(failures, key=lambda f: order[f.spec.name])))

    todo = []
    for spec in specs:
        done = _finished(spec, out / spec.name) if config.resume else None
        if done is not None:
            _log(f"{spec.name}: reusing the finished run in {out / spec.name} (--resume)")
            results.append(done)
        else:
            todo.append(spec)
    todo = longest_first(todo)
    ctx = multiprocessing.get_context("spawn")
    with cf.ProcessPoolExecutor(max_workers=config.jobs, mp_context=ctx) as pool:
        futures = {_submit(pool, spec, config, dm_path, model, out, perturbed): spec for spec in todo}
        try:
            for fut in cf.as_completed(futures):
                spec = futures[fut]
                try:
                    r = fut.result()
                except CvvcError as e:
                    _log(f"{spec.name}: FAILED (logs in {out / spec.name}): {e}")
                    failures.append(RunFailure(spec=spec, error=str(e), out_dir=str(out / spec.name)))
                else:
                    mt = r.metrics
                    _log(f"{spec.name}: NVV {mt.nvv}, NTC {mt.ntc}, total cost {mt.total_cost:.1f} "
                         f"({r.wall_s:.0f} s)")
                    results.append(r)
                _write(out, snapshot())
        except BaseException:
            for f in futures:
                f.cancel()
            raise
    evaluation = snapshot()
    _write(out, evaluation)
    if failures:
        names = ", ".join(f.spec.name for f in evaluation.failures)
        raise EvaluateError(f"{len(failures)} of {len(specs)} run(s) failed ({names}); the others are in "
                            f"{out / 'results.md'}; see each failed run's folder for its logs, fix, then rerun "
                            "with --resume to run only what is missing")
    return evaluation


def _log(msg: str) -> None:
    print(f"[cvvc evaluate] {msg}", file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------------------------------
# Tables
# ---------------------------------------------------------------------------------------------------


def kvarh_from_mvar_intervals(q_mvar_intervals: float, control_period_s: float) -> float:
    """Reactive energy [kvarh] from the metrics' ``sum |Q| [Mvar] x control intervals`` (paper Table IV unit)."""
    return q_mvar_intervals * 1000.0 * control_period_s / 3600.0


def _row_label(r: RunResult, robust: bool, bands: bool) -> list[str]:
    case = r.spec.case
    if bands and case in ("C", "D"):
        case = f"{case} ({r.spec.bandwidth_v120:g} V)"
    cells = [r.spec.season, case]
    if robust:
        cells.append(_VARIANT_LABEL[r.spec.variant])
    return cells


def render_results_md(ev: Evaluation) -> str:
    """The evaluation as markdown: Table II/III layout, Table IV (PV reactive energy), Table V (tap changes)."""
    robust = ev.config.robustness
    bands = len(ev.config.bandwidths_v120) > 1
    head = ["Season", "Case"] + (["Variant"] if robust else [])
    days = sorted({r.spec.days for r in ev.runs})
    cap_ids = sorted({k for r in ev.runs for k in r.metrics.cap_switches_per_bank})
    cap_head = ["Cap sw", "Cap Cost"] if cap_ids else []  # feeders with capacitor banks in the device map
    lines = [f"# cvvc evaluate: {ev.feeder_id}", "",
             f"Evaluation year seed {ev.config.year_seed}, model trained on year seed {ev.config.train_seed}; "
             f"{', '.join(f'{d:g}' for d in days)} day(s) per season from the first of the season's month; "
             f"{len(ev.runs)} runs in {ev.wall_s:.0f} s wall time (jobs={ev.config.jobs})."
             + (f" Case {REFERENCE_CASE}: OpenDSS's own control loop at {ev.config.reference_step_s:g} s steps on "
                "the same loads and PV (unity power factor), not through the bus."
                if any(r.spec.case == REFERENCE_CASE for r in ev.runs) else ""), "",
             "## Voltage violations and costs (paper Tables II/III layout)", "",
             "| " + " | ".join(head + ["MVVM [pu]", "NVV", "NTC"] + cap_head[:1] + ["Q Cost", "T Cost"] + cap_head[1:]
                               + ["Total", "wall [s]"]) + " |",
             "|" + "---|" * (len(head) + 7 + len(cap_head))]
    for r in ev.runs:
        mt = r.metrics
        cap_sw = [str(mt.cap_switches)] if cap_ids else []
        cap_cost = [f"{mt.cap_cost:.2f}"] if cap_ids else []
        lines.append("| " + " | ".join(_row_label(r, robust, bands) + [
            f"{mt.mvvm_pu:.4f}", str(mt.nvv), str(mt.ntc)] + cap_sw + [f"{mt.q_cost:.1f}",
            f"{mt.t_cost:.2f}"] + cap_cost + [f"{mt.total_cost:.1f}", f"{r.wall_s:.0f}"]) + " |")
    pv_ids = sorted({k for r in ev.runs for k in r.metrics.q_mvar_intervals})
    lines += ["", "## Reactive energy per PV plant (paper Table IV)", "",
              f"Sum of |Q| over the window in Mvar x control intervals ({ev.control_period_s} s), and in kvarh.", "",
              "| " + " | ".join(head + [f"{p} [Mvar·int]" for p in pv_ids] + [f"{p} [kvarh]" for p in pv_ids]) + " |",
              "|" + "---|" * (len(head) + 2 * len(pv_ids))]
    for r in ev.runs:
        q = r.metrics.q_mvar_intervals
        vals = [float(q.get(p, 0.0)) for p in pv_ids]
        lines.append("| " + " | ".join(_row_label(r, robust, bands) + [f"{v:.1f}" for v in vals] + [
            f"{kvarh_from_mvar_intervals(v, ev.control_period_s):.0f}" for v in vals]) + " |")
    reg_ids = sorted({k for r in ev.runs for k in r.metrics.taps_changes})
    lines += ["", "## Tap changes per regulator (paper Table V)", "",
              "| " + " | ".join(head + reg_ids + ["total"]) + " |", "|" + "---|" * (len(head) + len(reg_ids) + 1)]
    for r in ev.runs:
        t = r.metrics.taps_changes
        lines.append("| " + " | ".join(_row_label(r, robust, bands) + [str(t.get(g, 0)) for g in reg_ids]
                                       + [str(r.metrics.ntc)]) + " |")
    if cap_ids:
        lines += ["", "## Capacitor switchings per bank", "",
                  "Switching operations (one per step of a bank opened or closed), local control and commands.", "",
                  "| " + " | ".join(head + cap_ids + ["total"]) + " |", "|" + "---|" * (len(head) + len(cap_ids) + 1)]
        for r in ev.runs:
            sw = r.metrics.cap_switches_per_bank
            lines.append("| " + " | ".join(_row_label(r, robust, bands) + [str(sw.get(c, 0)) for c in cap_ids]
                                           + [str(r.metrics.cap_switches)]) + " |")
    if ev.failures:
        lines += ["", "## Failed runs", ""]
        lines += [f"- {f.spec.name}: {f.error.splitlines()[0] if f.error else '?'} (logs in `{f.out_dir}`)"
                  for f in ev.failures]
    lines.append("")
    return "\n".join(lines)
