"""``cvvc evaluate`` on IEEE 13: real runs through the bus (bridge, agent, recorder), tables, bad input."""

from __future__ import annotations

import datetime as dt
import json
import os
import subprocess
import sys
from pathlib import Path

import msgspec
import numpy as np
import pytest

from cvvc.evaluate import (
    EvaluateConfig,
    EvaluateError,
    evaluate,
    longest_first,
    parse_cases,
    parse_seasons,
    perturbation_commands,
    perturbed_device_map,
    plan_runs,
    render_results_md,
    season_window,
)
from cvvc.launch import RunSummary
from cvvc.run_report import render_summary

REPO = Path(__file__).resolve().parents[2]
IEEE13 = REPO / "feeders" / "ieee13.toml"


@pytest.fixture(scope="module")
def small_evaluation(tmp_path_factory, ieee13_model, profile_cache):
    """Cases D and none on IEEE 13, summer, the first 0.05 day (72 one-minute steps) of July, on a local Dask
    cluster of two workers."""
    out = tmp_path_factory.mktemp("evaluate") / "out"
    config = EvaluateConfig(feeder=str(IEEE13), model=str(ieee13_model), cases=("D", "none"), seasons=("summer",),
                            days_per_season=0.05, out=str(out), cache=str(profile_cache.parent), progress=False,
                            jobs=2)
    return out, evaluate(config)


def test_evaluate_writes_results_json_with_every_run(small_evaluation):
    out, ev = small_evaluation
    data = json.loads((out / "results.json").read_text())
    assert [r["spec"]["case"] for r in data["runs"]] == ["D", "none"]
    for r in data["runs"]:
        assert r["spec"]["season"] == "summer" and r["spec"]["start"] == "2023-07-01"
        assert r["steps"] == 72
        assert r["metrics"]["steps"] == 72
        assert set(r["metrics"]["taps_changes"]) == {"reg1", "reg2", "reg3"}
        assert set(r["metrics"]["q_mvar_intervals"]) == {"pv633", "pv675", "pv680"}
        assert Path(r["recording"]).is_file()
        assert r["lockstep_misses"] == 0
    d, none = data["runs"]
    assert d["decisions"] == 15  # every 5 simulated minutes: t = 0, 5, ..., 70
    assert none["decisions"] == 0  # the baseline runs no agent
    assert [r["attempts"] for r in data["runs"]] == [1, 1]
    assert "local Dask cluster, jobs=2" in (out / "results.md").read_text()


@pytest.mark.bus
def test_runs_on_a_local_cluster_of_two_workers_measure_what_they_measure_in_process(small_evaluation, tmp_path):
    """The same two runs, each through cvvc.launch.run in this process, give the same metrics frames."""
    from cvvc.evaluate import _run_config
    from cvvc.launch import run

    out, ev = small_evaluation
    worker_pids = {int(line.split(" pid ")[1].split()[0]) for r in ev.runs
                   for line in (Path(r.out_dir) / "attempts.txt").read_text().splitlines()}
    assert os.getpid() not in worker_pids  # the runs ran in the cluster's worker processes
    for r in ev.runs:
        here = run(_run_config(r.spec, ev.config, Path(ev.feeder), Path(ev.model), tmp_path, None))
        assert here.steps == r.steps and here.decisions == r.decisions
        assert here.metrics == r.metrics, r.spec.name


def test_a_recordings_time_span_starts_at_the_first_simulated_minute(small_evaluation):
    """The agent's status before its first frame (t_ns 0) does not pull the recorded
    span back to 1970; the span starts at 2023-07-01 00:00 local standard time (UTC-5) and covers the window."""
    from mcap.reader import make_reader

    out, ev = small_evaluation
    first_ns = int(dt.datetime(2023, 7, 1, 5, tzinfo=dt.UTC).timestamp()) * 10**9
    for r in ev.runs:
        with open(r.recording, "rb") as f:
            stats = make_reader(f).get_summary().statistics
        assert stats.message_start_time == first_ns, r.spec.name
        assert stats.message_end_time == first_ns + (r.steps - 1) * 60 * 10**9, r.spec.name


def test_results_md_shows_capacitor_switchings_only_for_maps_with_banks(small_evaluation):
    import msgspec

    out, ev = small_evaluation
    assert "Cap sw" not in (out / "results.md").read_text()  # IEEE 13's map lists no bank
    runs = tuple(msgspec.structs.replace(r, metrics=msgspec.structs.replace(
        r.metrics, cap_switches=3, cap_cost=4.0, cap_switches_per_bank={"cap1": 2, "cap2": 1})) for r in ev.runs)
    md = render_results_md(msgspec.structs.replace(ev, runs=runs))
    assert "| Season | Case | MVVM [pu] | NVV | NTC | Cap sw | Q Cost | T Cost | Cap Cost | Total | wall [s] |" in md
    assert "## Capacitor switchings per bank" in md and "| Season | Case | cap1 | cap2 | total |" in md
    assert "| summer | none | 2 | 1 | 3 |" in md


def test_results_md_has_the_paper_table_rows(small_evaluation):
    out, ev = small_evaluation
    md = (out / "results.md").read_text()
    assert "| Season | Case | MVVM [pu] | NVV | NTC | Q Cost | T Cost | Total | wall [s] |" in md
    for r in ev.runs:
        mt = r.metrics
        row = (f"| summer | {r.spec.case} | {mt.mvvm_pu:.4f} | {mt.nvv} | {mt.ntc} | {mt.q_cost:.1f} | "
               f"{mt.t_cost:.2f} | {mt.total_cost:.1f} |")
        assert row in md
        taps = " | ".join(str(mt.taps_changes[g]) for g in ("reg1", "reg2", "reg3"))
        assert f"| summer | {r.spec.case} | {taps} | {mt.ntc} |" in md
    assert "pv633 [kvarh]" in md and "(paper Table IV)" in md and "(paper Table V)" in md


def test_results_list_each_agent_runs_soft_and_hold_decisions_and_its_decision_time(small_evaluation):
    """The soft and hold counts (read by hand from each run's agent-summary.json before) and the
    agent's decision time of every run, in results.json and results.md; none for the baseline, which has no agent."""
    out, ev = small_evaluation
    d, none = ev.runs
    agent = json.loads((Path(d.out_dir) / "agent-summary.json").read_text())
    assert (d.soft, d.holds, d.reasons) == (agent["soft"], agent["holds"], agent["reasons"])
    assert d.tolerated == agent["tolerated"] <= d.soft
    assert d.soft + d.holds == sum(d.reasons.values())
    assert set(d.decision_ms) == {"p50", "p99", "max"}
    assert 0.0 < d.decision_ms["p50"] <= d.decision_ms["p99"] <= d.decision_ms["max"] < 60_000.0
    cpu = agent["decision_cpu_ms"]  # the deciding thread's CPU time: within the decision's wall time
    assert 0.0 < cpu["p50"] <= d.decision_ms["p50"] and cpu["max"] <= d.decision_ms["max"]
    assert none.decision_ms == {} and none.decisions == 0
    md = (out / "results.md").read_text()
    assert "## Decisions" in md
    row = f"| summer | D | 15 | {d.soft} ({d.soft / 15:.0%}; {d.tolerated}) | {d.holds} |"
    assert row in md and f"| {d.decision_ms['p99']:.1f} | {d.decision_ms['max']:.1f} |" in md
    assert "| summer | none | 0 |" not in md.split("## Decisions")[1]
    live = md.split("## Live accuracy")[1].split("##")[0]  # the agent's run is judged, the baseline has nothing to
    assert "| summer | D |" in live and "| summer | none |" not in live  # judge
    assert d.live is not None and d.live.decisions == 15 and none.live is None
    minutes = md.split("## Every minute (no average)")[1].split("##")[0]
    assert f"| summer | none | {none.metrics.node_minutes_outside_opt:,} |" in minutes
    report = (Path(d.out_dir) / "report.md").read_text()
    assert f"decision time (the agent's, per control step): p50 {d.decision_ms['p50']:.1f} ms" in report
    assert f"the deciding thread's CPU time p50 {cpu['p50']:.1f} ms" in report


def test_results_md_judges_the_agent_run_against_no_control_of_its_season(small_evaluation):
    """Without case A in the evaluation, only the goals against no control and the bounds are judged."""
    out, ev = small_evaluation
    d, none = ev.runs
    goals = (out / "results.md").read_text().split("## Closed-loop goals")[1].split("##")[0]
    (row,) = [line for line in goals.splitlines() if line.startswith("| summer | D |")]
    cells = [c.strip() for c in row.strip("|").split("|")]
    nvv, ntc, cost, ansi = cells[2:6]
    assert nvv == ntc == cost == ""  # no case A to judge them against
    dm, nm = d.metrics.node_minutes_outside_ansi, none.metrics.node_minutes_outside_ansi
    assert ansi == (f"{dm:,}" if dm <= nm else f"**{dm:,}** > {nm:,}")
    assert "| summer | none |" not in goals
    # the simulation states the limits it judged against and counts how fast each regulator moved
    assert d.metrics.opt_limits_pu == (0.975, 1.04) and cells[7].startswith(f"{d.metrics.v_min_pu:.4f}")
    assert set(d.metrics.steps_over_tap_rate) == set(d.metrics.taps_changes) and cells[-1] == "0"


@pytest.mark.process  # ``cvvc evaluate`` as a program
def test_unknown_case_or_season_is_a_clear_error(tmp_path):
    with pytest.raises(EvaluateError, match="unknown case.*E.*choose from A,B,C,D,none,local"):
        parse_cases("D,E")
    with pytest.raises(EvaluateError, match="unknown season.*monsoon"):
        parse_seasons("summer,monsoon")
    with pytest.raises(EvaluateError, match="unknown season"):
        evaluate(EvaluateConfig(feeder=str(IEEE13), seasons=("monsoon",), out=str(tmp_path)))  # type: ignore[arg-type]
    with pytest.raises(EvaluateError, match="days-per-season 40"):
        season_window("winter", 40)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-m", "cvvc", "evaluate", "--cases", "D,X", "--out", str(tmp_path / "x")],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 2
    assert "unknown case(s) X" in proc.stderr and "Traceback" not in proc.stderr


def test_case_a_runs_start_first_and_the_rest_keep_their_order(tmp_path):
    config = EvaluateConfig(feeder=str(IEEE13), cases=("none", "D", "A", "B"), seasons=("winter", "summer"),
                            out=str(tmp_path))
    planned = plan_runs(config)
    started = longest_first(planned)
    assert sorted(s.name for s in started) == sorted(s.name for s in planned)
    assert [s.case for s in started[:2]] == ["A", "A"] and all(s.case != "A" for s in started[2:])
    rest = [s.name for s in planned if s.case != "A"]
    assert [s.name for s in started[2:]] == rest


def test_season_window_is_the_month_or_its_first_days():
    assert season_window("winter", None) == ("2023-01-01", 31.0)
    assert season_window("spring", None) == ("2023-04-01", 30.0)
    assert season_window("fall", 7) == ("2023-10-01", 7.0)


def test_model_error_map_perturbs_lines_and_loads_within_ten_percent(tmp_path):
    text = "New Line.a bus1=x bus2=y length=2.0 units=km\nnew load.L1 bus1=y kW=100 kvar=10\nNew Line.b bus1=y\n"
    cmds = perturbation_commands(text, pct=10.0, seed=3)
    assert len(cmds) == 2  # line b has no explicit length: left alone
    length = float(cmds[0].split("=")[1])
    kw = float(cmds[1].split("=")[1])
    assert cmds[0].startswith("Line.a.length=") and 1.8 <= length <= 2.2 and length != 2.0
    assert cmds[1].startswith("Load.L1.kW=") and 90 <= kw <= 110 and kw != 100
    assert perturbation_commands(text, pct=10.0, seed=3) == cmds

    from schemas.devicemap import load_device_map
    from simulator_bridge.opendss.engine import FeederEngine

    path = perturbed_device_map(IEEE13, tmp_path / "perturbed", pct=10.0, seed=7)
    nominal, perturbed = load_device_map(IEEE13), load_device_map(path)
    assert perturbed.feeder.name == nominal.feeder.name
    assert perturbed.fingerprint() != nominal.fingerprint()
    a, b = FeederEngine(nominal), FeederEngine(perturbed)
    try:
        ratio = b.load_kw_nominal / a.load_kw_nominal
        assert np.all((ratio >= 0.9) & (ratio <= 1.1)) and np.ptp(ratio) > 0.01
        assert a.node_names == b.node_names
        assert 1e-4 < np.abs(a.node_voltages_pu() - b.node_voltages_pu()).max() < 0.05
    finally:
        a.close()
        b.close()


def test_resume_reuses_finished_runs(small_evaluation, ieee13_model, profile_cache):
    out, ev = small_evaluation
    stamps = {r.spec.name: (Path(r.out_dir) / "summary.json").stat().st_mtime_ns for r in ev.runs}
    again = evaluate(EvaluateConfig(feeder=str(IEEE13), model=str(ieee13_model), cases=("D", "none"),
                                    seasons=("summer",), days_per_season=0.05, out=str(out),
                                    cache=str(profile_cache.parent), progress=False, resume=True))
    assert [r.metrics for r in again.runs] == [r.metrics for r in ev.runs]
    assert {r.spec.name: (Path(r.out_dir) / "summary.json").stat().st_mtime_ns for r in again.runs} == stamps


def test_a_failed_run_is_listed_and_the_others_kept(tmp_path, profile_cache, dask_scheduler):
    """A run that fails is retried once (two attempts), then listed; the other run finishes."""
    out = tmp_path / "out"
    config = EvaluateConfig(feeder=str(IEEE13), model=str(tmp_path / "no-such-model.json"), cases=("D", "none"),
                            seasons=("winter",), days_per_season=0.01, out=str(out),
                            cache=str(profile_cache.parent), progress=False, scheduler=dask_scheduler)
    with pytest.raises(EvaluateError, match=r"1 of 2 run\(s\) failed \(winter-D-bw4\).*--resume"):
        evaluate(config)
    data = json.loads((out / "results.json").read_text())
    assert [r["spec"]["case"] for r in data["runs"]] == ["none"]
    assert [f["spec"]["case"] for f in data["failures"]] == ["D"]
    assert [f["attempts"] for f in data["failures"]] == [2] and "cannot read model" in data["failures"][0]["error"]
    assert len((out / "winter-D-bw4" / "attempts.txt").read_text().splitlines()) == 2
    md = (out / "results.md").read_text()
    assert "| winter | none |" in md and "## Failed runs" in md and "winter-D-bw4" in md and "2 attempt(s)" in md


def test_opendss_reference_case_beside_none(tmp_path, profile_cache, dask_scheduler):
    """The opendss case (OpenDSS's own control loop, no bus) gives the same table rows as a bus run, and, being the
    same local control physics of the same model on the same loads and PV (tests/simulator_bridge/
    test_opendss_loop.py), each regulator's tap count within one of the none case's; --resume reuses it. Both start
    settled, so the window is a winter morning's ramp (half a day), when the regulators move."""
    out = tmp_path / "out"
    config = EvaluateConfig(feeder=str(IEEE13), cases=("none", "opendss"), seasons=("winter",), days_per_season=0.5,
                            out=str(out), cache=str(profile_cache.parent), progress=False, scheduler=dask_scheduler)
    ev = evaluate(config)
    none, ref = ev.runs
    assert (none.spec.case, ref.spec.case) == ("none", "opendss")
    assert ref.recording is None and ref.steps == none.steps == 720
    assert none.metrics.ntc >= 5, "the window must move taps for the comparison to mean something"
    for g, n in none.metrics.taps_changes.items():
        assert abs(ref.metrics.taps_changes[g] - n) <= 1, (ref.metrics.taps_changes, none.metrics.taps_changes)
    assert ref.metrics.nvv == none.metrics.nvv and ref.metrics.q_cost == 0.0
    md = (out / "results.md").read_text()
    mt = ref.metrics
    assert f"| winter | opendss | {mt.mvvm_pu:.4f} | {mt.nvv} | {mt.ntc} |" in md
    assert "Case opendss: OpenDSS's own control loop at 5 s steps" in md
    stamp = (Path(ref.out_dir) / "summary.json").stat().st_mtime_ns
    again = evaluate(msgspec.structs.replace(config, resume=True))
    assert again.runs[1].metrics == mt and (Path(ref.out_dir) / "summary.json").stat().st_mtime_ns == stamp


def test_opendss_case_is_not_a_robustness_variant_and_needs_a_step_dividing_a_minute(tmp_path):
    assert parse_cases("none,opendss") == ("none", "opendss")
    with pytest.raises(EvaluateError, match="without --robustness"):
        evaluate(EvaluateConfig(feeder=str(IEEE13), cases=("opendss",), robustness=True, out=str(tmp_path)))
    with pytest.raises(EvaluateError, match="--reference-step-s 7 must divide 60"):
        evaluate(EvaluateConfig(feeder=str(IEEE13), cases=("opendss",), reference_step_s=7.0, out=str(tmp_path)))


@pytest.mark.process
def test_runs_with_lockstep_misses_are_listed_as_not_the_methods_figures(tmp_path, ieee13_model, profile_cache):
    """A bridge that waits only 1 ms for each decision goes on under local control at some control steps (a
    lockstep miss, as a starved machine causes); results.md lists the run apart, results.json counts the misses."""
    out = tmp_path / "out"
    ev = evaluate(EvaluateConfig(feeder=str(IEEE13), model=str(ieee13_model), cases=("D",), seasons=("summer",),
                                 days_per_season=0.05, out=str(out), cache=str(profile_cache.parent),
                                 progress=False, lockstep_timeout_s=0.001))
    (run,) = ev.runs
    assert run.lockstep_misses > 0
    assert json.loads((out / "results.json").read_text())["runs"][0]["lockstep_misses"] == run.lockstep_misses
    md = (out / "results.md").read_text()
    assert "## Runs with lockstep misses: not the method's figures" in md
    assert f"- summer-D-bw4: {run.lockstep_misses} of its control steps" in md
    summary = msgspec.json.decode((Path(run.out_dir) / "summary.json").read_bytes(), type=RunSummary)
    assert f"**{run.lockstep_misses} lockstep miss(es)**" in render_summary(summary, None)
    with pytest.raises(EvaluateError, match="lockstep-timeout-s"):
        evaluate(msgspec.structs.replace(ev.config, lockstep_timeout_s=0.0, out=str(tmp_path / "bad")))


def test_results_that_cannot_be_written_stop_the_evaluation_with_a_clear_error(tmp_path, ieee13_model, profile_cache,
                                                                               dask_scheduler):
    """A full disk (``results.json`` on /dev/full: every write fails with ENOSPC) stops the evaluation with an error
    that names the file and the way on; the finished run stays in its folder and ``--resume`` takes it."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "results.json").symlink_to("/dev/full")
    config = EvaluateConfig(feeder=str(IEEE13), model=str(ieee13_model), cases=("none",), seasons=("winter",),
                            days_per_season=0.01, out=str(out), cache=str(profile_cache.parent), progress=False,
                            scheduler=dask_scheduler)
    with pytest.raises(EvaluateError, match=r"cannot write .*results\.json: No space left on device; the 1 finished "
                                            r"run\(s\) are kept .*--resume"):
        evaluate(config)
    assert (out / "winter-none" / "summary.json").is_file()
    (out / "results.json").unlink()
    again = evaluate(msgspec.structs.replace(config, resume=True))
    assert [r.spec.name for r in again.runs] == ["winter-none"] and not again.failures
