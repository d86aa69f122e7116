"""``cvvc report run|evaluate``: PNG plots from the MCAP recording(s) of a run or an evaluation (paper Figs. 8-11).

What is plotted (matplotlib, Agg backend, no display needed):

- ``voltage_envelope.png`` (Fig. 9): every node's voltage averaged over 10-minute windows, then the max and min
  over nodes, against time, with the judged limits;
- ``pv_q.png`` (Fig. 10): each PV plant's reactive power (truth), 10-minute averages [kvar];
- ``taps.png`` (Fig. 11): each regulator's tap position (truth) at every step;
- ``cap_states.png`` (feeders with capacitor banks in their device map): each bank's closed steps (truth) at every
  step, with its switchings in the legend;
- ``estimation_error.png`` (Fig. 8-like): the agent's estimate minus the true voltage at the same node and
  ``t_ns`` [pu], over time (max/min/RMS per decision) and its histogram;
- ``worst_node.png``: at the critical node whose calibrated bounds missed most often (``simulator_bridge.
  live_accuracy``), the agent's estimate, the bounds it promised around it and the true voltage at every decision.

The data come from ``cvvc/<F>/sim/truth`` (TruthPack, or TruthFrame in older recordings, read as arrays by
``schemas.truth``: ``v_pu`` per node, ``taps``, ``pv_q_kvar``, ``cap_states``) and ``cvvc/<F>/agent/decision``
(Decision: ``estimates``), read with ``mcap.reader.make_reader``, the decisions decoded with a lean msgspec type
(only the fields used). A month of truth is streamed: nothing per node and step is kept.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

import msgspec
import numpy as np

from cvvc.errors import CommandError
from schemas.errors import CvvcError
from schemas.truth import TruthDecodeError, decode_truth
from simulator_bridge.simulation.live_accuracy import LiveAccuracy, LiveAccuracyAccumulator

if TYPE_CHECKING:
    from cvvc.launch import RunSummary

_T = TypeVar("_T")

__all__ = ["NodeTrace", "ReportError", "RunTrace", "envelope_figure", "errors_figure", "plot_evaluation", "plot_run",
           "pv_figure", "read_trace", "taps_figure", "window_envelope_pu", "worst_node_figure"]

WINDOW_STEPS = 10  # 10-minute averages at the 1-minute step


class ReportError(CommandError):
    """A run or evaluation folder that cannot be plotted; the message says what is missing."""


class _Estimate(msgspec.Struct):
    node: str
    v_pu: float
    bound_low_pu: float = 0.0
    bound_high_pu: float = 0.0


class _Decision(msgspec.Struct):
    step_t_ns: int
    estimates: list[_Estimate] = []


@dataclass(frozen=True)
class RunTrace:
    """One run's recording reduced for plotting. Times are ``t_ns`` of the window's first step.

    ``v_env_*`` are (W,) max/min over nodes of the 10-minute average voltage [pu]; ``taps`` (T, R) the taps at
    every step ``step_t_ns`` (T,); ``pv_q_kvar`` (W, K) 10-minute averages; ``err_t_ns`` (D,) decision times with
    ``err_max_pu``/``err_min_pu``/``err_rms_pu`` over the estimated nodes, and ``errors_pu`` every error.
    ``cap_states`` (T, C) each capacitor bank's closed steps at every step (C = 0 without banks).
    """

    t_ns: np.ndarray
    step_t_ns: np.ndarray
    v_env_max_pu: np.ndarray
    v_env_min_pu: np.ndarray
    taps: np.ndarray
    pv_q_kvar: np.ndarray
    regulator_ids: tuple[str, ...]
    pv_ids: tuple[str, ...]
    err_t_ns: np.ndarray
    err_max_pu: np.ndarray
    err_min_pu: np.ndarray
    err_rms_pu: np.ndarray
    errors_pu: np.ndarray
    limits_pu: tuple[float, float]
    cap_states: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    capacitor_ids: tuple[str, ...] = ()
    worst: NodeTrace | None = None  # the critical node whose bounds missed most often


@dataclass(frozen=True)
class NodeTrace:
    """One critical node at every decision (``t_ns`` (D,)): the estimate, its bounds as promised and the truth [pu];
    ``accuracy`` the run's live figures (``simulator_bridge.simulation.live_accuracy``) over every estimated node.
    """

    node: str
    t_ns: np.ndarray
    v_est_pu: np.ndarray
    bound_low_pu: np.ndarray
    bound_high_pu: np.ndarray
    v_true_pu: np.ndarray
    accuracy: LiveAccuracy


def window_envelope_pu(v_pu: np.ndarray, window_steps: int = WINDOW_STEPS) -> tuple[np.ndarray, np.ndarray]:
    """Max and min over nodes of the per-node ``window_steps`` average voltage (paper Fig. 9).

    Parameters
    ----------
    v_pu : (T, N) node voltages [pu]; a last partial window is averaged over the steps it has.

    Returns
    -------
    (W,) max and (W,) min [pu], W = ceil(T / window_steps).
    """
    v = np.asarray(v_pu, dtype=float)
    n_win = -(-v.shape[0] // window_steps)
    means = np.stack([v[w * window_steps:(w + 1) * window_steps].mean(axis=0) for w in range(n_win)])
    return means.max(axis=1), means.min(axis=1)


def _topic(reader, suffix: str) -> str | None:
    summary = reader.get_summary()
    if summary is None:
        return None
    for ch in summary.channels.values():
        if ch.topic.endswith(suffix):
            return ch.topic
    return None


def read_trace(mcap_path: str | Path, *, regulator_ids: tuple[str, ...] = (), pv_ids: tuple[str, ...] = (),
               limits_pu: tuple[float, float] = (0.965, 1.05), capacitor_ids: tuple[str, ...] = ()) -> RunTrace:
    """Reduce one run's MCAP recording to a :class:`RunTrace` (two streaming passes: decisions, then truth)."""
    from mcap.reader import make_reader

    path = Path(mcap_path)
    if not path.is_file():
        raise ReportError(f"{path}: no recording there; run with recording on (cvvc run without --no-record)")
    dec_dec = msgspec.json.Decoder(_Decision)
    with open(path, "rb") as f:
        reader = make_reader(f)
        truth_topic, decision_topic = _topic(reader, "/sim/truth"), _topic(reader, "/agent/decision")
        if truth_topic is None:
            raise ReportError(f"{path}: no sim/truth channel; the bridge must publish the truth (--truth-every)")
        estimates: dict[int, list[_Estimate]] = {}
        if decision_topic is not None:
            for _, _, msg in reader.iter_messages(topics=[decision_topic]):
                d = dec_dec.decode(msg.data)
                if d.estimates:
                    estimates[d.step_t_ns] = d.estimates
        node_index: dict[str, int] = {}
        t_list, step_t, vmax, vmin, taps, pvq, caps = [], [], [], [], [], [], []
        err_t, err_max, err_min, err_rms, errors = [], [], [], [], []
        judged: list[tuple[int, list[_Estimate], np.ndarray]] = []  # (t_ns, estimates, true v at their nodes)
        live: LiveAccuracyAccumulator | None = None
        acc_v = acc_q = np.zeros(0)  # the window's sums, started afresh at each window's first step
        n_acc = 0
        for _, channel, msg in reader.iter_messages(topics=[truth_topic]):
            try:  # compact (msgpack) or, in recordings made before it, JSON
                tr = decode_truth(msg.data, channel.message_encoding)
            except TruthDecodeError as bad:
                raise ReportError(f"{path}: {truth_topic} at {msg.log_time}: {bad}") from bad
            if tr.node_names:
                node_index = {n: i for i, n in enumerate(tr.node_names)}
                live = LiveAccuracyAccumulator(tr.node_names)
            v, q = tr.v_pu, tr.pv_q_kvar
            step_t.append(tr.t_ns)
            taps.append(tr.taps.tolist())
            caps.append(tr.cap_states.tolist())
            if n_acc == 0:
                t_list.append(tr.t_ns)
                acc_v, acc_q = v.copy(), q.copy()
            else:
                acc_v += v
                acc_q += q
            n_acc += 1
            if n_acc == WINDOW_STEPS:
                vmax.append(float((acc_v / n_acc).max()))
                vmin.append(float((acc_v / n_acc).min()))
                pvq.append(acc_q / n_acc)
                n_acc = 0
            est = estimates.get(tr.t_ns)
            if est and node_index:
                e = np.array([x.v_pu - v[node_index[x.node]] for x in est if x.node in node_index])
                known = [x for x in est if x.node in node_index]
                if live is not None and known:
                    live.add([x.node for x in known], np.array([x.v_pu for x in known]),
                             np.array([x.bound_low_pu for x in known]), np.array([x.bound_high_pu for x in known]), v)
                    judged.append((tr.t_ns, known, np.array([v[node_index[x.node]] for x in known])))
                if e.size:
                    err_t.append(tr.t_ns)
                    err_max.append(e.max())
                    err_min.append(e.min())
                    err_rms.append(float(np.sqrt(np.mean(e ** 2))))
                    errors.append(e)
        if n_acc:
            vmax.append(float((acc_v / n_acc).max()))
            vmin.append(float((acc_v / n_acc).min()))
            pvq.append(acc_q / n_acc)
    if not t_list:
        raise ReportError(f"{path}: the truth channel holds no frame")
    n_pv = len(pvq[0]) if pvq else 0
    return RunTrace(
        t_ns=np.asarray(t_list, dtype=np.int64), step_t_ns=np.asarray(step_t, dtype=np.int64),
        v_env_max_pu=np.asarray(vmax), v_env_min_pu=np.asarray(vmin),
        taps=np.asarray(taps, dtype=float).reshape(len(step_t), -1), pv_q_kvar=np.asarray(pvq).reshape(-1, n_pv),
        regulator_ids=regulator_ids, pv_ids=pv_ids, err_t_ns=np.asarray(err_t, dtype=np.int64),
        err_max_pu=np.asarray(err_max), err_min_pu=np.asarray(err_min), err_rms_pu=np.asarray(err_rms),
        errors_pu=np.concatenate(errors) if errors else np.zeros(0), limits_pu=limits_pu,
        cap_states=np.asarray(caps, dtype=float).reshape(len(step_t), -1), capacitor_ids=capacitor_ids,
        worst=_worst_node(live, judged))


def _worst_node(live: LiveAccuracyAccumulator | None,
                judged: list[tuple[int, list[_Estimate], np.ndarray]]) -> NodeTrace | None:
    """The series of the node whose bounds missed most often (None without judged estimates)."""
    worst = live.worst() if live is not None else None
    if live is None or worst is None:
        return None
    rows = [(t, x, v[j]) for t, est, v in judged for j, x in enumerate(est) if x.node == worst.node]
    return NodeTrace(node=worst.node, t_ns=np.array([t for t, _, _ in rows], dtype=np.int64),
                     v_est_pu=np.array([x.v_pu for _, x, _ in rows]),
                     bound_low_pu=np.array([x.bound_low_pu for _, x, _ in rows]),
                     bound_high_pu=np.array([x.bound_high_pu for _, x, _ in rows]),
                     v_true_pu=np.array([v for _, _, v in rows]), accuracy=live.result())


# ---------------------------------------------------------------------------------------------------
# Plots
# ---------------------------------------------------------------------------------------------------


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _days(t_ns: np.ndarray, t0_ns: int) -> np.ndarray:
    return (np.asarray(t_ns, dtype=np.int64) - t0_ns) / 86_400e9


def _decode(path: Path, typ: type[_T], what: str) -> _T:
    try:
        return msgspec.json.decode(path.read_bytes(), type=typ)
    except (msgspec.DecodeError, msgspec.ValidationError) as e:
        raise ReportError(f"{path}: not a {what} of this version ({e}); plot it with the version that wrote it, "
                          "or run it again") from e


def _run_meta(run_dir: Path) -> tuple[RunSummary, tuple[str, ...], tuple[str, ...], tuple[float, float]]:
    from cvvc.launch import RunSummary

    summary_path = run_dir / "summary.json"
    if not summary_path.is_file():
        raise ReportError(f"{run_dir}: no summary.json; pass a cvvc run output folder")
    summary = _decode(summary_path, RunSummary, "cvvc run summary")
    mt = summary.metrics
    limits = (0.965, 1.05)
    try:
        from schemas.devicemap import load_device_map

        lo, hi = load_device_map(summary.feeder).feeder.judged_limits_pu
        limits = (float(lo), float(hi))
    except (CvvcError, OSError):
        pass  # the paper's limits
    return summary, tuple(mt.taps_changes), tuple(mt.q_mvar_intervals), limits


def _trace_of(run_dir: Path) -> tuple[RunSummary, RunTrace]:
    summary, regs, pvs, limits = _run_meta(run_dir)
    caps = tuple(summary.metrics.cap_switches_per_bank)
    rec = summary.recording or str(run_dir / "session.mcap")
    path = Path(rec) if Path(rec).is_file() else run_dir / "session.mcap"
    return summary, read_trace(path, regulator_ids=regs, pv_ids=pvs, limits_pu=limits, capacitor_ids=caps)


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    _plt().close(fig)
    return path


def envelope_figure(traces: dict[str, RunTrace], title: str):
    """The 10-minute average voltage envelope (max and min over nodes [pu]) of each trace, with the limits."""
    plt = _plt()
    fig, (ax_hi, ax_lo) = plt.subplots(2, 1, figsize=(12, 6.5), sharex=True)
    t0 = min(int(tr.t_ns[0]) for tr in traces.values())
    lo, hi = next(iter(traces.values())).limits_pu
    for i, (label, tr) in enumerate(traces.items()):
        x = _days(tr.t_ns, t0)
        ax_hi.plot(x, tr.v_env_max_pu, color=f"C{i}", lw=0.9, label=label)
        ax_lo.plot(x, tr.v_env_min_pu, color=f"C{i}", lw=0.9, label=label)
    for ax, limit, which in ((ax_hi, hi, "max"), (ax_lo, lo, "min")):
        ax.axhline(limit, color="k", lw=0.8, ls=":", label=f"limit {limit:g} pu")
        ax.set_ylabel(f"{which} over nodes [pu]")
        ax.grid(alpha=0.3)
    ax_hi.set_title(title)
    ax_hi.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax_lo.set_xlabel("time [days from start]")
    return fig


def pv_figure(traces: dict[str, RunTrace], title: str):
    """Each plant's 10-minute average reactive power [kvar], one panel per trace."""
    plt = _plt()
    n = len(traces)
    fig, axes = plt.subplots(n, 1, figsize=(11, 2.4 * n + 0.6), sharex=True, squeeze=False)
    t0 = min(int(tr.t_ns[0]) for tr in traces.values())
    for ax, (label, tr) in zip(axes[:, 0], traces.items(), strict=True):
        x = _days(tr.t_ns, t0)
        for k in range(tr.pv_q_kvar.shape[1]):
            name = tr.pv_ids[k] if k < len(tr.pv_ids) else f"pv{k}"
            ax.plot(x[: tr.pv_q_kvar.shape[0]], tr.pv_q_kvar[:, k], lw=0.8, label=name)
        ax.set_ylabel("Q [kvar]")
        ax.set_title(f"{label}", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("time [days from start]")
    fig.suptitle(title)
    return fig


def taps_figure(traces: dict[str, RunTrace], title: str):
    """Each regulator's tap position [steps] over time, one panel per trace."""
    plt = _plt()
    n = len(traces)
    fig, axes = plt.subplots(n, 1, figsize=(11, 2.4 * n + 0.6), sharex=True, squeeze=False)
    t0 = min(int(tr.t_ns[0]) for tr in traces.values())
    for ax, (label, tr) in zip(axes[:, 0], traces.items(), strict=True):
        x = _days(tr.step_t_ns, t0)
        for r in range(tr.taps.shape[1]):
            name = tr.regulator_ids[r] if r < len(tr.regulator_ids) else f"reg{r}"
            ax.step(x, tr.taps[:, r], where="post", lw=0.8, label=name)
        ax.set_ylabel("tap")
        ax.set_title(f"{label}", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=4, loc="upper right")
    axes[-1, 0].set_xlabel("time [days from start]")
    fig.suptitle(title)
    return fig


def caps_figure(traces: dict[str, RunTrace], title: str):
    """Each capacitor bank's closed steps at every step, one panel per run; switchings in the legend."""
    plt = _plt()
    n = len(traces)
    fig, axes = plt.subplots(n, 1, figsize=(11, 2.4 * n + 0.6), sharex=True, squeeze=False)
    t0 = min(int(tr.step_t_ns[0]) for tr in traces.values())
    for ax, (label, tr) in zip(axes[:, 0], traces.items(), strict=True):
        x = _days(tr.step_t_ns, t0)
        for c in range(tr.cap_states.shape[1]):
            name = tr.capacitor_ids[c] if c < len(tr.capacitor_ids) else f"cap {c}"
            states = tr.cap_states[:, c]
            switches = int(np.abs(np.diff(states)).sum())
            ax.step(x, states + 0.04 * c, where="post", lw=0.9, label=f"{name} ({switches} switchings)")
        ax.set_ylabel("closed steps")
        ax.set_title(f"{label}", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=3, loc="upper right")
    axes[-1, 0].set_xlabel("time [days from start]")
    fig.suptitle(title)
    return fig


def errors_figure(traces: dict[str, RunTrace], title: str):
    """Estimation error (estimate - truth [pu]) over time and its histogram; None without estimates."""
    with_est = {k: v for k, v in traces.items() if v.err_t_ns.size}
    if not with_est:
        return None
    plt = _plt()
    fig, (ax, axh) = plt.subplots(1, 2, figsize=(12, 4.2), gridspec_kw={"width_ratios": [3, 1.2]})
    t0 = min(int(tr.t_ns[0]) for tr in traces.values())
    for i, (label, tr) in enumerate(with_est.items()):
        x = _days(tr.err_t_ns, t0)
        ax.fill_between(x, tr.err_min_pu, tr.err_max_pu, color=f"C{i}", alpha=0.25, lw=0)
        ax.plot(x, tr.err_rms_pu, color=f"C{i}", lw=0.8, label=f"{label}: RMS (band: min..max)")
        axh.hist(tr.errors_pu, bins=60, color=f"C{i}", alpha=0.5,
                 label=f"{label}: RMS {np.sqrt(np.mean(tr.errors_pu ** 2)):.4f}, "
                       f"max |e| {np.abs(tr.errors_pu).max():.4f}")
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xlabel("time [days from start]")
    ax.set_ylabel("estimate - truth [pu]")
    ax.set_title(title)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    axh.set_xlabel("estimate - truth [pu]")
    axh.set_ylabel("count")
    axh.legend(fontsize=7)
    return fig


def worst_node_figure(trace: RunTrace, title: str):
    """The worst node's estimate, promised bounds and truth over time; None without judged estimates."""
    w = trace.worst
    if w is None or not w.t_ns.size:
        return None
    plt = _plt()
    fig, ax = plt.subplots(figsize=(12, 4.2))
    hours = (w.t_ns - int(w.t_ns[0])) / 3.6e12
    ax.fill_between(hours, w.v_est_pu - w.bound_low_pu, w.v_est_pu + w.bound_high_pu, step="mid", color="C0",
                    alpha=0.25, lw=0, label="bounds the agent promised")
    ax.plot(hours, w.v_est_pu, color="C0", lw=0.9, drawstyle="steps-mid", label="agent's estimate")
    ax.plot(hours, w.v_true_pu, color="k", lw=0.9, drawstyle="steps-mid", label="true voltage")
    a = w.accuracy
    ax.set_title(f"{title}: node {w.node} (bounds missed {a.bound_miss_rate:.1%} of node-decisions over every "
                 f"critical node)", fontsize=10)
    ax.set_xlabel("hours from the first decision")
    ax.set_ylabel("voltage [pu]")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def _plots(traces: dict[str, RunTrace], title: str, out: Path, prefix: str = "") -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    paths = [_save(envelope_figure(traces, f"{title}: 10-min average voltage envelope"),
                   out / f"{prefix}voltage_envelope.png"),
             _save(pv_figure(traces, f"{title}: PV reactive power (10-min average)"), out / f"{prefix}pv_q.png"),
             _save(taps_figure(traces, f"{title}: regulator taps"), out / f"{prefix}taps.png")]
    if any(tr.cap_states.size for tr in traces.values()):
        paths.append(_save(caps_figure(traces, f"{title}: capacitor banks"), out / f"{prefix}cap_states.png"))
    err = errors_figure(traces, f"{title}: estimation error")
    return paths + ([_save(err, out / f"{prefix}estimation_error.png")] if err is not None else [])


def plot_run(run_dir: str | Path, *, out: str | Path | None = None) -> list[Path]:
    """The PNGs of one ``cvvc run`` folder (default into ``run_dir/plots``); returns their paths."""
    d = Path(run_dir)
    summary, trace = _trace_of(d)
    title = f"{summary.feeder_id} case {summary.case} from {summary.start}"
    folder = Path(out) if out else d / "plots"
    paths = _plots({f"case {summary.case}": trace}, title, folder)
    worst = worst_node_figure(trace, title)
    return paths + ([_save(worst, folder / "worst_node.png")] if worst is not None else [])


def plot_evaluation(eval_dir: str | Path, *, out: str | Path | None = None) -> list[Path]:
    """The PNGs of a ``cvvc evaluate`` folder: per season (and variant), every case together; returns paths."""
    d = Path(eval_dir)
    results_path = d / "results.json"
    if not results_path.is_file():
        raise ReportError(f"{d}: no results.json; pass a cvvc evaluate output folder")
    from cvvc.evaluate import Evaluation

    ev = _decode(results_path, Evaluation, "cvvc evaluate result")
    groups: dict[str, dict[str, RunTrace]] = {}
    for r in ev.runs:
        spec = r.spec
        if not r.recording:  # the opendss reference case: OpenDSS's own loop, nothing recorded
            continue
        run_dir = Path(r.out_dir)
        if not run_dir.is_dir():
            run_dir = d / Path(r.out_dir).name
        _, trace = _trace_of(run_dir)
        key: str
        label: str
        if spec.variant == "nominal":
            key = spec.season
            label = f"case {spec.case}"
        else:
            key = f"{spec.season}-robustness"
            label = spec.variant
        if spec.case in ("C", "D") and len(ev.config.bandwidths_v120) > 1:
            label += f" {spec.bandwidth_v120:g} V"
        groups.setdefault(key, {})[label] = trace
    paths: list[Path] = []
    out_dir = Path(out) if out else d / "plots"
    for group, traces in groups.items():
        paths += _plots(traces, f"{ev.feeder_id} {group}", out_dir, prefix=f"{group}-")
    return paths
