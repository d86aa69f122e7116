"""``cvvc evaluate`` on Dask: campaign files, run on a scheduler and two workers started as separate processes."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cvvc.campaign import load_campaign, run_campaign
from cvvc.evaluate import EvaluateConfig, EvaluateError, evaluate

REPO = Path(__file__).resolve().parents[2]
IEEE13 = REPO / "feeders" / "ieee13.toml"


def _stop(proc: subprocess.Popen) -> None:
    """Stop one process we started, by its pid: SIGINT, then SIGKILL after 15 s."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=15)


def _worker_pids(address: str, n: int, timeout_s: float) -> set[int]:
    """The pids of the ``n`` workers of the scheduler at ``address``, waiting for them at most ``timeout_s``."""
    from distributed import Client

    deadline = time.monotonic() + timeout_s
    while True:  # the scheduler process may not listen yet
        try:
            client = Client(address, timeout=5, set_as_default=False)
            break
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)
    with client:
        client.wait_for_workers(n, timeout=max(1.0, deadline - time.monotonic()))
        return set(client.run(os.getpid).values())


@pytest.fixture(scope="module")
def user_cluster(tmp_path_factory):
    """``dask scheduler`` and two ``dask worker`` processes on loopback, as a user starts them (free ports, waits
    with deadlines, stopped by pid); yields the scheduler's address, the workers' pids and the processes."""
    from schemas.bus import free_port

    port, http = free_port(), free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    logs = tmp_path_factory.mktemp("dask-logs")
    procs: list[subprocess.Popen] = []

    def start(name: str, args: list[str]) -> None:
        with open(logs / f"{name}.log", "wb") as log:
            procs.append(subprocess.Popen([sys.executable, "-m", "dask", *args], env=env, stdout=subprocess.DEVNULL,
                                          stderr=log, stdin=subprocess.DEVNULL, cwd=logs))

    try:
        start("scheduler", ["scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard",
                            "--dashboard-address", f"127.0.0.1:{http}"])
        for i in range(2):
            start(f"worker{i}", ["worker", address, "--host", "127.0.0.1", "--no-dashboard",
                                 "--dashboard-address", "127.0.0.1:0", "--nthreads", "1",
                                 "--no-nanny", "--name", f"w{i}"])
        yield address, _worker_pids(address, 2, 90.0), procs
    finally:
        for p in reversed(procs):
            _stop(p)


def test_no_scheduler_at_the_address_is_a_clear_error(tmp_path):
    from schemas.bus import free_port

    with pytest.raises(EvaluateError, match="no Dask scheduler answered at tcp://127.0.0.1:.*dask scheduler"):
        evaluate(EvaluateConfig(feeder=str(IEEE13), cases=("none",), seasons=("winter",), days_per_season=0.01,
                                out=str(tmp_path), scheduler=f"tcp://127.0.0.1:{free_port()}", progress=False))


def _write_campaign(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def campaign_out(tmp_path_factory, profile_cache, user_cluster):
    """IEEE 13 and a device map that does not load, cases none and D, one variant whose model file is missing:
    IEEE 13's case none finishes, its case D fails in the worker (twice: retried once), the bad map's runs are
    reported as not prepared. Runs on the user's cluster (a scheduler and two workers as separate processes).
    Returns the output folder and the campaign's error."""
    folder = tmp_path_factory.mktemp("campaign")
    (folder / "bad.toml").write_text('[feeder]\nname = "bad"\nmaster = "no-such-master.dss"\n')
    campaign = _write_campaign(folder / "c.toml", f'''
feeders = ["{IEEE13}", "bad.toml"]
cases = ["none", "D"]
seasons = ["winter"]
days_per_season = 0.01

[variants.lost-model]
model = "no-such-model.json"
''')
    out = folder / "out"
    with pytest.raises(EvaluateError) as err:
        run_campaign(campaign, out, scheduler=user_cluster[0], cache=str(profile_cache.parent), progress=False)
    return out, str(err.value)


def test_a_running_scheduler_with_two_worker_processes_runs_the_campaign(campaign_out, user_cluster):
    """Every attempt of every run executed in one of the user's worker processes, which outlive the campaign
    (the cluster is the user's); the tables name the cluster."""
    out, _ = campaign_out
    address, pids, procs = user_cluster
    attempts = sorted((out / "ieee13" / "lost-model").glob("*/attempts.txt"))
    ran_in = [int(line.split(" pid ")[1].split()[0]) for f in attempts for line in f.read_text().splitlines()]
    assert len(ran_in) == 3 and set(ran_in) <= pids  # none once, D twice (retried)
    assert all(p.poll() is None for p in procs)
    assert f"Dask cluster at {address}" in (out / "ieee13" / "lost-model" / "results.md").read_text()


def _rows(out: Path) -> list[dict[str, str]]:
    with open(out / "campaign.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_a_campaign_writes_one_tidy_row_per_run_and_each_feeders_tables(campaign_out):
    """Two feeders x two cases x one season x one variant: four rows of campaign.csv, in plan order; the finished
    run's row holds the metrics of its evaluation's results.json, whose results.md is beside."""
    out, _ = campaign_out
    rows = _rows(out)
    assert list(rows[0]) == [
        "feeder", "feeder_id", "variant", "case", "season", "bandwidth_v120", "start", "days", "status", "attempts",
        "error", "wall_s", "steps", "decisions", "lockstep_misses", "mvvm_pu", "nvv", "minutes_in_violation", "ntc",
        "q_cost", "t_cost", "total_cost", "v_min_pu", "v_max_pu", "taps_changes", "q_mvar_intervals", "cap_switches",
        "cap_cost", "cap_switches_per_bank", "node_minutes_outside_opt", "minutes_outside_opt",
        "node_minutes_outside_ansi", "minutes_outside_ansi", "steps_over_tap_rate", "opt_limits_pu", "live_rmse_pu",
        "live_within_001", "live_bound_miss_rate", "live_promised_miss_rate", "live_extremes_captured"]
    assert [(r["feeder"], r["feeder_id"], r["variant"], r["case"], r["season"], r["start"], r["status"])
            for r in rows] == [("ieee13", "ieee13", "lost-model", "none", "winter", "2023-01-01", "ok"),
                               ("ieee13", "ieee13", "lost-model", "D", "winter", "2023-01-01", "failed"),
                               ("bad", "", "lost-model", "none", "winter", "2023-01-01", "failed"),
                               ("bad", "", "lost-model", "D", "winter", "2023-01-01", "failed")]
    data = json.loads((out / "ieee13" / "lost-model" / "results.json").read_text())
    (run,) = data["runs"]
    mt, row = run["metrics"], rows[0]
    assert (int(row["nvv"]), int(row["ntc"]), float(row["total_cost"]), float(row["mvvm_pu"])) == (
        mt["nvv"], mt["ntc"], mt["total_cost"], mt["mvvm_pu"])
    assert json.loads(row["taps_changes"]) == mt["taps_changes"] and set(mt["taps_changes"]) == {"reg1", "reg2",
                                                                                               "reg3"}
    assert (row["steps"], row["attempts"], row["lockstep_misses"]) == ("14", "1", "0")
    assert json.loads(row["opt_limits_pu"]) == [0.975, 1.04] and json.loads(row["steps_over_tap_rate"]) == {
        "reg1": 0, "reg2": 0, "reg3": 0}
    assert "| winter | none |" in (out / "ieee13" / "lost-model" / "results.md").read_text()
    assert (out / "goals.md").read_text().endswith("Unmet: 0 of 0 goals judged.\n")  # no agent run finished


def test_a_campaign_reports_a_failed_run_after_one_retry_and_a_bad_feeder_while_the_others_finish(campaign_out):
    out, error = campaign_out
    assert error.startswith("3 run(s) of the campaign failed (ieee13/lost-model/winter-D-bw4, bad/lost-model (2 "
                            "runs: not prepared))")
    rows = {(r["feeder"], r["case"]): r for r in _rows(out)}
    d = rows["ieee13", "D"]
    assert (d["status"], d["attempts"]) == ("failed", "2") and "no-such-model.json" in d["error"]
    assert d["nvv"] == "" and d["wall_s"] == ""
    assert len((out / "ieee13" / "lost-model" / "winter-D-bw4" / "attempts.txt").read_text().splitlines()) == 2
    for case in ("none", "D"):
        assert (rows["bad", case]["status"], rows["bad", case]["attempts"]) == ("failed", "0")
        assert "bad.toml: invalid device map" in rows["bad", case]["error"]
    md = (out / "ieee13" / "lost-model" / "results.md").read_text()
    assert "## Failed runs" in md and "winter-D-bw4" in md and "2 attempt(s)" in md


@pytest.mark.parametrize(("text", "message"), [
    ('cases = ["D"]\nseasons = ["winter"]\n', "missing required field `feeders`"),
    ('feeders = ["x"]\ncases = ["E"]\nseasons = ["winter"]\n', "unknown case"),
    ('feeders = ["x"]\ncases = ["D"]\nseasons = ["winter"]\n[variants.a]\nbandwidth = 2\n', "unknown field"),
    ('feeders = ["x"]\ncases = ["D"]\nseasons = ["monsoon"]\n', "seasons"),
    ('feeders = ["x"]\ncases = ["D"]\nseasons = ["winter"]\nvariants = {}\n', "empty"),
])
def test_a_bad_campaign_file_is_a_clear_error(tmp_path, text, message):
    with pytest.raises(EvaluateError, match=message):
        load_campaign(_write_campaign(tmp_path / "c.toml", text))


def test_the_command_line_reports_a_bad_campaign_file_in_one_line(tmp_path, capsys):
    from cvvc.cli import main

    _write_campaign(tmp_path / "c.toml", 'feeders = ["x"]\ncases = ["D"]\nseasons = ["winter"]\nspeed = 2\n')
    argv = ["evaluate", "--campaign", str(tmp_path / "c.toml"), "--out", str(tmp_path / "out")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("cvvc evaluate: error: campaign file") and "unknown field `speed`" in err
    assert main([*argv, "--cases", "D"]) == 2
    assert "--cases: with --campaign, the campaign file says" in capsys.readouterr().err
