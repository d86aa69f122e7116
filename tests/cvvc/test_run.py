"""``cvvc run`` end to end on IEEE 13: real processes, real Zenoh on loopback, real OpenDSS, real MCAP."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import msgspec
import numpy as np
import pytest

from schemas import messages as m
from schemas.devicemap import load_device_map
from simulator_bridge.opendss.engine import FeederEngine
from simulator_bridge.simulation.metrics_stream import MetricsAccumulator
from tests.recorded import messages_by_topic

REPO = Path(__file__).resolve().parents[2]


def _cvvc(*args: str, cwd: Path, timeout_s: float = 300.0) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", "cvvc", *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout_s, check=False)


def _processes_mentioning(text: str) -> list[int]:
    pids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit() and int(d.name) != os.getpid():
            try:
                cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:
                continue
            if text in cmd:
                pids.append(int(d.name))
    return pids


@pytest.fixture(scope="module")
def one_hour_run(tmp_path_factory, ieee13_model, sharing_profiles):
    """One simulated hour of case D on IEEE 13, from 11:00 on a summer day (PV producing)."""
    work = tmp_path_factory.mktemp("run")
    out = work / "out"
    proc = _cvvc("run", "--feeder", str(REPO / "feeders" / "ieee13.toml"), "--model", str(ieee13_model),
                 "--days", str(1 / 24), "--start", "2023-07-10T11:00", "--out", str(out),
                 "--cache", str(sharing_profiles(work / "cache")), "--json", cwd=work)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out, json.loads(proc.stdout)


def test_recording_holds_frames_decisions_and_acks(one_hour_run):
    out, summary = one_hour_run
    rec = messages_by_topic(Path(summary["recording"]))
    steps = summary["steps"]
    assert steps == 60
    assert len(rec["cvvc/ieee13/meas/head"]) == steps
    for plant in ("pv675", "pv680", "pv633"):
        assert len(rec[f"cvvc/ieee13/meas/pv/{plant}"]) == steps
    decisions = rec["cvvc/ieee13/agent/decision"]
    assert len(decisions) == summary["decisions"] == 12  # every 5 simulated minutes
    assert all(d["status"] in ("optimal", "soft") for d in decisions), [d["reason"] for d in decisions]
    acks = [a for topic, msgs in rec.items() if "/ack/" in topic for a in msgs]
    commands = [c for d in decisions for c in d["commands"]]
    follow_ups = [f for d in decisions for f in d["follow_ups"]]
    assert len(acks) == len(commands) + len(follow_ups) > 0
    assert {a["status"] for a in acks} <= {"accepted", "clipped"}
    assert summary["lockstep_misses"] == 0


def test_follow_ups_are_applied_at_the_step_after_their_decision(one_hour_run):
    """Every re-centred band a decision announced was sent once the next minute's frames were in, applied before
    the minute after (lockstep waits for it), and shows in that minute's regulator frame."""
    out, summary = one_hour_run
    rec = messages_by_topic(Path(summary["recording"]))
    sent = {c["cmd_id"]: c for t, msgs in rec.items() if "/cmd/vr/" in t for c in msgs}
    frames = {(f["regulator_id"], f["t_ns"]): f for t, msgs in rec.items() if "/meas/vr/" in t for f in msgs}
    minute = 60_000_000_000
    checked = 0
    for d in rec["cvvc/ieee13/agent/decision"]:
        for cmd_id in d["follow_ups"]:
            c = sent[cmd_id]
            assert c["t_ns"] == d["step_t_ns"] + minute
            after = frames.get((c["regulator_id"], c["t_ns"] + minute))
            if after is not None:
                assert after["setpoint_v120"] == pytest.approx(c["action"]["setpoint_v120"], abs=1e-3)
                checked += 1
    assert checked >= 1 and summary["follow_up_misses"] == 0


def test_summary_metrics_equal_those_recomputed_from_the_recording(one_hour_run):
    out, summary = one_hour_run
    rec = messages_by_topic(Path(summary["recording"]))
    truth = rec["cvvc/ieee13/sim/truth"]
    assert len(truth) == summary["steps"]
    # judged on the feeder zone's phase nodes (downstream of the head meter), as the bridge judges them
    engine = FeederEngine(load_device_map(REPO / "feeders" / "ieee13.toml"))
    assert list(engine.node_names) == truth[0]["node_names"]
    zone = [i for i, n in enumerate(engine.node_names) if engine.node_in_feeder[i] and n[-2:] in (".1", ".2", ".3")]
    assert 0 < len(zone) < len(engine.node_names)
    acc = MetricsAccumulator(n_nodes=len(truth[0]["v_pu"]), regulator_ids=["reg1", "reg2", "reg3"],
                             pv_ids=["pv675", "pv680", "pv633"], cost_per_tap=0.14, cost_per_kvar=0.001,
                             judged_nodes=zone)
    prev = np.asarray(truth[0]["taps"])
    for frame in truth:
        taps = np.asarray(frame["taps"])
        acc.update(np.asarray(frame["v_pu"]), np.abs(taps - prev), np.asarray(frame["pv_q_kvar"]))
        prev = taps
    mine, theirs = acc.result(), summary["metrics"]
    # the recorded voltages are float32 (TruthPack): within 6e-8 pu of the simulated float64 values
    assert mine.mvvm_pu == pytest.approx(theirs["mvvm_pu"], abs=1e-7)
    assert mine.nvv == theirs["nvv"]
    assert mine.q_cost == pytest.approx(theirs["q_cost"], rel=1e-9)
    assert mine.v_min_pu == pytest.approx(theirs["v_min_pu"], abs=1e-7)
    assert mine.v_max_pu == pytest.approx(theirs["v_max_pu"], abs=1e-7)
    # Tap changes inside the first step are not visible as a difference between truth frames.
    assert mine.ntc <= theirs["ntc"] <= mine.ntc + 3 * 16


def test_commands_are_applied_by_the_devices(one_hour_run):
    """Every PV set point the agent sent shows in that plant's next frame (as acked: accepted or clipped)."""
    out, summary = one_hour_run
    rec = messages_by_topic(Path(summary["recording"]))
    applied = {}
    for topic, msgs in rec.items():
        if "/ack/pv/" in topic:
            for a in msgs:
                applied[a["cmd_id"]] = a["applied_value"]
    frames = {(f["plant_id"], f["t_ns"]): f for t, msgs in rec.items() if "/meas/pv/" in t for f in msgs}
    checked = 0
    for d in rec["cvvc/ieee13/agent/decision"]:
        for c in d["commands"]:
            if c["type"] == "pv":
                nxt = frames.get((c["plant_id"], d["step_t_ns"] + 60_000_000_000))
                if nxt is None:
                    continue  # the last decision of the run
                assert nxt["q_setpoint_kvar"] == pytest.approx(applied[c["cmd_id"]], abs=1e-6)
                checked += 1
    assert checked >= 30


def test_violations_not_worse_than_no_control(one_hour_run):
    out, summary = one_hour_run
    base, ctrl = summary["baseline"], summary["metrics"]
    assert base["steps"] == summary["steps"]
    assert ctrl["nvv"] <= base["nvv"]
    assert ctrl["mvvm_pu"] <= base["mvvm_pu"] + 1e-9


def test_summary_holds_the_case_and_the_baseline_in_the_same_shape(one_hour_run):
    """The case and no control side by side: the same fields with the same JSON types (the baseline used to be the
    simulator's Metrics, lists of numbers where the case had dicts by device id)."""
    out, summary = one_hour_run
    case, base = summary["metrics"], summary["baseline"]
    assert base is not None and set(base) == set(case)
    assert {k: type(v).__name__ for k, v in base.items()} == {k: type(v).__name__ for k, v in case.items()}
    assert set(base["taps_changes"]) == set(case["taps_changes"]) == {"reg1", "reg2", "reg3"}
    assert set(base["q_mvar_intervals"]) == {"pv675", "pv680", "pv633"}
    assert base["q_cost"] == 0.0 and all(v == 0.0 for v in base["q_mvar_intervals"].values())  # unity PF
    assert (base["start_t_ns"], base["steps"]) == (case["start_t_ns"], case["steps"])


def test_report_run_draws_the_case_against_no_control(one_hour_run, tmp_path):
    """``cvvc report run``: every plot holds the case and the baseline simulated in the same run, the x axis in
    hours of the day, and report.md explains the costs, ends its story with a verdict and shows the plots."""
    import matplotlib.pyplot as plt

    from cvvc.report import NO_CONTROL, envelope_figure, plot_run, pv_figure, run_traces, taps_figure

    out, summary = one_hour_run
    run_summary, traces = run_traces(out)
    assert list(traces) == ["case D", NO_CONTROL]
    base = traces[NO_CONTROL]
    assert base.step_t_ns.size == summary["steps"] and base.t_ns.size == 6  # 60 minutes in 10-minute windows
    np.testing.assert_array_equal(base.step_t_ns, traces["case D"].step_t_ns)  # the same minutes
    assert base.regulator_ids == ("reg1", "reg2", "reg3") and base.pv_ids == ("pv675", "pv680", "pv633")
    assert np.all(base.pv_q_kvar == 0.0)  # no control: unity power factor
    b = summary["baseline"]
    assert b["v_min_pu"] - 1e-9 <= base.v_env_min_pu.min() and base.v_env_max_pu.max() <= b["v_max_pu"] + 1e-9

    fig = envelope_figure(traces, "t")
    ax_hi, ax_lo = fig.axes
    assert [line.get_label() for line in ax_hi.lines[:2]] == ["case D", NO_CONTROL]
    np.testing.assert_array_equal(ax_hi.lines[1].get_ydata(), base.v_env_max_pu)
    np.testing.assert_array_equal(ax_lo.lines[1].get_ydata(), base.v_env_min_pu)
    assert "hour of day, 2023-07-10" in ax_lo.get_xlabel() and "[pu" in ax_hi.get_ylabel()
    legend = ax_hi.get_legend()
    assert legend.get_bbox_to_anchor().x0 > ax_hi.get_window_extent().x1 - 1  # the legend is right of the data
    fig_taps, fig_pv = taps_figure(traces, "t"), pv_figure(traces, "t")
    for f, series in ((fig_taps, base.taps), (fig_pv, base.pv_q_kvar)):
        ax_case, ax_base = f.axes
        assert NO_CONTROL in ax_base.get_title()
        for k, line in enumerate(ax_base.lines[: series.shape[1]]):
            np.testing.assert_array_equal(line.get_ydata(), series[:, k])
    assert "+ injects" in fig_pv.axes[0].get_ylabel()
    for f in (fig, fig_taps, fig_pv):
        plt.close(f)

    paths = plot_run(out, out=tmp_path / "plots")
    assert {p.name for p in paths} >= {"voltage_envelope.png", "pv_q.png", "taps.png"}
    report = (tmp_path / "plots" / "report.md").read_text()
    assert "## Costs" in report and "what it charges" in report and "0.14 per tap step" in report
    assert "spends nothing on reactive power" in report
    verdict = [line for line in report.splitlines() if line.startswith("**Verdict:**")]
    assert len(verdict) == 1 and "case D" in verdict[0]
    assert "![voltage envelope](voltage_envelope.png)" in report


def test_tap_steps_are_counted_by_the_side_of_the_limits_the_decision_in_force_saw(one_hour_run, tmp_path):
    """Every tap step of the truth frames is counted once, up or down, under the side of the limits the decision in
    force saw crossed: with limits wide of every estimate none, with the limits swapped (every estimate over the
    upper and under the lower) both; report.md lists them."""
    from types import SimpleNamespace

    from cvvc.report import BEFORE_FIRST_DECISION, limit_side, plot_run, read_trace

    out, summary = one_hour_run
    rec = Path(summary["recording"])
    taps = np.array([t["taps"] for t in messages_by_topic(rec)["cvvc/ieee13/sim/truth"]])
    diff = np.diff(taps, axis=0)
    assert np.abs(diff).sum() > 0, "the hour must move taps for the counts to mean something"
    for limits, sides in (((0.5, 1.5), {"neither"}), ((1.5, 0.5), {"both"}),
                          (tuple(summary["metrics"]["opt_limits_pu"]), {"neither", "over", "under", "both"})):
        rows = read_trace(rec, opt_limits_pu=limits).side_moves
        assert sum(r.up for r in rows) == np.clip(diff, 0, None).sum()
        assert sum(r.down for r in rows) == np.clip(-diff, 0, None).sum()
        assert {r.side for r in rows} <= sides | {BEFORE_FIRST_DECISION}
    assert limit_side([SimpleNamespace(v_pu=1.035, bound_low_pu=0.002, bound_high_pu=0.006)], (0.975, 1.04)) == "over"
    assert limit_side([SimpleNamespace(v_pu=0.978, bound_low_pu=0.004, bound_high_pu=0.0)], (0.975, 1.04)) == "under"
    assert limit_side([SimpleNamespace(v_pu=1.0, bound_low_pu=0.01, bound_high_pu=0.01)], (0.975, 1.04)) == "neither"
    plot_run(out, out=tmp_path / "plots")
    assert "## Tap steps, by the side of the limits" in (tmp_path / "plots" / "report.md").read_text()


def test_the_lowest_and_highest_minutes_name_their_node_and_what_moved_before_them(one_hour_run, tmp_path):
    """The run's extreme minutes are the truth's over the phase nodes (value, time, node), one per side within the
    hour (episodes an hour apart), each with the decision in force and every tap step of its own and the four minutes
    before it; the plotted envelope is over the same nodes."""
    from cvvc.extreme_minutes import LOOKBACK_STEPS
    from cvvc.report import BEFORE_FIRST_DECISION, plot_run, read_trace
    from simulator_bridge.simulation.metrics_stream import phase_nodes

    out, summary = one_hour_run
    rec = Path(summary["recording"])
    truth = messages_by_topic(rec)["cvvc/ieee13/sim/truth"]
    names = truth[0]["node_names"]
    v = np.array([t["v_pu"] for t in truth])[:, phase_nodes(names)]
    regs = tuple(summary["metrics"]["taps_changes"])
    trace = read_trace(rec, regulator_ids=regs)
    rows = trace.extremes
    assert [r.side for r in rows] == ["lowest", "highest"]
    assert trace.v_env_min_pu.min() >= v.min() and trace.v_env_max_pu.max() <= v.max()
    taps = np.array([t["taps"] for t in truth])
    for r, per_step in ((rows[0], v.min(axis=1)), (rows[1], -v.max(axis=1))):
        i = int(np.argmin(per_step))
        assert (r.t_ns, r.v_pu) == (truth[i]["t_ns"], abs(per_step[i]))
        assert truth[i]["v_pu"][names.index(r.node)] == r.v_pu
        assert r.decision != BEFORE_FIRST_DECISION or i < 5
        expected = [(i - j, ", ".join(f"{regs[k]} {int(d):+d}" for k, d in enumerate(taps[j] - taps[j - 1]) if d))
                    for j in range(max(i - LOOKBACK_STEPS + 1, 1), i + 1) if np.any(taps[j] != taps[j - 1])]
        assert list(r.moves) == expected
    # over the nodes the run's metrics judge (the zone's phase nodes), its extremes are the metrics' own
    from cvvc.report import judged_node_names
    from schemas.devicemap import load_device_map

    zone = judged_node_names(load_device_map(REPO / "feeders" / "ieee13.toml"))
    assert zone and not any(n.endswith(".4") for n in zone)
    low, high = read_trace(rec, judged_nodes=zone).extremes
    assert low.v_pu == pytest.approx(summary["metrics"]["v_min_pu"], abs=1e-6)
    assert high.v_pu == pytest.approx(summary["metrics"]["v_max_pu"], abs=1e-6)
    plot_run(out, out=tmp_path / "plots")
    report = (tmp_path / "plots" / "report.md").read_text()
    assert "## The lowest and highest minutes, and what moved before them" in report
    assert f"| lowest | {low.v_pu:.4f} | {low.node} |" in report


def test_no_process_left_behind_and_outputs_written(one_hour_run):
    out, summary = one_hour_run
    assert _processes_mentioning(str(out)) == []
    for name in ("summary.json", "report.md", "model.json", "session.mcap", "baseline_trace.npz"):
        assert (out / name).is_file(), name
    assert json.loads((out / "summary.json").read_text())["metrics"] == summary["metrics"]
    # (c): the run's figures are the processes' own (their summaries), not whatever the bus carried
    bridge, agent = (json.loads((out / f"{who}-summary.json").read_text()) for who in ("bridge", "agent"))
    assert bridge["metrics"] == summary["metrics"]
    assert agent["decisions"] == summary["decisions"] and agent["holds"] == summary["holds"]
    assert summary["soft"] + summary["holds"] == sum(summary["reasons"].values())


def test_a_run_whose_decisions_mostly_held_ends_with_a_clear_error():
    """: 288 of 288 decisions 'hold' printed like a result; now the run ends with the reasons."""

    from cvvc.launch import LaunchError, RunSummary, check_mostly_held
    from schemas.examples import example

    base = RunSummary(feeder="f.toml", feeder_id="f", case="A", start="2023-01-01", days=1.0, steps=1440,
                      wall_s=1.0, metrics=example(m.MetricsFrame),
                      baseline=None, lockstep_misses=0, decisions=288, out_dir="out", recording=None, model=None)
    check_mostly_held(msgspec.structs.replace(base, holds=144))  # half: not most
    with pytest.raises(LaunchError, match="288 of 288 decisions were 'hold'.*288 x 'case A: no oracle reply'"):
        check_mostly_held(msgspec.structs.replace(base, holds=288, reasons={"case A: no oracle reply": 288}))


def test_the_run_report_lists_the_steps_the_agent_measured():
    from cvvc.launch import RunSummary
    from cvvc.run_report import render_summary
    from schemas.examples import example

    base = RunSummary(feeder="f.toml", feeder_id="f", case="D", start="2023-01-01", days=1.0, steps=1440,
                      wall_s=1.0, metrics=example(m.MetricsFrame), baseline=None, lockstep_misses=0, decisions=288,
                      out_dir="out", recording=None, model=None)
    assert "tap steps as the regulators' compared readings measured them" not in render_summary(base, None)
    steps = {f"vr{i}": 0.6 + i / 100 for i in range(10)}
    text = render_summary(msgspec.structs.replace(base, measured_steps_v120=steps), None)
    assert "measured them: vr0 0.60 V, vr1 0.61 V," in text and "vr7 0.67 V and 2 more" in text
    assert "rent or buy" not in text
    assert "(rent or buy): 7 decision(s)" in render_summary(msgspec.structs.replace(base, bought=7), None)


def test_offline_replay_reproduces_every_decision(one_hour_run, tmp_path):
    out, summary = one_hour_run
    proc = _cvvc("replay", summary["recording"], "--offline", "--json", cwd=tmp_path)  # from another directory
    assert proc.returncode == 0, proc.stderr[-2000:]
    diff = json.loads(proc.stdout)["diff"]
    assert diff["recorded"] == diff["identical"] == 12
    assert diff["changed"] == diff["missing"] == diff["extra"] == 0


@pytest.mark.process  # ``cvvc run`` as a program
def test_bad_arguments_give_a_clear_error(tmp_path, ieee13_model):
    proc = _cvvc("run", "--feeder", str(tmp_path / "nowhere.toml"), "--days", "0.01", cwd=tmp_path)
    assert proc.returncode == 2
    assert "no device map there" in proc.stderr and "Traceback" not in proc.stderr
    proc = _cvvc("run", "--feeder", str(REPO / "feeders" / "ieee13.toml"), "--start", "2023-13-01",
                 "--model", str(ieee13_model), cwd=tmp_path)
    assert proc.returncode == 2 and "not a date" in proc.stderr
    proc = _cvvc("run", "--feeder", str(REPO / "feeders" / "ieee13.toml"), "--meas-delay-s", "30",
                 "--model", str(ieee13_model), cwd=tmp_path)  # a delay needs a clock to be late on
    assert proc.returncode == 2 and "--meas-delay-s needs --realtime" in proc.stderr


@pytest.mark.parametrize(
    ("case", "window", "hold", "expect"),
    [
        ("D", None, False, {"mode": "setpoints", "correction": True, "pv_margin_window_s": 1800.0,
                            "setpoint_hold": False}),
        ("D", 0.0, True, {"pv_margin_window_s": 0.0, "setpoint_hold": True}),  # the paper's method, hold on
        ("B", 600.0, True, {"mode": "taps", "pv_margin_window_s": 600.0, "setpoint_hold": False}),  # no hold in B
        ("A", None, False, {"full_visibility": True, "pv_margin_window_s": 1800.0}),
        ("A", 0.0, False, {"full_visibility": True, "pv_margin_window_s": 0.0}),  # the paper's case A
    ],
)
def test_case_flags_give_the_settings_the_agent_records(case, window, hold, expect):
    """``cvvc run/evaluate --pv-margin-window-s/--setpoint-hold`` reach the agent, and the recording says so."""
    import argparse

    from agent.cli import register, settings_from_args
    from cvvc.launch import agent_settings_args, case_agent_settings
    from schemas.settings import AgentOptions

    options = AgentOptions(setpoint_hold=hold, **({} if window is None else {"pv_margin_window_s": window}))
    settings = case_agent_settings(case, "ieee13", options)
    assert settings is not None
    for name, value in expect.items():
        assert getattr(settings, name) == value, name
    # the agent process decodes exactly these settings from its command line
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["agent", "--model", "-", *agent_settings_args(settings), "--mode", "taps"])
    assert settings_from_args(args) == settings
    assert case_agent_settings("none", "ieee13", options) is None
    assert case_agent_settings("local", "ieee13") is None


def test_the_run_is_secure_by_default_and_says_so(one_hour_run):
    """Without a flag the run's bus is mTLS with the access policy: the CA made on this first run sits in
    ``<cache>/ca``, apart from the role keys of ``<cache>/security`` that the processes present."""
    out, summary = one_hour_run
    assert summary["secure"] is True
    assert "mTLS with per-role certificates" in (out / "report.md").read_text()
    cache = out.parent / "cache"
    assert (cache / "ca" / "ca.key").is_file()
    assert not (cache / "security" / "ca.key").exists()
    for role in ("agent", "devices", "recorder", "router"):
        assert (cache / "security" / f"{role}.key").stat().st_mode & 0o777 == 0o600
    bridge = json.loads((out / "bridge-summary.json").read_text())
    assert bridge["metrics"] == summary["metrics"]  # the children joined the TLS router and the run completed


def test_a_clean_run_says_nothing_was_refused_or_missed_and_exits_0(one_hour_run):
    """The fixture's run exited 0; its summary and report say every decision came and nothing was refused."""
    out, summary = one_hour_run
    g = summary["integrity"]
    assert g["decisions_due"] == summary["decisions"] == 12 and g["decisions_missing"] == 0
    assert g["lockstep_misses"] == 0 and g["foreign_acks"] == 0 and g["foreign_decisions"] == 0
    assert g["commands_refused"] == {} and g["meter_readings_refused"] == {} and g["degraded"] == ""
    report = (out / "report.md").read_text()
    assert "integrity: 12 of 12 decisions due (0 missing)" in report and "degraded" not in report


@pytest.mark.process
@pytest.mark.slow  # a whole ``cvvc run`` that waits out its lockstep time-outs (3 s each: no decision can come)
def test_a_run_without_decisions_for_more_than_a_control_period_exits_3_and_says_why(tmp_path, ieee13_model,
                                                                                      sharing_profiles):
    """Every frame lost (``--drop-prob 1``): the agent decides nothing for two control periods. The run still writes
    its summary and report, and exits 3 (not 0, not an error's 2) with one line saying why."""
    out = tmp_path / "out"
    proc = _cvvc("run", "--feeder", str(REPO / "feeders" / "ieee13.toml"), "--model", str(ieee13_model),
                 "--days", str(10 / 1440), "--start", "2023-07-10T11:00", "--out", str(out), "--cache",
                 str(sharing_profiles(tmp_path / "cache")), "--no-baseline", "--no-record", "--drop-prob", "1",
                 "--lockstep-timeout-s", "3", "--json", cwd=tmp_path)
    assert proc.returncode == 3, proc.stderr[-3000:]
    lines = [x for x in proc.stderr.splitlines() if x.startswith("cvvc run: degraded")]
    assert len(lines) == 1 and "2 of 2 control steps without a decision of the agent" in lines[0], proc.stderr[-2000:]
    summary = json.loads(proc.stdout)
    assert summary["integrity"]["decisions_missing"] == 2 and summary["integrity"]["degraded"]
    assert "**degraded for more than one control period**" in (out / "report.md").read_text()


@pytest.mark.process
@pytest.mark.slow  # a whole ``cvvc run``
def test_an_insecure_run_warns_and_records_it(tmp_path, sharing_profiles):
    proc = _cvvc("run", "--feeder", str(REPO / "feeders" / "ieee13.toml"), "--case", "none", "--days", str(3 / 1440),
                 "--out", str(tmp_path / "out"), "--cache", str(sharing_profiles(tmp_path / "cache")), "--no-baseline",
                 "--json",
                 "--insecure", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "WARNING --insecure: the bus runs without TLS and without access control" in proc.stderr
    assert json.loads(proc.stdout)["secure"] is False
    assert "**bus: insecure**" in (tmp_path / "out" / "report.md").read_text()
    assert not (tmp_path / "cache" / "ca").exists() and not (tmp_path / "cache" / "security").exists()
    both = _cvvc("run", "--insecure", "--secure", "--days", "0.01", cwd=tmp_path)
    assert both.returncode == 2 and "not allowed with argument" in both.stderr
