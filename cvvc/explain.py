"""``cvvc report decision RUN --at TIME``: why the agent decided what it did at one control step of a recording.

The agent is re-run offline on the recording's frames (``agent.runtime.decide_offline_in_detail``, the recorded model
and settings, as ``cvvc replay --offline``) up to the decision of the step at or before ``TIME``; that decision is then
taken apart:

* what it sent, and every solve it made (``main``, ``deadband``, ``buy`` ...: ``Decision.solves``), with its cost, tap
  moves and Q;
* the rows of its problem nearest their limits: the estimate now and after the decision, each limit and what
  tightened it from the optimization limits: the estimate's calibrated bound (as applied, widened out of the training
  envelope, the gap of the correction filter) and the variability margin, the larger of the PV margin
  (``AgentOptions.pv_margin_window_s``) and the drift margin (``AgentOptions.drift_margin``), read from the
  controller's own problem built with and without the margins (``CvvcController.problem``).

Local times are the profiles' fixed local standard time (UTC-5, docs/profiles-and-metrics.md). The re-run must
reproduce the recorded decision (``cvvc replay --offline`` checks it for a whole recording); the explanation says
whether it did for this one.
"""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import msgspec
import numpy as np

from cvvc.errors import CommandError
from cvvc.local_time import LOCAL_UTC_OFFSET_NS, local_minute

__all__ = ["DecisionExplanation", "ExplainError", "LimitRow", "SolveLine", "explain_decision", "local_time_ns",
           "render_explanation"]

_NS = 1_000_000_000


class ExplainError(CommandError):
    """A recording that cannot be explained at that time (no such step, no model, a case A session)."""


class SolveLine(msgspec.Struct, frozen=True, kw_only=True):
    """One solve of the decision: its role, status, cost [cost units], tap moves (device: [from, to]) and Q [kvar]."""

    role: str
    status: str
    cost: float
    moves: dict[str, tuple[int, int]]
    q_kvar: dict[str, float]
    reason: str = ""
    taken: bool = False  # the solve the decision took (the deadband's relabelled, rent or buy's move ...)


class LimitRow(msgspec.Struct, frozen=True, kw_only=True):
    """One row of the decision's problem: its estimate now and after the decision [pu], its limits [pu] and what
    tightened each from the optimization limits: the bound as applied and the variability margin (PV or drift) [pu].
    """

    row: str
    v_now_pu: float
    v_after_pu: float
    lower_pu: float
    upper_pu: float
    lower_bound_pu: float
    upper_bound_pu: float
    lower_margin_pu: float
    upper_margin_pu: float
    slack_pu: float  # the nearer limit's distance from the estimate after the decision (negative: past it)
    # ``v_after_pu``: the prediction of the solve the decision took


class DecisionExplanation(msgspec.Struct, frozen=True, kw_only=True):
    """One decision taken apart (module docstring)."""

    step_t_ns: int
    local_time: str
    status: str
    reason: str
    commands: list[str]  # "quantity value", ``recordings.offline.command_values``
    reproduced: bool  # the re-run's decision is the recorded one (``recordings.offline.diff_decisions``: identical)
    optimization_limits_pu: tuple[float, float]
    solves: list[SolveLine]
    rows: list[LimitRow]


def local_time_ns(text: str) -> int:
    """``YYYY-MM-DDTHH:MM`` in the profiles' local standard time -> UTC epoch [ns]."""
    try:
        naive = dt.datetime.fromisoformat(text)
    except ValueError as e:
        raise ExplainError(f"--at {text!r}: give a local time as YYYY-MM-DDTHH:MM") from e
    if naive.tzinfo is not None:
        raise ExplainError(f"--at {text!r}: give the profiles' local time without a zone (UTC-5, no daylight saving)")
    return int(naive.replace(tzinfo=dt.UTC).timestamp()) * _NS - LOCAL_UTC_OFFSET_NS


def explain_decision(recording: str | Path, at_t_ns: int, *, rows: int = 6) -> DecisionExplanation:
    """The decision of the control step at or before ``at_t_ns`` [UTC ns] of ``recording`` (a run folder or its
    ``session.mcap``), re-run offline and taken apart; ``rows``: how many rows nearest their limits to keep.
    """
    from agent.runtime import DecisionMaker, decide_offline_in_detail
    from recordings.errors import RecordingError
    from recordings.info import recording_info
    from recordings.offline import METADATA_NAME, agent_inputs, recorded_decisions, recorded_frames, recorded_model

    path = Path(recording)
    path = path / "session.mcap" if path.is_dir() else path
    try:
        meta = recording_info(path).metadata.get(METADATA_NAME, {})
        recorded = {d.step_t_ns: d for d in recorded_decisions(path)}
    except (OSError, RecordingError) as e:
        raise ExplainError(f"{path}: {e}") from e
    steps = sorted(t for t in recorded if t <= at_t_ns)
    if not steps:
        first = min(recorded, default=None)
        raise ExplainError(f"{path}: no recorded decision at or before {local_minute(at_t_ns)}"
                           + (f" (the first is at {local_minute(first)})" if first is not None else ""))
    target = steps[-1]
    model_path = recorded_model(path, meta.get("model_path", ""))
    if not model_path or not Path(model_path).is_file():
        raise ExplainError(f"{path}: the model it names ({model_path or 'none'}) is not there")
    try:
        model, settings = agent_inputs(model_path, meta.get("agent_settings", ""))
    except RecordingError as e:  # a case A session, settings that do not decode
        raise ExplainError(str(e)) from e
    maker = DecisionMaker(model, settings)
    for message, decision in decide_offline_in_detail(model, settings, recorded_frames(path), maker=maker):
        if message.step_t_ns == target:
            return _explain(message, recorded[target], decision, maker, rows)
        if message.step_t_ns > target:
            break
    raise ExplainError(f"{path}: the offline re-run made no decision for the step of {local_minute(target)}")


def _explain(message, recorded, decision, maker, n_rows: int) -> DecisionExplanation:
    from agent.bank_rows import bank_row_names
    from recordings.offline import command_values, diff_decisions

    controller, model = maker.controller, maker.model
    reg_ids = [r.id for r in model.regulators] + [c.id for c in model.capacitors]
    pv_ids = [p.id for p in model.pv]
    lo_opt, hi_opt = (float(x) for x in model.optimization_limits_pu)
    solves = []
    taps0 = None
    rows: list[LimitRow] = []
    # the solve the decision took: its Q and cost (``Decision.pv_q_kvar``, ``objective``); the main one otherwise
    taken = next((k for k, (_, s) in enumerate(decision.solves)
                  if decision.pv_q_kvar is not None and s.cost == decision.objective
                  and np.array_equal(s.q_new_kvar, decision.pv_q_kvar)), 0)
    if controller.last_problem is not None and decision.solves:
        inputs, snap, state, outside, plants = controller.last_problem
        plain = controller.problem(snap, state, out_of_envelope=outside, plants=plants, margins=False)
        taps0 = np.asarray(inputs.taps)
        n = inputs.v0_pu.shape[0]
        names = [c.name for c in model.critical_nodes][:n] if state.critical else []
        banks = bank_row_names(model.capacitors)
        names += banks if len(names) + len(banks) == n else [f"row {i}" for i in range(len(names), n)]
        lo, hi = (np.broadcast_to(np.asarray(x, float), (n,)) for x in (inputs.v_min_pu, inputs.v_max_pu))
        lo0, hi0 = (np.broadcast_to(np.asarray(x, float), (n,)) for x in (plain.v_min_pu, plain.v_max_pu))
        after = np.asarray(decision.solves[taken][1].v_pred_pu, float)[:n]
        slack = np.minimum(hi - after, after - lo)
        for i in np.argsort(slack, kind="stable")[:n_rows]:
            node = i < len(model.critical_nodes) and state.critical
            rows.append(LimitRow(
                row=names[i], v_now_pu=float(inputs.v0_pu[i]), v_after_pu=float(after[i]),
                lower_pu=float(lo[i]), upper_pu=float(hi[i]),
                lower_bound_pu=float(lo0[i] - lo_opt) if node else 0.0,
                upper_bound_pu=float(hi_opt - hi0[i]) if node else 0.0,
                lower_margin_pu=float(lo[i] - lo0[i]), upper_margin_pu=float(hi0[i] - hi[i]),
                slack_pu=float(slack[i])))
    for k_solve, (role, s) in enumerate(decision.solves):
        new = np.asarray(s.taps_new)
        moves = {} if taps0 is None else {reg_ids[k]: (int(taps0[k]), int(new[k]))
                                          for k in range(min(len(reg_ids), new.size)) if new[k] != taps0[k]}
        solves.append(SolveLine(role=role, status=s.status, cost=float(s.cost), moves=moves,
                                q_kvar={p: round(float(q), 1) for p, q in zip(pv_ids, s.q_new_kvar, strict=False)},
                                reason=s.reason[:300], taken=k_solve == taken))
    return DecisionExplanation(
        step_t_ns=message.step_t_ns, local_time=local_minute(message.step_t_ns), status=message.status,
        reason=message.reason, commands=[f"{k} {v:g}" for k, v in command_values(message).items()],
        reproduced=diff_decisions([recorded], [message]).identical == 1,
        optimization_limits_pu=(lo_opt, hi_opt), solves=solves, rows=rows)


def render_explanation(x: DecisionExplanation) -> str:
    """The explanation as text for a terminal."""
    lo, hi = x.optimization_limits_pu
    out = [f"decision of {x.local_time} (local standard time, UTC-5): {x.status}"
           + (f": {x.reason}" if x.reason else ""),
           "re-run offline: " + ("the recorded decision, reproduced" if x.reproduced
                                 else "NOT the recorded decision (model or settings differ): read with care"),
           "sent: " + ("; ".join(x.commands) if x.commands else "nothing"), "", "solves (* the one taken):"]
    for s in x.solves:
        moves = ", ".join(f"{k} {a} -> {b}" for k, (a, b) in s.moves.items()) or "no move"
        q = ", ".join(f"{k} {v:g}" for k, v in s.q_kvar.items() if v) or "no Q"
        out.append(f"{'*' if s.taken else ' '} {s.role:<9} {s.status:<8} cost {s.cost:.4f}  {moves}; Q [kvar]: {q}"
                   + (f"  ({s.reason})" if s.reason else ""))
    if x.rows:
        out += ["", f"rows nearest their limits (optimization limits {lo:g}-{hi:g} pu; each limit is the optimization "
                    "limit tightened by the estimate's bound and the variability margin, PV or drift):",
                "  row                      now      after    lower = opt + bound + margin      upper = opt - bound - "
                "margin      slack"]
        for r in x.rows:
            out.append(f"  {r.row:<22} {r.v_now_pu:.4f}   {r.v_after_pu:.4f}   "
                       f"{r.lower_pu:.4f} = {lo:g} + {r.lower_bound_pu:.4f} + {r.lower_margin_pu:.4f}   "
                       f"{r.upper_pu:.4f} = {hi:g} - {r.upper_bound_pu:.4f} - {r.upper_margin_pu:.4f}   "
                       f"{r.slack_pu:+.4f}")
    return "\n".join(out)
