"""``cvvc report run|evaluate``: PNG plots from the MCAP recording(s) of a run or an evaluation (paper Figs. 8-11).

What is plotted (matplotlib, Agg backend, no display needed), every run's series beside no control's when the run
simulated it (``cvvc run`` writes the baseline's series to ``baseline_trace.npz``; dashed, in its own panel where
the plot has one per run), times in hour of day (date and hour over several days), local standard time (UTC-5):

- ``voltage_envelope.png`` (Fig. 9): every node's voltage averaged over 10-minute windows, then the max and min
  over nodes, against time, with the judged limits;
- ``pv_q.png`` (Fig. 10): each PV plant's reactive power (truth), 10-minute averages [kvar, + injects];
- ``taps.png`` (Fig. 11): each regulator's tap position (truth) at every step;
- ``cap_states.png`` (feeders with capacitor banks in their device map): each bank's closed steps (truth) at every
  step, with its switchings in the legend;
- ``estimation_error.png`` (Fig. 8-like): the agent's estimate minus the true voltage at the same node and
  ``t_ns`` [pu], over time (max/min/RMS per decision) and its histogram;
- ``worst_node.png``: at the critical node whose calibrated bounds missed most often (``simulator_bridge.
  live_accuracy``), the agent's estimate, the bounds it promised around it and the true voltage at every decision.

``cvvc report run`` also writes ``report.md`` (the run's report, ``cvvc.run_report``, with the plots in it).
The data come from ``cvvc/<F>/sim/truth`` (read as arrays by ``schemas.truth`` in every encoding it was recorded
in: ``v_pu`` per node, ``taps``, ``pv_q_kvar``, ``cap_states``) and ``cvvc/<F>/agent/decision`` (Decision:
``estimates``), read with ``mcap.reader.make_reader``, the decisions decoded with a lean msgspec type (only the
fields used). A month of truth is streamed (``cvvc.run_trace.TruthSeries``): nothing per node and step is kept.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import msgspec
import numpy as np

from agent.tap_moves import HELD_BY_DEADBAND
from cvvc.errors import CommandError
from cvvc.extreme_minutes import ExtremeMinutes
from cvvc.local_time import LOCAL_UTC_OFFSET_NS
from cvvc.run_trace import (
    BASELINE_TRACE,
    WINDOW_STEPS,
    LimitMinutes,
    NodeTrace,
    RunTrace,
    SideMoves,
    TruthSeries,
    read_series,
    window_envelope_pu,
)
from cvvc.step_effect import TapStepAccumulator, tap_steps_text
from schemas.errors import CvvcError
from schemas.truth import TruthDecodeError, decode_truth
from simulator_bridge.simulation.live_accuracy import LiveAccuracyAccumulator
from simulator_bridge.simulation.metrics import VIOLATION_TOLERANCE_PU
from simulator_bridge.simulation.metrics_stream import phase_nodes, zone_phase_nodes

if TYPE_CHECKING:
    from cvvc.evaluation import Evaluation
    from cvvc.launch import RunSummary
    from schemas.devicemap import DeviceMap

_T = TypeVar("_T")

__all__ = ["BEFORE_FIRST_DECISION", "NO_CONTROL", "NodeTrace", "ReportError", "RunTrace", "decision_kind",
           "decode_evaluation", "decode_summary", "envelope_figure", "errors_figure", "judged_node_names", "limit_side",
           "plot_evaluation", "plot_run", "pv_figure", "read_trace", "run_traces", "taps_figure",
           "window_envelope_pu", "worst_node_figure"]


class ReportError(CommandError):
    """A run or evaluation folder that cannot be plotted; the message says what is missing."""


class _Estimate(msgspec.Struct):
    node: str
    v_pu: float
    bound_low_pu: float = 0.0
    bound_high_pu: float = 0.0


class _Decision(msgspec.Struct):
    step_t_ns: int
    status: str = ""
    reason: str = ""
    estimates: list[_Estimate] = []
    dv_dtap_pu: list[list[float]] = []


BEFORE_FIRST_DECISION = "before the first decision"


def limit_side(estimates: list[_Estimate], limits_pu: tuple[float, float]) -> str:
    """Which side of ``limits_pu`` a decision saw crossed before its action (``SideMoves.side``): ``over`` where some
    estimate + its upper bound is above the upper limit, ``under`` where some estimate - its lower bound is below the
    lower one, ``both`` or ``neither``.
    """
    over = any(e.v_pu + e.bound_high_pu > limits_pu[1] + VIOLATION_TOLERANCE_PU for e in estimates)
    under = any(e.v_pu - e.bound_low_pu < limits_pu[0] - VIOLATION_TOLERANCE_PU for e in estimates)
    return "both" if over and under else "over" if over else "under" if under else "neither"


def decision_kind(status: str, reason: str) -> str:
    """What a recorded decision was: ``optimal``, ``soft form`` (eq. 17), ``taps held by the tap deadband`` or
    ``hold`` (``LimitMinutes.kind``).
    """
    if status == "soft":
        return "taps held by the tap deadband" if reason.startswith(HELD_BY_DEADBAND) else "soft form"
    return status or "optimal"


class _InForce:
    """A label of the decision in force at each truth step (its kind, or the side of the limits it saw crossed), from
    the run's decisions' ``(step, label)`` pairs.
    """

    def __init__(self, decided: list[tuple[int, str]]) -> None:
        self._decided = sorted(decided)
        self._i = -1

    def at(self, t_ns: int) -> str:
        """The label of the latest decision of a step before ``t_ns`` (steps come in time order)."""
        while self._i + 1 < len(self._decided) and self._decided[self._i + 1][0] < t_ns:
            self._i += 1
        return self._decided[self._i][1] if self._i >= 0 else BEFORE_FIRST_DECISION


def _topic(reader, suffix: str) -> str | None:
    summary = reader.get_summary()
    if summary is None:
        return None
    for ch in summary.channels.values():
        if ch.topic.endswith(suffix):
            return ch.topic
    return None


def read_trace(mcap_path: str | Path, *, regulator_ids: tuple[str, ...] = (), pv_ids: tuple[str, ...] = (),
               limits_pu: tuple[float, float] = (0.965, 1.05), capacitor_ids: tuple[str, ...] = (),
               opt_limits_pu: tuple[float, float] | None = None,
               judged_nodes: frozenset[str] | None = None) -> RunTrace:
    """Reduce one run's MCAP recording to a :class:`RunTrace` (two streaming passes: decisions, then truth).

    Voltages are the ``judged_nodes``' (the feeder zone's phase nodes, ``judged_node_names``, as the run's metrics), or
    without them every phase node's (a neutral's is no customer's). ``opt_limits_pu``: the optimization limits the run
    was judged against (its metrics' ``opt_limits_pu``); with them, the minutes any node spent outside them are
    counted by the decision in force (``RunTrace.limit_minutes``), and the regulators' tap steps by the side of them
    that decision saw crossed (``RunTrace.side_moves``). Always: the lowest and highest minutes with the taps and banks
    that moved up to each (``RunTrace.extremes``).
    """
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
        sensitivities: tuple[list[str], np.ndarray] | None = None  # the critical nodes and the model's dV/dtap
        decided: list[tuple[int, str]] = []  # (step, kind) of every decision
        sides: list[tuple[int, str]] = []  # (step, the side of the limits it saw crossed) of every decision
        if decision_topic is not None:
            for _, _, msg in reader.iter_messages(topics=[decision_topic]):
                d = dec_dec.decode(msg.data)
                decided.append((d.step_t_ns, decision_kind(d.status, d.reason)))
                if opt_limits_pu is not None:
                    sides.append((d.step_t_ns, limit_side(d.estimates, opt_limits_pu)))
                if d.estimates:
                    estimates[d.step_t_ns] = d.estimates
                    if sensitivities is None and len(d.dv_dtap_pu) == len(d.estimates):
                        sensitivities = [x.node for x in d.estimates], np.asarray(d.dv_dtap_pu, float)
        node_index: dict[str, int] = {}
        phase = np.zeros(0, bool)  # the phase nodes (no neutral), once the frames have named the nodes
        phase_names: tuple[str, ...] = ()
        series = TruthSeries(WINDOW_STEPS)
        err_t, err_max, err_min, err_rms, errors = [], [], [], [], []
        judged: list[tuple[int, list[_Estimate], np.ndarray]] = []  # (t_ns, estimates, true v at their nodes)
        live: LiveAccuracyAccumulator | None = None
        steps: TapStepAccumulator | None = None
        in_force, side_in_force = _InForce(decided), _InForce(sides)
        extremes = ExtremeMinutes(regulator_ids, capacitor_ids)
        outside: dict[str, list[int]] = {}  # kind -> [minutes under, minutes over] the optimization limits
        moved: dict[str, list[int]] = {}  # side -> [tap steps up, tap steps down]
        last_taps: np.ndarray | None = None
        for _, channel, msg in reader.iter_messages(topics=[truth_topic], log_time_order=True):
            try:  # every encoding the truth was ever recorded in (schemas.truth)
                tr = decode_truth(msg.data, channel.message_encoding)
            except TruthDecodeError as bad:
                raise ReportError(f"{path}: {truth_topic} at {msg.log_time}: {bad}") from bad
            if tr.node_names:
                node_index = {n: i for i, n in enumerate(tr.node_names)}
                phase = phase_nodes(tr.node_names) if judged_nodes is None else \
                    np.array([n in judged_nodes for n in tr.node_names], dtype=bool)
                phase_names = tuple(n for n, j in zip(tr.node_names, phase, strict=True) if j)
                live = LiveAccuracyAccumulator(tr.node_names)
                if sensitivities is not None and regulator_ids:
                    steps = TapStepAccumulator(tr.node_names, *sensitivities, regulator_ids)
            v = tr.v_pu
            v_phase = v[phase] if phase.shape == v.shape else v  # frames before the names: every node
            kind = in_force.at(tr.t_ns)
            if opt_limits_pu is not None and v_phase.size:
                counts = outside.setdefault(kind, [0, 0])
                counts[0] += bool(v_phase.min() < opt_limits_pu[0] - VIOLATION_TOLERANCE_PU)
                counts[1] += bool(v_phase.max() > opt_limits_pu[1] + VIOLATION_TOLERANCE_PU)
                taps = np.asarray(tr.taps, int)
                if last_taps is not None and taps.shape == last_taps.shape and np.any(taps != last_taps):
                    steps_moved = moved.setdefault(side_in_force.at(tr.t_ns), [0, 0])
                    steps_moved[0] += int(np.clip(taps - last_taps, 0, None).sum())
                    steps_moved[1] += int(np.clip(last_taps - taps, 0, None).sum())
                last_taps = taps
            series.add(tr.t_ns, v_phase, tr.taps, tr.pv_q_kvar, tr.cap_states)
            extremes.add(tr.t_ns, v_phase, tr.taps, tr.cap_states, kind,
                         phase_names if tr.node_names and phase.shape == v.shape else None)
            if steps is not None:
                steps.add(tr.t_ns, v, tr.taps, tr.pv_q_kvar, tr.cap_states)
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
    if not series.step_t_ns:
        raise ReportError(f"{path}: the truth channel holds no frame")
    trace = series.trace(regulator_ids=regulator_ids, pv_ids=pv_ids, limits_pu=limits_pu, capacitor_ids=capacitor_ids)
    return replace(trace, err_t_ns=np.asarray(err_t, dtype=np.int64), err_max_pu=np.asarray(err_max),
                   err_min_pu=np.asarray(err_min), err_rms_pu=np.asarray(err_rms),
                   errors_pu=np.concatenate(errors) if errors else np.zeros(0), worst=_worst_node(live, judged),
                   tap_steps=steps.result() if steps is not None else (),
                   limit_minutes=tuple(LimitMinutes(k, under, over) for k, (under, over) in outside.items()
                                       if under or over),
                   side_moves=tuple(SideMoves(side, up, down) for side, (up, down) in moved.items()),
                   extremes=extremes.result())


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

NO_CONTROL = "no control"  # the label of the baseline a ``cvvc run`` simulated beside the case
_LEGEND = {"loc": "upper left", "bbox_to_anchor": (1.01, 1.0), "borderaxespad": 0.0}  # outside the data, right
Q_LABEL = "Q [kvar]\n(+ injects, - absorbs)"
TAP_LABEL = "tap [steps]\n(+ raises voltage)"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _clock(t_ns: np.ndarray) -> np.ndarray:
    """Simulation times [ns since the UTC epoch] as local standard time (UTC-5), ``datetime64[ns]`` for the x axis."""
    return (np.asarray(t_ns, dtype=np.int64) + LOCAL_UTC_OFFSET_NS).astype("datetime64[ns]")


def _time_axis(ax, traces: dict[str, RunTrace]) -> None:
    """Label the x axis in hour of day (one day) or date and hour (several days), local standard time."""
    import matplotlib.dates as mdates

    first = min(int(tr.step_t_ns[0]) for tr in traces.values() if tr.step_t_ns.size)
    last = max(int(tr.step_t_ns[-1]) for tr in traces.values() if tr.step_t_ns.size)
    day0 = str(_clock(np.array([first]))[0])[:10]
    if last - first <= 86_400 * 10**9:
        ax.xaxis.set_major_formatter(mdates.DateFormatter("%H:%M"))
        ax.set_xlabel(f"hour of day, {day0} (local standard time, UTC-5)")
    else:
        ax.xaxis.set_major_formatter(mdates.DateFormatter("%m-%d %H:%M"))
        ax.set_xlabel("date and hour (local standard time, UTC-5)")
        for label in ax.get_xticklabels():
            label.set_rotation(20)


def _style(label: str) -> dict[str, object]:
    """The baseline dashed, every case solid (so a device keeps its colour across the panels)."""
    return {"ls": "--"} if label == NO_CONTROL else {}


def _panel_title(label: str) -> str:
    return (f"{label}: regulators on their own local control, PV at unity power factor" if label == NO_CONTROL
            else label)


def _decode(path: Path, typ: type[_T], what: str) -> _T:
    try:
        return msgspec.json.decode(path.read_bytes(), type=typ)
    except (msgspec.DecodeError, msgspec.ValidationError) as e:
        raise ReportError(f"{path}: not a {what} of this version ({e}); plot it with the version that wrote it, "
                          "or run it again") from e


def decode_evaluation(path: Path) -> Evaluation:
    """A ``cvvc evaluate`` folder's ``results.json``, or ``ReportError`` saying it is not one of this version."""
    from cvvc.evaluation import Evaluation

    return _decode(path, Evaluation, "cvvc evaluate result")


def decode_summary(path: Path, typ: type[_T]) -> _T:
    """A run's ``summary.json``; one written before the baseline took the case's form (the simulator's ``Metrics``:
    lists by device, ``n_steps``) is read with its baseline turned into that form.
    """
    try:
        raw = msgspec.json.decode(path.read_bytes())
        base = raw.get("baseline") if isinstance(raw, dict) else None
        if isinstance(base, dict) and "n_steps" in base and isinstance(raw.get("metrics"), dict):
            from simulator_bridge.bus.publishing import metrics_frame
            from simulator_bridge.simulation.metrics import Metrics

            case = raw["metrics"]
            raw["baseline"] = msgspec.to_builtins(metrics_frame(
                msgspec.convert(base, Metrics), t_ns=int(case.get("t_ns", 0)), seq=1,
                feeder_id=str(case.get("feeder_id", "")), start_t_ns=int(case.get("start_t_ns", 0)), final=True))
        return msgspec.convert(raw, typ)
    except (msgspec.DecodeError, msgspec.ValidationError, ValueError, TypeError) as e:
        raise ReportError(f"{path}: not a cvvc run summary of this version ({e}); plot it with the version that "
                          "wrote it, or run it again") from e


def _run_meta(run_dir: Path) -> tuple[RunSummary, DeviceMap | None]:
    """A run folder's summary and its device map, read once (None when the map cannot be read any more)."""
    from cvvc.launch import RunSummary
    from schemas.devicemap import load_device_map

    summary_path = run_dir / "summary.json"
    if not summary_path.is_file():
        raise ReportError(f"{run_dir}: no summary.json; pass a cvvc run output folder")
    summary = decode_summary(summary_path, RunSummary)
    try:
        dm = load_device_map(summary.feeder)
    except (CvvcError, OSError):
        dm = None
    return summary, dm


def judged_node_names(dm: DeviceMap) -> frozenset[str] | None:
    """The names of the nodes a feeder's metrics judge (``zone_phase_nodes``: the zone's phase nodes), from its
    circuit compiled once; None when the circuit cannot be compiled any more (then every phase node is taken).
    """
    from simulator_bridge.opendss.engine import FeederEngine

    try:
        engine = FeederEngine(dm)
    except (CvvcError, OSError):
        return None
    zone = zone_phase_nodes(engine)
    return None if zone is None else frozenset(engine.node_names[i] for i in zone)


@functools.lru_cache(maxsize=8)
def _judged_of_map(feeder: str) -> frozenset[str] | None:
    """``judged_node_names`` of the device map at ``feeder``, once per map (an evaluation's runs share theirs)."""
    from schemas.devicemap import load_device_map

    try:
        return judged_node_names(load_device_map(feeder))
    except (CvvcError, OSError):
        return None


def _trace_of(run_dir: Path, summary: RunSummary, dm: DeviceMap | None) -> RunTrace:
    mt = summary.metrics
    limits = (0.965, 1.05)  # the paper's limits, without the map
    if dm is not None:
        lo, hi = dm.feeder.judged_limits_pu
        limits = (float(lo), float(hi))
    rec = summary.recording or str(run_dir / "session.mcap")
    path = Path(rec) if Path(rec).is_file() else run_dir / "session.mcap"
    return read_trace(path, regulator_ids=tuple(mt.taps_changes), pv_ids=tuple(mt.q_mvar_intervals),
                      limits_pu=limits, capacitor_ids=tuple(mt.cap_switches_per_bank),
                      opt_limits_pu=mt.opt_limits_pu,
                      judged_nodes=None if dm is None else _judged_of_map(summary.feeder))


def _baseline_of(run_dir: Path) -> RunTrace | None:
    """The no-control baseline's series ``cvvc run`` wrote beside its recording (None: ``--no-baseline``)."""
    path = run_dir / BASELINE_TRACE
    if not path.is_file():
        return None
    try:
        return read_series(path)
    except (OSError, ValueError, KeyError) as e:
        raise ReportError(f"{path}: not a baseline trace of this version ({e}); run it again") from e


def _save(fig, path: Path) -> Path:
    fig.savefig(path, dpi=110, bbox_inches="tight")  # tight: the legends outside the axes are kept
    _plt().close(fig)
    return path


def envelope_figure(traces: dict[str, RunTrace], title: str):
    """The 10-minute average voltage envelope (max and min over nodes [pu]) of each trace, with the limits."""
    plt = _plt()
    fig, (ax_hi, ax_lo) = plt.subplots(2, 1, figsize=(12, 6.5), sharex=True)
    lo, hi = next(iter(traces.values())).limits_pu
    for i, (label, tr) in enumerate(traces.items()):
        x = _clock(tr.t_ns)
        ax_hi.plot(x, tr.v_env_max_pu, color=f"C{i}", lw=0.9, label=label, **_style(label))
        ax_lo.plot(x, tr.v_env_min_pu, color=f"C{i}", lw=0.9, label=label, **_style(label))
    for ax, limit, which in ((ax_hi, hi, "highest"), (ax_lo, lo, "lowest")):
        ax.axhline(limit, color="k", lw=0.8, ls=":", label=f"judged limit {limit:g} pu")
        ax.set_ylabel(f"{which} node\n[pu of nominal L-N]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, **_LEGEND)
    ax_hi.set_title(title)
    _time_axis(ax_lo, traces)
    return fig


def _panels_figure(traces: dict[str, RunTrace], title: str, ylabel: str, draw: Callable[[Any, str, RunTrace], None]):
    """One panel per trace (same scales, the time axis below), each drawn by ``draw(ax, label, trace)``."""
    plt = _plt()
    n = len(traces)
    fig, axes = plt.subplots(n, 1, figsize=(11, 2.4 * n + 0.6), sharex=True, sharey=True, squeeze=False)
    for ax, (label, tr) in zip(axes[:, 0], traces.items(), strict=True):
        draw(ax, label, tr)
        ax.set_ylabel(ylabel)
        ax.set_title(_panel_title(label), fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, **_LEGEND)
    _time_axis(axes[-1, 0], traces)
    fig.suptitle(title)
    return fig


def _draw_pv(ax, label: str, tr: RunTrace) -> None:
    x = _clock(tr.t_ns)
    for k in range(tr.pv_q_kvar.shape[1]):
        name = tr.pv_ids[k] if k < len(tr.pv_ids) else f"pv{k}"
        ax.plot(x[: tr.pv_q_kvar.shape[0]], tr.pv_q_kvar[:, k], color=f"C{k}", lw=0.8, label=name, **_style(label))
    ax.axhline(0.0, color="k", lw=0.5)


def _draw_taps(ax, label: str, tr: RunTrace) -> None:
    x = _clock(tr.step_t_ns)
    for r in range(tr.taps.shape[1]):
        name = tr.regulator_ids[r] if r < len(tr.regulator_ids) else f"reg{r}"
        ax.step(x, tr.taps[:, r], where="post", color=f"C{r}", lw=0.8, label=name, **_style(label))


def _draw_caps(ax, label: str, tr: RunTrace) -> None:
    x = _clock(tr.step_t_ns)
    for c in range(tr.cap_states.shape[1]):
        name = tr.capacitor_ids[c] if c < len(tr.capacitor_ids) else f"cap {c}"
        states = tr.cap_states[:, c]
        switches = int(np.abs(np.diff(states)).sum())
        ax.step(x, states + 0.04 * c, where="post", color=f"C{c}", lw=0.9,
                label=f"{name} ({switches} switchings)", **_style(label))


def pv_figure(traces: dict[str, RunTrace], title: str):
    """Each plant's 10-minute average reactive power [kvar, + injects], one panel per trace (same scale)."""
    return _panels_figure(traces, title, Q_LABEL, _draw_pv)


def taps_figure(traces: dict[str, RunTrace], title: str):
    """Each regulator's tap position [steps] over time, one panel per trace (same scale)."""
    return _panels_figure(traces, title, TAP_LABEL, _draw_taps)


def caps_figure(traces: dict[str, RunTrace], title: str):
    """Each capacitor bank's closed steps at every step, one panel per run; switchings in the legend."""
    return _panels_figure(traces, title, "closed steps", _draw_caps)


def errors_figure(traces: dict[str, RunTrace], title: str):
    """Estimation error (estimate - truth [pu]) over time and its histogram; None without estimates."""
    with_est = {k: v for k, v in traces.items() if v.err_t_ns.size}
    if not with_est:
        return None
    plt = _plt()
    fig, (ax, axh) = plt.subplots(1, 2, figsize=(12, 4.2), gridspec_kw={"width_ratios": [3, 1.2]})
    for i, (label, tr) in enumerate(with_est.items()):
        x = _clock(tr.err_t_ns)
        ax.fill_between(x, tr.err_min_pu, tr.err_max_pu, color=f"C{i}", alpha=0.25, lw=0)
        ax.plot(x, tr.err_rms_pu, color=f"C{i}", lw=0.8, label=f"{label}: RMS (band: min..max)")
        axh.hist(tr.errors_pu, bins=60, color=f"C{i}", alpha=0.5,
                 label=f"{label}: RMS {np.sqrt(np.mean(tr.errors_pu ** 2)):.4f}, "
                       f"max |e| {np.abs(tr.errors_pu).max():.4f}")
    ax.axhline(0, color="k", lw=0.6)
    _time_axis(ax, with_est)
    ax.set_ylabel("estimate - truth [pu]\n(+: estimate too high)")
    ax.set_title(title)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(0.0, -0.22), borderaxespad=0.0)
    ax.grid(alpha=0.3)
    axh.set_xlabel("estimate - truth [pu]")
    axh.set_ylabel("count")
    axh.legend(fontsize=7, loc="upper left", bbox_to_anchor=(0.0, -0.22), borderaxespad=0.0)
    return fig


def worst_node_figure(trace: RunTrace, title: str):
    """The worst node's estimate, promised bounds and truth over time; None without judged estimates."""
    w = trace.worst
    if w is None or not w.t_ns.size:
        return None
    plt = _plt()
    fig, ax = plt.subplots(figsize=(12, 4.2))
    x = _clock(w.t_ns)
    ax.fill_between(x, w.v_est_pu - w.bound_low_pu, w.v_est_pu + w.bound_high_pu, step="mid", color="C0",
                    alpha=0.25, lw=0, label="bounds the agent promised")
    ax.plot(x, w.v_est_pu, color="C0", lw=0.9, drawstyle="steps-mid", label="agent's estimate")
    ax.plot(x, w.v_true_pu, color="k", lw=0.9, drawstyle="steps-mid", label="true voltage")
    a = w.accuracy
    ax.set_title(f"{title}: node {w.node} (bounds missed {a.bound_miss_rate:.1%} of node-decisions over every "
                 f"critical node)", fontsize=10)
    _time_axis(ax, {"": trace})
    ax.set_ylabel("voltage [pu of nominal L-N]")
    ax.legend(fontsize=8, **_LEGEND)
    ax.grid(alpha=0.3)
    return fig


def _plots(traces: dict[str, RunTrace], title: str, out: Path, prefix: str = "") -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    paths = [_save(envelope_figure(traces, f"{title}: voltage envelope (10-min averages over every node)"),
                   out / f"{prefix}voltage_envelope.png"),
             _save(pv_figure(traces, f"{title}: PV reactive power (10-min averages)"), out / f"{prefix}pv_q.png"),
             _save(taps_figure(traces, f"{title}: regulator taps"), out / f"{prefix}taps.png")]
    if any(tr.cap_states.size for tr in traces.values()):
        paths.append(_save(caps_figure(traces, f"{title}: capacitor banks"), out / f"{prefix}cap_states.png"))
    err = errors_figure(traces, f"{title}: estimation error")
    return paths + ([_save(err, out / f"{prefix}estimation_error.png")] if err is not None else [])


def run_traces(run_dir: str | Path) -> tuple[RunSummary, dict[str, RunTrace]]:
    """A ``cvvc run`` folder's traces: the case's from its recording, then no control's when it was simulated."""
    summary, _, traces = _run_traces(Path(run_dir))
    return summary, traces


def _run_traces(d: Path) -> tuple[RunSummary, DeviceMap | None, dict[str, RunTrace]]:
    summary, dm = _run_meta(d)
    traces = {f"case {summary.case}": _trace_of(d, summary, dm)}
    baseline = _baseline_of(d)
    if baseline is not None:
        traces[NO_CONTROL] = baseline
    return summary, dm, traces


def plot_run(run_dir: str | Path, *, out: str | Path | None = None) -> list[Path]:
    """The PNGs of one ``cvvc run`` folder (default into ``run_dir/plots``), the case against no control when the
    run simulated it, and ``report.md`` beside them (the run's report with the plots); returns the PNGs' paths.
    """
    from cvvc.run_report import extreme_minutes_text, limit_minutes_text, render_summary, side_moves_text

    d = Path(run_dir)
    summary, dm, traces = _run_traces(d)
    title = f"{summary.feeder_id} case {summary.case} from {summary.start}"
    folder = Path(out) if out else d / "plots"
    paths = _plots(traces, title, folder)
    worst = worst_node_figure(traces[f"case {summary.case}"], title)
    paths += [_save(worst, folder / "worst_node.png")] if worst is not None else []
    report_dir = folder if out else d
    links = [f"![{p.stem.replace('_', ' ')}]({p.relative_to(report_dir).as_posix()})" for p in paths]
    trace = traces[f"case {summary.case}"]
    steps = trace.tap_steps
    measured = f"\n## What the truth says of the model\n\n- {tap_steps_text(steps)}\n" if steps else ""
    outside = limit_minutes_text(trace.limit_minutes, summary.metrics.opt_limits_pu)
    outside += side_moves_text(trace.side_moves, summary.metrics.opt_limits_pu)
    outside += extreme_minutes_text(trace.extremes)
    (report_dir / "report.md").write_text(render_summary(summary, dm) + measured + outside + "\n## Plots\n\n"
                                          + "\n\n".join(links) + "\n")
    return paths


def plot_evaluation(eval_dir: str | Path, *, out: str | Path | None = None) -> list[Path]:
    """The PNGs of a ``cvvc evaluate`` folder: per season (and variant), every case together; returns paths."""
    d = Path(eval_dir)
    results_path = d / "results.json"
    if not results_path.is_file():
        raise ReportError(f"{d}: no results.json; pass a cvvc evaluate output folder")
    ev = decode_evaluation(results_path)
    groups: dict[str, dict[str, RunTrace]] = {}
    for r in ev.runs:
        spec = r.spec
        if not r.recording:  # the opendss reference case: OpenDSS's own loop, nothing recorded
            continue
        run_dir = Path(r.out_dir)
        if not run_dir.is_dir():
            run_dir = d / Path(r.out_dir).name
        trace = _trace_of(run_dir, *_run_meta(run_dir))
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
