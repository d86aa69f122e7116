"""Training pipeline: scenarios (II.A), power flows (II.B, Algorithm 1), critical nodes (II.C), fits (II.D).

``train(device_map_path, ...)`` returns a ``TrainResult`` holding the model (``regression.model.CvvcModel``)
and a summary of what was done. It drives OpenDSS only through ``simulator_bridge.opendss.engine.FeederEngine``.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import NamedTuple

import msgspec
import numpy as np

from regression.model import (
    CriticalNode,
    CvvcModel,
    FitStats,
    PvInfo,
    RegulatorInfo,
    SensitivityFit,
    TrainingSettings,
    calendar_features,
    extended_feature_names,
    feature_names,
)
from schemas.settings import TrainingOptions
from training.capbanks import bank_controls, bank_infos, bank_sensitivities
from training.critical import extreme_nodes, movable_nodes, node_phase, select_critical, upstream_regulators
from training.errors import TrainingError
from training.extended import (
    SINGLE_TAP_SHIFTS,
    device_shifted_voltages,
    near_extreme_cover,
    perturb_devices,
    reading_matrix,
    zone_extreme_cover,
)
from training.fits import (
    SensitivitySamples,
    choose_c_kvar,
    fit_sensitivity,
    fit_voltage_regression,
    fit_voltages_with_holdout,
    sensitivity_rel_err,
    sensitivity_samples,
    tap_sensitivities,
)
from training.powerflows import (
    BASE,
    PowerFlowSet,
    ScenarioInput,
    run_power_flows,
    settle_taps,
)
from training.scenarios import ScenarioSet, calendar_cover, select_scenarios, summarize_year

__all__ = ["TRAINING_REVISION", "TrainResult", "TrainSummary", "load_profiles", "train"]

#: Bump when training changes what it produces, so cached models (``cvvc run``'s cache) are retrained.
TRAINING_REVISION = 12  # 3: critical nodes in the zone, movable only; 4: model format 2; 5: bounds and banks;
# 6: cvvc run trains the extended set on feeders with banks (training.extended.default_feature_options);
# 7: the extended set's cover also takes each regulator zone's extremes (training.extended.zone_extreme_cover);
# 8: the extended set's calendar cover, seasonal and weekly calendar terms (training.extended.EXTENDED_OPTIONS);
# 9: the bounds are calibrated over set-point-shifted windows too (training.calibration.SETPOINT_OFFSET_TAPS);
# the banks' local controls as the agent predicts them (training.capbanks.bank_controls);
# 10: bounds from node-scaled scores pooled, the level set by held-out windows (training.conformal);
# 11: the banks' VoltOverride (training.capbanks.bank_controls, override_*);
# 12: the calibration windows' simulations start settled (simulator_bridge.simulation.qsts.SETTLE_S)

_DEFAULT_OPTIONS = TrainingOptions()
_HOLDOUT_EVERY = 5  # every 5th scenario is held out to choose eq. (3)'s form and to report validation error


class TrainSummary(msgspec.Struct, frozen=True, kw_only=True):
    """What ``cvvc train --json`` prints. Voltages [pu], Q [kvar], times [s]."""

    feeder: str
    selection: str
    year_seed: int
    blocks: tuple[int, int]
    non_empty_blocks: int
    scenarios: int
    power_flows: int
    failed_power_flows: int
    critical_nodes: int
    node_count: int
    critical_share: float
    seconds: float
    seconds_power_flows: float
    workers: int
    tap0: list[int]
    q_head_range_kvar: tuple[float, float]
    c_kvar: float
    condition_number: float
    voltage_rmse_pu: float
    voltage_max_abs_pu: float
    validation_rmse_pu: float
    validation_max_abs_pu: float
    sensitivity_median_rel_err: float
    sensitivity_forms: dict[str, int]
    power_fits_with_negative_b: int
    calibration_minutes: int = 0  # held-out minutes the estimate bounds were calibrated on (0: no bounds)
    bound_p50_pu: float = 0.0  # median over critical nodes of the calibrated bound (upper + lower) / 2
    bound_level: float = 0.0  # the one-sided quantile level the bounds were taken at (training.conformal)
    bound_held_out_miss: float = 0.0  # that level's miss rate on held-out calibration windows
    seconds_calibration: float = 0.0
    cover_minutes: int = 0  # calendar cover: base-flow minutes beyond the scenarios (``calendar_cover_per_cell``)


@dataclass(frozen=True)
class TrainResult:
    """The trained model and the summary of the run."""

    model: CvvcModel
    summary: TrainSummary


def load_profiles(device_map, engine, *, seed: int, cache_dir: str | Path | None):
    """The feeder's year profiles for ``seed`` (see ``simulator_bridge.simulation.profiles.feeder_profiles``)."""
    from simulator_bridge.simulation.profiles import feeder_profiles

    return feeder_profiles(device_map, engine, seed=seed, cache_dir=cache_dir)


def _check_device_map(dm, feature_set: str = "paper") -> None:
    if not dm.pv:
        raise TrainingError(
            f"feeder {dm.feeder.name!r}: the device map has no PV plant; add at least one [[pv]] entry "
            "(the estimator regresses on PV plant measurements)"
        )
    if not dm.regulator and not dm.capacitor:
        raise TrainingError(
            f"feeder {dm.feeder.name!r}: the device map has no regulator and no capacitor bank; add a "
            "[[regulator]] (the correction of eq. (6)-(7) needs a regulator secondary measurement) or a "
            "[[capacitor]] entry"
        )


def _inputs(profiles, steps: np.ndarray, first_index: int = 0) -> list[ScenarioInput]:
    return [
        ScenarioInput(
            index=first_index + i,
            load_kw=profiles.load_kw(int(s), int(s) + 1)[0].astype(float),
            pv_kw=profiles.pv_kw(int(s), int(s) + 1)[0].astype(float),
        )
        for i, s in enumerate(steps)
    ]


def _tap_perturbation(engine, first: ScenarioInput, tap0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Algorithm 1 lines 2-6 and eq. (4): +1 tap of each regulator on the first scenario, Q = 0."""
    engine.set_loads_kw(first.load_kw)
    engine.set_pv(first.pv_kw, np.zeros(len(first.pv_kw)))
    engine.set_taps(tap0)
    engine.solve()
    v0 = engine.node_voltages_pu()
    v_tap = np.empty((len(tap0), v0.size))
    for r in range(len(tap0)):
        step = 1 if tap0[r] < engine.reg_tap_max[r] else -1  # at the top tap, step down and divide by -1
        t = tap0.copy()
        t[r] += step
        engine.set_taps(t)
        engine.solve()
        v_tap[r] = v0 + (engine.node_voltages_pu() - v0) / step
    engine.set_taps(tap0)
    engine.solve()
    return v0, tap_sensitivities(v0, v_tap)


def _q_sensitivities(engine, first: ScenarioInput, tap0: np.ndarray) -> np.ndarray:
    """dV/dQ of every node to each plant on the first scenario at Q = 0 [pu/kvar] (for ``movable_nodes``)."""
    engine.set_loads_kw(first.load_kw)
    engine.set_pv(first.pv_kw, np.zeros(len(first.pv_kw)))
    engine.set_taps(tap0)
    # Not restored in place (on a large feeder, undoing the moves leaves ~1e-4 pu, which the check refuses):
    # every later stage sets loads, PV and taps itself.
    dv_dq = engine.perturbation_sensitivities(restore=False).dv_dq
    engine.set_pv(first.pv_kw, np.zeros(len(first.pv_kw)))
    engine.set_taps(tap0)
    return dv_dq


def _critical(engine, dm, flows: PowerFlowSet, dv_dtap_all: np.ndarray, dv_dq_all: np.ndarray, margin_pu: float,
              tap0: np.ndarray, dv_dcap_all: np.ndarray | None):
    names = engine.node_names
    phases = np.asarray([node_phase(n) for n in names])
    v_ref = np.median(flows.v_pu, axis=0)
    eligible = (phases >= 1) & (phases <= 3) & (v_ref > 0.5)  # real phases of energised nodes
    # Nodes upstream of the head meter (the transmission side of the substation) are not the feeder: no
    # device of the feeder controls them, so they are never extremes to constrain (a source bus at
    # 1.045 pu would otherwise make every optimization infeasible above its 1.04 pu limit). Nor is a node that
    # no controlled device can move (an LTC's primary inside the zone, a stiff bus): critical.movable_nodes.
    eligible &= np.asarray(engine.node_in_feeder, bool)
    eligible &= movable_nodes(dv_dtap_all, dv_dq_all, engine.pv_kva)
    head = np.asarray([i for i in engine.head_node_index if eligible[i]], int)  # where the head meter is
    pv_nodes = np.asarray(sorted({i for idx in engine.pv_node_index for i in idx}), int)
    reg_primary = np.asarray(engine.reg_primary_node, int)
    required = {
        "head": head,
        "reg_primary": reg_primary[eligible[reg_primary]] if reg_primary.size else reg_primary,
        "reg_secondary": np.asarray(engine.reg_secondary_node, int),  # always: the correction reads them
        "pv": pv_nodes[eligible[pv_nodes]] if pv_nodes.size else pv_nodes,
    }
    upstream = upstream_regulators(dv_dtap_all, engine.reg_secondary_node)
    if margin_pu > 0:
        base = flows.v_pu[flows.plant == BASE]  # one flow per scenario: the Q sweeps move the extremes little
        shifted = device_shifted_voltages(base, dv_dtap_all, tap0, engine.reg_tap_max, dv_dcap_all,
                                          single_shifts=SINGLE_TAP_SHIFTS)
        every = np.concatenate([flows.v_pu.astype(np.float32), shifted])
        required["near_extreme"] = np.union1d(near_extreme_cover(every, eligible, margin_pu),
                                              zone_extreme_cover(every, eligible, upstream, margin_pu))
    crit = select_critical(required, extreme_nodes(flows.v_pu, eligible=eligible))
    return crit, upstream, phases


def train(
    device_map_path: str | Path,
    options: TrainingOptions = _DEFAULT_OPTIONS,
    *,
    workers: int | None = None,
    cache_dir: str | Path | None = None,
    profiles=None,
    progress: bool = True,
) -> TrainResult:
    """Train the estimator of one feeder (paper II.A-II.D) with ``options`` (``schemas.settings.TrainingOptions``:
    every setting, its default and its meaning).

    Parameters
    ----------
    device_map_path : the feeder's device map TOML.
    options : the training settings; the model records them (``CvvcModel.settings``, ``feature_set``).
    workers : power-flow processes; None: one per core; 1: in this process.
    cache_dir : where to cache the year profiles (None: no cache; the CLI passes ``schemas.cache.profiles_dir``).
    profiles : use these ``YearProfiles`` instead of generating them (tests).
    progress : progress bar on stderr when it is a terminal.

    Raises
    ------
    TrainingError
        No PV plant or regulator in the map, no usable scenario, a singular regression.
    """
    from schemas.devicemap import load_device_map
    from simulator_bridge.opendss.engine import FeederEngine
    from simulator_bridge.simulation.profiles import UTC_OFFSET_H

    o, f = options, options.features  # the run's settings and its feature set

    t_start = time.perf_counter()
    device_map_path = Path(device_map_path)
    dm = load_device_map(device_map_path)
    _check_device_map(dm, f.feature_set)
    engine = FeederEngine(dm, tolerance=o.tolerance)
    for what, d in (("load", engine.load_distance_ohm), ("PV plant", engine.pv_distance_ohm)):
        if not np.all(np.isfinite(d)):
            raise TrainingError(
                f"feeder {dm.feeder.name!r}: a {what} is not connected to source bus "
                f"{dm.feeder.source_bus!r}; check feeder.source_bus in the device map"
            )
    if profiles is None:
        profiles = load_profiles(dm, engine, seed=o.year_seed, cache_dir=cache_dir)
    if profiles.n_loads != len(engine.load_kw_nominal) or profiles.n_pv != len(engine.pv_kva):
        raise TrainingError(
            f"profiles have {profiles.n_loads} loads / {profiles.n_pv} plants, the feeder "
            f"{len(engine.load_kw_nominal)} / {len(engine.pv_kva)}; delete the profile cache"
        )

    # II.A: representative scenarios
    summary = summarize_year(profiles, engine.load_distance_ohm, engine.pv_distance_ohm)
    scen: ScenarioSet = select_scenarios(summary, blocks=o.blocks, selection=o.selection, seed=o.year_seed)
    inputs = _inputs(profiles, scen.steps)
    cover = calendar_cover(profiles.n_steps, profiles.year, per_cell=f.calendar_cover_per_cell, seed=o.year_seed,
                           exclude=scen.steps)
    all_steps = np.concatenate([scen.steps, cover]).astype(int)

    # tap0: local control at rest at the year's mean load and mean PV
    if summary.mean_load_kw is None or summary.mean_pv_kw is None:  # summarize_year always gives them
        raise TrainingError("the year summary has no mean load and PV (build it with summarize_year)")
    engine.set_loads_kw(summary.mean_load_kw)
    engine.set_pv(summary.mean_pv_kw, np.zeros(len(engine.pv_kva)))
    engine.set_taps(np.zeros(len(engine.regulator_ids), int))
    tap0 = settle_taps(engine)
    cap0 = engine.cap_states()  # every training flow keeps the banks here (the engine's compile-time state)

    # Algorithm 1 lines 2-6 (eq. 4), then the Q sweeps
    _, dv_dtap_all = _tap_perturbation(engine, inputs[0], tap0)
    pert = perturb_devices(engine, inputs[0].load_kw, inputs[0].pv_kw, tap0) if f.feature_set != "paper" else None
    t_pf = time.perf_counter()
    n_workers = max(1, min((os.cpu_count() or 1) if workers is None else workers, len(inputs)))
    flows = run_power_flows(
        engine,
        inputs,
        device_map_path=str(device_map_path),
        tolerance=o.tolerance,
        q_steps_pct=o.q_steps_pct,
        combined_pct=o.combined_pct,
        workers=n_workers,
        progress=progress,
    )
    if flows.n == 0:
        raise TrainingError(f"feeder {dm.feeder.name!r}: no training power flow converged; check the feeder")
    weights = np.ones(flows.n)
    if cover.size:  # base flows only, each weighted as a guided scenario's flows together
        extra = run_power_flows(engine, _inputs(profiles, cover, len(scen.steps)), device_map_path=str(device_map_path),
                                tolerance=o.tolerance, q_steps_pct=(), combined_pct=(), workers=n_workers,
                                progress=progress)
        weights = np.concatenate([weights, np.full(extra.n, flows.n / np.unique(flows.scenario).size)])
        flows = replace(PowerFlowSet.concat([flows, extra]), workers=flows.workers)
    seconds_pf = time.perf_counter() - t_pf

    # II.C: critical nodes
    dv_dq_all = _q_sensitivities(engine, inputs[0], tap0)
    # the banks' per-step sensitivities: the extended set's perturbations have them already
    dv_dcap_all = bank_sensitivities(engine, inputs, tap0, cap0) if pert is None else pert.dv_dcap_pu
    crit, upstream_all, phases = _critical(engine, dm, flows, dv_dtap_all, dv_dq_all, f.critical_margin_pu, tap0,
                                           None if pert is None else dv_dcap_all)
    nodes = crit.nodes
    pos = {int(n): i for i, n in enumerate(nodes)}

    # II.D: eq. (5) on the critical nodes (the target is the voltage at tap0: identity for frozen-tap flows)
    v_crit = flows.v_pu[:, nodes] - (flows.taps - tap0) @ dv_dtap_all[nodes].T
    if f.calendar and f.feature_set == "paper":
        raise TrainingError("calendar features belong to the extended feature sets; add --features extended")
    cal = (calendar_features(np.asarray([profiles.t_ns(int(all_steps[i])) for i in flows.scenario], np.int64),
                             UTC_OFFSET_H, f.calendar_seasonal, f.calendar_weekly)
           if f.calendar else np.zeros((flows.n, 0)))
    ext = None if pert is None else _extended(dm, engine, flows, pert, nodes, cap0, o.rcond, f.feature_set,
                                              cal.shape[1], float(UTC_OFFSET_H),
                                              _CalendarTerms(seasonal=f.calendar_seasonal, weekly=f.calendar_weekly))
    x = flows.features if ext is None else np.concatenate([flows.features, cal, ext.readings], axis=1)
    vfit, val_rmse, val_max = fit_voltages_with_holdout(flows.scenario, x, v_crit, rcond=o.rcond, weights=weights,
                                                        every=_HOLDOUT_EVERY)
    # eq. (3): samples from single-plant sweeps, form chosen on held-out scenarios
    samples = sensitivity_samples(flows.scenario, flows.plant, flows.pv_q_kvar, flows.q_head_kvar, v_crit)
    q_range = (float(flows.q_head_kvar.min()), float(flows.q_head_kvar.max()))
    c_kvar = choose_c_kvar(*q_range)
    sens = _fit_sensitivities(samples, nodes.size, engine.pv_ids, c_kvar, q_range)
    sens_rel = sensitivity_rel_err(sens, samples)
    forms = {f: sum(x.form == f for row in sens for x in row) for f in ("constant", "linear", "power")}
    neg_b = sum(x.form == "power" and x.b < 0 for row in sens for x in row)

    # the model file
    crit_nodes = [
        CriticalNode(
            name=engine.node_names[int(n)],
            phase=int(phases[int(n)]),  # type: ignore[arg-type]
            kinds=list(crit.kinds[i]),
            upstream_regulator=None if upstream_all[int(n)] < 0 else int(upstream_all[int(n)]),
        )
        for i, n in enumerate(nodes)
    ]
    regs = []
    for r, spec in enumerate(dm.regulator):
        sec = int(engine.reg_secondary_node[r])
        step_v120 = float(dv_dtap_all[sec, r] / engine.reg_pu_per_v120[r])
        regs.append(
            RegulatorInfo(
                id=spec.id,
                secondary_node=pos[sec],
                pu_per_v120=float(engine.reg_pu_per_v120[r]),
                tap_min=-int(engine.reg_tap_max[r]),
                tap_max=int(engine.reg_tap_max[r]),
                step_v120=round(step_v120, 4) if 0.1 < step_v120 < 5 else 0.75,
                cost_per_tap=spec.cost_per_tap,
                max_taps_per_interval=spec.max_taps_per_interval,
                default_setpoint_v120=float(engine.reg_default_setpoint_v120[r]),
                default_band_v120=float(engine.reg_default_band_v120[r]),
            )
        )
    pvs = [PvInfo(id=p.id, kva=p.kva, pmpp_kw=p.pmpp_kw, cost_per_kvar=p.cost_per_kvar, phases=p.phases) for p in dm.pv]
    seconds = time.perf_counter() - t_start
    from schemas.version import __version__

    fit_stats = FitStats(
        voltage_rmse_pu=float(np.sqrt(np.mean(vfit.rmse_pu**2))),
        voltage_max_abs_pu=vfit.max_abs_pu,
        sensitivity_median_rel_err=sens_rel if np.isfinite(sens_rel) else 0.0,
        per_node_rmse_pu=[float(x) for x in vfit.rmse_pu],
        validation_rmse_pu=val_rmse if np.isfinite(val_rmse) else 0.0,
        validation_max_abs_pu=val_max if np.isfinite(val_max) else 0.0,
        condition_number=vfit.condition_number if np.isfinite(vfit.condition_number) else 0.0,
    )
    model = CvvcModel(
        feeder_name=dm.feeder.name,
        fingerprint=dm.fingerprint(),
        cvvc_version=__version__,
        settings=TrainingSettings(
            year_seed=o.year_seed,
            selection=o.selection,
            blocks=(int(o.blocks[0]), int(o.blocks[1])),
            q_steps_pct=list(o.q_steps_pct),
            scenarios=len(scen.steps),
            power_flows=flows.n,
            seconds=round(seconds, 3),
            combined_pct=list(o.combined_pct),
            rcond=o.rcond,
            tolerance=o.tolerance,
            critical_margin_pu=f.critical_margin_pu,
            calendar_cover_per_cell=f.calendar_cover_per_cell,
        ),
        feature_names=feature_names(len(dm.pv)) if ext is None
        else extended_feature_names(len(dm.pv), ext.names, f.calendar, f.calendar_seasonal, f.calendar_weekly),
        critical_nodes=crit_nodes,
        regulators=regs,
        pv=pvs,
        alpha=vfit.alpha.tolist(),
        tap0=[int(t) for t in tap0],
        dv_dtap_pu=dv_dtap_all[nodes].tolist(),
        sens_q=sens,
        optimization_limits_pu=dm.feeder.optimization_limits_pu,
        judged_limits_pu=dm.feeder.judged_limits_pu,
        control_period_s=dm.feeder.control_period_s,
        node_count=len(engine.node_names),
        fit=fit_stats,
        **_bank_fields(bank_controls(engine, inputs, tap0, cap0, bank_infos(engine, dm, cap0)), dv_dcap_all[nodes],
                       ext),
    )
    t_cal = time.perf_counter()
    if o.calibration_minutes > 0:
        from training.calibration import calibrate_bounds

        bounds = calibrate_bounds(model, engine, profiles, training_steps=all_steps,
                                  training_features=flows.features, minutes=o.calibration_minutes,
                                  alpha=o.bound_alpha, progress=progress)
        model = msgspec.structs.replace(model, bounds=bounds)
    seconds_cal = time.perf_counter() - t_cal
    _check_finite(model)
    b = model.bounds
    summ = TrainSummary(
        feeder=dm.feeder.name,
        selection=o.selection,
        year_seed=o.year_seed,
        blocks=(int(o.blocks[0]), int(o.blocks[1])),
        non_empty_blocks=scen.non_empty_blocks,
        scenarios=len(scen.steps),
        power_flows=flows.n,
        failed_power_flows=flows.failed,
        critical_nodes=int(nodes.size),
        node_count=len(engine.node_names),
        critical_share=float(nodes.size / len(engine.node_names)),
        seconds=round(seconds, 3),
        seconds_power_flows=round(seconds_pf, 3),
        workers=flows.workers,
        tap0=model.tap0,
        q_head_range_kvar=q_range,
        c_kvar=c_kvar,
        condition_number=vfit.condition_number,
        voltage_rmse_pu=fit_stats.voltage_rmse_pu,
        voltage_max_abs_pu=fit_stats.voltage_max_abs_pu,
        validation_rmse_pu=val_rmse,
        validation_max_abs_pu=val_max,
        sensitivity_median_rel_err=fit_stats.sensitivity_median_rel_err,
        sensitivity_forms=forms,
        calibration_minutes=0 if b is None else b.calibration_minutes,
        bound_p50_pu=0.0 if b is None else float(np.median((np.add(b.upper_pu, b.lower_pu)) / 2.0)),
        bound_level=0.0 if b is None else b.level,
        bound_held_out_miss=0.0 if b is None else b.held_out_miss,
        seconds_calibration=round(seconds_cal, 3),
        power_fits_with_negative_b=neg_b,
        cover_minutes=int(cover.size),
    )
    return TrainResult(model=model, summary=summ)


class _CalendarTerms(NamedTuple):
    """The calendar terms beyond time of day and day of year (``regression.model.calendar_features``)."""

    seasonal: int  # the daily harmonics (0, 1 or 2) also taken times the yearly one
    weekly: bool  # the weekend and its daily shape


@dataclass(frozen=True)
class _Extended:
    """The extended feature set's training products."""

    names: list[str]  # the readings, model order
    readings: np.ndarray  # (F, J) readings of every flow [pu]
    model_fields: dict  # the CvvcModel fields of the extended set


def _bank_fields(banks: list, dv_dcap_pu: np.ndarray, ext: _Extended | None) -> dict:
    """The model's bank fields: the banks and their per-step sensitivities (``training.capbanks``), or the
    extended feature set's, which carry the same banks with their reading references and their own
    perturbations (``training.extended``).
    """
    fields: dict = {"capacitors": banks, "dv_dcap_pu": dv_dcap_pu.tolist() if banks else []}
    if ext is not None:  # its banks carry their reading references; ``banks`` their local controls
        fields.update(ext.model_fields)
        fields["capacitors"] = [msgspec.structs.replace(b, v_ref_v=e.v_ref_v)
                                for b, e in zip(banks, ext.model_fields["capacitors"], strict=True)]
    return fields


def _extended(
    dm, engine, flows: PowerFlowSet, pert, nodes: np.ndarray, cap0: np.ndarray, rcond: float, feature_set: str,
    n_calendar: int, utc_offset_h: float, calendar_terms: _CalendarTerms,
) -> _Extended:
    """The banks' static term, the feature mapping and (``extended_readings``) the readings as regressors."""
    n_reg = flows.reg_pu.shape[1]
    v_ref = np.median(flows.cap_v_v, axis=0) if flows.cap_v_v.size else np.zeros(0)
    if np.any(v_ref <= 0):
        raise TrainingError("a capacitor bank's bus reads 0 V in training; check its bus in the device map")
    readings = reading_matrix(flows.reg_pu, flows.cap_v_v, v_ref)
    use = feature_set == "extended_readings"
    # the bank readings' perturbations are in V: per unit of v_ref like the readings
    scale = np.concatenate([np.ones(pert.feature_dtap.shape[0] - v_ref.size), 1.0 / v_ref])
    f_tap, f_cap = pert.feature_dtap * scale[:, None], pert.feature_dcap * scale[:, None]
    reading_fit = fit_voltage_regression(flows.features, readings, rcond=rcond)
    names = [f"reg:{r.id}" for r in dm.regulator] + [f"cap:{c.id}" for c in dm.capacitor]
    if len(names) != n_reg + v_ref.size:
        raise TrainingError("the device map's regulators and banks do not match the engine's")
    n_paper = flows.features.shape[1]
    if not use:  # no readings: the mapping of the paper features only
        names, readings = [], readings[:, :0]
        f_tap, f_cap = f_tap[:n_paper], f_cap[:n_paper]
    # the calendar features follow the paper's; no device moves them
    f_tap = np.insert(f_tap, [n_paper] * n_calendar, 0.0, axis=0)
    f_cap = np.insert(f_cap, [n_paper] * n_calendar, 0.0, axis=0)
    caps = [msgspec.structs.replace(c, v_ref_v=float(v)) for c, v in zip(bank_infos(engine, dm, cap0), v_ref,
                                                                                 strict=True)]
    fields = {
        "feature_set": feature_set,
        "capacitors": caps,
        "cap0": [int(c) for c in cap0],
        "dv_dcap_pu": pert.dv_dcap_pu[nodes].tolist() if cap0.size else [],
        "readings": names,
        "feature_dtap": f_tap.tolist(),
        "feature_dcap": f_cap.tolist(),
        "reading_alpha": reading_fit.alpha.tolist() if use else [],
        "calendar": n_calendar > 0,
        "calendar_seasonal": calendar_terms.seasonal if n_calendar else 0,
        "calendar_weekly": calendar_terms.weekly and n_calendar > 0,
        "utc_offset_h": utc_offset_h,
    }
    return _Extended(names=names, readings=readings, model_fields=fields)


def _fit_sensitivities(
    samples: SensitivitySamples, n_nodes: int, pv_ids, c_kvar: float, q_range: tuple[float, float]
) -> list[list[SensitivityFit]]:
    """Eq. (3) fit of every (critical node, plant) pair; the form is chosen on held-out scenarios."""
    s_hold = (samples.scenario % _HOLDOUT_EVERY) == _HOLDOUT_EVERY - 1
    for k, pv_id in enumerate(pv_ids):
        if not np.any(samples.plant == k):
            raise TrainingError(
                f"PV plant {pv_id!r} has no Q sweep (no reactive headroom at any scenario); raise its kva "
                "above pmpp_kw in the device map"
            )
    sens = []
    for i in range(n_nodes):
        row = []
        for k in range(len(pv_ids)):
            m = samples.plant == k
            fit, _ = fit_sensitivity(
                samples.q_head_kvar[m],
                samples.dv_dq_pu_per_kvar[m, i],
                c_kvar=c_kvar,
                q_range_kvar=q_range,
                holdout=s_hold[m],
            )
            row.append(fit)
        sens.append(row)
    return sens


def _check_finite(model: CvvcModel) -> None:
    bad = []
    if not np.all(np.isfinite(np.asarray(model.alpha, float))):
        bad.append("alpha")
    if not np.all(np.isfinite(np.asarray(model.dv_dtap_pu, float))):
        bad.append("dv_dtap_pu")
    if not np.all(np.isfinite(np.asarray(model.dv_dcap_pu, float))):
        bad.append("dv_dcap_pu")
    if not all(np.isfinite([f.a, f.b, f.c]).all() for row in model.sens_q for f in row):
        bad.append("sens_q")
    if bad:
        raise TrainingError(
            f"training produced non-finite {', '.join(bad)}; use more scenarios (--blocks) "
            "or check the feeder for non-converging power flows"
        )
