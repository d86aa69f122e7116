"""QSTS speed: steps per second of :class:`Qsts` against bare OpenDSS solves of the same steps.

``bench_qsts`` builds the feeder and a profile year, settles the regulators with a few untimed QSTS
steps (the first minutes from tap 0 are dominated by tap moves), then times, in the same process and
on the same rows:

* **qsts**: ``Qsts.step()`` — set loads and PV (Q per the local default), solve, read every field
  device and every node voltage, regulator local control (extra solves after tap moves);
* **bare**: ``FeederEngine.bare_steps_s`` — per row set loads and PV output, set the taps and capacitor
  states (every RegControl and CapControl of the model) the QSTS ended that step with (replayed, so both pay
  OpenDSS's costly re-factorisation after a move), solve; nothing else. The QSTS also solves once more per
  instant at which a device acted inside the step (its event clock), which bare does not.

``ratio = qsts time / bare time`` (best of a few alternating repeats); the goal is under 1.3.
Profile generation is timed separately.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from benchmarks.results import QstsBench, to_json
from schemas.devicemap import load_device_map
from simulator_bridge.opendss.engine import FeederEngine
from simulator_bridge.simulation.profiles import make_profiles, month_steps
from simulator_bridge.simulation.qsts import Qsts

__all__ = ["bench_qsts"]


def bench_qsts(device_map_path: str | Path, steps: int, *, seed: int = 1, month: int = 7,
               start_hour: float = 6.0, warmup_steps: int = 10, repeats: int = 3) -> QstsBench:
    """Measure QSTS steps/s for one feeder and the ratio to bare OpenDSS solves of the same steps.

    The window is run ``repeats`` times, QSTS and bare alternating, each from the same taps; the best
    time of each is kept (the machine is shared: the minimum is the least disturbed measurement).

    Parameters
    ----------
    device_map_path : the feeder's device map (TOML).
    steps : timed steps (1 minute each).
    seed : profile seed. month, start_hour : where in the year the timed window starts [local time].
    warmup_steps : untimed QSTS steps before the window (regulators settle from tap 0).
    repeats : runs of the window for each of QSTS and bare.

    Returns
    -------
    QstsBench
        ``feeder``, ``n_nodes``, ``steps``, ``qsts_steps_per_s``, ``bare_steps_per_s``, ``ratio`` (best qsts
        time / best bare time), ``tap_changes`` and ``cap_switches`` (the map's devices, in the window),
        ``qsts_s`` and ``bare_s`` (every repeat's time [s]), ``compile_s``, ``profiles_s``.
    """
    dm = load_device_map(device_map_path)
    t = time.perf_counter()
    engine = FeederEngine(dm)
    compile_s = time.perf_counter() - t
    t = time.perf_counter()
    profiles = make_profiles(seed=seed, load_kw_nominal=engine.load_kw_nominal, pv_pmpp_kw=engine.pv_pmpp_kw,
                             load_distance_ohm=engine.load_distance_ohm)
    profiles_s = time.perf_counter() - t
    start = month_steps(profiles, month).start + int(start_hour * 3600 // profiles.step_s)
    stop = min(start + warmup_steps + steps, profiles.n_steps)
    warm = Qsts(engine, profiles, start_step=start, chunk_steps=stop - start)
    for _ in range(warmup_steps):
        warm.step()
    window = range(start + warmup_steps, stop)
    taps0, caps0 = engine.control_taps(), engine.control_cap_states()
    load_kw = np.asarray(profiles.load_kw(window.start, window.stop), dtype=float)
    pv_kw = np.clip(np.asarray(profiles.pv_kw(window.start, window.stop), dtype=float), 0.0, engine.pv_pmpp_kw)

    qsts_s, bare_s = [], []
    tap_changes = cap_switches = 0
    for _ in range(repeats):
        _restore(engine, taps0, caps0)
        qsts = Qsts(engine, profiles, start_step=window.start, chunk_steps=len(window))
        taps = np.empty((len(window), len(taps0)), dtype=int)
        caps = np.empty((len(window), len(caps0)), dtype=int)
        tap_changes = cap_switches = 0
        t = time.perf_counter()
        for j in range(len(window)):
            res = qsts.step()
            taps[j], caps[j] = engine.control_taps(), engine.control_cap_states()
            tap_changes += int(res.tap_changes.sum())
            cap_switches += int(res.cap_switches.sum())
        qsts_s.append(time.perf_counter() - t)
        _restore(engine, taps0, caps0)
        bare_s.append(engine.bare_steps_s(load_kw, pv_kw, taps, caps))
    engine.close()
    n = len(window)
    return QstsBench(
        feeder=dm.feeder.name,
        n_nodes=len(engine.node_names),
        steps=n,
        qsts_steps_per_s=n / min(qsts_s),
        bare_steps_per_s=n / min(bare_s),
        ratio=min(qsts_s) / min(bare_s),
        tap_changes=tap_changes,
        cap_switches=cap_switches,
        qsts_s=qsts_s,
        bare_s=bare_s,
        compile_s=compile_s,
        profiles_s=profiles_s,
    )


def _restore(engine: FeederEngine, taps: np.ndarray, caps: np.ndarray) -> None:
    for r, tap in enumerate(taps):
        engine.set_control_tap(r, int(tap))
    for j, n in enumerate(caps):
        engine.set_control_cap_state(j, int(n))


if __name__ == "__main__":  # pragma: no cover - manual use: python -m benchmarks.bench_qsts MAP STEPS
    import sys

    print(to_json(bench_qsts(sys.argv[1], int(sys.argv[2]))))
