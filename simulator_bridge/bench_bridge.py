"""Bridge speed: lockstep steps per second with a trivial responder, against the bare QSTS engine.

``bench_bridge`` runs, on the same feeder, start and number of 1-minute steps:

* **bare**: ``Qsts.step()`` in a loop (no bus), the reference (best of two runs);
* **lockstep**: ``run_bridge`` in lockstep behind an in-process Zenoh router, with a *trivial responder* in a
  separate process (spawned, plain ``zenoh``): it holds an agent liveliness token and answers every
  control step's head frame, from its subscriber callback, with an empty ``hold`` Decision.

It reports both rates, ``overhead = bare rate / lockstep rate − 1`` (goal: under 20 % on the rural feeder),
and the round trip from the publication of a control step's head frame to the reception of the decision
(p50, p99, measured by the bridge). Run ``python -m simulator_bridge.bench_bridge [STEPS]`` for IEEE 123 and
the rural feeder.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import sys
import time
from pathlib import Path
from typing import Any

__all__ = ["bench_bridge", "main"]

_START = "2023-07-01T06:00"  # local standard time: a summer morning, PV ramping up


def _responder(endpoint: str, feeder_id: str, control_period_s: int, ready: Any, stop: Any) -> None:
    """The trivial agent: answer every control step's head frame with an empty Decision (child process)."""
    import msgspec
    import zenoh

    from schemas import messages as m

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    enc = msgspec.json.Encoder()
    head_dec = msgspec.json.Decoder(m.HeadFrame)
    period_ns = control_period_s * 1_000_000_000
    with zenoh.open(conf) as session:
        pub = session.declare_publisher(f"cvvc/{feeder_id}/agent/decision",
                                        congestion_control=zenoh.CongestionControl.BLOCK,
                                        priority=zenoh.Priority.REAL_TIME, express=True)
        seq = [0]

        def on_head(sample: zenoh.Sample) -> None:
            frame = head_dec.decode(sample.payload.to_bytes())
            if frame.t_ns % period_ns:
                return
            seq[0] += 1
            pub.put(enc.encode(m.Decision(t_ns=frame.t_ns, seq=seq[0], source="bench-responder",
                                          feeder_id=feeder_id, step_t_ns=frame.t_ns, in_reply_to=frame.seq,
                                          status="hold", reason="bench")))

        sub = session.declare_subscriber(f"cvvc/{feeder_id}/meas/head", on_head)
        token = session.liveliness().declare_token(f"cvvc/{feeder_id}/alive/agent/bench")
        ready.set()
        stop.wait(600)
        token.undeclare()
        sub.undeclare()
        pub.undeclare()


def bench_bridge(device_map: str | Path, steps: int, *, seed: int = 1, truth_every: int = 1,
                 cache_dir: str | None = ".cvvc-cache") -> dict:
    """Lockstep bridge vs bare QSTS on ``steps`` 1-minute steps of one feeder.

    Parameters
    ----------
    device_map : the feeder's device map TOML. steps : steps to time (the same for both).
    seed : profile seed. truth_every : the bridge's truth frame decimation (1: every step, as in a run).
    cache_dir : profile cache.

    Returns
    -------
    dict with ``feeder``, ``n_nodes``, ``steps``, ``bare_steps_per_s``, ``lockstep_steps_per_s``,
    ``overhead`` (bare rate / lockstep rate − 1), ``round_trip_p50_ms``, ``round_trip_p99_ms``,
    ``control_steps``, ``lockstep_misses``.
    """
    from schemas.bus import BusConfig, free_port, open_session
    from schemas.devicemap import load_device_map
    from simulator_bridge.bridge import BridgeConfig, cached_profiles, run_bridge, start_step_of
    from simulator_bridge.engine import FeederEngine
    from simulator_bridge.qsts import Qsts

    dm = load_device_map(device_map)
    bare_s = []
    for _ in range(2):  # best of two, each on a fresh engine from the same start (machine noise is large)
        engine = FeederEngine(dm)
        try:
            profiles = cached_profiles(dm, engine, seed=seed, cache_dir=cache_dir)
            start = start_step_of(_START, profiles.start_t_ns, profiles.n_steps, profiles.step_s)
            qsts = Qsts(engine, profiles, start_step=start)
            t = time.perf_counter()
            for _ in range(steps):
                qsts.step()
            bare_s.append(time.perf_counter() - t)
            n_nodes = len(engine.node_names)
        finally:
            engine.close()

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    ctx = mp.get_context("spawn")
    ready, stop = ctx.Event(), ctx.Event()
    with open_session(BusConfig(mode="router", listen=(endpoint,))):
        proc = ctx.Process(target=_responder, args=(endpoint, dm.feeder.name, dm.feeder.control_period_s,
                                                    ready, stop), daemon=True)
        proc.start()
        try:
            if not ready.wait(60):
                raise RuntimeError("bench responder did not start within 60 s")
            config = BridgeConfig(device_map_path=str(device_map), start=_START, steps=steps, clock="lockstep",
                                  timeout_s=5.0, wait_agent_s=10.0, year_seed=seed, truth_every=truth_every,
                                  cache_dir=cache_dir)
            summary = run_bridge(config, BusConfig(mode="peer", connect=(endpoint,)))
        finally:
            stop.set()
            proc.join(10)
            if proc.is_alive():
                proc.terminate()
                proc.join(5)
    bare_rate = steps / min(bare_s)
    return {
        "feeder": dm.feeder.name,
        "n_nodes": n_nodes,
        "steps": steps,
        "bare_steps_per_s": round(bare_rate, 1),
        "lockstep_steps_per_s": round(summary.steps_per_s, 1),
        "overhead": round(bare_rate / summary.steps_per_s - 1.0, 3),
        "round_trip_p50_ms": None if summary.round_trip_p50_s is None else round(1e3 * summary.round_trip_p50_s, 3),
        "round_trip_p99_ms": None if summary.round_trip_p99_s is None else round(1e3 * summary.round_trip_p99_s, 3),
        "control_steps": summary.control_steps,
        "decisions": summary.decisions,
        "lockstep_misses": summary.lockstep_misses,
        "truth_every": truth_every,
    }


def main(argv: list[str] | None = None) -> int:
    """Print the bench for IEEE 123 and the embedded rural feeder (``argv[0]``: steps, default 1440)."""
    from simulator_bridge.cli import DEFAULT_CACHE_ROOT, ensure_default_feeder

    args = sys.argv[1:] if argv is None else argv
    steps = int(args[0]) if args else 1440
    repo = Path(__file__).resolve().parents[1]
    for path in (repo / "feeders" / "ieee123.toml", ensure_default_feeder(DEFAULT_CACHE_ROOT)):
        for truth_every in (1, 0):
            print(json.dumps(bench_bridge(path, steps, truth_every=truth_every)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
