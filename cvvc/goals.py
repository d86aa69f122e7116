"""The closed-loop goals an agent's run is judged by, against case A and no control on the same days.

Each check is one line of docs/profiles-and-metrics.md "Closed-loop goals"; a run of case C or D is judged against
the runs of case ``A`` and ``none`` of its season and variant in the same evaluation (a check whose reference run is
missing is not made):

* ``NVV``: at most case A's + 0.1 % of no control's;
* ``NTC``: at most 1.5x case A's tap changes; ``cost``: total cost at most 1.15x case A's;
* ``ANSI A``, ``opt. limits``: node-minutes outside ANSI C84.1 Range A and outside the optimization limits, judged
  every minute, at most no control's;
* ``1-min V``: the 1-minute V min and V max no further outside the optimization limits than no control's (inside
  them is never worse);
* ``bounds``: the calibrated bounds' realised miss rate at most ``HOLD_FACTOR`` (2) x the rate they promise (live);
* ``banks``: each bank's switchings at most no control's + 1 a day;
* ``soft``: decisions on the soft form (eq. 17) at most 5 % of the decisions, or case A's count; the tap deadband's
  soft decisions (taps held for a predicted violation within the deadband, the limits widened by it met) are not the
  soft form and are shown beside it;
* ``MVVM``: at most 0.005 pu;
* ``tap rate``: no step at which a regulator had moved faster than its RegControl's ``tapdelay`` allows (judged by the
  simulation on the moves it counted, ``metrics.over_tap_rate``; not judged for runs that did not count them).
"""

from __future__ import annotations

from collections.abc import Iterable

import msgspec

from cvvc.evaluation import Evaluation, RunResult
from simulator_bridge.simulation.live_accuracy import HOLD_FACTOR

__all__ = ["GOALS", "GOALS_LEGEND", "GoalCheck", "goal_cells", "render_campaign_goals", "run_goals", "season_goals"]

GOALS = ("NVV", "NTC", "cost", "ANSI A", "opt. limits", "1-min V", "bounds", "banks", "soft", "MVVM", "tap rate")
NVV_SHARE_OF_NONE = 0.001
NTC_RATIO = 1.5
COST_RATIO = 1.15
BANK_EXTRA_PER_DAY = 1.0
SOFT_SHARE = 0.05
MVVM_PU = 0.005
GOALS_LEGEND = ("Each agent run (cases C, D) against case A and no control of its season "
                "(docs/profiles-and-metrics.md, \"Closed-loop goals\"): the run's figure, bold with its limit where "
                "the goal is not met; blank where the reference run is not there.")


class GoalCheck(msgspec.Struct, frozen=True, kw_only=True):
    """One goal of one run: met or not, the run's figure and the limit it is held to, as printed."""

    goal: str
    met: bool
    value: str
    limit: str


def run_goals(d: RunResult, a: RunResult | None, none: RunResult | None) -> tuple[GoalCheck, ...]:
    """The goals of the agent's run ``d`` against case A's run ``a`` and no control's ``none`` of the same days."""
    out: list[GoalCheck] = []
    md = d.metrics
    if a is not None and none is not None:
        limit = a.metrics.nvv + NVV_SHARE_OF_NONE * none.metrics.nvv
        out.append(GoalCheck(goal="NVV", met=md.nvv <= limit, value=f"{md.nvv:,}", limit=f"{limit:,.0f}"))
    if a is not None:
        ntc = NTC_RATIO * a.metrics.ntc
        out.append(GoalCheck(goal="NTC", met=md.ntc <= ntc, value=f"{md.ntc:,}", limit=f"{ntc:,.1f}"))
        cost = COST_RATIO * a.metrics.total_cost
        out.append(GoalCheck(goal="cost", met=md.total_cost <= cost, value=f"{md.total_cost:,.1f}",
                             limit=f"{cost:,.1f}"))
    if none is not None:
        mn = none.metrics
        out.append(GoalCheck(goal="ANSI A", met=md.node_minutes_outside_ansi <= mn.node_minutes_outside_ansi,
                             value=f"{md.node_minutes_outside_ansi:,}", limit=f"{mn.node_minutes_outside_ansi:,}"))
        out.append(GoalCheck(goal="opt. limits", met=md.node_minutes_outside_opt <= mn.node_minutes_outside_opt,
                             value=f"{md.node_minutes_outside_opt:,}", limit=f"{mn.node_minutes_outside_opt:,}"))
        if md.opt_limits_pu is not None:
            lo, hi = min(mn.v_min_pu, md.opt_limits_pu[0]), max(mn.v_max_pu, md.opt_limits_pu[1])
            out.append(GoalCheck(goal="1-min V", met=lo <= md.v_min_pu and md.v_max_pu <= hi,
                                 value=f"{md.v_min_pu:.4f}-{md.v_max_pu:.4f}", limit=f"{lo:.4f}-{hi:.4f}"))
    live = d.live
    if live is not None and live.promised_miss_rate is not None and live.bound_samples:
        out.append(GoalCheck(goal="bounds", met=bool(live.bounds_hold()), value=f"{live.bound_miss_rate:.2%}",
                             limit=f"{HOLD_FACTOR * live.promised_miss_rate:.2%}"))
    if none is not None and md.cap_switches_per_bank:
        extra = BANK_EXTRA_PER_DAY * d.spec.days
        base = none.metrics.cap_switches_per_bank
        excess = {b: n - base.get(b, 0) for b, n in md.cap_switches_per_bank.items()}
        worst = max(excess, key=lambda b: excess[b])  # the bank furthest past no control's
        out.append(GoalCheck(goal="banks", met=excess[worst] <= extra,
                             value=f"{worst}: {md.cap_switches_per_bank[worst]}",
                             limit=f"{base.get(worst, 0) + extra:g}"))
    if a is not None and d.decisions:
        soft = max(SOFT_SHARE * d.decisions, a.soft)
        form = d.soft - d.tolerated
        out.append(GoalCheck(goal="soft", met=form <= soft, limit=f"{soft:,.0f}",
                             value=f"{form:,}" + (f" (+{d.tolerated:,} deadband)" if d.tolerated else "")))
    out.append(GoalCheck(goal="MVVM", met=md.mvvm_pu <= MVVM_PU, value=f"{md.mvvm_pu:.4f}", limit=f"{MVVM_PU:.4f}"))
    if md.steps_over_tap_rate:
        fastest = max(md.steps_over_tap_rate, key=lambda r: md.steps_over_tap_rate[r])
        n = md.steps_over_tap_rate[fastest]
        out.append(GoalCheck(goal="tap rate", met=n == 0, value=f"{fastest}: {n}" if n else "0", limit="0"))
    return tuple(out)


def season_goals(runs: Iterable[RunResult]) -> list[tuple[RunResult, tuple[GoalCheck, ...]]]:
    """Every run of case C or D with its goals, against the case A and no-control runs of its season and variant."""
    runs = list(runs)
    ref = {(r.spec.case, r.spec.season, r.spec.variant): r for r in runs if r.spec.case in ("A", "none")}
    out = []
    for r in runs:
        if r.spec.case not in ("C", "D"):
            continue
        a, none = ref.get(("A", r.spec.season, r.spec.variant)), ref.get(("none", r.spec.season, r.spec.variant))
        if a is None and none is None:
            continue
        out.append((r, run_goals(r, a, none)))
    return out


def goal_cells(checks: tuple[GoalCheck, ...]) -> list[str]:
    """A markdown cell per goal of ``GOALS``: the run's figure, bold with its limit when unmet; blank: not judged."""
    by = {c.goal: c for c in checks}
    return ["" if g not in by else by[g].value if by[g].met else f"**{by[g].value}** > {by[g].limit}" for g in GOALS]


def render_campaign_goals(evaluations: dict[str, Evaluation]) -> str:
    """``goals.md`` of a campaign: each feeder's agent runs, the goals they miss, and the count over the campaign."""
    lines = ["# Closed-loop goals", "", GOALS_LEGEND, "",
             "| feeder | season | case | " + " | ".join(GOALS) + " | unmet |", "|" + "---|" * (len(GOALS) + 4)]
    unmet = judged = 0
    for key, ev in evaluations.items():
        for r, checks in season_goals(ev.runs):
            miss = sum(not c.met for c in checks)
            unmet, judged = unmet + miss, judged + len(checks)
            case = r.spec.case if r.spec.variant == "nominal" else f"{r.spec.case} ({r.spec.variant})"
            lines.append(f"| {key} | {r.spec.season} | {case} | " + " | ".join(goal_cells(checks)) + f" | {miss} |")
    lines += ["", f"Unmet: {unmet} of {judged} goals judged.", ""]
    return "\n".join(lines)
