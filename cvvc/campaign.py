"""``cvvc evaluate --campaign FILE.toml``: feeders x cases x seasons x variants, as tasks of one Dask cluster.

The campaign file (docs/results.md, "Campaigns")::

    feeders = ["feeders/ieee13.toml", "rural"]  # device maps (relative to this file) or folders; "rural": embedded
    cases = ["D", "none"]
    seasons = ["winter", "summer"]
    days_per_season = 7                         # optional; default: the whole month
    year_seed = 2                               # optional (default 2); train_seed likewise (default 1)

    [variants.base]                             # a variant: named options of the evaluation; {} = the defaults

    [variants.bw2]
    bandwidths_v120 = [2.0]

Each (feeder, variant) is one evaluation (:func:`cvvc.evaluate.prepare_evaluation`: feeder, model and year
profiles built once, here) with its folder ``OUT/<feeder>/<variant>/`` holding ``results.md``, ``results.json``
and the run folders; every run of every evaluation is a task of the same cluster. ``OUT/campaign.csv`` is tidy:
one row per run with feeder, variant, case, season, bandwidth, status (``ok`` or ``failed``, with the error and
the number of attempts) and every metric (a per-device metric is one JSON object cell). ``OUT/goals.md`` judges
every agent run against case A and no control of its season (``cvvc.goals``).
"""

from __future__ import annotations

import csv
import io
import sys
import time
from pathlib import Path
from typing import Annotated

import msgspec

from cvvc.case import AGENT_FLAGS
from cvvc.evaluate import (
    EvaluateConfig,
    EvaluateError,
    Evaluation,
    PreparedEvaluation,
    Season,
    parse_cases,
    plan_runs,
    prepare_evaluation,
    run_prepared,
    write_results,
)
from cvvc.goals import render_campaign_goals
from schemas import messages as m
from schemas.errors import CvvcError
from schemas.settings import AgentOptions, RunCase
from simulator_bridge.simulation.live_accuracy import LiveAccuracy

__all__ = ["EMBEDDED_FEEDER", "Campaign", "CampaignResult", "Variant", "campaign_rows", "load_campaign",
           "run_campaign", "variant_agent"]

EMBEDDED_FEEDER = "rural"  # a campaign's name for the embedded rural feeder (``--feeder`` left out)
_Name = Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9_.-]+$", max_length=64)]


class Variant(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Options of one variant: each overrides the evaluation's default (``cvvc evaluate``'s flag of that name).

    ``[variants.NAME.agent]`` is a case file's ``[agent]`` section (``schemas.settings.AgentOptions``: any of its
    keys, the rest their defaults); ``pv_margin_window_s``, ``setpoint_hold`` and ``control_banks`` written at the
    variant's level are the same settings (files written before the section existed), and an ``[agent]``
    ``bandwidth_v120`` is the variant's one bandwidth when ``bandwidths_v120`` is left out.
    """

    bandwidths_v120: tuple[float, ...] | None = None  # --bandwidth-v [V on the 120 V base]
    agent: AgentOptions | None = None  # [variants.NAME.agent]: the agent's options
    pv_margin_window_s: float | None = None  # --pv-margin-window-s [s]
    setpoint_hold: bool | None = None  # --setpoint-hold
    control_banks: bool | None = None  # --control-banks
    reference_step_s: float | None = None  # --reference-step-s [s]
    model: str | None = None  # --model: a model file (relative to the campaign file); default: trained and cached


class Campaign(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A campaign file: every feeder x case x season x variant is one run."""

    feeders: Annotated[list[str], msgspec.Meta(min_length=1)]
    cases: Annotated[list[str], msgspec.Meta(min_length=1)]
    seasons: Annotated[list[Season], msgspec.Meta(min_length=1)]
    days_per_season: Annotated[float, msgspec.Meta(gt=0)] | None = None
    year_seed: int = RunCase().window.year_seed
    train_seed: int = RunCase().feeder.train_seed
    variants: dict[_Name, Variant] = msgspec.field(default_factory=lambda: {"base": Variant()})


class CampaignResult(msgspec.Struct, frozen=True, kw_only=True):
    """A finished campaign: one evaluation per (feeder, variant) and the tidy table's path."""

    evaluations: dict[str, Evaluation]  # by "<feeder>/<variant>"
    csv: str
    wall_s: float


def load_campaign(path: str | Path) -> Campaign:
    """Read and check a campaign file; a bad one raises :class:`EvaluateError` naming the file and the field."""
    try:
        campaign = msgspec.toml.decode(Path(path).read_bytes(), type=Campaign)
    except OSError as e:
        raise EvaluateError(f"campaign file {path}: {e.strerror or e}") from e
    except (msgspec.DecodeError, msgspec.ValidationError) as e:
        raise EvaluateError(f"campaign file {path}: {e}") from e
    parse_cases(",".join(campaign.cases))  # unknown cases: the CLI's message
    if not campaign.variants:
        raise EvaluateError(f"campaign file {path}: [variants] is empty; leave it out for one default variant")
    return campaign


def variant_agent(variant: Variant, name: str = "") -> AgentOptions:
    """The agent options of a variant: its ``[agent]`` section with the variant-level agent keys laid over it;
    ``EvaluateError`` when the two say different things.
    """
    agent = variant.agent or AgentOptions()
    for key in AGENT_FLAGS:
        value = getattr(variant, key)
        if value is None:
            continue
        if variant.agent is not None and getattr(agent, key) != value and \
                getattr(variant.agent, key) != getattr(AgentOptions(), key):
            raise EvaluateError(f"variant {name!r}: {key} is {value} at the variant's level and "
                                f"{getattr(variant.agent, key)} in its [agent] section; keep one")
        agent = msgspec.structs.replace(agent, **{key: value})
    return agent


def _feeder_label(feeder: str) -> str:
    if feeder == EMBEDDED_FEEDER:
        return feeder
    p = Path(feeder)
    return p.name if p.is_dir() or p.suffix != ".toml" else p.stem


def _configs(campaign: Campaign, base: Path, out: Path, *, jobs: int, scheduler: str | None, cache: str | None,
             progress: bool, resume: bool) -> dict[tuple[str, str], EvaluateConfig]:
    """The evaluation of each (feeder label, variant name)."""
    configs = {}
    for feeder in campaign.feeders:
        label = _feeder_label(feeder)
        path = None if feeder == EMBEDDED_FEEDER else str((base / feeder) if not Path(feeder).is_absolute()
                                                         else Path(feeder))
        for name, v in campaign.variants.items():
            if (label, name) in configs:
                raise EvaluateError(f"two feeders of the campaign are both named {label!r}: give them folders or "
                                    "files of different names")
            opts = {k: val for k, val in msgspec.structs.asdict(v).items() if val is not None}
            opts["agent"] = variant_agent(v, name)
            for key in AGENT_FLAGS:
                opts.pop(key, None)
            if "model" in opts:
                opts["model"] = str(base / opts["model"])
            configs[(label, name)] = EvaluateConfig(
                feeder=path, cases=tuple(campaign.cases), seasons=tuple(campaign.seasons),
                days_per_season=campaign.days_per_season, year_seed=campaign.year_seed,
                train_seed=campaign.train_seed, jobs=jobs, scheduler=scheduler, cache=cache, progress=progress,
                resume=resume, out=str(out / label / name), **opts)
    return configs


def run_campaign(path: str | Path, out: str | Path, *, jobs: int = 1, scheduler: str | None = None,
                 cache: str | None = None, progress: bool = True, resume: bool = False) -> CampaignResult:
    """Run a campaign file's every run on one Dask cluster; write each evaluation's tables and ``campaign.csv``.

    An evaluation that cannot be prepared (e.g. a bad device map) is reported with all its runs failed, and the
    others go on; so does a run that fails twice. :class:`EvaluateError` at the end if anything failed.
    """
    t0 = time.monotonic()
    campaign = load_campaign(path)
    out = Path(out)
    configs = _configs(campaign, Path(path).resolve().parent, out, jobs=jobs, scheduler=scheduler, cache=cache,
                       progress=progress, resume=resume)
    preps: dict[str, PreparedEvaluation] = {}
    broken: dict[str, tuple[EvaluateConfig, str]] = {}
    for (feeder, variant), config in configs.items():
        key = f"{feeder}/{variant}"
        try:
            preps[key] = prepare_evaluation(config, label=f"{key}/")
        except CvvcError as e:
            print(f"[cvvc evaluate] {key}: cannot be prepared, its runs are skipped: {e}", file=sys.stderr,
                  flush=True)
            broken[key] = (config, str(e))
    run_prepared(list(preps.values()), next(iter(configs.values())))
    evaluations = {key: write_results(prep) for key, prep in preps.items()}
    out.mkdir(parents=True, exist_ok=True)
    csv_path = out / "campaign.csv"
    for path, text in ((csv_path, campaign_rows(evaluations, broken)), (out / "goals.md",
                                                                          render_campaign_goals(evaluations))):
        try:
            path.write_text(text)
        except OSError as e:
            raise EvaluateError(f"cannot write {path}: {e.strerror or e}; each feeder's results.json under {out} "
                                "holds its runs; free the space, then rerun with --resume") from e
    failed = [f"{k}/{f.spec.name}" for k, ev in evaluations.items() for f in ev.failures]
    failed += [f"{k} ({len(plan_runs(config))} runs: not prepared)" for k, (config, _) in broken.items()]
    if failed:
        n = sum(len(ev.failures) for ev in evaluations.values()) + sum(len(plan_runs(c)) for c, _ in broken.values())
        raise EvaluateError(f"{n} run(s) of the campaign failed ({', '.join(failed)}); the rest are in {csv_path}")
    return CampaignResult(evaluations=evaluations, csv=str(csv_path), wall_s=round(time.monotonic() - t0, 1))


_SPEC = ["feeder", "feeder_id", "variant", "case", "season", "bandwidth_v120", "start", "days"]
_RUN = ["status", "attempts", "error", "wall_s", "steps", "decisions", "lockstep_misses"]
_HEADER = ("t_ns", "seq", "source", "feeder_id", "final", "steps", "start_t_ns")  # the frame's, or already a column
_METRICS = [f.name for f in msgspec.structs.fields(m.MetricsFrame) if f.name not in _HEADER]
_LIVE = ["live_rmse_pu", "live_within_001", "live_bound_miss_rate", "live_promised_miss_rate",
         "live_extremes_captured"]  # the agent's estimates against the truth (empty without an agent)


def _live_cells(live: LiveAccuracy | None) -> list[object]:
    if live is None or not live.samples:
        return [""] * len(_LIVE)
    return [live.rmse_pu, live.within_001, live.bound_miss_rate if live.bound_samples else "",
            "" if live.promised_miss_rate is None else live.promised_miss_rate, live.extremes_captured]


def _cell(value: object) -> object:
    return msgspec.json.encode(value).decode() if isinstance(value, (dict, tuple, list)) else value


def campaign_rows(evaluations: dict[str, Evaluation], broken: dict[str, tuple[EvaluateConfig, str]]) -> str:
    """``campaign.csv``: one row per planned run, finished (``ok``) or ``failed``, evaluation by evaluation."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(_SPEC + _RUN + _METRICS + _LIVE)
    blank = [""] * (len(_RUN) - 3 + len(_METRICS) + len(_LIVE))
    for key, ev in evaluations.items():
        feeder, variant = key.split("/", 1)
        runs = {r.spec.name: r for r in ev.runs}
        failures = {f.spec.name: f for f in ev.failures}
        for s in plan_runs(ev.config):
            head = [feeder, ev.feeder_id, variant, s.case, s.season, s.bandwidth_v120, s.start, s.days]
            if s.name in runs:
                r = runs[s.name]
                mt = msgspec.structs.asdict(r.metrics)
                w.writerow(head + ["ok", r.attempts, "", r.wall_s, r.steps, r.decisions, r.lockstep_misses]
                           + [_cell(mt[n]) for n in _METRICS] + _live_cells(r.live))
            elif s.name in failures:
                f = failures[s.name]
                w.writerow(head + ["failed", f.attempts, f.error.splitlines()[0] if f.error else ""] + blank)
    for key, (config, error) in broken.items():
        feeder, variant = key.split("/", 1)
        for s in plan_runs(config):
            w.writerow([feeder, "", variant, s.case, s.season, s.bandwidth_v120, s.start, s.days, "failed", 0,
                        error.splitlines()[0]] + blank)
    return buf.getvalue()
