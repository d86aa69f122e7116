"""Where a few AMI meters would pay: the critical nodes ranked by the gain a meter measurably brings.

Some nodes no feeder-level measurement can estimate: a 240 V service whose voltage follows its own customer's load.
Their error decides the estimate bounds, hence how much of the voltage band the agent must leave unused. A meter
read every ``interval`` minutes at such a node (``[[meter]]`` in the device map, ``agent.ami``) removes most of it.
This module measures, for every critical node, what a meter there would gain, and ranks the nodes by it:

1. QSTS (OpenDSS, 1-minute steps, regulators on local control, PV at unity power factor) over the first minutes of
   each month asked, of the profile year asked (by default the training year: advice from what a planner has before
   any field data; a run on another year then judges it);
2. the corrected estimate (eq. 5-7) of every critical node against the truth, as ``cvvc report accuracy`` does;
3. a meter at node ``n`` (``training.ami.ami_estimate_v_pu``: reading plus noise, the estimate moved by the latest
   reading's residual) and its squared error; a node's **gain** is the squared error a meter removes there (a meter
   changes no other node's estimate, so the best ``K`` sites are the ``K`` largest gains);
4. per site, the RMSE without and with the meter, the share of the critical nodes' squared error it carries, and the
   share of minutes outside the model's bounds (without a meter) and outside its AMI bounds (with one).

``write_advised_map`` writes the device map with the advised ``[[meter]]`` entries (same fingerprint: the model
serves both), so a run with and without them shows the gain live.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import msgspec
import numpy as np

from regression.model import CvvcModel, ModelArrays, read_model
from training.accuracy import WITHIN_PU
from training.ami import AMI_SEED, ami_estimate_v_pu, check_ami_options
from training.errors import TrainingError

__all__ = ["MeterAdvice", "MeterSite", "advise_meters", "rank_sites", "write_advised_map"]

class MeterSite(msgspec.Struct, frozen=True, kw_only=True):
    """One critical node as a meter site: its figures without and with a meter (errors in pu).

    ``gain``: the share of the critical nodes' squared error (no meter) that a meter here removes.
    ``miss_rate``: share of minutes with the truth outside the model's bounds; ``miss_rate_metered``: outside its
    AMI bounds with the meter (None: a model without AMI bounds).
    """

    rank: int
    node: str
    rmse_pu: float
    rmse_metered_pu: float
    gain: float
    miss_rate: float | None
    miss_rate_metered: float | None


class MeterAdvice(msgspec.Struct, frozen=True, kw_only=True):
    """The ``k`` best meter sites of a feeder's critical nodes, best first (fewer when fewer nodes gain from a meter),
    and the feeder's figures without and with them (every critical node: RMSE [pu], share within ±0.01 pu, share
    outside the bounds).
    """

    feeder: str
    model: str
    year_seed: int
    months: list[int]
    minutes: int
    interval_min: int
    noise_pu: float
    k: int
    already_metered: list[str]
    sites: list[MeterSite]
    rmse_pu: float
    rmse_with_k_pu: float
    within: float
    within_with_k: float
    miss_rate: float | None
    miss_rate_with_k: float | None


def _miss(err: np.ndarray, upper: np.ndarray, lower: np.ndarray) -> np.ndarray:
    """Per node, the share of rows with ``err = true - estimate`` outside ``[-lower, upper]``."""
    return np.mean((err > upper) | (-err > lower), axis=0)


def rank_sites(err: np.ndarray, err_metered: np.ndarray, exclude: Sequence[int] = ()) -> np.ndarray:
    """Critical-node indices, best meter site first: by the squared error a meter removes (``err`` (T, N) without
    meters, ``err_metered`` (T, N) with one at every node), ties to the lower index; ``exclude`` left out, and so is
    every node where a meter removes nothing (its noise outweighs the estimate's error there).
    """
    gain = np.sum(np.square(err), axis=0) - np.sum(np.square(err_metered), axis=0)
    order = np.lexsort((np.arange(gain.size), -gain))
    skip = set(int(i) for i in exclude)
    return np.array([int(i) for i in order if int(i) not in skip and gain[i] > 0.0], int)


def advise_meters(model_path: str | Path, device_map_path: str | Path, *, k: int, months: Sequence[int] = (1, 7),
                  minutes: int = 1440, year_seed: int = 1, interval_min: int = 15, noise_pu: float = 0.001,
                  cache_dir: str | Path | None = None, progress: bool = True) -> MeterAdvice:
    """Rank the model's critical nodes as meter sites (module docstring) and keep the ``k`` best."""
    from schemas.devicemap import load_device_map
    from simulator_bridge.opendss.engine import FeederEngine
    from simulator_bridge.simulation.profiles import feeder_profiles, month_steps
    from training.accuracy import simulate_month

    dm = load_device_map(device_map_path)
    model = read_model(model_path, expect_fingerprint=dm.fingerprint())
    names = [c.name for c in model.critical_nodes]
    if not 1 <= k <= len(names):
        raise TrainingError(f"{k} meters asked for; the model has {len(names)} critical nodes (1..{len(names)})")
    if not months or any(not 1 <= m <= 12 for m in months):
        raise TrainingError(f"months {list(months)}: give months in 1..12")
    if minutes < interval_min:
        raise TrainingError(f"{minutes} minutes per month: at least one meter interval ({interval_min}) needed")
    check_ami_options(interval_min, noise_pu, 0)
    engine = FeederEngine(dm, tolerance=1e-8)
    index = {n: i for i, n in enumerate(engine.node_names)}
    nodes = np.asarray([index[n] for n in names], int)
    arrays = ModelArrays.of(model)
    profiles = feeder_profiles(dm, engine, seed=year_seed, cache_dir=cache_dir)
    rng = np.random.default_rng(AMI_SEED)
    errs, metered = [], []
    for month in months:
        steps = month_steps(profiles, month)[: int(minutes)]
        truth = simulate_month(engine, profiles, steps, nodes, sens_minutes=0, progress=progress)
        est = truth.corrected_estimate(arrays)
        errs.append(truth.v_pu - est)
        with_meter = ami_estimate_v_pu(est, truth.v_pu, interval_min=interval_min, noise_pu=noise_pu, latency_min=0,
                                       rng=rng)
        metered.append(truth.v_pu - with_meter)
    err, err_m = np.concatenate(errs), np.concatenate(metered)
    return _advice(model, dm, Path(model_path), err, err_m, k=k, months=list(months), year_seed=year_seed,
                   interval_min=interval_min, noise_pu=noise_pu)


def _advice(model: CvvcModel, dm, model_path: Path, err: np.ndarray, err_m: np.ndarray, *, k: int, months: list[int],
            year_seed: int, interval_min: int, noise_pu: float) -> MeterAdvice:
    names = [c.name for c in model.critical_nodes]
    already = [m.node for m in dm.meter if m.node in names]
    order = rank_sites(err, err_m, exclude=[names.index(n) for n in already])[:k]
    sq = np.sum(np.square(err), axis=0)
    total_sq = float(sq.sum()) or 1.0
    b = model.bounds
    miss = miss_m = None
    if b is not None:
        miss = _miss(err, np.asarray(b.upper_pu), np.asarray(b.lower_pu))
        if b.ami_upper_pu:
            miss_m = _miss(err_m, np.asarray(b.ami_upper_pu), np.asarray(b.ami_lower_pu))
    rmse, rmse_m = np.sqrt(np.mean(np.square(err), axis=0)), np.sqrt(np.mean(np.square(err_m), axis=0))
    sites = [MeterSite(rank=r + 1, node=names[i], rmse_pu=float(rmse[i]), rmse_metered_pu=float(rmse_m[i]),
                       gain=float((sq[i] - np.sum(np.square(err_m[:, i]))) / total_sq),
                       miss_rate=None if miss is None else float(miss[i]),
                       miss_rate_metered=None if miss_m is None else float(miss_m[i]))
             for r, i in enumerate(order)]
    chosen = np.array(sorted(set(order.tolist()) | {names.index(n) for n in already}), int)
    with_k = err.copy()
    with_k[:, chosen] = err_m[:, chosen]
    miss_k = None
    if miss is not None:
        per = miss.copy()
        if miss_m is not None:
            per[chosen] = miss_m[chosen]
        miss_k = float(per.mean())
    return MeterAdvice(
        feeder=dm.feeder.name, model=str(model_path), year_seed=year_seed, months=months, minutes=int(err.shape[0]),
        interval_min=interval_min, noise_pu=noise_pu, k=k, already_metered=already, sites=sites,
        rmse_pu=float(np.sqrt(np.mean(np.square(err)))), rmse_with_k_pu=float(np.sqrt(np.mean(np.square(with_k)))),
        within=float(np.mean(np.abs(err) <= WITHIN_PU)), within_with_k=float(np.mean(np.abs(with_k) <= WITHIN_PU)),
        miss_rate=None if miss is None else float(miss.mean()), miss_rate_with_k=miss_k,
    )


_METER_ID = re.compile(r"^ami(\d+)$")


def write_advised_map(device_map_path: str | Path, advice: MeterAdvice, out: str | Path, *,
                      interval_s: int | None = None) -> Path:
    """Write the device map with ``advice``'s sites as ``[[meter]]`` entries to ``out``, beside the map.

    The map's paths are relative to its folder and its fingerprint covers them, so the advised map must sit in the
    same folder (the model then serves both). Meter ids ``ami<N>`` continue after the map's own.
    """
    from schemas.devicemap import load_device_map

    src, dst = Path(device_map_path), Path(out)
    if src.is_dir():
        src = src / "devicemap.toml"
    if dst.resolve().parent != src.resolve().parent:
        raise TrainingError(f"{dst}: write the advised map beside {src} (its paths are relative to its folder)")
    if dst.resolve() == src.resolve():
        raise TrainingError(f"{dst}: that is the map itself; give another file name")
    dm = load_device_map(src)
    used = [int(m.group(1)) for m in (_METER_ID.match(x.id) for x in dm.meter) if m]
    first = max(used, default=0) + 1
    every = interval_s if interval_s is not None else advice.interval_min * 60
    lines = [f"\n# AMI meters advised by `cvvc feeder advise-meters` (model {Path(advice.model).name}, year seed "
             f"{advice.year_seed}, months {advice.months}): the {len(advice.sites)} critical nodes where a meter read "
             f"every {advice.interval_min} min removes the most squared error; without them the critical nodes' RMSE "
             f"{advice.rmse_pu:.5f} pu, with them {advice.rmse_with_k_pu:.5f} pu."]
    for j, site in enumerate(advice.sites):
        lines += ["[[meter]]", f'id = "ami{first + j}"', f'node = "{site.node}"', f"interval_s = {every}", ""]
    dst.write_text(src.read_text().rstrip("\n") + "\n" + "\n".join(lines))
    written = load_device_map(dst)  # the map still decodes, with the same fingerprint
    if written.fingerprint() != dm.fingerprint():
        raise TrainingError(f"{dst}: the advised map's fingerprint differs from {src}'s")
    return dst
