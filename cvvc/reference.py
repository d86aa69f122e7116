"""The ``opendss`` reference case of ``cvvc evaluate``: OpenDSS's own control loop on the same days.

The same feeder, year profiles (``year_seed``), days, loads and PV (unity power factor, as in the ``none`` case)
as the bus runs, stepped minute by minute by OpenDSS's own RegControls and CapControls in its time-driven control
mode at ``step_s`` [s] (:func:`simulator_bridge.opendss.opendss_loop.reference_metrics`), with the same metrics on the
feeder zone. It is OpenDSS's reference, not a field-device run: nothing goes through the bus, no process is
started, and nothing is recorded; the run folder gets a ``summary.json`` (so ``--resume`` reuses it) and a
``report.md``.
"""

from __future__ import annotations

import datetime as dt
import time
from pathlib import Path

import msgspec

from cvvc.launch import LaunchError, RunSummary
from cvvc.run_report import render_summary

__all__ = ["REFERENCE_CASE", "ReferenceConfig", "run_reference"]

REFERENCE_CASE = "opendss"
"""The case name of OpenDSS's own control loop in ``cvvc evaluate --cases``."""


class ReferenceConfig(msgspec.Struct, frozen=True, kw_only=True):
    """One reference run: a prepared device map, the window, the profile year, OpenDSS's step."""

    feeder: str  # device map TOML (already prepared: ``prepare_feeder_and_model``)
    start: str  # YYYY-MM-DD[THH:MM], local standard time of the profiles
    days: float
    year_seed: int
    cache: str  # the profile cache folder (``schemas.cache.profiles_dir``)
    out: str  # the run folder
    step_s: float = 5.0


def run_reference(config: ReferenceConfig) -> RunSummary:
    """Run the reference case (see the module docstring); write ``summary.json`` and ``report.md``."""
    from schemas.devicemap import load_device_map
    from simulator_bridge.bus.publishing import metrics_frame
    from simulator_bridge.opendss.engine import EngineError, FeederEngine
    from simulator_bridge.opendss.opendss_loop import reference_metrics
    from training.train import load_profiles

    try:
        start = dt.datetime.fromisoformat(config.start)
    except ValueError as e:
        raise LaunchError(f"start {config.start!r} is not a date (YYYY-MM-DD or YYYY-MM-DDTHH:MM)") from e
    t0 = time.monotonic()
    dm = load_device_map(Path(config.feeder))
    steps = int(round(config.days * 1440))
    engine = FeederEngine(dm)
    try:
        profiles = load_profiles(dm, engine, seed=config.year_seed, cache_dir=config.cache)
    finally:
        engine.close()
    first = int((start - dt.datetime(start.year, 1, 1)).total_seconds()) // 60
    try:
        metrics = reference_metrics(dm, profiles, start_step=first, steps=steps, step_s=config.step_s)
    except EngineError as e:
        raise LaunchError(f"{dm.feeder.name}: the OpenDSS reference failed: {e}") from e
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    frame = metrics_frame(metrics, t_ns=profiles.t_ns(first + steps), seq=1, feeder_id=dm.feeder.name,
                          start_t_ns=profiles.t_ns(first), final=True)
    summary = RunSummary(feeder=str(config.feeder), feeder_id=dm.feeder.name, case=REFERENCE_CASE,
                         start=start.isoformat(timespec="minutes"), days=config.days, steps=steps,
                         wall_s=round(time.monotonic() - t0, 2), metrics=frame, baseline=None, lockstep_misses=0,
                         decisions=0, out_dir=str(out), recording=None, model=None)
    (out / "summary.json").write_bytes(msgspec.json.format(msgspec.json.encode(summary), indent=2))
    (out / "report.md").write_text(render_summary(summary, dm).replace(
        "- model: none (baseline case)",
        f"- OpenDSS's own control loop at {config.step_s:g} s steps (no bus, no processes, no recording)"))
    return summary
