"""The bridge's test harness, shared by test_bridge.py and test_publisher_process.py (their fixtures are in
conftest.py): ``run_bridge`` on the session's OpenDSS thread, or ``python -m cvvc bridge`` as a subprocess."""

from __future__ import annotations

import sys
import threading
from pathlib import Path
from typing import Any

from dssthread import Job, run_in_dss_thread

from schemas.bus import BusConfig

FEEDER = "ieee13"
T0 = "2023-07-01T12:00"  # noon: PV has headroom limits, so clipping shows
STEP_NS = 60 * 1_000_000_000


# ------------------------------------------------------------------------------------ the test client
#: Bound on the first frames of a bridge subprocess or publisher process: a fresh interpreter imports (and compiles
#: the feeder) first: seconds when idle, tens of seconds on a loaded 2-core machine. It only bounds a failure.
STARTUP_S = 90.0


def bridge_thread(config: Any, endpoint: str) -> tuple[Job, threading.Event, list[Any]]:
    """``run_bridge`` on the session's OpenDSS thread (``dssthread``); the job's ``out`` gets its summary."""
    from simulator_bridge.bus.bridge import run_bridge

    stop = threading.Event()
    job = run_in_dss_thread(lambda: run_bridge(config, BusConfig(mode="peer", connect=(endpoint,)), stop=stop))
    return job, stop, job.out


def finish(th: Job, stop: threading.Event, out: list[Any], *, stop_now: bool = False) -> Any:
    if stop_now:
        stop.set()
    th.join(timeout=30)
    assert not th.is_alive(), "bridge thread did not finish"
    assert out and not isinstance(out[0], BaseException), out
    return out[0]


def bridge_config(device_map_path: Path, cache_dir: Path, **kw: Any) -> Any:
    from simulator_bridge.bus.bridge import BridgeConfig

    base = dict(device_map_path=str(device_map_path), start=T0, steps=10, clock="lockstep", timeout_s=10.0,
                wait_agent_s=10.0, cache_dir=str(cache_dir), truth_every=0)
    base.update(kw)
    return BridgeConfig(**base)


def bridge_cmd(endpoint: str, device_map_path: Path, cache_dir: Path, *extra: str) -> list[str]:
    """A bridge process on ``endpoint``: ``--insecure`` unless ``extra`` gives its certificates (``--secure-dir``)."""
    security = [] if "--secure-dir" in extra else ["--insecure"]
    return [sys.executable, "-m", "cvvc", "bridge", "--feeder", str(device_map_path), "--connect", endpoint,
            *security, "--cache-dir", str(cache_dir), "--start", T0, "--json", *extra]
