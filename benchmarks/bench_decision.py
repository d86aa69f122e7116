"""The agent's decision time over a whole day, beside OSQP's own solve (the floor) and case A, on the same states.

For ``control_steps`` control steps of a QSTS day (regulators on local control, PV at unity; 288 = a whole day
of 5-minute steps), it records the frames the bridge would send, then times:

- **agent** (cases B-D) on those frames, built exactly as the bridge builds them and fed one by one to the
  agent's ``DecisionMaker`` (aligner -> estimator -> QP -> rounding -> set points -> messages): aligned frames in,
  commands out. One run, each decision timed once as it happens live (no best-of-N); the first decision (a
  cold start) is reported apart. The older figure, per step the fastest of ``repeats`` runs, is kept beside it,
  labelled (each run uses a fresh ``DecisionMaker`` and makes the same decisions);
- **the floor**: OSQP's own set-up and solve (its default polishing, the agent's settings otherwise) of each
  decision's relaxation, the problem the agent's solve started from;
- **case A**, on every ``case_a_every``-th step during the simulation: the bridge's oracle work (perturbation
  power flows of every plant and regulator, on a second engine set to that step's state, so that the
  simulation the agent sees is not disturbed) plus the all-node problem solved by the same solver; its ratio is
  against the agent's time on the same steps.

Every ratio compares figures measured in this one call, on the same states; the machine's load is reported.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.results import DecisionBench

__all__ = ["bench_decision"]


def bench_decision(
    device_map_path: str | Path,
    *,
    control_steps: int = 288,
    cache: Path | None = None,
    start_hour: float = 0.0,
    month: int = 7,
    repeats: int = 1,
    case_a_every: int = 1,
) -> DecisionBench:
    """Time the agent's decisions on a feeder's frames, and case A's (oracle perturbations + solve) beside them.

    Parameters
    ----------
    device_map_path : the feeder's device map (its model is trained once into ``cache`` if absent).
    control_steps : control steps simulated (QSTS, year seed 2) from ``start_hour`` [h] of ``month``'s first day.
    cache : the cache root (``schemas.cache.cache_root``).
    repeats : runs of the agent; the first gives the figures, all of them the labelled best-of-N figure.
    case_a_every : case A is timed on every this-many-th control step (1: every step).

    Returns
    -------
    DecisionBench
        Sizes, the agent's per-decision times [ms] (p50, p99, max, the cold first decision, best-of-N), OSQP's,
        case A's mean time [ms], its oracle's share [ms], and the ratios.
    """
    from agent.runtime import AgentSettings, DecisionMaker
    from agent.snapshot import snapshot_from
    from agent.solve import solve_cvvc
    from agent.state import oracle_state
    from regression.model import read_model, write_model
    from schemas import keys
    from schemas import messages as m
    from schemas.cache import cache_root
    from schemas.devicemap import load_device_map
    from schemas.settings import TrainingOptions
    from simulator_bridge.bus.dnp3_fleet import regulator_phases
    from simulator_bridge.field import devices as dv
    from simulator_bridge.opendss.engine import FeederEngine
    from simulator_bridge.simulation.profiles import month_steps
    from simulator_bridge.simulation.qsts import Qsts
    from training.extended import default_feature_options
    from training.train import TRAINING_REVISION, load_profiles, train

    cache = cache_root(cache)
    dm = load_device_map(device_map_path)
    model_path = cache / "models" / f"{dm.feeder.name}-{dm.fingerprint()}-y1-r{TRAINING_REVISION}.json"
    if not model_path.is_file():
        model_path.parent.mkdir(parents=True, exist_ok=True)
        opts = default_feature_options(dm)  # the model ``cvvc run`` trains
        write_model(train(device_map_path, TrainingOptions(features=opts), cache_dir=cache / "profiles",
                          progress=False).model, model_path)
    model = read_model(model_path, expect_fingerprint=dm.fingerprint())
    engine = FeederEngine(dm)
    profiles = load_profiles(dm, engine, seed=2, cache_dir=cache / "profiles")
    start = month_steps(profiles, month).start + int(start_hour * 60)
    sim = Qsts(engine, profiles, start_step=start)
    # case A's perturbation flows run on a second engine set to each control step's state: on the simulation's own
    # engine they would move the later steps' power flows, hence the agent's frames (one IEEE 8500 decision took
    # 43.7 ms instead of 12 on such frames; docs/agent.md)
    oracle = FeederEngine(dm)
    fid = dm.feeder.name
    pvs = [dv.PvInverter(p.id, k, float(engine.pv_kva[k]), "unity_pf") for k, p in enumerate(model.pv)]
    if [r.id for r in model.regulators] != list(engine.regulator_ids):
        raise ValueError("the model's regulators are not the feeder's, in its order: retrain the model")
    regs = [  # as the bridge's: tap range and phase from the feeder
        dv.RegulatorController(r.id, i, int(engine.reg_tap_max[i]), r.default_setpoint_v120, r.default_band_v120)
        for i, r in enumerate(model.regulators)
    ]
    phases = regulator_phases(engine)
    caps = [  # the model's banks report too (the aligner waits for them), on their local control
        dv.CapBankController(c.id, i, int(engine.cap_steps[i]), float(engine.cap_kvar[i]),
                             engine.cap_control_type[i])
        for i, c in enumerate(model.capacitors)
    ]
    steps: list[list[tuple[str, Any]]] = []
    case_a_s, oracle_s, sizes, case_a_at = [], [], [], []
    oracle_dv: list[float] = []  # the oracle engine's voltages against the simulation's [pu]
    reference = DecisionMaker(model, AgentSettings(feeder_id=fid))  # decides along, for case A's inputs
    seq = 0
    for _ in range(control_steps * 5):
        res = sim.step()
        rd, t = res.readings, int(res.t_ns)
        if t % reference.period_ns:
            continue
        seq += 1
        frames: list[tuple[str, Any]] = [
            (
                keys.meas_head(fid),
                dv.head_frame(
                    feeder_id=fid,
                    t_ns=t,
                    seq=seq,
                    v_mag_v=rd.head_v_mag_v,
                    v_ang_deg=rd.head_v_ang_deg,
                    i_mag_a=rd.head_i_mag_a,
                    i_ang_deg=rd.head_i_ang_deg,
                    p_kw=rd.head_p_kw,
                    q_kvar=rd.head_q_kvar,
                ),
            )
        ]
        frames += [
            (
                keys.meas_pv(fid, pv.plant_id),
                dv.pv_frame(
                    plant=pv,
                    t_ns=t,
                    seq=seq,
                    p_kw=rd.pv_p_kw[k],
                    q_kvar=rd.pv_q_kvar[k],
                    v_v=rd.pv_v_v[k],
                    available_p_kw=float(res.pv_p_kw[k]),
                    q_setpoint_kvar=pv.q_setpoint_kvar,
                ),
            )
            for k, pv in enumerate(pvs)
        ]
        frames += [
            (
                keys.meas_vr(fid, reg.regulator_id),
                dv.reg_frame(
                    reg=reg,
                    t_ns=t,
                    seq=seq,
                    phase=phases[r],
                    v120=float(rd.reg_v120[r]),
                    v_compared_120=float(rd.reg_v120_compared[r]),
                    tap=int(res.taps[r]),
                    setpoint_v120=reg.setpoint_v120,
                    band_v120=reg.band_v120,
                    mode=reg.mode,
                ),
            )
            for r, reg in enumerate(regs)
        ]
        frames += [
            (
                keys.meas_cap(fid, cap.capacitor_id),
                dv.cap_frame(cap=cap, t_ns=t, seq=seq, closed_steps=int(res.cap_states[i]),
                             v_v=float(rd.cap_v_v[i]), control_value=None, active=None),
            )
            for i, cap in enumerate(caps)
        ]
        steps.append(frames)
        aligned_now = [a for key, frame in frames for a, _ in reference.on_frame(key, frame)]
        if not aligned_now or (len(steps) - 1) % max(case_a_every, 1):
            continue
        oracle.set_state(engine.state())  # loads, PV, every RegControl's tap and every bank, as the bridge's twin
        oracle.solve()
        v = oracle.node_voltages_pu()  # the state, before the perturbations (not timed: they solve it again)
        t0 = time.perf_counter()
        # not restored in place (the next step sets the state again; on large feeders undoing the moves drifts)
        sens = oracle.perturbation_sensitivities(restore=False)  # solves the state first
        t1 = time.perf_counter()
        oracle_dv.append(float(np.max(np.abs(v - res.v_pu))))
        reply = m.OracleReply(
            t_ns=t,
            seq=seq,
            source="bridge",
            feeder_id=fid,
            node_names=[],
            v_pu=v.tolist(),
            dv_dq_pu_per_kvar=np.nan_to_num(sens.dv_dq).tolist(),
            dv_dtap_pu=sens.dv_dtap.tolist(),
            taps=[int(x) for x in oracle.taps()],
            dv_dp_pu_per_kw=np.nan_to_num(sens.dv_dp).tolist(),
        )
        snap = snapshot_from(aligned_now[0], model)
        solve_cvvc(reference.controller.problem(snap, oracle_state(model, reply, snap.reg_tap)))
        case_a_s.append(time.perf_counter() - t0)
        oracle_s.append(t1 - t0)
        sizes.append(len(v))
        case_a_at.append(len(steps) - 1)

    load = os.getloadavg()[0]
    runs = [_run_agent(model, fid, steps) for _ in range(max(repeats, 1))]
    per_step = np.array(runs) * 1e3  # (repeats, steps) [ms]
    first = per_step[0, 1:]  # the first run; its cold first decision apart
    best = per_step.min(axis=0)[1:]
    floor = np.array([_osqp_seconds(qp) for qp in _relaxations(model, fid, steps, solve_cvvc)]) * 1e3
    ca = np.array(case_a_s) * 1e3
    agent_there = per_step[0, case_a_at]
    return DecisionBench(
        feeder=fid,
        critical_nodes=len(model.critical_nodes),
        nodes=sizes[0] if sizes else 0,
        plants=len(model.pv),
        regulators=len(model.regulators),
        control_steps=len(steps),
        agent_p50_ms=round(float(np.percentile(first, 50)), 3),
        agent_p99_ms=round(float(np.percentile(first, 99)), 3),
        agent_max_ms=round(float(first.max()), 3),
        agent_cold_first_decision_ms=round(float(per_step[0, 0]), 3),
        agent_best_of_n_p50_ms=round(float(np.percentile(best, 50)), 3),
        agent_best_of_n_p99_ms=round(float(np.percentile(best, 99)), 3),
        best_of_n=max(repeats, 1),
        osqp_p50_ms=round(float(np.percentile(floor, 50)), 3) if floor.size else 0.0,
        osqp_p99_ms=round(float(np.percentile(floor, 99)), 3) if floor.size else 0.0,
        ratio_agent_to_osqp_p50=round(float(np.percentile(first, 50) / np.percentile(floor, 50)), 2)
        if floor.size else 0.0,
        case_a_steps=len(case_a_at),
        case_a_mean_ms=round(float(ca.mean()), 2),
        case_a_oracle_mean_ms=round(float(np.mean(oracle_s)) * 1e3, 2),
        case_a_state_max_dv_pu=float(f"{max(oracle_dv):.2g}"),
        ratio_case_a_to_agent_mean=round(float(ca.mean() / agent_there.mean()), 1),
        load_average=round(load, 2),
        method=(f"agent: one run, each decision once (first decision apart); best-of-N: per step the fastest of "
                f"{max(repeats, 1)} runs; OSQP: set-up + solve of each decision's relaxation; case A: on 1 step in "
                f"{max(case_a_every, 1)}, ratio against the agent's time on those steps"),
        goal="agent p99 <= 5 ms on every feeder (p50 <= 1 ms rural); >= 50x faster than case A on IEEE 8500",
    )


def _run_agent(model: Any, fid: str, steps: list[list[tuple[str, Any]]]) -> list[float]:
    """Seconds per control step of a fresh ``DecisionMaker`` fed ``steps`` (aligned frames in, messages out)."""
    from agent.runtime import AgentSettings, DecisionMaker

    maker = DecisionMaker(model, AgentSettings(feeder_id=fid))
    seconds = []
    for frames in steps:
        t0 = time.perf_counter()
        for key, frame in frames:
            for aligned, d in maker.on_frame(key, frame):
                maker.to_message(aligned, d)
        seconds.append(time.perf_counter() - t0)
    return seconds


def _relaxations(model: Any, fid: str, steps: list[list[tuple[str, Any]]], solve: Any) -> list[Any]:
    """The relaxed problem of every decision after the first (a run of its own, not timed).

    The controller calls ``agent.controller.solve_cvvc``; for this run it is wrapped to keep each solution's
    relaxation, and restored after.
    """
    import agent.controller as controller

    kept: list[Any] = []

    def keeping(inputs: Any, **kwargs: Any) -> Any:
        solution = solve(inputs, **kwargs)
        if solution.relaxed_problem is not None:
            kept.append(solution.relaxed_problem)
        return solution

    controller.solve_cvvc = keeping
    try:
        _run_agent(model, fid, steps)
    finally:
        controller.solve_cvvc = solve
    return kept[1:]


def _osqp_seconds(qp: Any) -> float:
    """Seconds of OSQP's own set-up and solve of ``qp`` with the agent's settings for it (``osqp_settings``), its
    polishing on, no warm start, at most 4000 iterations.
    """
    import osqp

    from agent.solve.relaxation import osqp_settings

    t0 = time.perf_counter()
    solver = osqp.OSQP(algebra="builtin")
    solver.setup(qp.P, qp.c, qp.A, qp.lower, qp.upper, **{**osqp_settings(qp), "max_iter": 4000, "polishing": True})
    solver.solve(raise_error=False)
    return time.perf_counter() - t0
