"""Synthetic but physically plausible CVVC problems and models, for tests and the solver benchmark.

A feeder at the paper's size: 47 critical nodes, 3 three-phase PV plants, 8 single-phase regulators (two
three-phase banks in cascade, ``A`` = regulators 0-2 and ``B`` = 3-5, plus single-phase ``C`` = 6 on phase a
and ``D`` = 7 on phase b, both behind ``A``). A tap step raises the nodes behind the regulator on its phase by
about 0.6 % (+/-10 %, 32 steps); PV reactive power moves voltages by 1e-6..3e-5 pu/kvar. Nothing here is used
by the running agent.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from agent.cvvc_qp import CvvcInputs
from regression.model import (
    CriticalNode,
    CvvcModel,
    NodeKind,
    PvInfo,
    RegulatorInfo,
    SensitivityFit,
    TrainingSettings,
    feature_names,
)

__all__ = ["cvvc_day_sequence", "random_cvvc_inputs", "synthetic_model"]

_STEP_PU = 0.00625
# Regulators upstream of each zone, per phase (0=a, 1=b, 2=c): zone -> list of regulator indices per phase.
_ZONE_REGS = {
    "head": ([], [], []),
    "A": ([0], [1], [2]),
    "B": ([0, 3], [1, 4], [2, 5]),
    "C": ([0, 6], [1], [2]),
    "D": ([0, 3], [1, 4, 7], [2, 5]),
}
_ZONES = ("head", "A", "A", "B", "B", "C", "D")


def _topology(n_nodes: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N,) phase, (N, R) tap sensitivity [pu/step], (N,) nearest upstream regulator (-1 none)."""
    phase = np.arange(n_nodes) % 3
    zone = [_ZONES[i % len(_ZONES)] for i in range(n_nodes)]
    dv_dtap = np.zeros((n_nodes, 8))
    upstream = np.full(n_nodes, -1)
    for i in range(n_nodes):
        regs = _ZONE_REGS[zone[i]][phase[i]]
        for r in regs:
            dv_dtap[i, r] = _STEP_PU * rng.uniform(0.85, 1.0)
        if regs:
            upstream[i] = regs[-1]
        # weak coupling to the other phases' regulators of the same banks (unbalanced lines)
        for ph in range(3):
            if ph != phase[i]:
                for r in _ZONE_REGS[zone[i]][ph]:
                    dv_dtap[i, r] = _STEP_PU * rng.uniform(-0.08, 0.08)
    return phase, dv_dtap, upstream


def random_cvvc_inputs(rng: np.random.Generator, *, n_nodes: int = 47, n_pv: int = 3) -> CvvcInputs:
    """One random realistic CVVC problem at the paper's size (8 regulators).

    Voltages spread around a level that is sometimes high (midday PV) and sometimes low (evening peak), so
    some problems need no action, most need a little, and a few are infeasible.
    """
    _, dv_dtap, _ = _topology(n_nodes, rng)
    kva = rng.uniform(900.0, 1500.0, n_pv)
    dv_dq = rng.uniform(1e-6, 3e-5, (n_nodes, n_pv))
    level = rng.choice([0.99, 1.03, 1.045, 0.975, 1.0])
    v0 = level + rng.normal(0.0, 0.012, n_nodes)
    p_kw = kva * rng.uniform(0.0, 0.9, n_pv)
    q_head = np.sqrt(np.maximum(kva**2 - p_kw**2, 0.0))
    q0 = rng.uniform(-0.3, 0.3, n_pv) * q_head
    taps = rng.integers(-8, 9, 8)
    return CvvcInputs(
        v0_pu=v0,
        dv_dq_pu_per_kvar=dv_dq,
        dv_dtap_pu=dv_dtap,
        q0_kvar=q0,
        q_min_kvar=-q_head,
        q_max_kvar=q_head,
        q_rating_kvar=kva,
        taps=taps,
        tap_min=np.full(8, -16),
        tap_max=np.full(8, 16),
        max_taps_per_interval=np.full(8, 4),
        cost_per_tap=np.full(8, 0.14),
        cost_per_kvar=np.full(n_pv, 0.001),
        v_min_pu=0.975,
        v_max_pu=1.04,
    )


def synthetic_model(seed: int = 0, *, n_nodes: int = 47, n_pv: int = 3) -> CvvcModel:
    """A ``CvvcModel`` of the synthetic feeder (8 regulators), built directly (no training).

    Voltages fall with head P and Q (about -2e-6 pu/kW, -4e-6 pu/kvar per phase) and rise with plant P and Q;
    regulator ``r``'s secondary is the first node behind it on its phase. Sensitivities use all three fit
    forms.
    """
    rng = np.random.default_rng(seed)
    phase, dv_dtap, upstream = _topology(n_nodes, rng)
    n_feat = 6 + 2 * n_pv
    alpha = np.zeros((n_nodes, n_feat + 1))
    for i in range(n_nodes):
        alpha[i, phase[i]] = -rng.uniform(1e-6, 4e-6)  # head P of the node's phase
        alpha[i, 3 + phase[i]] = -rng.uniform(2e-6, 8e-6)  # head Q of the node's phase
        alpha[i, 6::2][:n_pv] = rng.uniform(2e-6, 1e-5, n_pv) / 3  # plant total P
        alpha[i, 7::2][:n_pv] = rng.uniform(3e-6, 2e-5, n_pv) / 3  # plant total Q
        alpha[i, -1] = 1.02 + rng.normal(0.0, 0.005)
    secondary = []
    for r in range(8):
        behind = np.flatnonzero(upstream == r)
        secondary.append(int(behind[0]))
    forms = ("power", "linear", "constant")
    sens = []
    for i in range(n_nodes):
        row = []
        for k in range(n_pv):
            a0 = rng.uniform(2e-6, 2e-5)
            form = forms[(i + k) % 3]
            if form == "power":
                # negative exponent: sensitivity rises with head Q (reference experiment, trap 2)
                b = -rng.uniform(0.05, 0.3)
                c = 6000.0
                row.append(SensitivityFit(form="power", a=a0 / c ** (-b), b=b, c=c, q_min_kvar=-3000, q_max_kvar=5000))
            elif form == "linear":
                row.append(SensitivityFit(form="linear", a=a0, b=a0 * 2e-5, q_min_kvar=-3000, q_max_kvar=5000))
            else:
                row.append(SensitivityFit(form="constant", a=a0))
        sens.append(row)
    nodes = []
    for i in range(n_nodes):
        kinds: list[NodeKind] = ["reg_secondary"] if i in secondary else (["head"] if i == 0 else ["extreme"])
        ph: Literal[1, 2, 3] = (1, 2, 3)[int(phase[i])]
        nodes.append(
            CriticalNode(
                name=f"n{i}.{ph}",
                phase=ph,
                kinds=kinds,
                upstream_regulator=None if upstream[i] < 0 else int(upstream[i]),
            )
        )
    return CvvcModel(
        feeder_name="synthetic47",
        fingerprint="synthetic47-" + str(seed),
        cvvc_version="test",
        settings=TrainingSettings(
            year_seed=seed,
            selection="random",
            blocks=(5, 5),
            q_steps_pct=[-50.0, 50.0],
            scenarios=0,
            power_flows=0,
            seconds=0.0,
        ),
        feature_names=feature_names(n_pv),
        critical_nodes=nodes,
        regulators=[RegulatorInfo(id=f"vr{r}", secondary_node=secondary[r], pu_per_v120=1.0 / 120.0) for r in range(8)],
        pv=[PvInfo(id=f"pv{k}", kva=1200.0, pmpp_kw=1080.0, cost_per_kvar=0.001) for k in range(n_pv)],
        alpha=alpha.tolist(),
        tap0=[0] * 8,
        dv_dtap_pu=dv_dtap.tolist(),
        sens_q=sens,
        node_count=1284,
    )


def cvvc_day_sequence(rng: np.random.Generator, *, n_steps: int = 288, n_nodes: int = 47, n_pv: int = 3):
    """A day of 5-minute problems on one synthetic feeder, to drive a closed loop (``send`` the solution).

    A generator: yields ``CvvcInputs``; the caller sends back ``(taps_new, q_new_kvar)`` and the next
    problem's voltages include the effect of those actions. Voltages follow a load dip and a midday PV rise
    with noise, so some intervals need no action and some need taps and Q.
    """
    base = random_cvvc_inputs(rng, n_nodes=n_nodes, n_pv=n_pv)
    offsets = rng.normal(0.0, 0.01, n_nodes)
    taps0 = base.taps.copy()
    taps = taps0.copy()
    q = np.zeros(n_pv)
    kva = base.q_rating_kvar
    for step in range(n_steps):
        hour = 24.0 * step / n_steps
        pv = max(0.0, np.sin(np.pi * (hour - 6.0) / 12.0))
        load = 0.6 + 0.4 * np.exp(-((hour - 19.0) ** 2) / 8.0)
        v_nat = 1.015 + offsets + 0.04 * pv - 0.03 * load + rng.normal(0.0, 0.002, n_nodes)
        v0 = v_nat + base.dv_dtap_pu @ (taps - taps0) + base.dv_dq_pu_per_kvar @ q
        p_kw = 0.9 * kva * pv * rng.uniform(0.9, 1.0, n_pv)
        q_head = np.sqrt(np.maximum(kva**2 - p_kw**2, 0.0))
        inputs = CvvcInputs(
            v0_pu=v0,
            dv_dq_pu_per_kvar=base.dv_dq_pu_per_kvar,
            dv_dtap_pu=base.dv_dtap_pu,
            q0_kvar=np.clip(q, -q_head, q_head),
            q_min_kvar=-q_head,
            q_max_kvar=q_head,
            q_rating_kvar=kva,
            taps=taps,
            tap_min=base.tap_min,
            tap_max=base.tap_max,
            max_taps_per_interval=base.max_taps_per_interval,
            cost_per_tap=base.cost_per_tap,
            cost_per_kvar=base.cost_per_kvar,
            v_min_pu=base.v_min_pu,
            v_max_pu=base.v_max_pu,
        )
        taps_new, q_new = yield inputs
        taps, q = np.asarray(taps_new, int), np.asarray(q_new, float)
