"""The controller's snapshot of one aligned step (``MeasurementSnapshot``), built from the aligner's frames in the
model's device order: a pure function of the frames and the model, no I/O, no clock.

The runtime (``agent.runtime``) builds one for every control step, live and offline, with the agent's settings
(``AgentSettings.reading_window_s``, ``last_good_s``, ``reading_fit_s``).
"""

from __future__ import annotations

import math

import numpy as np

from agent.aligner import AlignedFrames
from agent.decision import MeasurementSnapshot
from agent.readings import fitted_reading_v120
from regression.model import CvvcModel
from schemas import messages as m

__all__ = ["reading_noise_v120", "snapshot_from", "steps_seen_v120"]

_PHASE_INDEX = {"a": 0, "b": 1, "c": 2}
_FIT_MIN = 16  # readings a fit needs: with four terms, fewer are noisier than the mean of five
#: another regulator's move blurs a regulator's own step when it moves that one's secondary by at least this share
#: of what that one's own tap step does there (the model's dV/dtap at the regulators' secondaries)
_COUPLED_SHARE = 0.1
_FEW = 8  # NumPy sums fewer values than this one after the other (``_mean``)


def snapshot_from(aligned: AlignedFrames, model: CvvcModel, *, reading_window_s: float = 300.0,
                  last_good_s: float = 0.0, reading_fit_s: float = 0.0) -> MeasurementSnapshot:
    """The controller's snapshot of one aligned step, in the model's device order.

    ``reading_window_s`` > 0: each regulator's voltage readings are the mean of its frames of the last
    ``reading_window_s`` at the present tap (``AlignedFrames.vr_recent``), not the last frame's alone: 1 %
    SCADA-class noise on one reading made eq. (8)'s set points hunt (6,076 tap changes in a rural winter week); the
    mean of five 1-minute frames has a noise 2.2 times smaller, and the step a tap change makes is never averaged in.

    ``last_good_s`` > 0: a feeder-head, PV or regulator frame lost at the control step is replaced by the latest
    one of the same device received within that many seconds before it (last good value), instead of a hold
    (head), a plant left uncommanded (its command expired after two lost frames and it went back to unity power
    factor: a 1.8 V jump at the regulators and NVV 188 in five minutes of a rural winter week at 5 % lost frames)
    or a frozen regulator without correction.

    ``reading_fit_s`` > 0: each regulator's readings of that many seconds at the present taps (every regulator's)
    are regressed on the head's P and Q and evaluated now (``agent.readings``); with fewer than 8 such readings,
    or no head frame now, the mean above is kept.
    """
    good_since = aligned.t_ns - int(last_good_s * 1e9)
    head = aligned.head
    if head is None and last_good_s > 0 and aligned.head_recent is not None and aligned.head_recent.t_ns > good_since:
        head = aligned.head_recent
    n_pv, n_reg = len(model.pv), len(model.regulators)
    head_p = np.zeros(3)
    head_q = np.zeros(3)
    if head is not None:
        for ph in head.phases:
            head_p[_PHASE_INDEX[ph.phase]] = ph.p_kw
            head_q[_PHASE_INDEX[ph.phase]] = ph.q_kvar
    pv_p, pv_q, pv_kva, pv_sp = (np.zeros(n_pv) for _ in range(4))
    pv_ok = np.zeros(n_pv, bool)
    pv_age = np.zeros(n_pv)
    for k, plant in enumerate(model.pv):
        pf = aligned.pv.get(plant.id)
        last = aligned.pv_recent.get(plant.id)
        if pf is None and last_good_s > 0 and last is not None and last.t_ns > good_since:
            pf = last  # a plant left without a command for two periods goes back to its local mode
        if pf is None:
            pv_sp[k] = np.nan
            continue
        # The apparent power available now: the plant's Q headroom is what the inverter says it is
        # (``q_available_kvar``: 0 at night, when it gives no reactive power).
        pv_p[k], pv_q[k] = pf.p_kw, pf.q_kvar
        pv_age[k] = max(aligned.t_ns - pf.t_ns, 0) / 1e9
        pv_kva[k] = min(float(np.hypot(pf.p_kw, pf.q_available_kvar)), pf.s_rated_kva)
        pv_sp[k] = np.nan if pf.q_setpoint_kvar is None else pf.q_setpoint_kvar
        pv_ok[k] = True
    reg_v, reg_vc, reg_tap = np.full(n_reg, 120.0), np.full(n_reg, 120.0), np.zeros(n_reg, int)
    reg_ok = np.zeros(n_reg, bool)
    reg_noise = np.full(n_reg, np.nan)
    reg_fresh = np.array([aligned.vr.get(reg.id) is not None for reg in model.regulators], bool)
    for r, reg in enumerate(model.regulators):
        f = aligned.vr.get(reg.id)
        recent = aligned.vr_recent.get(reg.id, ())
        if f is None and last_good_s > 0 and recent and recent[-1].t_ns > good_since:
            f = recent[-1]
        if f is None:
            continue
        reg_v[r] = f.phases[0].v_120
        reg_vc[r] = f.v_compared_120
        reg_tap[r] = f.tap
        since = aligned.t_ns - int(reading_window_s * 1e9)
        same_tap = [x for x in recent if x.t_ns > since and x.tap == f.tap and x.phases]
        readings = [x.phases[0].v_120 for x in same_tap]
        reg_noise[r] = reading_noise_v120(readings)
        if reading_window_s > 0 and len(same_tap) > 1:
            reg_v[r] = _mean(readings)
            reg_vc[r] = _mean([x.v_compared_120 for x in same_tap])
        if reading_fit_s > 0 and head is not None:
            fitted = _fitted_readings(aligned, reg.id, f, head, reading_fit_s, reg.step_v120)
            if fitted is not None:
                reg_v[r], reg_vc[r] = fitted
        reg_ok[r] = True
    cap_steps = np.zeros(len(model.capacitors), int)
    cap_ok = np.zeros(len(model.capacitors), bool)
    cap_v = np.full(len(model.capacitors), np.nan)
    cap_value = np.full(len(model.capacitors), np.nan)
    for c, bank in enumerate(model.capacitors):
        cf = aligned.cap.get(bank.id)
        if cf is not None and cf.steps == bank.steps:  # a bank reporting another number of steps is not the model's
            cap_steps[c], cap_ok[c], cap_v[c] = cf.closed_steps, True, cf.v_v
            if cf.mode == "local" and cf.control_value is not None:
                cap_value[c] = cf.control_value
    return MeasurementSnapshot(
        t_ns=aligned.t_ns, head_p_kw=head_p, head_q_kvar=head_q, pv_p_kw=pv_p, pv_q_kvar=pv_q,
        pv_kva_available=pv_kva, pv_q_setpoint_kvar=pv_sp, reg_v120=reg_v, reg_v120_compared=reg_vc,
        reg_tap=reg_tap, head_valid=head is not None, pv_valid=pv_ok, reg_valid=reg_ok,
        cap_steps=cap_steps, cap_valid=cap_ok, cap_v_v=cap_v, reg_fresh=reg_fresh, head_fresh=aligned.head is not None,
        pv_fresh=np.array([plant.id in aligned.pv for plant in model.pv], bool), pv_age_s=pv_age,
        reg_v120_now=np.array([_own_reading(aligned.vr.get(reg.id)) for reg in model.regulators], float),
        cap_control_value=cap_value, reg_v120_noise=reg_noise, reg_steps_seen=steps_seen_v120(aligned, model))


def steps_seen_v120(aligned: AlignedFrames, model: CvvcModel) -> tuple[tuple[tuple[int, float], ...], ...]:
    """Per regulator (the model's order), what one tap step did to its compared reading, from its recent frames.

    Each pair of consecutive frames (at most a control period apart) between which the regulator's tap moved by one
    step gives ``(t_ns of the later frame, change of the compared reading per tap up)`` [V on 120 V base], unless a
    coupled regulator (one whose step moves this one's secondary by ``_COUPLED_SHARE`` of its own step or more, by
    the model's dV/dtap) changed tap between the same frames, or its frames there are missing. The change is the
    regulator's own measurement of its step, line-drop compensation included: on IEEE 123's substation regulator
    (R = 3, X = 7.5 V) the raw reading moves 0.75 V per step and the compared one 0.57-0.60 V.
    """
    regs = model.regulators
    period_ns = int(model.control_period_s * 1e9)
    since = aligned.t_ns - 2 * period_ns  # the controller keeps what it saw: the last two periods' moves suffice
    frames = [[f for f in aligned.vr_recent.get(reg.id, ()) if f.t_ns >= since - period_ns] for reg in regs]
    moves = [[(a, b) for a, b in zip(fs, fs[1:], strict=False)
              if abs(b.tap - a.tap) == 1 and b.t_ns > since and 0 < b.t_ns - a.t_ns <= period_ns] for fs in frames]
    if not any(moves):  # most decisions: no regulator moved one step lately (nothing else to read)
        return tuple(() for _ in regs)
    rows = [model.dv_dtap_pu[r.secondary_node] for r in regs]
    if all(len(row) == len(regs) for row in rows):
        dv = np.abs(np.asarray(rows, float))
        coupled = dv >= _COUPLED_SHARE * np.diag(dv)[:, None]  # [r, r2]: r2's move blurs r's step
    else:  # sensitivities that do not fit the regulators: every other regulator's move blurs
        coupled = np.ones((len(regs), len(regs)), bool)
    taps = [{f.t_ns: f.tap for f in fs} for fs in frames]
    out: list[tuple[tuple[int, float], ...]] = []
    for r, pairs in enumerate(moves):
        others = [r2 for r2 in np.flatnonzero(coupled[r]) if r2 != r]
        out.append(tuple((int(b.t_ns), float(b.v_compared_120 - a.v_compared_120) * (b.tap - a.tap))
                         for a, b in pairs
                         if all(a.t_ns in taps[r2] and b.t_ns in taps[r2] and taps[r2][a.t_ns] == taps[r2][b.t_ns]
                                for r2 in others)))
    return tuple(out)


def reading_noise_v120(readings: list[float]) -> float:
    """The noise of a regulator's consecutive readings at one tap [V on 120 V base]: the standard deviation of their
    second differences over sqrt(6) (white noise of sigma gives 6 sigma^2; a load's slow drift nearly cancels); NaN
    with fewer than 4 readings.
    """
    if len(readings) < 4:
        return float("nan")
    if len(readings) >= _FEW + 2:
        return float(np.std(np.diff(np.asarray(readings, float), n=2)) / np.sqrt(6.0))
    d1 = [float(b) - float(a) for a, b in zip(readings, readings[1:], strict=False)]
    d2 = [b - a for a, b in zip(d1, d1[1:], strict=False)]
    mean = _mean(d2)
    return math.sqrt(_mean([(d - mean) * (d - mean) for d in d2])) / math.sqrt(6.0)


def _mean(values: list[float]) -> float:
    """The mean of ``values``, equal to ``np.mean``'s: under ``_FEW`` values, where NumPy adds them one after the
    other, in Python (a microsecond, where NumPy's call takes several: a decision takes eight regulators' means and
    noises); ``_FEW`` or more through NumPy (it adds them in eight partial sums then).
    """
    if len(values) >= _FEW:
        return float(np.mean(np.asarray(values, float)))
    total = 0.0
    for v in values:
        total += v
    return total / len(values)


def _own_reading(frame: m.RegFrame | None) -> float:
    """A regulator's own frame's raw secondary voltage [V on 120 V base]; NaN without a frame or a phase."""
    return float(frame.phases[0].v_120) if frame is not None and frame.phases else float("nan")


def _fitted_readings(aligned: AlignedFrames, reg_id: str, now: m.RegFrame, head: m.HeadFrame,
                     fit_s: float, step_v120: float) -> tuple[float, float] | None:
    """A regulator's raw and compared readings fitted on the head's P, Q and voltage (``agent.readings``), from its
    frames of the last ``fit_s`` that have a head frame of the same time, each moved to the present tap
    (``step_v120`` [V] per tap); or None.
    """
    heads = {x.t_ns: x for x in aligned.head_history}
    since = aligned.t_ns - int(fit_s * 1e9)
    rows = [(x, heads[x.t_ns]) for x in aligned.vr_recent.get(reg_id, ())
            if x.t_ns > since and x.phases and x.t_ns in heads]
    if not rows:
        return None
    phase = now.phases[0].phase if now.phases else "a"
    x = np.array([_head_regressors(h, phase) for _, h in rows])
    x_now = np.array(_head_regressors(head, phase))
    shift = np.array([(now.tap - f.tap) * step_v120 for f, _ in rows])
    v = fitted_reading_v120(np.array([f.phases[0].v_120 for f, _ in rows]) + shift, x, x_now, min_points=_FIT_MIN)
    vc = fitted_reading_v120(np.array([f.v_compared_120 for f, _ in rows]) + shift, x, x_now, min_points=_FIT_MIN)
    return None if v is None or vc is None else (v, vc)


def _head_regressors(head: m.HeadFrame, phase: str) -> tuple[float, float, float]:
    """The head's total P [kW], Q [kvar] and the voltage of ``phase`` (else the phases' mean) [V]."""
    volts: dict[str, float] = {p.phase: p.v_mag_v for p in head.phases}
    v = volts[phase] if phase in volts else float(np.mean(list(volts.values()))) if volts else 0.0
    return head.p_kw, head.q_kvar, v
