"""Our local device physics against OpenDSS's own control loop, on the same circuit and per-minute loads.

``python -m simulator_bridge.opendss.control_check MAP.toml [--minutes 1440] [--step-s 1] [--low 0.3 --high 1.1]``
runs a day of a sinusoidal load multiplier (``low`` at 04:00, ``high`` at 16:00; every load scaled, PV at 0)
through :class:`~simulator_bridge.simulation.qsts.Qsts` and through
:func:`~simulator_bridge.opendss.opendss_loop.opendss_control_loop`
(OpenDSS steps of ``step_s``, loads held per minute), and prints, per RegControl and CapControl, the
position changes seen minute by minute on each side and the largest offset, in minutes, between matching
changes. A device *matches* when both sides make the same sequence of positions, each change within
one minute of the other's.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schemas.devicemap import DeviceMap, load_device_map
from simulator_bridge.opendss.engine import FeederEngine
from simulator_bridge.opendss.opendss_loop import opendss_control_loop
from simulator_bridge.simulation.qsts import Qsts

__all__ = ["ControlComparison", "DeviceComparison", "MinuteProfiles", "compare_with_opendss", "day_multiplier"]

_NS = 1_000_000_000
_DAY0_NS = 1_704_067_200 * _NS  # 2024-01-01 00:00 UTC: minute 0 is midnight (the time-type CapControl's clock)


class MinuteProfiles:
    """Per-minute load rows and PV available power [kW] (PV at 0 unless ``pv_kw`` is given) with the interface
    ``Qsts`` and ``opendss_loop.reference_metrics`` read; minute 0 at ``start_t_ns``.
    """

    def __init__(self, load_kw: np.ndarray, n_pv: int, *, start_t_ns: int = _DAY0_NS,
                 pv_kw: np.ndarray | None = None) -> None:
        self._load = np.asarray(load_kw, dtype=float)
        self.n_steps, self.n_loads = self._load.shape
        self.n_pv, self.step_s, self.start_t_ns = n_pv, 60, start_t_ns
        self._pv = np.zeros((self.n_steps, n_pv)) if pv_kw is None else np.asarray(pv_kw, dtype=float)
        if self._pv.shape != (self.n_steps, n_pv):
            raise ValueError(f"pv_kw has shape {self._pv.shape}, expected ({self.n_steps}, {n_pv})")

    def t_ns(self, step: int) -> int:
        """Time of minute ``step`` [ns since the UTC epoch]."""
        return self.start_t_ns + step * 60 * _NS

    def load_kw(self, start: int, stop: int) -> np.ndarray:
        """(stop - start, n_loads) every load's active power for minutes ``start..stop-1`` [kW]."""
        return self._load[start:stop]

    def pv_kw(self, start: int, stop: int) -> np.ndarray:
        """(stop - start, n_pv) every plant's available AC power for minutes ``start..stop-1`` [kW]."""
        return self._pv[start:stop]


def day_multiplier(n_minutes: int, low: float, high: float) -> np.ndarray:
    """(n_minutes,) a sinusoidal load multiplier: ``low`` at 04:00, ``high`` at 16:00 (minute 0 = midnight)."""
    m = np.arange(n_minutes)
    return low + (high - low) * 0.5 * (1.0 - np.cos(2.0 * np.pi * (m - 240) / 1440.0))


@dataclass(frozen=True)
class DeviceComparison:
    """One device's positions minute by minute, ours against OpenDSS's.

    ``changes_ours``/``changes_opendss``: position changes summed over minutes (|Δ| per minute);
    ``same_sequence``: both make the same sequence of positions; ``max_offset_min``: largest offset between
    matching changes [min] (``-1`` when the sequences differ).
    """

    name: str
    kind: str  # "regcontrol" | "capcontrol"
    changes_ours: int
    changes_opendss: int
    same_sequence: bool
    max_offset_min: int

    @property
    def matches(self) -> bool:
        """The same sequence of positions, each change at most one minute apart."""
        return self.same_sequence and self.max_offset_min <= 1


@dataclass(frozen=True)
class ControlComparison:
    """The whole run: every device, and the per-minute positions of both sides."""

    devices: tuple[DeviceComparison, ...]
    taps_ours: np.ndarray
    taps_opendss: np.ndarray
    caps_ours: np.ndarray
    caps_opendss: np.ndarray
    step_s: float
    ours_s: float
    opendss_s: float


def _changes(x: np.ndarray, x0: int) -> tuple[list[int], list[int]]:
    """(minutes at which the position changed, the positions after each change)."""
    prev = np.concatenate([[x0], x[:-1]])
    idx = np.flatnonzero(x != prev)
    return idx.tolist(), x[idx].tolist()


def _compare(name: str, kind: str, ours: np.ndarray, ref: np.ndarray, x0: int) -> DeviceComparison:
    mo, vo = _changes(ours, x0)
    mr, vr = _changes(ref, x0)
    same = vo == vr
    offset = max((abs(a - b) for a, b in zip(mo, mr, strict=True)), default=0) if same else -1
    n_ours = int(np.abs(np.diff(np.concatenate([[x0], ours]))).sum())
    n_ref = int(np.abs(np.diff(np.concatenate([[x0], ref]))).sum())
    return DeviceComparison(name, kind, n_ours, n_ref, same, offset)


def compare_with_opendss(device_map: DeviceMap, load_kw: np.ndarray, *, step_s: float = 1.0) -> ControlComparison:
    """Run ``load_kw`` (n_minutes, n_loads) through ``Qsts`` and OpenDSS's own loop; compare every device."""
    import time

    eng = FeederEngine(device_map)
    try:
        taps0, caps0 = eng.control_taps(), eng.control_cap_states()
        q = Qsts(eng, MinuteProfiles(load_kw, len(eng.pv_ids)), start_step=0, settle_s=0)
        n = len(load_kw)
        taps = np.zeros((n, len(taps0)), dtype=int)
        caps = np.zeros((n, len(caps0)), dtype=int)
        t = time.perf_counter()
        for m in range(n):
            q.step()
            taps[m], caps[m] = eng.control_taps(), eng.control_cap_states()
        ours_s = time.perf_counter() - t
        regs, ccs = eng.reg_controls, eng.cap_controls
    finally:
        eng.close()
    ref = opendss_control_loop(device_map, load_kw, step_s=step_s)
    devices = [_compare(r.name, "regcontrol", taps[:, i], ref.taps[:, i], int(taps0[i])) for i, r in enumerate(regs)]
    devices += [_compare(c.name, "capcontrol", caps[:, j], ref.cap_states[:, j], int(caps0[j]))
                for j, c in enumerate(ccs)]
    return ControlComparison(tuple(devices), taps, ref.taps, caps, ref.cap_states, step_s, ours_s, ref.elapsed_s)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m simulator_bridge.opendss.control_check",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("device_map", type=Path)
    ap.add_argument("--minutes", type=int, default=1440)
    ap.add_argument("--step-s", type=float, default=1.0, help="OpenDSS's time step [s], a divisor of 60")
    ap.add_argument("--low", type=float, default=0.3, help="load multiplier at 04:00")
    ap.add_argument("--high", type=float, default=1.1, help="load multiplier at 16:00")
    args = ap.parse_args(argv)
    dm = load_device_map(args.device_map)
    eng = FeederEngine(dm)
    base = eng.load_kw_nominal.copy()
    eng.close()
    load = day_multiplier(args.minutes, args.low, args.high)[:, None] * base[None, :]
    res = compare_with_opendss(dm, load, step_s=args.step_s)
    print(f"{dm.feeder.name}: {args.minutes} min, multiplier {args.low}-{args.high}, OpenDSS step {args.step_s:g} s; "
          f"ours {res.ours_s:.1f} s, OpenDSS {res.opendss_s:.1f} s")
    print(f"{'device':<28}{'kind':<12}{'ours':>6}{'OpenDSS':>9}{'same seq':>10}{'max offset':>12}")
    for d in res.devices:
        print(f"{d.name:<28}{d.kind:<12}{d.changes_ours:>6}{d.changes_opendss:>9}{str(d.same_sequence):>10}"
              f"{d.max_offset_min:>12}")
    print(f"all match: {all(d.matches for d in res.devices)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
