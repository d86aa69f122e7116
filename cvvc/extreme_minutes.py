"""A run's lowest and highest minutes, and the taps and banks that moved in the minutes up to each
(``cvvc report run``).

The paper's metrics average ten minutes; a 1-minute extreme is often one device's move: a bank that opened on its own
control drops its phase's secondaries by 0.02-0.04 pu in a minute (IEEE 8500), a regulator steps at the wrong time.
Read from the truth frames, step by step with bounded memory per step: each step's extremes over the nodes it is given
(those the run's metrics judge: ``cvvc.report.read_trace``), the node that has each, the decision in force, and what
moved since the step before (tap steps per regulator, closed steps per bank). The lowest and the highest minutes are
then taken as episodes, each at least ``EPISODE_GAP_NS`` from the others of its side, so that one ramp does not fill
the table.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np

__all__ = ["EPISODE_GAP_NS", "LOOKBACK_STEPS", "ROWS_PER_SIDE", "ExtremeMinute", "ExtremeMinutes"]

EPISODE_GAP_NS = 3_600_000_000_000  # an hour between the extremes of one side
LOOKBACK_STEPS = 5  # the steps whose moves are listed with an extreme: its own and the four before
ROWS_PER_SIDE = 3
_Ranked = tuple[int, float, str, str, tuple[tuple[int, str], ...]]  # (t_ns, voltage, node, decision, moves)


@dataclass(frozen=True)
class ExtremeMinute:
    """One extreme step: ``side`` lowest or highest, its time ``t_ns``, the voltage ``v_pu`` [pu] at ``node``, the
    kind of the decision in force (``cvvc.report.decision_kind``), and ``moves``: ``(steps before, what moved)`` of
    the steps up to it with a move, latest last (``0``: between the step before and this one).
    """

    side: Literal["lowest", "highest"]
    t_ns: int
    v_pu: float
    node: str
    decision: str
    moves: tuple[tuple[int, str], ...]


class ExtremeMinutes:
    """Takes a run's truth steps in time order (``add``) and gives its extreme minutes (``result``).

    ``regulator_ids`` / ``capacitor_ids`` name the frames' taps and bank states (the device map's order); a frame
    with another number of either is named by position.
    """

    def __init__(self, regulator_ids: tuple[str, ...] = (), capacitor_ids: tuple[str, ...] = ()) -> None:
        self._reg_ids, self._cap_ids = regulator_ids, capacitor_ids
        self._names: tuple[str, ...] = ()
        self._last: tuple[np.ndarray, np.ndarray] | None = None
        self._recent: deque[tuple[int, str]] = deque(maxlen=LOOKBACK_STEPS)  # (step index, what moved) per step
        self._step = -1
        # per step: (t_ns, v_min, node of v_min, v_max, node of v_max, decision, moves up to it)
        self._steps: list[tuple[int, float, str, float, str, str, tuple[tuple[int, str], ...]]] = []

    def add(self, t_ns: int, v_pu: np.ndarray, taps: np.ndarray, cap_states: np.ndarray, decision: str,
            node_names: tuple[str, ...] | None = None) -> None:
        """One truth step: the judged nodes' voltages ``v_pu`` [pu], the taps and the banks' closed steps after the
        step, and the kind of the decision in force; ``node_names`` (of ``v_pu``'s nodes) when they change.
        """
        self._step += 1
        if node_names:
            self._names = tuple(node_names)
        taps, caps = np.asarray(taps, int), np.asarray(cap_states, int)
        moved = self._moved(taps, caps)
        if moved:
            self._recent.append((self._step, moved))
        self._last = (taps, caps)
        moves = tuple((self._step - i, text) for i, text in self._recent if self._step - i < LOOKBACK_STEPS)
        v = np.asarray(v_pu, float)
        if v.size:
            lo, hi = int(np.argmin(v)), int(np.argmax(v))
            self._steps.append((int(t_ns), float(v[lo]), self._node(lo, v.size), float(v[hi]), self._node(hi, v.size),
                                decision, moves))

    def _node(self, i: int, n: int) -> str:
        """The name of node ``i`` of ``n`` (by position when the names do not fit)."""
        return self._names[i] if len(self._names) == n else f"node {i}"

    def _moved(self, taps: np.ndarray, caps: np.ndarray) -> str:
        """What moved since the step before: ``<regulator> +k`` per tap change, ``<bank> closed|opened`` per bank."""
        if self._last is None:
            return ""
        last_taps, last_caps = self._last
        parts: list[str] = []
        if taps.shape == last_taps.shape:
            ids = self._reg_ids if len(self._reg_ids) == taps.size else tuple(f"regulator {r}"
                                                                              for r in range(taps.size))
            parts += [f"{ids[r]} {int(d):+d}" for r, d in enumerate(taps - last_taps) if d]
        if caps.shape == last_caps.shape:
            ids = self._cap_ids if len(self._cap_ids) == caps.size else tuple(f"bank {c}" for c in range(caps.size))
            for c, d in enumerate(caps - last_caps):
                if d:
                    steps = f" {abs(int(d))} steps" if abs(d) > 1 else ""
                    parts.append(f"{ids[c]} {'closed' if d > 0 else 'opened'}{steps}")
        return ", ".join(parts)

    def result(self, rows_per_side: int = ROWS_PER_SIDE) -> tuple[ExtremeMinute, ...]:
        """The lowest steps, lowest first, then the highest, highest first: each at least ``EPISODE_GAP_NS`` from
        the ones of its side before it (ties by time).
        """
        lowest = [(t, lo, lo_node, decision, moves) for t, lo, lo_node, _, _, decision, moves in self._steps]
        highest = [(t, hi, hi_node, decision, moves) for t, _, _, hi, hi_node, decision, moves in self._steps]
        return (self._episodes("lowest", sorted(lowest, key=lambda r: (r[1], r[0])), rows_per_side)
                + self._episodes("highest", sorted(highest, key=lambda r: (-r[1], r[0])), rows_per_side))

    @staticmethod
    def _episodes(side: Literal["lowest", "highest"], ranked: list[_Ranked], n: int) -> tuple[ExtremeMinute, ...]:
        """The first ``n`` of ``ranked`` steps each at least ``EPISODE_GAP_NS`` from the ones taken before it."""
        out: list[ExtremeMinute] = []
        for t, v, node, decision, moves in ranked:
            if len(out) == n:
                break
            if all(abs(t - x.t_ns) >= EPISODE_GAP_NS for x in out):
                out.append(ExtremeMinute(side=side, t_ns=t, v_pu=v, node=node, decision=decision, moves=moves))
        return tuple(out)
