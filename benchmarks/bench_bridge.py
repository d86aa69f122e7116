"""Bridge speed: lockstep steps per second with a trivial responder, against the bare QSTS engine.

``bench_bridge`` runs, on the same feeder, start and number of 1-minute steps:

* **bare**: ``Qsts.step()`` in a loop (no bus), the reference;
* **lockstep**: ``run_bridge`` in lockstep, with a *trivial responder* in a separate process (spawned, plain
  ``zenoh``, in router mode: the bridge connects to it): it holds an agent liveliness token and answers every
  control step's head frame, from its subscriber callback, with an empty ``hold`` Decision.

It reports both rates, ``overhead = bare rate / lockstep rate − 1`` (goal: under 20 % on the rural feeder),
and the round trip from the publication of a control step's head frame to the reception of the decision
(p50, p99, measured by the bridge). The two are timed alternately, ``repeats`` times, and medians compared.
Run ``python -m benchmarks.bench_bridge [STEPS [PUBLISHER ...]]`` for IEEE 123 and the rural feeder, once per
``BridgeConfig.publisher`` setting (default: ``inline``, then ``process``).
"""

from __future__ import annotations

import json
import multiprocessing as mp
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import msgspec

from benchmarks.results import BridgeBench, Publisher

__all__ = ["bench_bridge", "main"]

_START = "2023-07-01T06:00"  # local standard time: a summer morning, PV ramping up


def _responder(endpoint: str, feeder_id: str, control_period_s: int, ready: Any, stop: Any) -> None:
    """The trivial agent: answer every control step's head frame with an empty Decision (child process).

    Its session is the router the bridge connects to, as a launcher's would be: the bridge process holds only
    the bridge.
    """
    import zenoh

    from schemas import messages as m

    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
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


def bench_bridge(device_map: str | Path, steps: int, *, seed: int = 1, truth_every: int = 1, repeats: int = 3,
                 cache_dir: str | None = None, publisher: Publisher = "auto") -> BridgeBench:
    """Lockstep bridge vs bare QSTS on ``steps`` 1-minute steps of one feeder.

    The two are timed alternately ``repeats`` times (bare, bridge, bare, bridge, ...) on fresh engines from the
    same start, and the medians are compared: the machine is shared and its speed drifts by tens of percent.

    Parameters
    ----------
    device_map : the feeder's device map TOML. steps : steps to time (the same for both).
    seed : profile seed. truth_every : the bridge's truth frame decimation (1: every step, as in a run).
    repeats : alternations. cache_dir : profile cache. publisher : ``BridgeConfig.publisher``.

    Returns
    -------
    BridgeBench
        ``feeder``, ``n_nodes``, ``steps``, ``bare_steps_per_s``, ``lockstep_steps_per_s`` (medians),
        ``overhead`` (median bare rate / median lockstep rate − 1), ``overheads`` (per alternation),
        ``overhead_cpu`` (median CPU time of the bridge process's loop, Zenoh's threads included / median bare
        CPU time − 1), ``overhead_thread_cpu`` (the same for the stepping thread alone), ``publisher_cpu_share``
        (median CPU time of the publisher process from its first step on / median bare CPU time; 0 when
        publishing inline), ``decision_wait_share`` (the stepping thread's waits for the decisions / median bare
        time: their part of ``overhead``), ``round_trip_p50_ms``, ``round_trip_p99_ms`` (medians over the
        runs), ``control_steps``, ``lockstep_misses`` (total).
    """
    from schemas.bus import free_port
    from schemas.devicemap import load_device_map

    dm = load_device_map(device_map)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    ctx = mp.get_context("spawn")
    ready, stop = ctx.Event(), ctx.Event()
    bare, bare_cpu, runs = [], [], []
    proc = ctx.Process(target=_responder, args=(endpoint, dm.feeder.name, dm.feeder.control_period_s, ready, stop),
                       daemon=True)
    proc.start()
    try:
        if not ready.wait(60):
            raise RuntimeError("bench responder did not start within 60 s")
        for _ in range(repeats):
            wall, cpu, n_nodes = _bare_times(dm, steps, seed=seed, cache_dir=cache_dir)
            bare.append(steps / wall)
            bare_cpu.append(cpu)
            runs.append(_bridge_run(device_map, endpoint, steps, seed=seed, truth_every=truth_every,
                                    cache_dir=cache_dir, publisher=publisher))
    finally:
        stop.set()
        proc.join(10)
        if proc.is_alive():
            proc.terminate()
            proc.join(5)
    lock = [r.steps_per_s for r in runs]
    bare_s = steps / statistics.median(bare)  # median bare wall time [s]
    p50 = [r.round_trip_p50_s for r in runs if r.round_trip_p50_s is not None]
    p99 = [r.round_trip_p99_s for r in runs if r.round_trip_p99_s is not None]
    return BridgeBench(
        feeder=dm.feeder.name,
        n_nodes=n_nodes,
        steps=steps,
        bare_steps_per_s=round(statistics.median(bare), 1),
        lockstep_steps_per_s=round(statistics.median(lock), 1),
        overhead=round(statistics.median(bare) / statistics.median(lock) - 1.0, 3),
        overheads=[round(b / x - 1.0, 3) for b, x in zip(bare, lock, strict=True)],
        overhead_cpu=round(statistics.median(r.cpu_s for r in runs) / statistics.median(bare_cpu) - 1.0, 3),
        overhead_thread_cpu=round(statistics.median(r.thread_cpu_s for r in runs) / statistics.median(bare_cpu)
                                  - 1.0, 3),
        publisher_cpu_share=round(statistics.median(r.publisher_cpu_s for r in runs)
                                  / statistics.median(bare_cpu), 3),
        decision_wait_share=round(statistics.median(r.decision_wait_s for r in runs) / bare_s, 3),
        round_trip_p50_ms=round(1e3 * statistics.median(p50), 3) if p50 else None,
        round_trip_p99_ms=round(1e3 * statistics.median(p99), 3) if p99 else None,
        control_steps=runs[0].control_steps,
        decisions=sum(r.decisions for r in runs),
        lockstep_misses=sum(r.lockstep_misses for r in runs),
        truth_every=truth_every,
        publisher=publisher,
        publisher_used=runs[0].publisher,  # what "auto" chose
    )


def _bare_times(dm: Any, steps: int, *, seed: int, cache_dir: str | None) -> tuple[float, float, int]:
    """Wall and CPU time [s] of ``steps`` ``Qsts.step()`` alone on a fresh engine, and the feeder's node count."""
    from simulator_bridge.bus.bridge import cached_profiles, start_step_of
    from simulator_bridge.opendss.engine import FeederEngine
    from simulator_bridge.simulation.qsts import Qsts

    engine = FeederEngine(dm)
    try:
        profiles = cached_profiles(dm, engine, seed=seed, cache_dir=cache_dir)
        start = start_step_of(_START, profiles.start_t_ns, profiles.n_steps, profiles.step_s)
        qsts = Qsts(engine, profiles, start_step=start)
        t, cpu = time.perf_counter(), time.process_time()
        for _ in range(steps):
            qsts.step()
        return time.perf_counter() - t, time.process_time() - cpu, len(engine.node_names)
    finally:
        engine.close()


def _bridge_run(device_map: str | Path, endpoint: str, steps: int, *, seed: int, truth_every: int,
                cache_dir: str | None, publisher: Publisher) -> Any:
    from schemas.bus import BusConfig
    from simulator_bridge.bus.bridge import BridgeConfig, run_bridge

    config = BridgeConfig(device_map_path=str(device_map), start=_START, steps=steps, clock="lockstep",
                          timeout_s=5.0, wait_agent_s=10.0, year_seed=seed, truth_every=truth_every,
                          cache_dir=cache_dir, publisher=publisher)
    return run_bridge(config, BusConfig(mode="peer", connect=(endpoint,)))


def main(argv: list[str] | None = None) -> int:
    """Print the bench for IEEE 123 and the embedded rural feeder (``argv[0]``: steps, default 1440; ``argv[1:]``:
    publisher settings, default ``inline process``).
    """
    from schemas.cache import cache_root
    from simulator_bridge.rural.default_feeder import ensure_default_feeder

    args = sys.argv[1:] if argv is None else argv
    steps = int(args[0]) if args else 1440
    known: dict[str, Publisher] = {"auto": "auto", "inline": "inline", "process": "process"}
    if bad := [a for a in args[1:] if a not in known]:
        print(f"unknown publisher(s) {bad}: choose from {sorted(known)}", file=sys.stderr)
        return 2
    publishers = [known[a] for a in args[1:]] or ["inline", "process"]
    repo = Path(__file__).resolve().parents[1]
    for path in (repo / "feeders" / "ieee123.toml", ensure_default_feeder(cache_root(None))):
        for truth_every in (1, 0):
            for publisher in publishers:
                print(json.dumps(msgspec.to_builtins(bench_bridge(path, steps, truth_every=truth_every,
                                                                    publisher=publisher))), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
