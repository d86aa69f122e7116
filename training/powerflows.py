"""Training power flows (paper Algorithm 1), optionally in parallel worker processes.

For every representative scenario: loads and available PV from the year profiles, regulators frozen at
``tap0``, one base flow with every plant at Q = 0, then for each plant its Q swept from -100 % to +100 %
of its reactive capability (its kVA rating) in 20 % steps, skipping values outside the headroom
``sqrt(kVA^2 - P^2)`` (Algorithm 1, lines 7-19). The base flow is shared by the plants' sweeps (the paper
runs the 0 % step once per plant; the results are identical).

Beyond the paper (reference experiment, trap 4): optional *combined* flows with every plant at the same
share of its own headroom at once, which widens the head-Q range the regression sees.

``tap0`` comes from ``settle_taps``: regulator local control (set point and band of each controller, one
step at a time) iterated to rest in one power flow at the year's mean load and mean PV.
"""

from __future__ import annotations

import multiprocessing
import os
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace

import numpy as np

from regression.model import features
from schemas.errors import CvvcError
from training.errors import TrainingError

__all__ = [
    "BASE",
    "COMBINED",
    "PowerFlowSet",
    "ScenarioInput",
    "q_plan",
    "run_power_flows",
    "settle_taps",
    "solve_scenario",
]

BASE = -1  # ``plant`` label of a scenario's base flow (every plant at Q = 0)
COMBINED = -2  # ``plant`` label of a combined flow (every plant perturbed together)


@dataclass(frozen=True)
class ScenarioInput:
    """What one scenario sets in the engine."""

    index: int  # scenario number
    load_kw: np.ndarray  # (n_loads,) [kW]
    pv_kw: np.ndarray  # (K,) available PV power [kW]


@dataclass(frozen=True)
class PowerFlowSet:
    """Every training power flow; arrays have F rows."""

    scenario: np.ndarray  # (F,) int
    plant: np.ndarray  # (F,) int: k perturbed alone, BASE or COMBINED
    q_pct: np.ndarray  # (F,) requested Q of the perturbed plant(s) [% of kVA, or of headroom if COMBINED]
    features: np.ndarray  # (F, M) regression features (regression.model.features)
    q_head_kvar: np.ndarray  # (F,) feeder-head Q, sum of phases [kvar]
    pv_q_kvar: np.ndarray  # (F, K) applied plant Q [kvar], generator convention
    v_pu: np.ndarray  # (F, n_nodes) every node voltage [pu]
    taps: np.ndarray  # (F, R) tap positions of each flow
    reg_pu: np.ndarray  # (F, R) each regulator's raw secondary reading [pu of its secondary node]
    cap_v_v: np.ndarray  # (F, C) each map capacitor bank's bus voltage reading, line-to-neutral [V]
    failed: int  # power flows that did not converge (skipped)
    workers: int = 1  # processes that ran them

    @property
    def n(self) -> int:
        """Number of power flows in the set."""
        return int(self.scenario.size)

    @staticmethod
    def concat(parts: Sequence[PowerFlowSet]) -> PowerFlowSet:
        """The sets ``parts`` one after the other (the rows of empty ones left out, the first kept if all are
        empty); ``failed`` counts every part's, an empty one's too (a scenario whose flows all failed).
        """
        failed = sum(p.failed for p in parts)
        parts = [p for p in parts if p.n] or list(parts[:1])
        return PowerFlowSet(
            scenario=np.concatenate([p.scenario for p in parts]),
            plant=np.concatenate([p.plant for p in parts]),
            q_pct=np.concatenate([p.q_pct for p in parts]),
            features=np.concatenate([p.features for p in parts]),
            q_head_kvar=np.concatenate([p.q_head_kvar for p in parts]),
            pv_q_kvar=np.concatenate([p.pv_q_kvar for p in parts]),
            v_pu=np.concatenate([p.v_pu for p in parts]),
            taps=np.concatenate([p.taps for p in parts]),
            reg_pu=np.concatenate([p.reg_pu for p in parts]),
            cap_v_v=np.concatenate([p.cap_v_v for p in parts]),
            failed=failed,
        )


def q_plan(
    pv_p_kw: np.ndarray,
    kva: np.ndarray,
    q_steps_pct: Sequence[float],
    combined_pct: Sequence[float] = (),
) -> list[tuple[int, float, np.ndarray]]:
    """List the Q set points of one scenario's flows (Algorithm 1, lines 8-16), base flow first.

    Parameters
    ----------
    pv_p_kw : (K,) plant active power in this scenario [kW].
    kva : (K,) inverter ratings [kVA].
    q_steps_pct : Q steps in % of kVA, e.g. -100, -80, ..., 100 (0 is the shared base flow).
    combined_pct : steps in % of each plant's headroom applied to all plants at once.

    Returns
    -------
    List of (plant label, percent, Q vector (K,) [kvar]).
    """
    p = np.asarray(pv_p_kw, float)
    s = np.asarray(kva, float)
    headroom = np.sqrt(np.maximum(s**2 - p**2, 0.0))
    plan: list[tuple[int, float, np.ndarray]] = [(BASE, 0.0, np.zeros(p.size))]
    for k in range(p.size):
        for pct in q_steps_pct:
            q = pct / 100.0 * s[k]
            if pct == 0 or abs(q) > headroom[k] * (1 + 1e-9):
                continue  # the base flow / outside the PV excess capacity: skip (line 15)
            qv = np.zeros(p.size)
            qv[k] = q
            plan.append((k, float(pct), qv))
    for pct in combined_pct:
        if pct != 0:
            plan.append((COMBINED, float(pct), pct / 100.0 * headroom))
    return plan


def solve_scenario(
    engine,
    scenario: ScenarioInput,
    kva: np.ndarray,
    q_steps_pct: Sequence[float],
    combined_pct: Sequence[float],
) -> PowerFlowSet:
    """Run one scenario's flows on ``engine`` at its present taps and record them."""
    engine.set_loads_kw(scenario.load_kw)
    taps = np.asarray(engine.taps(), int)
    plan = q_plan(scenario.pv_kw, kva, q_steps_pct, combined_pct)
    rows: list[tuple] = []
    failed = 0
    for plant, pct, q in plan:
        applied = engine.set_pv(scenario.pv_kw, q)
        try:
            engine.solve()
        except CvvcError:
            failed += 1
            if plant == BASE:  # no base flow: the sweeps have no reference, drop the scenario
                return _empty(len(kva), len(engine.node_names), len(taps), len(engine.capacitor_ids),
                              failed=len(plan))
            continue
        r = engine.readings()
        feat = features(r.head_p_kw, r.head_q_kvar, r.pv_p_kw.sum(axis=1), r.pv_q_kvar.sum(axis=1))
        rows.append(
            (
                plant,
                pct,
                feat,
                float(np.sum(r.head_q_kvar)),
                np.asarray(applied, float),
                engine.node_voltages_pu(),
                np.asarray(r.reg_v120, float) * np.asarray(engine.reg_pu_per_v120, float),
                np.asarray(r.cap_v_v, float),
            )
        )
    engine.set_pv(scenario.pv_kw, np.zeros(len(kva)))  # line 18: revert PV Q to 0
    return PowerFlowSet(
        scenario=np.full(len(rows), scenario.index, int),
        plant=np.asarray([r[0] for r in rows], int),
        q_pct=np.asarray([r[1] for r in rows], float),
        features=np.asarray([r[2] for r in rows], float),
        q_head_kvar=np.asarray([r[3] for r in rows], float),
        pv_q_kvar=np.asarray([r[4] for r in rows], float).reshape(len(rows), len(kva)),
        v_pu=np.asarray([r[5] for r in rows], float).reshape(len(rows), len(engine.node_names)),
        taps=np.tile(taps, (len(rows), 1)),
        reg_pu=np.asarray([r[6] for r in rows], float).reshape(len(rows), len(taps)),
        cap_v_v=np.asarray([r[7] for r in rows], float).reshape(len(rows), len(engine.capacitor_ids)),
        failed=failed,
    )


def _empty(n_pv: int, n_nodes: int, n_reg: int, n_cap: int = 0, *, failed: int = 0) -> PowerFlowSet:
    return PowerFlowSet(
        scenario=np.zeros(0, int),
        plant=np.zeros(0, int),
        q_pct=np.zeros(0),
        features=np.zeros((0, 6 + 2 * n_pv)),
        q_head_kvar=np.zeros(0),
        pv_q_kvar=np.zeros((0, n_pv)),
        v_pu=np.zeros((0, n_nodes)),
        taps=np.zeros((0, n_reg), int),
        reg_pu=np.zeros((0, n_reg)),
        cap_v_v=np.zeros((0, n_cap)),
        failed=failed,
    )


def settle_taps(engine, *, max_rounds: int = 64) -> np.ndarray:
    """Regulator local control iterated to rest in the engine's present state; returns the taps.

    Each round solves, then moves every regulator whose compared voltage is outside its band
    (``reg_default_setpoint_v120 +/- reg_default_band_v120 / 2``) one step towards it. Stops when all are
    in band, when a tap limit is hit, or when a state repeats (band narrower than a step).
    """
    from simulator_bridge.simulation.qsts import tap_direction

    seen: set[tuple[int, ...]] = set()
    for _ in range(max_rounds):
        engine.solve()
        r = engine.readings()
        taps = np.asarray(r.reg_tap, int)
        seen.add(tuple(taps))
        move = tap_direction(r.reg_v120_compared, engine.reg_default_setpoint_v120, engine.reg_default_band_v120)
        new = np.clip(taps + move, -engine.reg_tap_max, engine.reg_tap_max)
        if np.array_equal(new, taps) or tuple(new) in seen:
            return taps
        engine.set_taps(new)
    engine.solve()
    return np.asarray(engine.taps(), int)


# ---------------------------------------------------------------- worker processes
_WORKER: dict = {}


def _init_worker(device_map_path: str, tolerance: float, taps: list[int]) -> None:
    from schemas.devicemap import load_device_map
    from simulator_bridge.opendss.engine import FeederEngine

    engine = FeederEngine(load_device_map(device_map_path), tolerance=tolerance)
    engine.set_taps(np.asarray(taps, int))
    _WORKER["engine"] = engine


def _run_chunk(chunk: list[ScenarioInput], q_steps_pct, combined_pct) -> PowerFlowSet:
    engine = _WORKER["engine"]
    parts = [solve_scenario(engine, s, engine.pv_kva, q_steps_pct, combined_pct) for s in chunk]
    return PowerFlowSet.concat(parts)


def run_power_flows(
    engine,
    scenarios: Sequence[ScenarioInput],
    *,
    device_map_path: str,
    tolerance: float,
    q_steps_pct: Sequence[float],
    combined_pct: Sequence[float] = (),
    workers: int | None = None,
    progress: bool = True,
    parallel_min_s: float = 20.0,
) -> PowerFlowSet:
    """All scenarios' flows; in ``workers`` spawned processes (one engine each) when it pays.

    The first scenario runs in this process and is timed. The rest go to a pool of spawned workers only
    when more than one worker is allowed and the estimated serial time of the rest exceeds
    ``parallel_min_s``: starting a worker (imports, compiling the feeder) costs a few seconds, more than
    all of IEEE 123's power flows (about 1 s).

    Parameters
    ----------
    engine : the caller's ``FeederEngine`` with taps set to tap0 (used when ``workers == 1``).
    scenarios : the scenarios, in order.
    device_map_path : for the workers to build their own engine.
    tolerance : OpenDSS solve tolerance of the workers' engines.
    q_steps_pct, combined_pct : see ``q_plan``.
    workers : process count; None: ``os.cpu_count()``; 1: in this process.
    progress : show a tqdm bar on stderr (only when stderr is a terminal).
    parallel_min_s : estimated serial seconds above which the worker pool is used.
    """
    from tqdm import tqdm

    if not scenarios:
        raise TrainingError("no scenarios to run; the training year selected nothing")
    n_cpu = os.cpu_count() or 1
    workers = max(1, min(n_cpu if workers is None else workers, len(scenarios) - 1))
    per_scenario = len(q_plan(scenarios[0].pv_kw, engine.pv_kva, q_steps_pct, combined_pct))
    bar = tqdm(
        total=len(scenarios) * per_scenario,
        desc="training power flows",
        unit="pf",
        file=sys.stderr,
        disable=not (progress and sys.stderr.isatty()),
    )
    tap0 = np.asarray(engine.taps(), int)
    parts: list[PowerFlowSet] = []
    try:
        t0 = time.perf_counter()
        parts.append(
            solve_scenario(
                engine,
                scenarios[0],
                engine.pv_kva,
                q_steps_pct,
                combined_pct,
            )
        )
        bar.update(parts[0].n + parts[0].failed)
        rest = list(scenarios[1:])
        if workers == 1 or (time.perf_counter() - t0) * len(rest) < parallel_min_s:
            for s in rest:
                part = solve_scenario(engine, s, engine.pv_kva, q_steps_pct, combined_pct)
                parts.append(part)
                bar.update(part.n + part.failed)
            return PowerFlowSet.concat(parts)
        n_chunks = min(len(rest), 4 * workers)
        chunks = [list(c) for c in np.array_split(np.asarray(rest, dtype=object), n_chunks)]
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(
            max_workers=workers,
            mp_context=ctx,
            initializer=_init_worker,
            initargs=(str(device_map_path), tolerance, [int(t) for t in tap0]),
        ) as pool:
            futures = [pool.submit(_run_chunk, c, list(q_steps_pct), list(combined_pct)) for c in chunks]
            for f in futures:
                try:
                    part = f.result()
                except BrokenProcessPool as e:
                    raise TrainingError(
                        "a power-flow worker process died (out of memory, or a script without an "
                        "`if __name__ == '__main__':` guard); retry with --workers 1"
                    ) from e
                parts.append(part)
                bar.update(part.n + part.failed)
        return replace(PowerFlowSet.concat(parts), workers=workers)
    finally:
        bar.close()
        engine.set_taps(tap0)
