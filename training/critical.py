"""Critical nodes (paper II.C) and the upstream regulator of each (for eq. (6)-(7)).

Critical nodes: the feeder-head nodes, the primary and secondary nodes of every regulator, the PV plant
nodes, plus every node that is the highest or the lowest voltage in any training power flow; all of them taken in
the feeder zone (downstream of the head meter) only, and only where a controlled device can move the voltage
(:func:`movable_nodes`): an LTC's subtransmission primary or the source bus is never critical, since no decision of
the agent changes it and a limit there would only make the optimization infeasible. Regulator secondaries are
always kept (the eq. (6)-(7) correction reads them).

The upstream regulator is found without walking the topology: regulator r is upstream of node i when one
tap step of r moves node i by more than ``share`` (0.5) of the step it gives r's own secondary node (from
the eq. (4) tap perturbation). Among the regulators upstream of a node, the nearest is the one whose
secondary lies downstream of the most other upstream regulators. Because a single-phase regulator moves
other phases very little, this also matches the phase; a ganged three-phase regulator moves every phase
downstream and is upstream of all of them (its secondary-node measurement is one phase: the correction
of the other phases uses that phase's error, a documented approximation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["MOVABLE_PU", "CriticalSet", "extreme_nodes", "movable_nodes", "node_phase", "select_critical",
           "upstream_regulators"]

#: A node is movable when one tap step of some regulator, or some plant's whole reactive range (``kva`` kvar),
#: moves it by at least this much [pu]: 0.001 pu is 0.12 V on the 120 V base, a sixth of a 5/8 % tap step.
MOVABLE_PU = 1e-3


def node_phase(name: str) -> int:
    """Phase number of an OpenDSS node name ``"bus.phase"`` (0 when it has none)."""
    _, _, tail = name.rpartition(".")
    return int(tail) if tail.isdigit() else 0


def extreme_nodes(v_pu: np.ndarray, *, eligible: np.ndarray | None = None) -> np.ndarray:
    """Nodes that are the max or the min voltage in at least one power flow.

    Parameters
    ----------
    v_pu : (F, n) node voltages of F power flows [pu].
    eligible : (n,) bool, nodes that may be chosen (e.g. phases 1-3, energised); None: all.

    Returns
    -------
    Sorted unique node indices.
    """
    v = np.asarray(v_pu, float)
    if eligible is not None:
        v = np.where(eligible[None, :], v, np.nan)
    if v.size == 0:
        return np.zeros(0, int)
    hi = np.nanargmax(v, axis=1)
    lo = np.nanargmin(v, axis=1)
    return np.unique(np.concatenate([hi, lo]))


def movable_nodes(dv_dtap_pu: np.ndarray, dv_dq_pu_per_kvar: np.ndarray, kva: np.ndarray, *,
                  threshold_pu: float = MOVABLE_PU) -> np.ndarray:
    """Nodes whose voltage a controlled device can move, from the training sensitivities.

    Parameters
    ----------
    dv_dtap_pu : (n, R) voltage change per tap step of each regulator [pu/step] (eq. (4)).
    dv_dq_pu_per_kvar : (n, K) voltage change per kvar of each plant [pu/kvar]; NaN columns count as 0.
    kva : (K,) plant ratings [kVA]: a plant can move its Q over ``±kva``.
    threshold_pu : the smallest move that counts [pu].

    Returns
    -------
    (n,) bool: ``max_r |dv_dtap| >= threshold`` or ``max_k |dv_dq| * kva_k >= threshold``.
    """
    tap = np.abs(np.asarray(dv_dtap_pu, float))
    q = np.abs(np.nan_to_num(np.asarray(dv_dq_pu_per_kvar, float))) * np.asarray(kva, float)[None, :]
    n = tap.shape[0] if tap.ndim == 2 else q.shape[0]
    best = np.zeros(n)
    if tap.size:
        best = np.maximum(best, tap.max(axis=1))
    if q.size:
        best = np.maximum(best, q.max(axis=1))
    return best >= threshold_pu


def upstream_regulators(dv_dtap_pu: np.ndarray, reg_secondary_node: np.ndarray, *, share: float = 0.5) -> np.ndarray:
    """Nearest upstream regulator of every node, from tap sensitivities (eq. (4)).

    Parameters
    ----------
    dv_dtap_pu : (n, R) voltage change of every node per tap step of each regulator [pu/step].
    reg_secondary_node : (R,) node index of each regulator's secondary.
    share : node i is downstream of r when ``dv_dtap[i, r] > share * dv_dtap[secondary_r, r]``.

    Returns
    -------
    (n,) int regulator index, -1 where no regulator is upstream.
    """
    d = np.asarray(dv_dtap_pu, float)
    n, n_reg = d.shape
    if n_reg == 0:
        return np.full(n, -1, int)
    sec = np.asarray(reg_secondary_node, int)
    own_step = d[sec, np.arange(n_reg)]
    down = d > share * np.maximum(own_step, 1e-12)[None, :]  # (n, R)
    # depth[r]: how many other regulators lie upstream of r's secondary
    depth = down[sec].sum(axis=1) - np.diag(down[sec])
    out = np.full(n, -1, int)
    for i in range(n):
        cand = np.flatnonzero(down[i])
        if cand.size:
            out[i] = int(cand[np.argmax(depth[cand])])
    return out


@dataclass(frozen=True)
class CriticalSet:
    """Critical nodes in ascending node order, with why each was chosen."""

    nodes: np.ndarray  # (N,) int node indices
    kinds: tuple[tuple[str, ...], ...]  # (N,) kinds of each node (model.NodeKind values)


def select_critical(required: dict[str, np.ndarray], extremes: np.ndarray) -> CriticalSet:
    """Union of the required nodes (kind -> node indices) and the extreme-voltage nodes.

    ``required`` keys are ``"head"``, ``"reg_primary"``, ``"reg_secondary"``, ``"pv"``.
    """
    kinds: dict[int, list[str]] = {}
    for kind, idx in required.items():
        for i in np.asarray(idx, int).ravel():
            kinds.setdefault(int(i), [])
            if kind not in kinds[int(i)]:
                kinds[int(i)].append(kind)
    for i in np.asarray(extremes, int).ravel():
        kinds.setdefault(int(i), [])
        if "extreme" not in kinds[int(i)]:
            kinds[int(i)].append("extreme")
    nodes = np.asarray(sorted(kinds), int)
    return CriticalSet(nodes=nodes, kinds=tuple(tuple(kinds[int(i)]) for i in nodes))
