"""Representative scenario selection (paper II.A, eq. (1)-(2)).

For every minute of the training year we compute the feeder load, the total PV output and the load and
PV centres ``D_L`` and ``D_PV``. The (load, PV) plane is cut into blocks; from every non-empty block we
take six minutes: the max, median and min of ``D_L`` and of ``D_PV`` (guided selection), or six at random
(random selection, the comparison of the paper's Fig. 8a).

Our reading of the paper (see docs/method.md):

- "Feeder head load" is the sum of the customer loads [kW] (gross load, before PV). The head P of a power
  flow would need a solve per minute and mixes load and PV, which the other axis already shows.
- ``D_i`` is the electrical distance of the load's / plant's bus from the feeder head: the magnitude of the
  summed positive-sequence series impedance ``|sum (R1 + jX1) * length|`` along the path [ohm].
- At minutes with no PV output eq. (2) is 0/0; we set ``D_PV = 0`` there.
- A minute is picked once: when a pick repeats an earlier one (ties, tiny blocks), the next minute in the
  same order that is not yet picked is taken instead, so a block with at least six minutes gives six.
- Blocks are equal-width bins between the year's min and max of each axis; empty blocks are skipped (a
  block with no minute represents nothing that happened).
"""

from __future__ import annotations

import calendar
from dataclasses import dataclass
from typing import Literal

import numpy as np

from training.errors import TrainingError

__all__ = [
    "PICK_KINDS",
    "ScenarioSet",
    "YearSummary",
    "calendar_cover",
    "center_ohm",
    "select_scenarios",
    "summarize_year",
]

PICK_KINDS = ("dl_max", "dl_median", "dl_min", "dpv_max", "dpv_median", "dpv_min")


def center_ohm(power_kw: np.ndarray, distance_ohm: np.ndarray) -> np.ndarray:
    """Power-weighted electrical distance, paper eq. (1) (loads) and eq. (2) (PV).

    Parameters
    ----------
    power_kw : (T, L) injections or loads per element [kW].
    distance_ohm : (L,) electrical distance of each element's bus from the feeder head [ohm].

    Returns
    -------
    (T,) centre [ohm]; 0 where the total power is 0 (e.g. PV at night).
    """
    power_kw = np.asarray(power_kw, float)
    total = power_kw.sum(axis=-1)
    weighted = power_kw @ np.asarray(distance_ohm, float)
    out = np.zeros_like(total)
    np.divide(weighted, total, out=out, where=np.abs(total) > 1e-9)
    return out


@dataclass(frozen=True)
class YearSummary:
    """Per-minute aggregates of the training year (all arrays (T,))."""

    load_kw: np.ndarray  # sum of customer loads [kW]
    pv_kw: np.ndarray  # sum of available PV power [kW]
    d_load_ohm: np.ndarray  # eq. (1) [ohm]
    d_pv_ohm: np.ndarray  # eq. (2) [ohm]
    mean_load_kw: np.ndarray | None = None  # (n_loads,) year mean of each load [kW]
    mean_pv_kw: np.ndarray | None = None  # (K,) year mean of each plant's available power [kW]


def summarize_year(
    profiles, load_distance_ohm: np.ndarray, pv_distance_ohm: np.ndarray, *, chunk: int = 20_160
) -> YearSummary:
    """Eq. (1)-(2) for every step of ``profiles`` (a ``YearProfiles``), read in chunks of ``chunk`` steps."""
    parts: list[tuple[np.ndarray, ...]] = []
    load_sum = np.zeros(profiles.n_loads)
    pv_sum = np.zeros(profiles.n_pv)
    for start in range(0, profiles.n_steps, chunk):
        stop = min(start + chunk, profiles.n_steps)
        load = profiles.load_kw(start, stop)
        pv = profiles.pv_kw(start, stop)
        load_sum += load.sum(axis=0)
        pv_sum += pv.sum(axis=0)
        d_load = center_ohm(load, load_distance_ohm)
        parts.append((load.sum(axis=1), pv.sum(axis=1), d_load, center_ohm(pv, pv_distance_ohm)))
    cols = [np.concatenate(c) for c in zip(*parts, strict=True)]
    return YearSummary(
        load_kw=cols[0],
        pv_kw=cols[1],
        d_load_ohm=cols[2],
        d_pv_ohm=cols[3],
        mean_load_kw=load_sum / profiles.n_steps,
        mean_pv_kw=pv_sum / profiles.n_steps,
    )


@dataclass(frozen=True)
class ScenarioSet:
    """The selected minutes, in block order (row-major over (load bin, PV bin)), then pick order.

    ``steps[0]`` is "the first scenario" of Algorithm 1 (tap perturbation).
    """

    steps: np.ndarray  # (S,) int, indices into the year
    block: np.ndarray  # (S,) int, flat block index (load_bin * n_pv_bins + pv_bin)
    kind: tuple[str, ...]  # (S,) one of PICK_KINDS, or "random"
    blocks: tuple[int, int]  # (load bins, PV bins)
    non_empty_blocks: int
    minutes_per_block: np.ndarray  # (load bins, PV bins) int


def _bin(x: np.ndarray, n: int) -> np.ndarray:
    lo, hi = float(x.min()), float(x.max())
    if hi - lo <= 1e-12 * max(1.0, abs(hi)):
        return np.zeros(x.shape, int)
    return np.minimum(((x - lo) / (hi - lo) * n).astype(int), n - 1)


def _guided_picks(d_load: np.ndarray, d_pv: np.ndarray) -> list[tuple[int, str]]:
    """Positions (into the block's minutes) of the six guided picks, deduplicated."""
    chosen: list[tuple[int, str]] = []
    taken: set[int] = set()
    for d, prefix in ((d_load, "dl"), (d_pv, "dpv")):
        order = np.argsort(d, kind="stable")
        mid = (len(order) - 1) // 2
        # candidate orders: max (from the top), median (outwards from the middle), min (from the bottom)
        around_mid = sorted(range(len(order)), key=lambda i: (abs(i - mid), i))
        for name, seq in (("max", order[::-1]), ("median", order[around_mid]), ("min", order)):
            for pos in seq:
                if int(pos) not in taken:
                    taken.add(int(pos))
                    chosen.append((int(pos), f"{prefix}_{name}"))
                    break
    return chosen


def select_scenarios(
    summary: YearSummary,
    *,
    blocks: tuple[int, int],
    selection: Literal["guided", "random"],
    seed: int = 0,
    per_block: int = 6,
) -> ScenarioSet:
    """Pick representative minutes (paper II.A).

    Parameters
    ----------
    summary : per-minute load, PV and centres (``summarize_year``).
    blocks : number of bins on the load axis and on the PV axis.
    selection : "guided" (max/median/min of D_L and D_PV per block) or "random" (``per_block`` at random).
    seed : seed of the random selection.
    per_block : scenarios per block for random selection (guided always tries six).

    Raises
    ------
    TrainingError
        When the year is empty or the block counts are not positive.
    """
    n_load, n_pv = blocks
    if n_load < 1 or n_pv < 1:
        raise TrainingError(f"blocks must be positive, got {blocks}; use e.g. --blocks 5 5")
    if summary.load_kw.size == 0:
        raise TrainingError("the training year has no minutes; check the profiles")
    lb = _bin(summary.load_kw, n_load)
    pb = _bin(summary.pv_kw, n_pv)
    flat = lb * n_pv + pb
    counts = np.bincount(flat, minlength=n_load * n_pv)
    rng = np.random.default_rng(seed)
    order = np.argsort(flat, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)])
    steps: list[int] = []
    block_of: list[int] = []
    kinds: list[str] = []
    for b in np.flatnonzero(counts):
        minutes = order[starts[b] : starts[b + 1]]  # ascending minute order
        if selection == "guided":
            picks = _guided_picks(summary.d_load_ohm[minutes], summary.d_pv_ohm[minutes])
        elif selection == "random":
            chosen = rng.choice(len(minutes), size=min(per_block, len(minutes)), replace=False)
            picks = [(int(p), "random") for p in chosen]
        else:
            raise TrainingError(f"unknown selection {selection!r}; use 'guided' or 'random'")
        for pos, kind in picks:
            steps.append(int(minutes[pos]))
            block_of.append(int(b))
            kinds.append(kind)
    return ScenarioSet(
        steps=np.asarray(steps, int),
        block=np.asarray(block_of, int),
        kind=tuple(kinds),
        blocks=(n_load, n_pv),
        non_empty_blocks=int(np.count_nonzero(counts)),
        minutes_per_block=counts.reshape(n_load, n_pv),
    )


def calendar_cover(n_steps: int, year: int, *, per_cell: int, seed: int, exclude: np.ndarray) -> np.ndarray:
    """Minutes spread over the calendar: ``per_cell`` at random in every (month, local hour of day) cell.

    Beyond the paper. The guided selection picks each (load, PV) block's extremes of ``D_L`` and ``D_PV``: a few
    minutes per block, whatever their hour and season. A customer secondary's voltage follows its own customer's
    load, whose share of the feeder's changes with the hour and the season (archetypes, time shifts); what eq. (5)
    can learn of that share from the calendar features it learns from these minutes, so they are spread evenly
    over the year's hours and months (``training.train.train``'s ``calendar_cover``).

    Parameters
    ----------
    n_steps : minutes in the year; step 0 is local standard midnight of 1 January of ``year``.
    year : the profiles' calendar year (month lengths).
    per_cell : minutes per (month, hour) cell (0: none).
    seed : seed of the random draw.
    exclude : steps already picked (never drawn again).

    Returns
    -------
    (S,) int steps, sorted, at most ``12 * 24 * per_cell``.

    Raises
    ------
    TrainingError
        When ``per_cell`` is negative.
    """
    if per_cell < 0:
        raise TrainingError(f"calendar cover: {per_cell} minutes per cell; use 0 (none) or more")
    if per_cell == 0 or n_steps <= 0:
        return np.zeros(0, int)
    rng = np.random.default_rng(seed)
    taken = set(np.asarray(exclude, int).tolist())
    out: list[int] = []
    first_day = 0
    for month in range(1, 13):
        days = calendar.monthrange(year, month)[1]
        for hour in range(24):
            cand = [s for day in range(first_day, first_day + days) for s in range(day * 1440 + hour * 60,
                                                                                    day * 1440 + hour * 60 + 60)
                    if s < n_steps and s not in taken]
            if cand:
                picks = rng.choice(len(cand), size=min(per_cell, len(cand)), replace=False)
                out.extend(int(cand[i]) for i in picks)
        first_day += days
    return np.asarray(sorted(out), int)
