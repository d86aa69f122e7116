"""The report of one ``cvvc run`` (``report.md``, printed at its end): its metrics beside no control's, its costs
and what they charge, a one-line verdict, its decisions and their most frequent reasons, lockstep misses, the
recording and its gaps; and the sections read from the recording (``cvvc report run``): the minutes outside the
limits and the tap steps by the decision in force, the lowest and highest minutes with what moved before them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from cvvc.extreme_minutes import LOOKBACK_STEPS
from cvvc.local_time import local_minute
from simulator_bridge.rural.synthesis import UTC_OFFSET_H
from simulator_bridge.simulation.live_accuracy import HOLD_FACTOR

if TYPE_CHECKING:
    from cvvc.extreme_minutes import ExtremeMinute
    from cvvc.run_summary import RunSummary
    from cvvc.run_trace import LimitMinutes, SideMoves
    from schemas.devicemap import DeviceMap
    from simulator_bridge.simulation.live_accuracy import LiveAccuracy

__all__ = ["cost_lines", "decision_time_text", "extreme_minutes_text", "limit_minutes_text", "live_accuracy_text",
           "measured_steps_text", "render_summary", "side_moves_text", "top_reasons", "verdict"]


def top_reasons(reasons: dict[str, int], n: int = 3) -> str:
    """The ``n`` most frequent reasons of soft and hold decisions, as one line."""
    top = sorted(reasons.items(), key=lambda kv: -kv[1])[:n]
    return "; ".join(f"{count} x {reason!r}" for reason, count in top) or "none given"


def decision_time_text(ms: dict[str, float]) -> str:
    """``p50 x ms, p99 y ms, max z ms`` of a summary's ``decision_ms`` (empty: no decision)."""
    return ", ".join(f"{k} {ms[k]:.1f} ms" for k in ("p50", "p99", "max") if k in ms) or "no decision"


def measured_steps_text(steps_v120: dict[str, float], n: int = 8) -> str:
    """``creg1a 0.58 V, ...``: each regulator's tap step as its compared reading measured it (the first ``n``)."""
    text = ", ".join(f"{rid} {v:.2f} V" for rid, v in list(steps_v120.items())[:n])
    return text + (f" and {len(steps_v120) - n} more" if len(steps_v120) > n else "")


def _count_table(title: str, intro: str, columns: tuple[str, str, str], rows: list[tuple[str, int, int]]) -> str:
    """A report section: a title, a line of introduction and a table of two counts per label, largest first."""
    lines = ["", f"## {title}", "", intro, "", f"| {' | '.join(columns)} |", "|---|---|---|"]
    lines += [f"| {label} | {a:,} | {b:,} |" for label, a, b in sorted(rows, key=lambda r: -(r[1] + r[2]))]
    return "\n".join(lines) + "\n"


def limit_minutes_text(rows: tuple[LimitMinutes, ...], limits_pu: tuple[float, float] | None) -> str:
    """The report's section on the minutes with any node outside the optimization limits, by the decision in force
    (``cvvc.report.read_trace``); empty without limits or without such minutes.
    """
    if limits_pu is None or not rows:
        return ""
    lo, hi = limits_pu
    return _count_table("Minutes outside the optimization limits, by the decision in force",
                        f"A step's truth against the decision of an earlier step; any node the metrics judge under "
                        f"{lo:g} or over {hi:g} pu.", ("decision in force", "minutes under", "minutes over"),
                        [(r.kind, r.under, r.over) for r in rows])


def side_moves_text(rows: tuple[SideMoves, ...], limits_pu: tuple[float, float] | None) -> str:
    """The report's section on the regulators' tap steps by the side of the optimization limits the decision in force
    saw crossed (``cvvc.report.read_trace``): a run whose steps go down after ``over`` and up after ``under`` chases
    both limits, its bounds closing the band between them; empty without limits or without tap steps.
    """
    if limits_pu is None or not rows:
        return ""
    lo, hi = limits_pu
    return _count_table("Tap steps, by the side of the limits the decision in force saw crossed",
                        f"Before its action, some critical node's estimate + bound over {hi:g} pu (over), estimate - "
                        f"bound under {lo:g} pu (under), both, or neither.",
                        ("decision in force saw", "steps up", "steps down"), [(r.side, r.up, r.down) for r in rows])


def extreme_minutes_text(rows: tuple[ExtremeMinute, ...]) -> str:
    """The report's section on the run's lowest and highest minutes and what moved in the minutes up to each
    (``cvvc.extreme_minutes``); empty without truth steps.
    """
    if not rows:
        return ""
    lines = ["", "## The lowest and highest minutes, and what moved before them", "",
             f"Each minute's extreme over the nodes the metrics judge, at least an hour apart on each side; the taps "
             f"and banks that moved in that minute and the {LOOKBACK_STEPS - 1} before it (minutes before it in "
             f"brackets; local standard time, UTC{UTC_OFFSET_H:+d}).", "",
             "| minute | | voltage [pu] | node | decision in force | moved |", "|---|---|---|---|---|---|"]
    for r in rows:
        moved = "; ".join(f"{text} ({ago})" for ago, text in r.moves) or "nothing"
        lines.append(f"| {local_minute(r.t_ns)} | {r.side} | {r.v_pu:.4f} | {r.node} | {r.decision} | {moved} |")
    return "\n".join(lines) + "\n"


def live_accuracy_text(a: LiveAccuracy) -> str:
    """One line on the agent's estimates against the truth of their step: error, bounds' misses and a verdict."""
    text = (f"live accuracy at the critical nodes ({a.decisions} decisions x nodes, against the truth of their step):"
            f" RMSE {a.rmse_pu:.4f} pu, {100 * a.within_001:.1f} % within ±0.01 pu, extremes captured "
            f"{100 * a.extremes_captured:.0f} % of decisions")
    if a.bound_samples:
        text += (f"; bounds missed {100 * a.bound_miss_rate:.1f} % of {a.bound_samples:,} node-decisions "
                 f"({a.misses_below:,} below, {a.misses_above:,} above)")
        verdict = a.bounds_hold()
        if verdict is not None and a.promised_miss_rate is not None:
            text += (f", promised at most {100 * a.promised_miss_rate:.1f} %: "
                     + (f"held (within {HOLD_FACTOR:g}x)" if verdict else f"**not held** (more than {HOLD_FACTOR:g}x)"))
    if a.worst is not None:
        text += (f"; worst node {a.worst.node} (RMSE {a.worst.rmse_pu:.4f} pu, "
                 f"{a.worst.misses_below + a.worst.misses_above} misses)")
    return text


def render_summary(s: RunSummary, dm: DeviceMap | None) -> str:
    """The run's summary as a short markdown report: its metrics beside no control's, what the costs charge (the
    prices of ``dm``, the run's device map; None: not named) and a one-line verdict.
    """
    mt, base = s.metrics, s.baseline
    rows = [("MVVM [pu]", "mvvm_pu"), ("NVV [node-minutes of 10-min average outside the judged limits]", "nvv"),
            ("minutes in violation", "minutes_in_violation"), ("NTC [tap steps moved]", "ntc"),
            ("V min, 1-minute [pu]", "v_min_pu"), ("V max, 1-minute [pu]", "v_max_pu"),
            ("node-minutes outside the optimization limits", "node_minutes_outside_opt"),
            ("minutes with a node outside the optimization limits", "minutes_outside_opt"),
            ("node-minutes outside ANSI Range A (0.95-1.05 pu)", "node_minutes_outside_ansi"),
            ("minutes with a node outside ANSI Range A", "minutes_outside_ansi")]
    if mt.cap_switches_per_bank:  # capacitor banks in the device map
        rows[4:4] = [("capacitor switchings", "cap_switches")]
    lines = [f"# cvvc run: case {s.case} on {s.feeder_id}, {s.start}, {s.days:g} day(s)", "",
             f"| metric | case {s.case} | no control |", "|---|---|---|"]
    for label, key in rows:
        b = "" if base is None else _fmt(getattr(base, key), key)
        lines.append(f"| {label} | {_fmt(getattr(mt, key), key)} | {b} |")
    why = f"; most frequent reasons: {top_reasons(s.reasons)}" if s.holds or s.soft else ""
    deadband = f" of which {s.tolerated} the tap deadband's" if s.tolerated else ""
    lines += ["", *cost_lines(s, dm), "", f"**Verdict:** {verdict(s)}", "",
              f"- decisions: {s.decisions} (soft {s.soft}{deadband}, hold {s.holds}{why}); lockstep misses: "
              f"{s.lockstep_misses}; wall time {s.wall_s:.1f} s",
              *([f"- bands re-centred a step after a move: {s.follow_ups} (late: {s.follow_up_misses})"]
                if s.follow_ups or s.follow_up_misses else []),
              *([f"- tap moves taken once the Q standing in for them had cost as much (rent or buy): {s.bought} "
                 "decision(s)"] if s.bought else []),
              *([f"- tap steps as the regulators' compared readings measured them: "
                 f"{measured_steps_text(s.measured_steps_v120)}"]
                if s.measured_steps_v120 else []),
              *([f"- decision time (the agent's, per control step): {decision_time_text(s.decision_ms)}"
                 + (f"; the deciding thread's CPU time {decision_time_text(s.decision_cpu_ms)}"
                    if s.decision_cpu_ms else "")]
                if s.decision_ms else []),
              *([f"- {live_accuracy_text(s.live)}"] if s.live is not None and s.live.samples else []),
              *([f"- **{s.lockstep_misses} lockstep miss(es)**: at those control steps the bridge went on under local "
                 f"control without the agent's decision (a starved machine or a stopped agent): these metrics are "
                 f"not case {s.case}'s alone"] if s.lockstep_misses else []),
              ("- bus: mTLS with per-role certificates and the deny-by-default access policy" if s.secure else
               "- **bus: insecure** (`--insecure`): no TLS, no access control; any local process could read "
               "and command"),
              *_field_lines(s),
              *_integrity_lines(s),
              f"- recording: `{s.recording}`" if s.recording else "- recording: off", *_recorder_lines(s),
              f"- model: `{s.model}`" if s.model else "- model: none (baseline case)",
              f"- case file: `{s.case_file}` (every setting of the run: `settings` in summary.json)" if s.case_file
              else "- case file: none (flags and defaults; every setting of the run: `settings` in summary.json)", ""]
    return "\n".join(lines)


def _counts(d: dict[str, int]) -> str:
    """``a 3, b 1``: counts by key, most first (``none`` when empty)."""
    return ", ".join(f"{k} {n:,}" for k, n in sorted(d.items(), key=lambda kv: (-kv[1], kv[0]))) or "none"


def _field_lines(s: RunSummary) -> list[str]:
    """The report's line on how the field devices reached the bus (none when every frame was the bridge's)."""
    if s.pv_protocol == "bus" and s.field_protocol == "bus":
        return []
    pv = ("PV plants behind SunSpec (a `cvvc adapter sunspec` each; steps some frame came late: "
          f"{s.sunspec_frame_misses})" if s.pv_protocol == "sunspec" else "PV plants on the bridge's frames")
    field = ("regulators and banks behind DNP3 (a `cvvc adapter dnp3` each; steps some frame came late: "
             f"{s.dnp3_frame_misses})" if s.field_protocol == "dnp3" else "regulators and banks on the bridge's frames")
    return [f"- field devices: {pv}; {field}"]


def _integrity_lines(s: RunSummary) -> list[str]:
    """The report's lines on what the run refused, missed or found overwritten, and whether control was lost."""
    g = s.integrity
    if s.case in ("none", "local"):
        return []
    lines = [f"- integrity: {s.decisions} of {g.decisions_due} decisions due ({g.decisions_missing} missing); inputs "
             f"refused: {_counts(g.inputs_refused)}; foreign acks {g.foreign_acks}; meter readings refused: "
             f"{_counts(g.meter_readings_refused)}; commands refused by device: {_counts(g.commands_refused)}; "
             f"refused by the bridge: {_counts(g.bridge_refused)}; decisions not the agent's: {g.foreign_decisions}"]
    if s.pv_protocol == "sunspec" or s.field_protocol == "dnp3":
        modbus = (f"; Modbus writes refused from another master: {_counts(g.foreign_master_writes)}"
                  if s.pv_protocol == "sunspec" else "")
        lines.append(f"- adapters: commands another master held in the device, scans by device: "
                     f"{_counts(g.foreign_writes)}{modbus}")
    if g.degraded:
        lines.append(f"- **degraded for more than one control period**: {g.degraded} (`cvvc run` exits 3)")
    return lines


def cost_lines(s: RunSummary, dm: DeviceMap | None) -> list[str]:
    """The cost table of a run (case and no control), each cost with what it charges, and why no control's costs
    are what they are.
    """
    mt, base = s.metrics, s.baseline
    prices = {} if dm is None else _prices(dm)
    rows = [("T cost (tap changes)", "t_cost", f"{prices.get('tap', 'the price')} per tap step moved, every "
                                                  "regulator (eq. 14)"),
            ("Q cost (PV reactive power)", "q_cost", f"{prices.get('kvar', 'the price')} per kvar of \\|Q\\| "
                                                      "held for one 5-minute control interval, every plant (eq. 15)")]
    if mt.cap_switches_per_bank:
        rows.append(("cap cost (bank switchings)", "cap_cost", f"{prices.get('switch', 'the price')} per step a "
                                                               "bank opens or closes"))
    rows.append(("total cost", "total_cost", "the sum of the above"))
    lines = ["## Costs", "", f"| cost [currency units] | case {s.case} | no control | what it charges |",
             "|---|---|---|---|"]
    for label, key, what in rows:
        b = "" if base is None else _fmt(getattr(base, key), key)
        lines.append(f"| {label} | {_fmt(getattr(mt, key), key)} | {b} | {what} |")
    lines += ["", "Costs are in the device map's currency units (prices per device in the map: `cost_per_tap`, "
              "`cost_per_kvar`, `cost_per_switch`). No control sends no command: its PV plants stay at unity power "
              "factor (Q = 0), so it spends nothing on reactive power; its regulators"
              + (" and banks" if mt.cap_switches_per_bank else "")
              + " act on their own local control, and the tap steps they move are charged at the same price."]
    return lines


def verdict(s: RunSummary) -> str:
    """One line: did the case keep the voltages better than no control, and at what cost."""
    mt, base, case = s.metrics, s.baseline, f"case {s.case}"
    if base is None:
        return (f"no baseline to compare with ({case} ran without one): {mt.nvv:,} node-minutes of violation, "
                f"total cost {_fmt(mt.total_cost)}.")
    cost = f"total cost {_fmt(mt.total_cost)} against {_fmt(base.total_cost)} without control"
    if mt.nvv < base.nvv:
        return (f"{case} cut the violations from {base.nvv:,} to {mt.nvv:,} node-minutes (MVVM "
                f"{_fmt(base.mvvm_pu)} -> {_fmt(mt.mvvm_pu)} pu); {cost}.")
    if mt.nvv > base.nvv:
        return (f"**{case} violated more than no control** ({mt.nvv:,} against {base.nvv:,} node-minutes, MVVM "
                f"{_fmt(mt.mvvm_pu)} against {_fmt(base.mvvm_pu)} pu); {cost}.")
    if mt.nvv == 0:
        return (f"neither {case} nor no control left the judged limits; a node was outside the optimization "
                f"limits in {mt.minutes_outside_opt:,} minutes against {base.minutes_outside_opt:,} (ANSI Range A: "
                f"{mt.minutes_outside_ansi:,} against {base.minutes_outside_ansi:,}); {cost}.")
    return (f"{case} left as many node-minutes of violation as no control ({mt.nvv:,}; MVVM {_fmt(mt.mvvm_pu)} "
            f"against {_fmt(base.mvvm_pu)} pu); {cost}.")


def _prices(dm: DeviceMap) -> dict[str, str]:
    """The feeder's prices as text (``tap``, ``kvar``, ``switch``: a value, or a range when devices differ)."""

    def text(values: list[float]) -> str | None:
        if not values:
            return None
        lo, hi = min(values), max(values)
        return f"{lo:g}" if lo == hi else f"{lo:g}-{hi:g}"

    found = {"tap": text([r.cost_per_tap for r in dm.regulator]), "kvar": text([p.cost_per_kvar for p in dm.pv]),
             "switch": text([c.cost_per_switch for c in dm.capacitor])}
    return {k: v for k, v in found.items() if v is not None}


def _recorder_lines(s: RunSummary) -> list[str]:
    """The report's lines on recorder restarts and the gaps they left (none when the recorder never died)."""
    lines = [f"- the recorder died and was restarted {s.recorder_restarts} time(s); control went on"
             ] if s.recorder_restarts else []
    for g in s.recording_gaps:
        span = (g.to_t_ns - g.from_t_ns) / 1e9 if g.from_t_ns >= 0 and g.to_t_ns >= 0 else float("nan")
        lines.append(f"  - gap {g.restart}: {span:.0f} s of simulated time not recorded ({g.reason[:200]})")
    if s.recorder_gave_up:
        lines.append("- the recorder died once more than its restarts allow: the recording ends early")
    return lines


_COUNTS = {"nvv", "minutes_in_violation", "ntc", "cap_switches", "node_minutes_outside_opt", "minutes_outside_opt",
           "node_minutes_outside_ansi", "minutes_outside_ansi"}  # whole numbers in both the run's and no control's


def _fmt(v: object, key: str = "") -> str:
    if key in _COUNTS and isinstance(v, int | float):
        return f"{round(v):,}"
    if isinstance(v, float):
        return f"{v:.4f}" if abs(v) < 10 else f"{v:.2f}"
    return str(v)
