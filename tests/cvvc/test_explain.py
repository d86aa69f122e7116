"""``cvvc report decision``: one recorded decision of a real IEEE 13 run re-run offline and taken apart."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import msgspec
import pytest

from cvvc.explain import DecisionExplanation, ExplainError, explain_decision, local_time_ns
from recordings.offline import recorded_decisions

REPO = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.process  # a whole ``cvvc run``


def _cvvc(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cvvc", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=600)


@pytest.fixture(scope="module")
def noon_run(tmp_path_factory, ieee13_model, sharing_profiles) -> Path:
    """Half a simulated hour of case D on IEEE 13 from 11:00 on a summer day (PV producing)."""
    work = tmp_path_factory.mktemp("explain")
    out = work / "out"
    proc = _cvvc("run", "--feeder", str(REPO / "feeders" / "ieee13.toml"), "--model", str(ieee13_model),
                 "--days", str(0.5 / 24), "--start", "2023-07-10T11:00", "--out", str(out),
                 "--cache", str(sharing_profiles(work / "cache")), cwd=work)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


def test_a_decision_is_reproduced_and_its_limits_taken_apart(noon_run):
    x = explain_decision(noon_run, local_time_ns("2023-07-10T11:22"), rows=4)
    assert x.local_time == "2023-07-10 11:20" and x.reproduced  # the step at or before 11:22
    recorded = {d.step_t_ns: d for d in recorded_decisions(noon_run / "session.mcap")}[x.step_t_ns]
    (taken,) = [s for s in x.solves if s.taken]  # the solve the decision took, whose prediction the rows show
    assert taken.cost == pytest.approx(recorded.solver.objective, abs=1e-9)
    estimates = {e.node: e for e in recorded.estimates}
    lo, hi = x.optimization_limits_pu
    assert len(x.rows) == 4 and [r.slack_pu for r in x.rows] == sorted(r.slack_pu for r in x.rows)
    for r in x.rows:
        e = estimates[r.row]
        assert r.v_now_pu == pytest.approx(e.v_pu, abs=1e-8)
        assert r.v_after_pu == pytest.approx(e.v_predicted_pu, abs=1e-8)
        assert r.upper_pu == pytest.approx(hi - r.upper_bound_pu - r.upper_margin_pu, abs=1e-12)
        assert r.lower_pu == pytest.approx(lo + r.lower_bound_pu + r.lower_margin_pu, abs=1e-12)
        # the bound takes at most the bound as applied, never more; the margin only tightens
        assert -1e-12 <= r.upper_bound_pu <= e.bound_high_pu + 1e-6
        assert -1e-12 <= r.lower_bound_pu <= e.bound_low_pu + 1e-6
        assert r.upper_margin_pu >= -1e-12 and r.lower_margin_pu >= -1e-12
        assert r.slack_pu == pytest.approx(min(r.upper_pu - r.v_after_pu, r.v_after_pu - r.lower_pu), abs=1e-12)


def test_a_time_before_the_first_decision_is_a_clear_error(noon_run):
    with pytest.raises(ExplainError, match=r"no recorded decision at or before 2023-07-10 10:00 \(the first is at "
                                           r"2023-07-10 11:00\)"):
        explain_decision(noon_run, local_time_ns("2023-07-10T10:00"))
    with pytest.raises(ExplainError, match="YYYY-MM-DDTHH:MM"):
        local_time_ns("11:00")


def test_the_command_prints_the_explanation_as_text_or_json(noon_run):
    proc = _cvvc("report", "decision", str(noon_run), "--at", "2023-07-10T11:05", cwd=noon_run)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("decision of 2023-07-10 11:05 (local standard time, UTC-5)")
    assert "the recorded decision, reproduced" in proc.stdout and "main " in proc.stdout
    proc = _cvvc("report", "decision", str(noon_run), "--at", "2023-07-10T11:05", "--json", "--rows", "2", cwd=noon_run)
    assert proc.returncode == 0, proc.stderr
    x = msgspec.json.decode(proc.stdout, type=DecisionExplanation)
    assert len(x.rows) == 2 and json.loads(proc.stdout)["reproduced"] is True
    bad = _cvvc("report", "decision", str(noon_run), "--at", "2023-07-10T11:05", "--rows", "0", cwd=noon_run)
    assert bad.returncode != 0 and "--rows 0" in bad.stderr
