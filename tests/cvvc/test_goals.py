"""The closed-loop goals (``cvvc.goals``): each check at its limit and one past it, on metrics frames of the schema."""

from __future__ import annotations

import msgspec
import pytest

from cvvc.evaluation import RunResult, RunSpec
from cvvc.goals import GOALS, goal_cells, run_goals, season_goals
from schemas import messages as m
from schemas.examples import example
from simulator_bridge.simulation.live_accuracy import LiveAccuracy


def _run(case: str, season: str = "summer", days: float = 3.0, live: LiveAccuracy | None = None,
         **metrics) -> RunResult:
    base = dict(mvvm_pu=0.0, nvv=0, ntc=0, total_cost=0.0, node_minutes_outside_ansi=0, node_minutes_outside_opt=0,
                cap_switches_per_bank={}, steps_over_tap_rate={}, v_min_pu=0.98, v_max_pu=1.03,
                opt_limits_pu=(0.975, 1.04))
    frame = msgspec.structs.replace(example(m.MetricsFrame), **{**base, **metrics})
    spec = RunSpec(case=case, season=season, bandwidth_v120=4.0, start="2023-07-01", days=days)
    return RunResult(spec=spec, metrics=frame, wall_s=1.0, steps=10, decisions=2, lockstep_misses=0, out_dir="",
                     recording=None, live=live)


A = _run("A", nvv=100, ntc=10, total_cost=20.0, mvvm_pu=0.004)
NONE = _run("none", nvv=20_000, node_minutes_outside_ansi=50, node_minutes_outside_opt=900,
            cap_switches_per_bank={"c1": 4, "c2": 0}, v_min_pu=0.96, v_max_pu=1.035)


def _met(d: RunResult, a: RunResult | None = A, none: RunResult | None = NONE) -> dict[str, bool]:
    return {c.goal: c.met for c in run_goals(d, a, none)}


@pytest.mark.parametrize(("goal", "at_limit", "past_limit"), [
    ("NVV", {"nvv": 120}, {"nvv": 121}),  # case A's 100 + 0.1 % of no control's 20,000
    ("NTC", {"ntc": 15}, {"ntc": 16}),  # 1.5x case A's 10
    ("cost", {"total_cost": 23.0}, {"total_cost": 23.01}),  # 1.15x case A's 20.0
    ("ANSI A", {"node_minutes_outside_ansi": 50}, {"node_minutes_outside_ansi": 51}),  # no control's
    ("opt. limits", {"node_minutes_outside_opt": 900}, {"node_minutes_outside_opt": 901}),
    ("banks", {"cap_switches_per_bank": {"c1": 7, "c2": 3}}, {"cap_switches_per_bank": {"c1": 7, "c2": 4}}),
    ("tap rate", {"steps_over_tap_rate": {"r1": 0, "r2": 0}}, {"steps_over_tap_rate": {"r1": 0, "r2": 1}}),
    # no lower than no control's 0.96 below the limits; up to the 1.04 limit above them (no control's 1.035 inside)
    ("1-min V", {"v_min_pu": 0.96, "v_max_pu": 1.04}, {"v_min_pu": 0.9599, "v_max_pu": 1.04}),
    ("1-min V", {"v_min_pu": 0.97, "v_max_pu": 1.04}, {"v_min_pu": 0.97, "v_max_pu": 1.0401}),
])
def test_each_goal_holds_at_its_limit_and_fails_one_past_it(goal, at_limit, past_limit):
    assert _met(_run("D", **at_limit))[goal] is True
    assert _met(_run("D", **past_limit))[goal] is False


def test_a_missed_goal_is_shown_bold_with_its_limit_and_a_met_one_as_the_figure():
    checks = run_goals(_run("D", ntc=16, total_cost=5.0, cap_switches_per_bank={"c1": 7, "c2": 4}), A, NONE)
    cells = dict(zip(GOALS, goal_cells(checks), strict=True))
    assert cells["NTC"] == "**16** > 15.0" and cells["cost"] == "5.0"
    assert cells["banks"] == "**c2: 4** > 3"  # the bank past its limit (c1's 7 is within 4 + 3)
    assert cells["bounds"] == "" and cells["MVVM"] == "0.0000"  # no live figures


def test_mvvm_is_held_to_0005_pu_and_soft_decisions_to_5_percent_or_case_as():
    assert _met(_run("D", mvvm_pu=0.005))["MVVM"] is True and _met(_run("D", mvvm_pu=0.0051))["MVVM"] is False
    d = msgspec.structs.replace(_run("D"), decisions=864, soft=43)  # 5 % of 864 is 43.2
    assert _met(d)["soft"] is True and _met(msgspec.structs.replace(d, soft=44))["soft"] is False
    assert _met(msgspec.structs.replace(d, soft=300), msgspec.structs.replace(A, soft=300))["soft"] is True
    # the tap deadband's soft decisions are not the soft form: 43 of eq. (17) beside 200 of the deadband are met
    deadband = msgspec.structs.replace(d, soft=243, tolerated=200)
    assert _met(deadband)["soft"] is True and _met(msgspec.structs.replace(deadband, soft=244))["soft"] is False
    (cell,) = [c.value for c in run_goals(deadband, A, NONE) if c.goal == "soft"]
    assert cell == "43 (+200 deadband)"


def test_the_bounds_are_held_to_twice_the_miss_rate_they_promise():
    def live(rate: float) -> LiveAccuracy:
        return LiveAccuracy(decisions=10, samples=1000, bound_samples=1000, bound_miss_rate=rate,
                            promised_miss_rate=0.01)

    assert _met(_run("D", live=live(0.02)))["bounds"] is True
    assert _met(_run("D", live=live(0.0201)))["bounds"] is False
    assert "bounds" not in _met(_run("D", live=LiveAccuracy(decisions=10, samples=1000)))  # no bounds to judge


def test_only_the_checks_whose_reference_runs_are_there_are_made():
    banks = {"c1": 0, "c2": 0}
    assert set(_met(_run("D", cap_switches_per_bank=banks), a=None)) == {"ANSI A", "opt. limits", "1-min V", "banks",
                                                                         "MVVM"}
    assert set(_met(_run("D", cap_switches_per_bank=banks), none=None)) == {"NTC", "cost", "soft", "MVVM"}
    assert "banks" not in _met(_run("D"))  # a map without banks
    assert "tap rate" not in _met(_run("D"))  # a run whose simulation did not count its regulators' rate
    assert "1-min V" not in _met(_run("D", opt_limits_pu=None))  # a recording that does not state its limits


def test_agent_runs_are_judged_against_the_reference_runs_of_their_own_season():
    runs = [A, NONE, _run("D", ntc=16), _run("D", "winter", ntc=100), _run("A", "winter", ntc=100),
            _run("none", "fall")]
    judged = season_goals(runs)
    assert [(r.spec.season, {c.goal: c.met for c in checks}["NTC"]) for r, checks in judged] == [
        ("summer", False), ("winter", True)]
