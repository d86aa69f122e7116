"""Capacitor banks' voltage sensitivities for the model (beyond the paper; docs/method.md "Capacitor decisions").

A bank's step is a fixed admittance: its effect on the voltages is nearly linear in its kvar, so one
finite difference per bank at a few representative scenarios (the first, the middle and the last of the
training scenarios, PV Q at 0, taps at ``tap0``), averaged, gives its per-step sensitivity. A bank that is
closed at its training state is opened one step (and the difference divided by -1), an open one closed one
step. The training flows keep every bank at ``closed0``, the engine's state at compile time.
"""

from __future__ import annotations

import numpy as np

from regression.model import CapacitorInfo

__all__ = ["SCENARIOS_PER_BANK", "bank_infos", "bank_sensitivities"]

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
