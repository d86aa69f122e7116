"""Capacitor banks' voltage sensitivities for the model (beyond the paper; docs/method.md "Capacitor decisions").

A bank's step is a fixed admittance: its effect on the voltages is nearly linear in its kvar, so one
finite difference per bank at a few representative scenarios (the first, the middle and the last of the
training scenarios, PV Q at 0, taps at ``tap0``), averaged, gives its per-step sensitivity. A bank that is
closed at its training state is opened one step (and the difference divided by -1), an open one closed one
step. The training flows keep every bank at ``closed0``, the engine's state at compile time.
"""

from __future__ import annotations

import msgspec
import numpy as np

from regression.model import CapacitorInfo

__all__ = ["PREDICTED_KINDS", "SCENARIOS_PER_BANK", "bank_controls", "bank_infos", "bank_sensitivities"]

#: CapControl types whose quantity is nearly linear in the plants' Q and the taps: the agent predicts them.
PREDICTED_KINDS = ("voltage", "kvar", "current")
_DQ_SHARE = 0.1  # each plant's Q perturbation: this share of its kVA rating

#: Representative scenarios the finite differences are averaged over (first, middle, last).
SCENARIOS_PER_BANK = 3


def _scenario_indices(n: int) -> list[int]:
    return sorted({0, n // 2, n - 1}) if n > 0 else []


def bank_sensitivities(engine, inputs, tap0: np.ndarray, cap0: np.ndarray) -> np.ndarray:
    """(nodes, C) voltage change of every node per closed step of each map bank [pu/step].

    ``inputs`` are the training ``ScenarioInput`` s; the engine is left at ``cap0`` and ``tap0``.
    """
    n_cap = len(cap0)
    n_nodes = len(engine.node_names)
    if n_cap == 0:
        return np.zeros((n_nodes, 0))
    picks = _scenario_indices(len(inputs))
    total = np.zeros((n_nodes, n_cap))
    for i in picks:
        s = inputs[i]
        engine.set_loads_kw(s.load_kw)
        engine.set_pv(s.pv_kw, np.zeros(len(s.pv_kw)))
        engine.set_taps(tap0)
        for c in range(n_cap):
            engine.set_cap_states(cap0)
            engine.solve()  # the base solved again before each move: a restored state drifts ~1e-4 pu
            v0 = engine.node_voltages_pu()
            step = -1 if cap0[c] > 0 else 1
            states = cap0.copy()
            states[c] += step
            engine.set_cap_states(states)
            engine.solve()
            total[:, c] += (engine.node_voltages_pu() - v0) / step
    engine.set_cap_states(cap0)
    engine.solve()
    return total / max(len(picks), 1)


def bank_infos(engine, device_map, cap0: np.ndarray) -> list[CapacitorInfo]:
    """The model's record of every map bank: rating, steps, phases, training state and switching cost."""
    return [
        CapacitorInfo(
            id=spec.id,
            steps=int(engine.cap_steps[c]),
            kvar_rated=float(engine.cap_kvar[c]),
            phases=engine.cap_phases[c],
            closed0=int(cap0[c]),
            cost_per_switch=float(spec.cost_per_switch),
            max_switches_per_interval=int(engine.cap_steps[c]),
        )
        for c, spec in enumerate(device_map.capacitor)
    ]


def bank_controls(engine, inputs, tap0: np.ndarray, cap0: np.ndarray,
                  banks: list[CapacitorInfo]) -> list[CapacitorInfo]:
    """``banks`` with their local control as the agent predicts it: the CapControl's type and ON/OFF settings, and
    its controlled quantity's sensitivity to each plant's Q [unit/kvar] and each regulator's tap [unit/step].

    Finite differences from the base state (PV Q at 0, ``tap0``, ``cap0``) at the representative scenarios of
    :func:`bank_sensitivities`, averaged: each plant's Q moved by ``_DQ_SHARE`` of its rating (within its
    headroom), each regulator one tap up (down at its top). Banks without a control, or of a type that is not nearly
    linear in them (power factor, time, follow), keep ``control_kind = "none"``. A kvar or current control with
    ``VoltOverride`` also gets the overriding voltage's limits and sensitivities, and that voltage per volt of the
    bank's bus reading (``override_*``): a low voltage closes such a bank and a high one opens it, whatever its kvar.
    """
    index = np.asarray(engine.cap_control_index, int)
    predicted = [c for c in range(len(banks))
                 if index[c] >= 0 and engine.cap_controls[index[c]].kind in PREDICTED_KINDS
                 and engine.cap_controls[index[c]].enabled]
    if not predicted:
        return banks
    n_pv, n_reg = len(engine.pv_ids), len(tap0)
    picks = _scenario_indices(len(inputs))
    # each predicted bank's controlled quantity, then the voltage its VoltOverride tests: one column each
    dq = np.zeros((2 * len(banks), n_pv))
    dtap = np.zeros((2 * len(banks), n_reg))
    rows = np.concatenate([predicted, len(banks) + np.asarray(predicted, int)])
    per_v = np.zeros(len(banks))

    def sensed() -> np.ndarray:
        _, value, v_override, _ = engine.sense()  # (reg_v120, cap_value, cap_v, cap_q_kvar)
        return np.concatenate([np.asarray(value, float)[index[predicted]],
                               np.asarray(v_override, float)[index[predicted]]])

    for i in picks:
        s = inputs[i]
        engine.set_loads_kw(s.load_kw)
        engine.set_taps(tap0)
        engine.set_cap_states(cap0)
        zero = np.zeros(n_pv)
        engine.set_pv(s.pv_kw, zero)
        engine.solve()
        base = sensed()
        bus_v = np.asarray(engine.readings().cap_v_v, float)[predicted]
        per_v[predicted] += base[len(predicted):] / np.where(bus_v > 0, bus_v, np.nan) / len(picks)
        for k in range(n_pv):
            q = zero.copy()
            q[k] = _DQ_SHARE * float(engine.pv_kva[k])
            applied = engine.set_pv(s.pv_kw, q)[k]
            if abs(applied) < 1e-6:  # no headroom at this scenario: absorb instead
                q[k] = -q[k]
                applied = engine.set_pv(s.pv_kw, q)[k]
            if abs(applied) < 1e-6:
                continue
            engine.solve()
            dq[rows, k] += (sensed() - base) / applied / len(picks)
        engine.set_pv(s.pv_kw, zero)
        for r in range(n_reg):
            step = 1 if tap0[r] < engine.reg_tap_max[r] else -1
            taps = np.asarray(tap0, int).copy()
            taps[r] += step
            engine.set_taps(taps)
            engine.solve()
            dtap[rows, r] += (sensed() - base) / step / len(picks)
        engine.set_taps(tap0)
    engine.solve()
    out = list(banks)
    for c in predicted:
        cc = engine.cap_controls[index[c]]
        out[c] = msgspec.structs.replace(banks[c], control_kind=cc.kind, control_on=float(cc.on),
                                         control_off=float(cc.off), control_dq=dq[c].tolist(),
                                         control_dtap=dtap[c].tolist())
        if cc.volt_override and cc.kind != "voltage" and np.isfinite(per_v[c]) and per_v[c] > 0:
            o = len(banks) + c
            out[c] = msgspec.structs.replace(out[c], override_vmin_v=float(cc.vmin_v), override_vmax_v=float(cc.vmax_v),
                                             override_per_v=float(per_v[c]), override_dq=dq[o].tolist(),
                                             override_dtap=dtap[o].tolist())
    return out
