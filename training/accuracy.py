"""Accuracy report: the trained estimator against OpenDSS over a month at 1-minute resolution.

Simulates one month of a year (usually another seed than training: out of sample) with regulator local
control (``simulator_bridge.simulation.qsts.Qsts``, PV at unity power factor), then estimates every critical node of
each model with paper eq. (5) and with the correction of eq. (6)-(7), and compares with OpenDSS's
voltages. At sampled minutes it also compares the eq. (3) sensitivities with perturbation truth
(``FeederEngine.perturbation_sensitivities``). Writes a PNG like the paper's Fig. 8.

Explicit option, not the paper's: ``ami_meters=K`` adds a row per model with K AMI meters at the critical
nodes of widest calibrated bounds (``training.ami``: placement, meter model and the estimate).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import msgspec
import numpy as np

from regression.batch import estimate_v_pu, eval_sensitivities, sensitivity_arrays
from regression.model import CvvcModel, ModelArrays, features, read_model
from training.ami import AMI_SEED, ami_estimate_v_pu, ami_placement, check_ami_options
from training.errors import TrainingError

__all__ = ["AccuracyReport", "ErrorStats", "MonthTruth", "accuracy_report", "error_stats", "simulate_month"]

WITHIN_PU = 0.01
EXTREME_GAP_PU = 0.002  #'s goal: the zone's extremes within this of a critical node's


class ErrorStats(msgspec.Struct, frozen=True, kw_only=True):
    """Estimation error (estimate - truth) over all (minute, critical node) samples [pu]."""

    label: str
    samples: int
    mean_pu: float
    rmse_pu: float
    p1_pu: float
    p99_pu: float
    max_abs_pu: float
    within_001: float  # share of samples with |error| <= 0.01 pu


class SensitivityStats(msgspec.Struct, frozen=True, kw_only=True):
    """Eq. (3) estimates vs perturbation truth over significant (node, plant) pairs at sampled minutes."""

    label: str
    minutes: int
    pairs: int
    median_rel_err: float
    p90_rel_err: float


class AccuracyReport(msgspec.Struct, frozen=True, kw_only=True):
    """Estimation accuracy of a model over a simulated month: errors at the critical nodes and every node."""

    feeder: str
    month: int
    year_seed: int
    minutes: int
    errors: list[ErrorStats]
    sensitivities: list[SensitivityStats]
    extreme_capture: dict[str, float]  # per model: share of minutes whose true max and min zone node are critical
    extreme_gap_max_pu: dict[str, float]  # per model: worst (true feeder extreme - critical-node extreme)
    extreme_gap_p99_pu: dict[str, float]
    extreme_within_gap: dict[str, float] = {}  # per model: share of minutes with both gaps <= EXTREME_GAP_PU
    png: str | None = None
    bound_alpha: dict[str, float] = {}  # per model with calibrated bounds: the promised miscoverage
    bound_miss_rate: dict[str, float] = {}  # ... and the realised share of (minute, node) outside the bounds
    # per model: the critical nodes with an AMI meter (explicit option; unset, so absent from JSON, without meters)
    ami_nodes: dict[str, list[str]] | msgspec.UnsetType = msgspec.UNSET


def error_stats(label: str, err_pu: np.ndarray) -> ErrorStats:
    """Summary statistics of an error array (any shape) [pu]."""
    e = np.asarray(err_pu, float).ravel()
    if e.size == 0:
        raise TrainingError("no samples to summarise; simulate at least one minute")
    return ErrorStats(
        label=label,
        samples=int(e.size),
        mean_pu=float(e.mean()),
        rmse_pu=float(np.sqrt(np.mean(e**2))),
        p1_pu=float(np.percentile(e, 1)),
        p99_pu=float(np.percentile(e, 99)),
        max_abs_pu=float(np.max(np.abs(e))),
        within_001=float(np.mean(np.abs(e) <= WITHIN_PU)),
    )


@dataclass(frozen=True)
class MonthTruth:
    """What the month simulation recorded (T minutes)."""

    steps: np.ndarray  # (T,)
    t_ns: np.ndarray  # (T,) UTC epoch nanoseconds of each minute
    features: np.ndarray  # (T, M)
    q_head_kvar: np.ndarray  # (T,)
    taps: np.ndarray  # (T, R)
    reg_v120: np.ndarray  # (T, R) raw secondary voltage [V on 120 V base]
    cap_states: np.ndarray  # (T, C) closed steps of each map capacitor bank
    cap_v_v: np.ndarray  # (T, C) each bank's bus voltage reading [V]
    v_pu: np.ndarray  # (T, len(nodes)) truth at the requested nodes
    nodes: np.ndarray  # node indices of v_pu's columns
    argmax: np.ndarray  # (T,) node of the highest voltage (phases 1-3, in the feeder zone)
    argmin: np.ndarray  # (T,) node of the lowest voltage
    v_max_pu: np.ndarray  # (T,) highest node voltage (phases 1-3)
    v_min_pu: np.ndarray  # (T,) lowest node voltage
    sens_steps: np.ndarray  # (S,) minutes (row index into steps) where sensitivities were perturbed
    sens_q_pu_per_kvar: np.ndarray  # (S, len(nodes), K) perturbation truth

    def corrected_estimate(self, arrays: ModelArrays) -> np.ndarray:
        """(T, N) the model's corrected estimates (eq. 5-7, as the agent computes them) at these minutes [pu]."""
        return estimate_v_pu(arrays, self.features, self.taps, self.reg_v120, caps=self.cap_states,
                             cap_v_v=self.cap_v_v, t_ns=self.t_ns)


def simulate_month(
    engine,
    profiles,
    steps: range | Sequence[int],
    nodes: np.ndarray,
    *,
    sens_minutes: int = 24,
    progress: bool = True,
    setpoint_offset_v120: np.ndarray | None = None,
) -> MonthTruth:
    """Run QSTS over ``steps`` (consecutive) and record features, taps and truth at ``nodes``.

    ``setpoint_offset_v120`` (R,) [V on the 120 V base]: the regulators' local set points moved by these from their
    defaults for the whole run (the tap states a central controller's set points create); None: the defaults.
    """
    from tqdm import tqdm

    from simulator_bridge.simulation.qsts import Qsts

    steps = list(steps)
    phases = np.asarray([n.rpartition(".")[2] for n in engine.node_names])
    eligible = np.isin(phases, ["1", "2", "3"]) & np.asarray(engine.node_in_feeder, bool)  # the zone's nodes
    qsts = Qsts(engine, profiles, start_step=steps[0])
    if setpoint_offset_v120 is not None:
        for reg, offset in enumerate(np.asarray(setpoint_offset_v120, float)):
            qsts.command_setpoint(reg, float(engine.reg_default_setpoint_v120[reg]) + offset, None)
    sens_at = set(np.linspace(0, len(steps) - 1, min(sens_minutes, len(steps))).round().astype(int).tolist())
    feats, qh, taps, v120, vv, amax, amin, s_rows, s_vals, vext = [], [], [], [], [], [], [], [], [], []
    caps, cap_v = [], []
    bar = tqdm(steps, desc="month", unit="min", file=sys.stderr, disable=not (progress and sys.stderr.isatty()))
    for i, _ in enumerate(bar):
        res = qsts.step()
        r = res.readings
        feats.append(features(r.head_p_kw, r.head_q_kvar, r.pv_p_kw.sum(axis=1), r.pv_q_kvar.sum(axis=1)))
        qh.append(float(np.sum(r.head_q_kvar)))
        taps.append(res.taps)
        v120.append(r.reg_v120)
        caps.append(r.cap_states)
        cap_v.append(r.cap_v_v)
        vv.append(res.v_pu[nodes])
        v_el = np.where(eligible & (res.v_pu > 0.5), res.v_pu, np.nan)
        amax.append(int(np.nanargmax(v_el)))
        amin.append(int(np.nanargmin(v_el)))
        vext.append((float(v_el[amax[-1]]), float(v_el[amin[-1]])))
        if i in sens_at:
            dv_dq = engine.perturbation_sensitivities().dv_dq
            s_rows.append(i)
            s_vals.append(dv_dq[nodes])
    bar.close()
    k = len(engine.pv_ids)
    return MonthTruth(
        steps=np.asarray(steps, int),
        t_ns=np.asarray([profiles.t_ns(int(s)) for s in steps], np.int64),
        features=np.asarray(feats),
        q_head_kvar=np.asarray(qh),
        taps=np.asarray(taps, float),
        reg_v120=np.asarray(v120),
        cap_states=np.asarray(caps, float).reshape(len(steps), -1),
        cap_v_v=np.asarray(cap_v, float).reshape(len(steps), -1),
        v_pu=np.asarray(vv),
        nodes=np.asarray(nodes, int),
        argmax=np.asarray(amax, int),
        argmin=np.asarray(amin, int),
        v_max_pu=np.asarray([x[0] for x in vext]),
        v_min_pu=np.asarray([x[1] for x in vext]),
        sens_steps=np.asarray(s_rows, int),
        sens_q_pu_per_kvar=np.asarray(s_vals).reshape(len(s_rows), len(nodes), k),
    )


def _label(model: CvvcModel, path: Path, labels: list[str]) -> str:
    base: str = model.settings.selection
    if model.feature_set != "paper":
        base = f"{base} {model.feature_set}"
    return base if base not in labels else f"{base} ({path.name})"


def _sens_stats(label: str, pred: np.ndarray, truth: np.ndarray) -> SensitivityStats:
    """Relative error over pairs whose median |dV/dQ| is >= 10 % of the node's largest plant's."""
    med = np.nanmedian(np.abs(truth), axis=0)  # (N, K)
    sig = med >= 0.1 * np.nanmax(med, axis=1, keepdims=True)
    t = truth[:, sig]
    p = pred[:, sig]
    ok = np.isfinite(t) & (np.abs(t) > 0)
    rel = np.abs(p[ok] - t[ok]) / np.abs(t[ok])
    if rel.size == 0:
        return SensitivityStats(label=label, minutes=int(truth.shape[0]), pairs=0, median_rel_err=0.0, p90_rel_err=0.0)
    return SensitivityStats(
        label=label,
        minutes=int(truth.shape[0]),
        pairs=int(sig.sum()),
        median_rel_err=float(np.median(rel)),
        p90_rel_err=float(np.percentile(rel, 90)),
    )


def accuracy_report(
    model_path: str | Path | Sequence[str | Path],
    device_map_path: str | Path,
    month: int,
    year_seed: int,
    *,
    png_path: str | Path | None = None,
    max_minutes: int | None = None,
    sens_minutes: int = 24,
    cache_dir: str | Path | None = None,
    progress: bool = True,
    ami_meters: int = 0,
    ami_interval_min: int = 15,
    ami_noise_pu: float = 0.001,
    ami_latency_min: int = 0,
    ami_seed: int = AMI_SEED,
) -> AccuracyReport:
    """Estimation error of one or more models over a month (paper IV.D-E, Fig. 8).

    Parameters
    ----------
    model_path : one model file or several (e.g. guided and random selection) of the same feeder.
    device_map_path : the feeder's device map.
    month : 1..12.
    year_seed : seed of the simulated year (use another than training's for out of sample).
    png_path : where to write the figure (None: no figure).
    max_minutes : simulate only the first minutes of the month (tests, quick looks).
    sens_minutes : minutes at which eq. (3) is compared with perturbation truth.
    ami_meters : explicit option, not the paper's: K AMI meters per model at the K critical nodes with the
        widest calibrated bounds (training information only); adds the row "..., with correction + K AMI
        meters (I min)" and ``ami_nodes``. 0 (default): no meter, the report as without the option.
    ami_interval_min : minutes between meter readings (from the first simulated minute).
    ami_noise_pu : standard deviation of the Gaussian reading noise [pu], seeded by ``ami_seed``.
    ami_latency_min : minutes from a reading to its first use. See ``training.ami`` for the estimate.
    """
    from schemas.devicemap import load_device_map
    from simulator_bridge.opendss.engine import FeederEngine
    from simulator_bridge.simulation.profiles import feeder_profiles, month_steps

    paths = [Path(model_path)] if isinstance(model_path, (str, Path)) else [Path(p) for p in model_path]
    if not paths:
        raise TrainingError("no model given; pass --model MODEL")
    dm = load_device_map(device_map_path)
    fp = dm.fingerprint()
    models = [read_model(p, expect_fingerprint=fp) for p in paths]
    if not 1 <= month <= 12:
        raise TrainingError(f"month {month} is not in 1..12")
    ami_cols = [_ami_cols(m, p, ami_meters) for m, p in zip(models, paths, strict=True)]  # fail before simulating
    if ami_meters > 0:
        check_ami_options(ami_interval_min, ami_noise_pu, ami_latency_min)
    engine = FeederEngine(dm, tolerance=1e-8)
    names = {n: i for i, n in enumerate(engine.node_names)}
    model_nodes = [np.asarray([names[c.name] for c in m.critical_nodes], int) for m in models]
    nodes = np.unique(np.concatenate(model_nodes))
    col = {int(n): j for j, n in enumerate(nodes)}
    profiles = feeder_profiles(dm, engine, seed=year_seed, cache_dir=cache_dir)
    steps = month_steps(profiles, month)
    if max_minutes is not None:
        steps = steps[: max(1, int(max_minutes))]
    truth = simulate_month(engine, profiles, steps, nodes, sens_minutes=sens_minutes, progress=progress)

    errors: list[ErrorStats] = []
    sens: list[SensitivityStats] = []
    capture: dict[str, float] = {}
    gap_max: dict[str, float] = {}
    gap_p99: dict[str, float] = {}
    bound_alpha: dict[str, float] = {}
    bound_miss: dict[str, float] = {}
    within_gap: dict[str, float] = {}
    curves: dict[str, np.ndarray] = {}
    labels: list[str] = []
    ami_nodes: dict[str, list[str]] = {}
    for m, path, mn, idx in zip(models, paths, model_nodes, ami_cols, strict=True):
        label = _label(m, path, labels)
        labels.append(label)
        arrays = ModelArrays.of(m)
        cols = [col[int(n)] for n in mn]
        v_true = truth.v_pu[:, cols]
        plain = estimate_v_pu(arrays, truth.features, truth.taps, caps=truth.cap_states, t_ns=truth.t_ns) - v_true
        est_corr = truth.corrected_estimate(arrays)
        corr = est_corr - v_true
        if m.bounds is not None:  # predicted against realised: the share of corrected estimates outside the bounds
            up, lo = np.asarray(m.bounds.upper_pu), np.asarray(m.bounds.lower_pu)
            bound_alpha[label] = m.bounds.alpha
            bound_miss[label] = float(np.mean((-corr > up) | (corr > lo)))
        errors.append(error_stats(f"{label}, no correction", plain))
        errors.append(error_stats(f"{label}, with correction", corr))
        if ami_meters > 0:
            ami = corr.copy()
            ami[:, idx] = ami_estimate_v_pu(est_corr[:, idx], v_true[:, idx], interval_min=ami_interval_min,
                                            noise_pu=ami_noise_pu, latency_min=ami_latency_min,
                                            seed=ami_seed) - v_true[:, idx]
            errors.append(error_stats(f"{label}, with correction + {ami_meters} AMI meters ({ami_interval_min} min)",
                                      ami))
            ami_nodes[label] = [m.critical_nodes[int(i)].name for i in idx]
        curves[f"{label}, no correction"] = plain.ravel()
        curves[f"{label}, with correction"] = corr.ravel()
        crit = set(mn.tolist())
        capture[label] = float(
            np.mean([a in crit and b in crit for a, b in zip(truth.argmax, truth.argmin, strict=True)])
        )
        gap = np.maximum(truth.v_max_pu - v_true.max(axis=1), v_true.min(axis=1) - truth.v_min_pu)
        gap_max[label] = float(gap.max())
        gap_p99[label] = float(np.percentile(gap, 99))
        within_gap[label] = float(np.mean(gap <= EXTREME_GAP_PU))
        if truth.sens_steps.size:
            pred = eval_sensitivities(sensitivity_arrays(m.sens_q), truth.q_head_kvar[truth.sens_steps])
            sens.append(_sens_stats(label, pred, truth.sens_q_pu_per_kvar[:, cols, :]))
    png = None
    if png_path is not None:
        png = str(_plot(curves, labels, Path(png_path), dm.feeder.name, month))
    return AccuracyReport(
        feeder=dm.feeder.name,
        month=month,
        year_seed=year_seed,
        minutes=len(truth.steps),
        errors=errors,
        sensitivities=sens,
        extreme_capture=capture,
        extreme_gap_max_pu=gap_max,
        extreme_gap_p99_pu=gap_p99,
        extreme_within_gap=within_gap,
        png=png,
        bound_alpha=bound_alpha,
        bound_miss_rate=bound_miss,
        ami_nodes=ami_nodes if ami_meters > 0 else msgspec.UNSET,
    )


def _ami_cols(model: CvvcModel, path: Path, meters: int) -> np.ndarray:
    """Critical-node indices of the model's AMI meters (``training.ami.ami_placement``); none for 0 meters."""
    if meters < 0:
        raise TrainingError(f"{meters} AMI meters: give 0 or more")
    if meters == 0:
        return np.zeros(0, int)
    if model.bounds is None:
        raise TrainingError(
            f"model {path.name} has no calibrated bounds, which place the AMI meters: retrain it with "
            "cvvc train (it calibrates bounds) or run without --ami-meters"
        )
    try:
        return ami_placement(np.asarray(model.bounds.upper_pu), np.asarray(model.bounds.lower_pu), meters)
    except TrainingError as e:
        raise TrainingError(f"model {path.name}: {e}") from e


def _plot(curves: dict[str, np.ndarray], labels: list[str], path: Path, feeder: str, month: int) -> Path:
    """Two panels like the paper's Fig. 8: (a) models with correction, (b) first model with/without."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=False)
    lim = max(0.012, float(np.percentile(np.abs(np.concatenate(list(curves.values()))), 99.9)))
    bins = np.linspace(-lim, lim, 81)
    for label in labels:
        axes[0].hist(curves[f"{label}, with correction"], bins=bins, histtype="step", density=True, label=label)
    axes[0].set_title(f"(a) selection, with correction - {feeder}, month {month}")
    first = labels[0]
    for suffix in ("no correction", "with correction"):
        axes[1].hist(curves[f"{first}, {suffix}"], bins=bins, histtype="step", density=True, label=suffix)
    axes[1].set_title(f"(b) correction ({first} selection)")
    for ax in axes:
        ax.axvline(-WITHIN_PU, color="grey", lw=0.8, ls="--")
        ax.axvline(WITHIN_PU, color="grey", lw=0.8, ls="--")
        ax.set_xlabel("voltage estimation error [pu]")
        ax.set_ylabel("density")
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
