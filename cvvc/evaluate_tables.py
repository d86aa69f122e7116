"""The tables of ``cvvc evaluate``: ``results.md`` in the paper's layout (Tables II-V) from an :class:`Evaluation`."""

from __future__ import annotations

from typing import TYPE_CHECKING

from cvvc.goals import GOALS, GOALS_LEGEND, goal_cells, season_goals
from cvvc.reference import REFERENCE_CASE
from cvvc.run_report import top_reasons

if TYPE_CHECKING:
    from cvvc.evaluation import Evaluation, RunResult

__all__ = ["kvarh_from_mvar_intervals", "render_results_md"]

_VARIANT_LABEL = {
    "nominal": "nominal (no noise, no drops, exact model)",
    "noise-pmu": "PMU-class noise 0.1 % (feeder head)",
    "noise-scada": "SCADA-class noise 1 % (PV plants, regulators)",
    "drop-1": "1 % of measurement frames dropped",
    "drop-5": "5 % of measurement frames dropped",
    "model-error": "model error: line impedances and loads x U(0.9, 1.1)",
}


def kvarh_from_mvar_intervals(q_mvar_intervals: float, control_period_s: float) -> float:
    """Reactive energy [kvarh] from the metrics' ``sum |Q| [Mvar] x control intervals`` (paper Table IV unit)."""
    return q_mvar_intervals * 1000.0 * control_period_s / 3600.0


def _row_label(r: RunResult, robust: bool, bands: bool) -> list[str]:
    case = r.spec.case
    if bands and case in ("C", "D"):
        case = f"{case} ({r.spec.bandwidth_v120:g} V)"
    cells = [r.spec.season, case]
    if robust:
        cells.append(_VARIANT_LABEL[r.spec.variant])
    return cells


def _engine(ev: Evaluation) -> str:
    if ev.config.scheduler:
        return f"Dask cluster at {ev.config.scheduler}"
    return f"local Dask cluster, jobs={ev.config.jobs}"


def render_results_md(ev: Evaluation) -> str:
    """The evaluation as markdown: Table II/III layout, Table IV (PV reactive energy), Table V (tap changes)."""
    robust = ev.config.robustness
    bands = len(ev.config.bandwidths_v120) > 1
    head = ["Season", "Case"] + (["Variant"] if robust else [])
    days = sorted({r.spec.days for r in ev.runs})
    cap_ids = sorted({k for r in ev.runs for k in r.metrics.cap_switches_per_bank})
    cap_head = ["Cap sw", "Cap Cost"] if cap_ids else []  # feeders with capacitor banks in the device map
    lines = [f"# cvvc evaluate: {ev.feeder_id}", "",
             f"Evaluation year seed {ev.config.year_seed}, model trained on year seed {ev.config.train_seed}; "
             f"{', '.join(f'{d:g}' for d in days)} day(s) per season from the first of the season's month; "
             f"{len(ev.runs)} runs in {ev.wall_s:.0f} s wall time ({_engine(ev)})."
             + (f" Case {REFERENCE_CASE}: OpenDSS's own control loop at {ev.config.reference_step_s:g} s steps on "
                "the same loads and PV (unity power factor), not through the bus."
                if any(r.spec.case == REFERENCE_CASE for r in ev.runs) else ""), "",
             "## Voltage violations and costs (paper Tables II/III layout)", "",
             "| " + " | ".join(head + ["MVVM [pu]", "NVV", "NTC"] + cap_head[:1] + ["Q Cost", "T Cost"] + cap_head[1:]
                               + ["Total", "wall [s]"]) + " |",
             "|" + "---|" * (len(head) + 7 + len(cap_head))]
    for r in ev.runs:
        mt = r.metrics
        cap_sw = [str(mt.cap_switches)] if cap_ids else []
        cap_cost = [f"{mt.cap_cost:.2f}"] if cap_ids else []
        lines.append("| " + " | ".join(_row_label(r, robust, bands) + [
            f"{mt.mvvm_pu:.4f}", str(mt.nvv), str(mt.ntc)] + cap_sw + [f"{mt.q_cost:.1f}",
            f"{mt.t_cost:.2f}"] + cap_cost + [f"{mt.total_cost:.1f}", f"{r.wall_s:.0f}"]) + " |")
    pv_ids = sorted({k for r in ev.runs for k in r.metrics.q_mvar_intervals})
    lines += ["", "## Reactive energy per PV plant (paper Table IV)", "",
              f"Sum of |Q| over the window in Mvar x control intervals ({ev.control_period_s} s), and in kvarh.", "",
              "| " + " | ".join(head + [f"{p} [Mvar·int]" for p in pv_ids] + [f"{p} [kvarh]" for p in pv_ids]) + " |",
              "|" + "---|" * (len(head) + 2 * len(pv_ids))]
    for r in ev.runs:
        q = r.metrics.q_mvar_intervals
        vals = [float(q.get(p, 0.0)) for p in pv_ids]
        lines.append("| " + " | ".join(_row_label(r, robust, bands) + [f"{v:.1f}" for v in vals] + [
            f"{kvarh_from_mvar_intervals(v, ev.control_period_s):.0f}" for v in vals]) + " |")
    reg_ids = sorted({k for r in ev.runs for k in r.metrics.taps_changes})
    lines += ["", "## Tap changes per regulator (paper Table V)", "",
              "| " + " | ".join(head + reg_ids + ["total"]) + " |", "|" + "---|" * (len(head) + len(reg_ids) + 1)]
    for r in ev.runs:
        t = r.metrics.taps_changes
        lines.append("| " + " | ".join(_row_label(r, robust, bands) + [str(t.get(g, 0)) for g in reg_ids]
                                       + [str(r.metrics.ntc)]) + " |")
    if cap_ids:
        lines += ["", "## Capacitor switchings per bank", "",
                  "Switching operations (one per step of a bank opened or closed), local control and commands.", "",
                  "| " + " | ".join(head + cap_ids + ["total"]) + " |", "|" + "---|" * (len(head) + len(cap_ids) + 1)]
        for r in ev.runs:
            sw = r.metrics.cap_switches_per_bank
            lines.append("| " + " | ".join(_row_label(r, robust, bands) + [str(sw.get(c, 0)) for c in cap_ids]
                                           + [str(r.metrics.cap_switches)]) + " |")
    lines += ["", "## Every minute (no average)", "",
              "Judged nodes outside the optimization limits and outside ANSI C84.1 Range A (0.95-1.05 pu), each "
              "minute on its own, and the 1-minute extremes.", "",
              "| " + " | ".join(head + ["node-min outside opt.", "min outside opt.", "node-min outside ANSI A",
                                        "min outside ANSI A", "V min [pu]", "V max [pu]"]) + " |",
              "|" + "---|" * (len(head) + 6)]
    for r in ev.runs:
        mt = r.metrics
        lines.append("| " + " | ".join(_row_label(r, robust, bands) + [
            f"{mt.node_minutes_outside_opt:,}", f"{mt.minutes_outside_opt:,}", f"{mt.node_minutes_outside_ansi:,}",
            f"{mt.minutes_outside_ansi:,}", f"{mt.v_min_pu:.4f}", f"{mt.v_max_pu:.4f}"]) + " |")
    judged = [r for r in ev.runs if r.live is not None and r.live.samples]
    if judged:
        lines += ["", "## Live accuracy (the agent's estimates against the truth of their step)", "",
                  "At the critical nodes, every decision: RMSE, share within ±0.01 pu, the calibrated bounds' "
                  "realised miss rate against the rate they promise, and the share of decisions whose true zone "
                  "extremes are both estimated.", "",
                  "| " + " | ".join(head + ["RMSE [pu]", "within ±0.01", "bounds missed", "promised",
                                            "extremes captured", "worst node"]) + " |",
                  "|" + "---|" * (len(head) + 6)]
        for r in judged:
            a = r.live
            if a is None:
                continue
            promised = "" if a.promised_miss_rate is None else f"{a.promised_miss_rate:.1%}"
            miss_rate = f"{a.bound_miss_rate:.1%}" if a.bound_samples else "no bounds"
            if a.bounds_hold() is False:
                miss_rate = f"**{miss_rate}**"
            lines.append("| " + " | ".join(_row_label(r, robust, bands) + [
                f"{a.rmse_pu:.4f}", f"{a.within_001:.1%}", miss_rate, promised, f"{a.extremes_captured:.0%}",
                a.worst.node if a.worst is not None else ""]) + " |")
    goals = season_goals(ev.runs)
    if goals:
        lines += ["", "## Closed-loop goals", "", GOALS_LEGEND, "",
                  "| " + " | ".join(head + list(GOALS) + ["unmet"]) + " |", "|" + "---|" * (len(head) + len(GOALS) + 1)]
        for r, checks in goals:
            lines.append("| " + " | ".join(_row_label(r, robust, bands) + goal_cells(checks)
                                           + [str(sum(not c.met for c in checks))]) + " |")
    agent_runs = [r for r in ev.runs if r.decisions]
    if agent_runs:
        lines += ["", "## Decisions", "",
                  "Soft: the hard limits were not met (paper eq. 17); hold: no command sent. Decision time: the "
                  "agent's wall time per control step, from the frames' alignment to the decision message.", "",
                  "| " + " | ".join(head + ["decisions", "soft (of which the tap deadband's)", "hold",
                                            "most frequent reason",
                                            "p50 [ms]", "p99 [ms]", "max [ms]"]) + " |",
                  "|" + "---|" * (len(head) + 7)]
        for r in agent_runs:
            why = top_reasons(r.reasons, 1).replace("|", "/") if r.reasons else ""
            ms = [f"{r.decision_ms[k]:.1f}" if k in r.decision_ms else "" for k in ("p50", "p99", "max")]
            lines.append("| " + " | ".join(_row_label(r, robust, bands) + [
                str(r.decisions), f"{r.soft} ({r.soft / r.decisions:.0%}; {r.tolerated})", str(r.holds), why] + ms)
                         + " |")
    missed = [r for r in ev.runs if r.lockstep_misses]
    if missed:
        lines += ["", "## Runs with lockstep misses: not the method's figures", "",
                  f"At these control steps the bridge waited {ev.config.lockstep_timeout_s:g} s for the agent's "
                  "decision and went on under local control (a starved machine, or an agent that stopped): a "
                  "regulator whose set point expired meanwhile is back on its own. Re-run them on a quieter machine "
                  "or with a longer `--lockstep-timeout-s`.", ""]
        lines += [f"- {r.spec.name}: {r.lockstep_misses} of its control steps" for r in missed]
    if ev.failures:
        lines += ["", "## Failed runs", ""]
        lines += [f"- {f.spec.name}: {f.error.splitlines()[0] if f.error else '?'} ({f.attempts} attempt(s), "
                  f"logs in `{f.out_dir}`)" for f in ev.failures]
    lines.append("")
    return "\n".join(lines)
