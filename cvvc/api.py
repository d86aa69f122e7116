"""The Python API of cvvc-edge: train a model, run a case, run an evaluation, and read what they wrote as pandas
DataFrames. Every name here is in ``__all__``; docs/api.md has a worked example.

Running
-------
``train(feeder)``
    Train the regression model of a feeder (its device map TOML; None: the embedded rural feeder) on real OpenDSS
    power flows and write it where ``run`` finds it (the cache), or to ``out``. Returns the model file's path.
``run(case)``
    One closed-loop run, as ``cvvc run case.toml`` does it: the bridge, the agent and the recorder as processes on a
    Zenoh router on loopback, then the no-control baseline of the same days. ``case`` is a
    ``schemas.settings.RunCase`` (build one with its sections: ``RunCase(feeder=FeederSection(map=...),
    window=WindowSection(start=..., days=...))``) or a case file's path (``cvvc init case.toml`` writes one).
    Returns the run's ``RunSummary`` (also written to ``<out>/summary.json``, with ``report.md`` and the recording
    ``session.mcap``).
``evaluate(config)``
    The paper's evaluation, as ``cvvc evaluate`` runs it: cases and seasons on a Dask cluster. ``config`` is an
    ``EvaluateConfig`` (or its fields as keywords). Returns the ``Evaluation`` (also ``<out>/results.json``).

Reading (pandas DataFrames)
---------------------------
``read_recording(path, keys=("**",))``
    An MCAP recording as ``{topic: DataFrame}``, one row per message, indexed by simulation time (local standard
    time, UTC-5); the truth (``cvvc/<F>/sim/truth``) with one column per node (``v_pu.<node>``).
``read_summary(run_dir)``
    A run's ``summary.json``: one row per metric, the case's column beside the no-control baseline's.
``read_evaluation(eval_dir)``
    An evaluation's ``results.json``: one row per run.

Errors
------
Every error of these functions is a ``CvvcError`` (``schemas.errors``) whose message says what was wrong: a bad case
file (``CaseFileError``), a run that cannot start or whose processes failed (``LaunchError``), a failed evaluation
run (``EvaluateError``), a file that cannot be read (``FramesError``).

Units, signs and time are docs/conventions.md's: voltages in pu of the node's nominal line-to-neutral voltage, Q in
kvar (+ injects), times as ``t_ns`` (ns since the UTC epoch, simulation time).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from cvvc.evaluation import EvaluateConfig, Evaluation
from cvvc.frames import FramesError
from cvvc.frames import evaluation_frame as read_evaluation
from cvvc.frames import recording_frames as read_recording
from cvvc.frames import summary_frame as read_summary
from cvvc.run_summary import RunSummary
from schemas.errors import CvvcError
from schemas.settings import (
    AgentOptions,
    BridgeSection,
    FeederSection,
    OutputSection,
    RunCase,
    SecuritySection,
    WindowSection,
)

__all__ = ["AgentOptions", "BridgeSection", "CvvcError", "EvaluateConfig", "Evaluation", "FeederSection",
           "FramesError", "OutputSection", "RunCase", "RunSummary", "SecuritySection", "WindowSection", "evaluate",
           "read_evaluation", "read_recording", "read_summary", "run", "train"]


def run(case: RunCase | str | Path, *, progress: bool = False) -> RunSummary:
    """Run one case end to end (``cvvc run``) and return its summary.

    Parameters
    ----------
    case : a ``RunCase``, or the path of a case file (TOML; its relative paths are relative to its folder).
    progress : draw the progress bars on stderr.

    Returns
    -------
    RunSummary
        The run's final metrics (``metrics``), the baseline's (``baseline``), the decisions, and where the output
        is: ``out_dir`` (``summary.json``, ``report.md``, the processes' logs), ``recording`` (the MCAP file).

    Raises
    ------
    CaseFileError
        The case file cannot be read or holds a key or value the settings tree refuses.
    LaunchError
        The run cannot start (bad window, a model of another feeder) or one of its processes failed; the message
        holds the end of that process's log.
    """
    from cvvc.case import load_case
    from cvvc.launch import RunConfig
    from cvvc.launch import run as launch

    case_file = None
    if not isinstance(case, RunCase):
        case_file = str(case)
        case = load_case(case)
    return launch(RunConfig.of_case(case, progress=progress, case_file=case_file))


def evaluate(config: EvaluateConfig | None = None, **fields: Any) -> Evaluation:
    """Run an evaluation (``cvvc evaluate``): every case of ``cases`` on the first days of every season of
    ``seasons``, each run a task of a Dask cluster, and write ``results.json`` and ``results.md`` into ``out``.

    Parameters
    ----------
    config : the evaluation; None: ``EvaluateConfig(**fields)``.
    fields : ``EvaluateConfig``'s fields, laid over ``config`` (``feeder``, ``cases``, ``seasons``,
        ``days_per_season``, ``out``, ``jobs``, ``cache``, ``progress``, ...).

    Raises
    ------
    EvaluateError
        A run failed (after one retry): the finished runs are written all the same (``read_evaluation`` reads
        them), and ``resume=True`` runs only what is missing.
    """
    import msgspec

    from cvvc.evaluate import evaluate as run_evaluation

    base = config or EvaluateConfig()
    merged = msgspec.structs.replace(base, **fields) if fields else base
    return run_evaluation(msgspec.convert(msgspec.to_builtins(merged), EvaluateConfig))


def train(feeder: str | Path | None = None, *, out: str | Path | None = None, train_seed: int = 1,
          cache: str | Path | None = None, progress: bool = False) -> Path:
    """Train the model of a feeder the way ``cvvc run`` does on first use and write it; returns its path.

    Parameters
    ----------
    feeder : a device map TOML (or a folder holding one); None: the embedded rural feeder.
    out : the model file to write; None: the cache, where ``run`` of the same feeder, ``train_seed`` and cache
        finds it (so the run trains nothing).
    train_seed : the profile year trained on (``FeederSection.train_seed``).
    cache : the cache root (None: ``$XDG_CACHE_HOME/cvvc-edge``); the profiles and the cached model go there.
    progress : draw the progress bars on stderr.

    Raises
    ------
    CvvcError
        The device map cannot be read (``DeviceMapError``), or training failed (``TrainingError``).
    """
    from cvvc.launch import cached_model_path, train_model
    from schemas.cache import cache_root
    from schemas.devicemap import load_device_map, resolve_device_map_path
    from simulator_bridge.rural.default_feeder import ensure_default_feeder

    root = cache_root(cache)
    dm_path = resolve_device_map_path(str(feeder)) if feeder is not None else ensure_default_feeder(root)
    path = Path(out) if out is not None else cached_model_path(load_device_map(dm_path), train_seed, root)
    return train_model(dm_path, path, train_seed=train_seed, cache=root, progress=progress)
