"""The types of ``cvvc evaluate``: its configuration, the runs it plans, what each run measured and the whole
evaluation (``results.json``); the tables (``cvvc.evaluate_tables``) and the campaign read them.
"""

from __future__ import annotations

from typing import Literal

import msgspec

from cvvc.launch import CASES
from schemas import messages as m
from schemas.settings import AgentOptions, RunCase
from simulator_bridge.simulation.live_accuracy import LiveAccuracy

__all__ = ["EVALUATION_YEAR", "ROBUSTNESS_VARIANTS", "SEASONS", "EvaluateConfig", "Evaluation", "RunFailure",
           "RunResult", "RunSpec", "Season", "Variant"]

Season = Literal["winter", "spring", "summer", "fall"]
SEASONS: tuple[Season, ...] = ("winter", "spring", "summer", "fall")
_DEFAULT = RunCase()  # the settings tree's defaults (``schemas.settings``)
EVALUATION_YEAR = 2023  # the calendar year of the generated profiles (``make_profiles`` default)
Variant = Literal["nominal", "noise-pmu", "noise-scada", "drop-1", "drop-5", "model-error"]
ROBUSTNESS_VARIANTS: tuple[Variant, ...] = ("nominal", "noise-pmu", "noise-scada", "drop-1", "drop-5", "model-error")


class EvaluateConfig(msgspec.Struct, frozen=True, kw_only=True):
    """Everything ``cvvc evaluate`` needs; built from the command line."""

    feeder: str | None = None  # None: the embedded rural feeder
    model: str | None = None
    cases: tuple[str, ...] = CASES
    seasons: tuple[Season, ...] = SEASONS
    # cases C/D's regulator bands [V on the 120 V base], one run each; empty: the agent's one (``agent.bandwidth_v120``)
    bandwidths_v120: tuple[float, ...] = ()
    year_seed: int = _DEFAULT.window.year_seed
    train_seed: int = _DEFAULT.feeder.train_seed
    days_per_season: float | None = None  # None: the whole month
    jobs: int = 1  # the local Dask cluster's worker processes (runs at a time); unused with ``scheduler``
    scheduler: str | None = None  # a running Dask scheduler (tcp://HOST:PORT) instead of a local cluster
    out: str = "runs/evaluate"
    cache: str | None = None  # cache root; None: schemas.cache.default_cache_root()
    robustness: bool = False
    agent: AgentOptions = msgspec.field(default_factory=AgentOptions)  # a case file's [agent]; its band per run above
    resume: bool = False  # reuse a run whose folder already holds a finished summary.json of the same spec
    perturbation_pct: float = 10.0
    perturbation_seed: int = 7
    progress: bool = True
    reference_step_s: float = 5.0  # OpenDSS's time step in the ``opendss`` case [s] (docs/simulation.md)
    # how long the bridge waits for the agent's decision at a control step before going on under local control [s].
    # Longer than ``cvvc run``'s 10 s: a miss is a starved machine, not the method, and its steps under local
    # control make the run's figures something else (IEEE 8500 summer on a loaded machine: 12 misses, 8 in a row,
    # the regulators' commands expired and the feeder went to 1.07 pu: NVV 8,380 against 764 on a quiet machine)
    lockstep_timeout_s: float = 60.0
    secure: bool = True  # every run's bus with mTLS and the access policy (``RunConfig.secure``); False: --insecure
    ca_dir: str | None = None  # the CA of the certificates; None: <cache>/ca, created on the first run

    def __post_init__(self) -> None:
        """No bands given: the agent's own (written out, so that ``results.json`` says which)."""
        if not self.bandwidths_v120:
            msgspec.structs.force_setattr(self, "bandwidths_v120", (self.agent.bandwidth_v120,))


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
    attempts: int = 1  # how many times the run was started (a failed attempt is retried once)
    soft: int = 0  # soft decisions as the agent counted them: the soft form (eq. 17) and the tap deadband's
    tolerated: int = 0  # of them, the tap deadband's (taps held, the limits widened by the deadband met)
    holds: int = 0  # decisions without a command
    reasons: dict[str, int] = {}  # the reasons of soft and hold decisions, by kind
    decision_ms: dict[str, float] = {}  # the agent's wall time per decision [ms]: p50, p99, max
    live: LiveAccuracy | None = None  # the agent's estimates and bounds against the truth of their step


class RunFailure(msgspec.Struct, frozen=True, kw_only=True):
    """A run that did not finish: its spec and why (the run folder keeps the processes' logs)."""

    spec: RunSpec
    error: str
    out_dir: str
    attempts: int = 1  # how many times the run was started (a failed run is retried once)


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
