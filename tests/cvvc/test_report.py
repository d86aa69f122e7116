"""``cvvc report run|evaluate``: PNGs from a short real evaluation's MCAP recordings, and the numbers behind them."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import msgspec
import numpy as np
import pytest
from mcap.reader import make_reader

from agent.tap_moves import HELD_BY_DEADBAND
from cvvc.evaluate import EvaluateConfig, evaluate
from cvvc.report import (
    BEFORE_FIRST_DECISION,
    ReportError,
    decision_kind,
    envelope_figure,
    errors_figure,
    plot_evaluation,
    plot_run,
    pv_figure,
    read_trace,
    taps_figure,
    window_envelope_pu,
)
from cvvc.step_effect import TapStepAccumulator
from schemas.truth import to_truth_frame, truth_pack

REPO = Path(__file__).resolve().parents[2]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def tiny_evaluation(tmp_path_factory, ieee13_model, profile_cache, dask_scheduler):
    """Case D on IEEE 13 for the first 25 minutes of April (one recording with truth and decisions)."""
    out = tmp_path_factory.mktemp("report") / "eval"
    ev = evaluate(EvaluateConfig(feeder=str(REPO / "feeders" / "ieee13.toml"), model=str(ieee13_model),
                                 cases=("D",), seasons=("spring",), days_per_season=25 / 1440, out=str(out),
                                 cache=str(profile_cache.parent), progress=False, scheduler=dask_scheduler))
    return out, ev


def _truth(path: Path) -> list[dict]:
    with path.open("rb") as f:
        return [msgspec.to_builtins(to_truth_frame(truth_pack(m.data, ch.message_encoding)))
                for _, ch, m in make_reader(f).iter_messages(log_time_order=True) if ch.topic.endswith("/sim/truth")]


def _assert_pngs(paths: list[Path], names: set[str]) -> None:
    """The files are PNGs with something drawn: ink (axes, labels, data) and coloured series (not only grey)."""
    import matplotlib.image

    assert {p.name for p in paths} == names
    for p in paths:
        assert p.read_bytes()[:8] == PNG_MAGIC, p
        rgb = matplotlib.image.imread(p)[..., :3]
        assert rgb.shape[0] > 300 and rgb.shape[1] > 1000, (p, rgb.shape)
        ink = np.any(rgb < 0.9, axis=-1).mean()
        assert 0.01 < ink < 0.5, (p, ink)  # axes, labels and data; not blank, not a filled canvas
        coloured = (rgb.max(axis=-1) - rgb.min(axis=-1)) > 0.3  # series colours; axes and text are grey
        assert coloured.sum() > 20, p


def test_report_run_writes_the_five_pngs(tiny_evaluation, tmp_path):
    out, ev = tiny_evaluation
    paths = plot_run(ev.runs[0].out_dir, out=tmp_path / "plots")
    _assert_pngs(paths, {"voltage_envelope.png", "pv_q.png", "taps.png", "estimation_error.png", "worst_node.png"})
    steps = read_trace(Path(ev.runs[0].recording), regulator_ids=("reg1", "reg2", "reg3")).tap_steps
    report = (tmp_path / "plots" / "report.md").read_text()
    assert ("## What the truth says of the model" in report) == bool(steps)
    assert all(f"{e.regulator} {e.share_of_model:.2f} ({e.steps} step" in report for e in steps)


def test_minutes_outside_the_limits_are_counted_by_the_decision_in_force(tiny_evaluation, tmp_path):
    """Limits at the recording's median extremes: every minute a node is under (over) them is counted once, against
    the decision of an earlier step (the first minutes, before any, apart); the run's report lists them when its own
    limits were left."""
    out, ev = tiny_evaluation
    rec = Path(ev.runs[0].recording)
    truth = _truth(rec)
    lo, hi = float(np.median([t["v_min_pu"] for t in truth])), float(np.median([t["v_max_pu"] for t in truth]))
    rows = read_trace(rec, opt_limits_pu=(lo, hi)).limit_minutes
    assert sum(r.under for r in rows) == sum(t["v_min_pu"] < lo for t in truth) > 0
    assert sum(r.over for r in rows) == sum(t["v_max_pu"] > hi for t in truth) > 0
    with rec.open("rb") as f:
        steps = sorted(msgspec.json.decode(m.data)["step_t_ns"] for _, ch, m in make_reader(f).iter_messages()
                       if ch.topic.endswith("/agent/decision"))
    first = [t for t in truth if t["t_ns"] <= steps[0]]  # the first decision acts from the next step on
    early = next((r for r in rows if r.kind == BEFORE_FIRST_DECISION), None)
    assert (early.under if early else 0) == sum(t["v_min_pu"] < lo for t in first)
    assert {r.kind for r in rows} <= {BEFORE_FIRST_DECISION, "optimal", "soft form", "taps held by the tap deadband",
                                      "hold"}
    assert decision_kind("soft", f"{HELD_BY_DEADBAND} 0.0010 pu predicted") == "taps held by the tap deadband"
    assert decision_kind("soft", "hard voltage limits infeasible") == "soft form"
    plot_run(ev.runs[0].out_dir, out=tmp_path / "plots")
    own = read_trace(rec, opt_limits_pu=ev.runs[0].metrics.opt_limits_pu).limit_minutes
    report = (tmp_path / "plots" / "report.md").read_text()
    assert ("## Minutes outside the optimization limits" in report) == bool(own)


def test_live_accuracy_from_the_recording_equals_the_bridges(tiny_evaluation):
    """Two paths to the same figures: the bridge judged each decision against its truth while the run went on;
    the report reads the recording's decisions and truth frames back. They agree on every count (the bridge has
    the float64 truth, the recording float32: within 1e-6 pu on the error)."""
    out, ev = tiny_evaluation
    live = ev.runs[0].live
    assert live is not None and live.decisions == 5 and live.bound_samples == live.samples > 0
    assert live.promised_miss_rate is not None and 0 < live.promised_miss_rate < 0.1
    w = read_trace(Path(ev.runs[0].recording)).worst
    assert w is not None and w.t_ns.size == 5
    again = w.accuracy
    assert (again.decisions, again.samples, again.bound_misses) == (live.decisions, live.samples, live.bound_misses)
    assert again.rmse_pu == pytest.approx(live.rmse_pu, abs=1e-6)
    outside = (w.v_true_pu < w.v_est_pu - w.bound_low_pu - 1e-6) | (w.v_true_pu > w.v_est_pu + w.bound_high_pu + 1e-6)
    assert int(outside.sum()) == w.accuracy.worst.misses_below + w.accuracy.worst.misses_above
    text = (out / "results.md").read_text()
    assert "## Live accuracy" in text and "## Every minute (no average)" in text


def test_report_evaluate_groups_cases_per_season(tiny_evaluation):
    out, ev = tiny_evaluation
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-m", "cvvc", "report", "evaluate", str(out)], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    paths = [Path(line) for line in proc.stdout.split()]
    _assert_pngs(paths, {"spring-voltage_envelope.png", "spring-pv_q.png", "spring-taps.png",
                         "spring-estimation_error.png"})  # the worst node is a run's own figure
    assert all(p.parent == out / "plots" for p in paths)


def test_trace_matches_the_recorded_truth(tiny_evaluation):
    out, ev = tiny_evaluation
    rec = Path(ev.runs[0].recording)
    truth = _truth(rec)
    assert len(truth) == 25
    v = np.array([t["v_pu"] for t in truth])
    trace = read_trace(rec)
    vmax, vmin = window_envelope_pu(v)
    assert trace.v_env_max_pu.shape == (3,)  # 10 + 10 + 5 minutes
    np.testing.assert_allclose(trace.v_env_max_pu, vmax, rtol=0, atol=1e-12)
    np.testing.assert_allclose(trace.v_env_min_pu, vmin, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(trace.taps, [t["taps"] for t in truth])
    q = np.array([t["pv_q_kvar"] for t in truth])
    np.testing.assert_allclose(trace.pv_q_kvar[-1], q[20:].mean(axis=0), atol=1e-9)
    # decisions every 5 minutes, each matched with the truth of its step
    assert trace.err_t_ns.size == 5
    assert trace.errors_pu.size > 0 and np.abs(trace.errors_pu).max() < 0.05
    # the regulators' single steps against the model: the same as the accumulator fed the decoded frames
    with rec.open("rb") as f:
        decision = next(msgspec.json.decode(m.data) for _, ch, m in make_reader(f).iter_messages()
                        if ch.topic.endswith("/agent/decision"))
    regulators = ("reg1", "reg2", "reg3")
    acc = TapStepAccumulator(truth[0]["node_names"], [e["node"] for e in decision["estimates"]],
                             np.array(decision["dv_dtap_pu"]), regulators)
    for t in truth:
        acc.add(t["t_ns"], np.array(t["v_pu"]), np.array(t["taps"]), np.array(t["pv_q_kvar"]),
                np.array(t["cap_states"]))
    assert read_trace(rec, regulator_ids=regulators).tap_steps == acc.result()
    assert trace.tap_steps == ()  # no regulator named, nothing measured


def test_figures_draw_the_trace(tiny_evaluation):
    """Each figure's axes hold the trace's numbers: envelopes and limits, plant Q, taps, estimation errors."""
    import matplotlib.pyplot as plt

    out, ev = tiny_evaluation
    recorded = read_trace(Path(ev.runs[0].recording))
    # distinct columns (the recorded night has every plant at Q = 0), so a plant drawn for another shows
    q, taps = recorded.pv_q_kvar, recorded.taps
    trace = dataclasses.replace(recorded, pv_q_kvar=q + np.arange(q.size).reshape(q.shape),
                                taps=taps + np.arange(taps.shape[1]))
    traces = {"case D": trace}
    lo, hi = trace.limits_pu
    fig = envelope_figure(traces, "t")
    ax_hi, ax_lo = fig.axes
    np.testing.assert_array_equal(ax_hi.lines[0].get_ydata(), trace.v_env_max_pu)
    np.testing.assert_array_equal(ax_lo.lines[0].get_ydata(), trace.v_env_min_pu)
    assert list(ax_hi.lines[1].get_ydata()) == [hi, hi] and list(ax_lo.lines[1].get_ydata()) == [lo, lo]
    fig_pv = pv_figure(traces, "t")
    (ax,) = fig_pv.axes
    assert len(ax.lines) == trace.pv_q_kvar.shape[1] + 1  # every plant, then the zero line between the signs
    for k, line in enumerate(ax.lines[:-1]):
        np.testing.assert_array_equal(line.get_ydata(), trace.pv_q_kvar[:, k])
    assert list(ax.lines[-1].get_ydata()) == [0.0, 0.0]
    fig_taps = taps_figure(traces, "t")
    (ax,) = fig_taps.axes
    assert len(ax.lines) == trace.taps.shape[1]
    for r, line in enumerate(ax.lines):
        np.testing.assert_array_equal(line.get_ydata(), trace.taps[:, r])
    fig_err = errors_figure(traces, "t")
    ax, axh = fig_err.axes
    np.testing.assert_array_equal(ax.lines[0].get_ydata(), trace.err_rms_pu)
    assert sum(patch.get_height() for patch in axh.patches) == trace.errors_pu.size  # every error binned
    for f in (fig, fig_pv, fig_taps, fig_err):
        plt.close(f)
    no_estimates = {"case none": dataclasses.replace(trace, err_t_ns=trace.err_t_ns[:0])}
    assert errors_figure(no_estimates, "t") is None


def test_window_envelope_by_hand():
    v = np.array([[1.0, 0.9], [1.1, 0.95], [1.2, 1.0]])
    vmax, vmin = window_envelope_pu(v, window_steps=2)
    np.testing.assert_allclose(vmax, [1.05, 1.2])
    np.testing.assert_allclose(vmin, [0.925, 1.0])


def test_missing_inputs_are_clear_errors(tmp_path):
    with pytest.raises(ReportError, match="no summary.json"):
        plot_run(tmp_path)
    with pytest.raises(ReportError, match="no results.json"):
        plot_evaluation(tmp_path)
    with pytest.raises(ReportError, match="no recording there"):
        read_trace(tmp_path / "missing.mcap")
    # a summary or results file of another layout: one clear error naming the file, not a half-drawn plot
    (tmp_path / "summary.json").write_text('{"feeder": "x", "metrics": {}}')
    with pytest.raises(ReportError, match="summary.json: not a cvvc run summary of this version"):
        plot_run(tmp_path)
    (tmp_path / "results.json").write_text('{"runs": []}')
    with pytest.raises(ReportError, match="results.json: not a cvvc evaluate result of this version"):
        plot_evaluation(tmp_path)


def test_truth_series_reduces_like_the_envelope_and_survives_its_file(tmp_path):
    """The baseline's series (``cvvc run`` fills it from simulated steps) reduce as the recording's do, and the
    ``.npz`` written beside the run reads back equal."""
    from cvvc.run_trace import TruthSeries, read_series, write_series

    rng = np.random.default_rng(3)
    v = 1.0 + 0.02 * rng.standard_normal((25, 7))
    q = rng.standard_normal((25, 2))
    series = TruthSeries()
    for t in range(25):
        series.add(1_700_000_000_000_000_000 + t * 60_000_000_000, v[t], np.array([t % 3, -t % 2]), q[t],
                   np.array([1]))
    trace = series.trace(regulator_ids=("r1", "r2"), pv_ids=("p1", "p2"), limits_pu=(0.95, 1.05),
                         capacitor_ids=("c1",))
    vmax, vmin = window_envelope_pu(v)
    np.testing.assert_allclose(trace.v_env_max_pu, vmax, atol=1e-12)
    np.testing.assert_allclose(trace.v_env_min_pu, vmin, atol=1e-12)
    np.testing.assert_allclose(trace.pv_q_kvar[-1], q[20:].mean(axis=0), atol=1e-12)
    assert trace.taps.shape == (25, 2) and trace.cap_states.shape == (25, 1)
    back = read_series(write_series(tmp_path / "b.npz", trace))
    for name in ("t_ns", "step_t_ns", "v_env_max_pu", "v_env_min_pu", "taps", "pv_q_kvar", "cap_states"):
        np.testing.assert_array_equal(getattr(back, name), getattr(trace, name))
    assert (back.regulator_ids, back.pv_ids, back.capacitor_ids, back.limits_pu) == (
        ("r1", "r2"), ("p1", "p2"), ("c1",), (0.95, 1.05))


def test_the_time_axis_is_hour_of_day_or_date_and_hour():
    """One day: hours of that day; several: date and hour, local standard time (UTC-5), both on the x axis label."""
    import matplotlib.pyplot as plt

    from cvvc.report import envelope_figure
    from cvvc.run_trace import TruthSeries

    t0 = 1_689_008_400_000_000_000  # 2023-07-10 12:00 at UTC-5
    for minutes, expect, first_tick in ((120, "hour of day, 2023-07-10", "12:00"),
                                        (3 * 1440, "date and hour", "07-10")):
        series = TruthSeries()
        for t in range(minutes):
            series.add(t0 + t * 60_000_000_000, np.full(3, 1.0), np.zeros(1), np.zeros(1), np.zeros(0))
        fig = envelope_figure({"case D": series.trace()}, "t")
        fig.canvas.draw()
        ax_lo = fig.axes[1]
        assert expect in ax_lo.get_xlabel() and "UTC-5" in ax_lo.get_xlabel()
        assert any(label.get_text().startswith(first_tick) for label in ax_lo.get_xticklabels()), [
            label.get_text() for label in ax_lo.get_xticklabels()]
        plt.close(fig)


def test_a_summary_written_before_the_baseline_took_the_cases_form_still_reads(tmp_path):
    """summary.json of earlier versions kept the baseline as the simulator's Metrics (lists by device, n_steps):
    read with it turned into the case's form, the same figures."""
    from cvvc.report import decode_summary
    from cvvc.run_summary import RunSummary
    from schemas import messages as m
    from schemas.examples import example
    from simulator_bridge.simulation.metrics import metrics_from_series

    rng = np.random.default_rng(5)
    old = metrics_from_series(1.0 + 0.04 * rng.standard_normal((30, 4)), rng.integers(0, 2, (30, 2)),
                              rng.normal(0, 50, (30, 3)), regulator_ids=["r1", "r2"], pv_ids=["p1", "p2", "p3"],
                              cost_per_tap=0.14, cost_per_kvar=0.001)
    case = example(m.MetricsFrame)
    summary = RunSummary(feeder="f.toml", feeder_id=case.feeder_id, case="D", start="2023-01-16", days=1.0,
                         steps=30, wall_s=1.0, metrics=case, baseline=None, lockstep_misses=0, decisions=6,
                         out_dir="out", recording=None, model=None)
    raw = msgspec.to_builtins(summary)
    raw["baseline"] = msgspec.to_builtins(old)
    (tmp_path / "summary.json").write_bytes(msgspec.json.encode(raw))
    back = decode_summary(tmp_path / "summary.json", RunSummary)
    assert isinstance(back.baseline, m.MetricsFrame) and back.metrics == case
    b = back.baseline
    assert (b.steps, b.nvv, b.ntc, b.start_t_ns) == (old.n_steps, old.nvv, old.ntc, case.start_t_ns)
    assert b.q_cost == pytest.approx(old.q_cost) and b.total_cost == pytest.approx(old.total_cost)
    assert b.taps_changes == dict(zip(old.regulator_ids, old.tap_changes_per_regulator, strict=True))
    assert list(b.q_mvar_intervals) == ["p1", "p2", "p3"]
