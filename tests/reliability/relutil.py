"""Helpers of the reliability tests: real child processes, a bus watcher, plain sessions, /proc memory."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

from benchmarks.fuzz_live import Watcher, plain_session  # noqa: F401  (re-exported for the tests)

REPO = Path(__file__).resolve().parents[2]
FEEDER_MAP = REPO / "feeders" / "ieee13.toml"
FEEDER = "ieee13"
NOON = "2023-07-01T12:00"  # PV produces: plants have headroom and are commanded


class Proc:
    """One ``python -m cvvc`` child process with its log file; stopped or killed by its pid."""

    def __init__(self, name: str, args: list[str], log_dir: Path) -> None:
        self.name = name
        self.log_path = log_dir / f"{name}.log"
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen([sys.executable, "-m", "cvvc", *args], cwd=REPO, stdout=log,
                                         stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                         env={**os.environ, "PYTHONUNBUFFERED": "1"})

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def stop(self, timeout_s: float = 20.0) -> int:
        """SIGINT, wait, then SIGKILL; returns the exit status."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        return int(self.proc.returncode)

    def kill(self) -> None:
        """SIGKILL now (the fault under test) and reap."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=10)


class Procs:
    """Starts children for one test and stops every one still running at the end."""

    def __init__(self, log_dir: Path, endpoint: str, model: Path | None, cache: Path) -> None:
        self.log_dir, self.endpoint, self.model, self.cache = log_dir, endpoint, model, cache
        self.children: list[Proc] = []
        self._n = 0

    def start(self, name: str, args: list[str]) -> Proc:
        self._n += 1
        # --insecure (a plain router) unless the test gives the child its certificates (--secure-dir)
        security = [] if "--secure-dir" in args else ["--insecure"]
        p = Proc(f"{self._n:02d}-{name}", [*args, "--connect", self.endpoint, *security], self.log_dir)
        self.children.append(p)
        return p

    def agent(self, *extra: str, stale_after_s: float = 2.0) -> Proc:
        return self.start("agent", ["agent", "--model", str(self.model), "--feeder-id", FEEDER,
                                    "--stale-after-s", str(stale_after_s), *extra])

    def bridge(self, *extra: str, start: str = NOON) -> Proc:
        return self.start("bridge", ["bridge", "--feeder", str(FEEDER_MAP), "--cache-dir", str(self.cache),
                                     "--start", start, "--truth-every", "0", *extra])

    def recorder(self, out: Path, *extra: str) -> Proc:
        return self.start("recorder", ["record", "--out", str(out), "--keys", f"cvvc/{FEEDER}/**", *extra])

    def close(self) -> None:
        for p in self.children:
            p.stop(timeout_s=15.0)


def rss_kib(pid: int, field: str = "VmRSS") -> int:
    """``VmRSS`` / ``VmHWM`` of a process from /proc [KiB]."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"no {field} in /proc/{pid}/status")


class Attack:
    """One attack on a secure lockstep window: ``arm`` runs once the agent is up and before the bridge starts, with
    the attacker's open session (declare publishers and subscribers, put what goes before the run); callbacks do what
    goes during it. ``sent`` counts what was put, by kind."""

    def __init__(self) -> None:
        self.sent: dict[str, int] = {}

    def arm(self, forger) -> None:  # a zenoh.Session
        raise NotImplementedError

    def count(self, kind: str, n: int = 1) -> None:
        self.sent[kind] = self.sent.get(kind, 0) + n

    def close(self) -> None:
        """Stop what the attack started (threads, connections); called once the window is over."""


def secure_window(tmp: Path, model: Path, cache: Path, sec: Path, *, steps: int, attacks: tuple[Attack, ...] = (),
                  attacker_role: str = "devices", sunspec: dict[str, str] | None = None) -> dict:
    """One lockstep window of IEEE 13 from ``NOON`` in the default (secure) mode: a router with the access policy on
    a free loopback port, the agent (with the device map) and a lockstep bridge as processes with their certificates
    of ``sec``, and, when ``attacks`` are given, an attacker's session holding the ``attacker_role`` certificate.
    ``sunspec`` (plant -> ``tcp/127.0.0.1:PORT``): those plants behind the bridge's simulated SunSpec inverters, each
    read and commanded by its ``cvvc adapter sunspec`` process (``cvvc run --pv-protocol sunspec``'s flags).
    Returns the agent's, the bridge's and the adapters' own summaries (``agent``, ``bridge``, ``links`` by plant)
    and each attack's ``sent`` counts.
    """
    import json

    import zenoh

    from cvvc import pv_protocol as pvp
    from schemas.bus import BusConfig, free_port, open_session, wait_for, zenoh_config
    from schemas.devicemap import load_device_map

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs = Procs(tmp, endpoint, model, cache)
    secure = ["--secure-dir", str(sec)]
    sunspec = sunspec or {}
    try:
        with open_session(BusConfig(mode="router", listen=(endpoint,), tls_dir=str(sec), role="router")), \
                zenoh.open(zenoh_config(BusConfig(connect=(endpoint,), tls_dir=str(sec),
                                                  role=attacker_role))) as forger:
            agent = procs.start("agent", ["agent", "--model", str(model), "--feeder-id", FEEDER,
                                          "--feeder", str(FEEDER_MAP), "--summary-out", str(tmp / "agent.json"),
                                          *secure])
            probe = forger.declare_publisher(f"cvvc/{FEEDER}/meas/pv/pv675")  # the agent subscribes to meas/**
            assert wait_for(lambda: bool(probe.matching_status.matching), 60.0), agent.log()[-2000:]
            dm = load_device_map(FEEDER_MAP)
            adapters = [procs.start(f"adapter.{pid}", pvp.adapter_args(
                dm, FEEDER, pid, ep, volt_var=False, connect=secure, summary_out=str(tmp / f"adapter.{pid}.json")))
                for pid, ep in sunspec.items()]
            for attack in attacks:
                attack.arm(forger)
            bridge = procs.start("bridge", ["bridge", "--feeder", str(FEEDER_MAP), "--cache-dir", str(cache),
                                            "--start", NOON, "--truth-every", "0", "--lockstep", "--timeout-s", "5",
                                            "--steps", str(steps), "--wait-agent-s", "60",
                                            "--summary-out", str(tmp / "bridge.json"), *pvp.bridge_args(sunspec),
                                            *secure])
            assert wait_for(lambda: not bridge.alive(), 240.0), bridge.log()[-2000:]
            assert bridge.proc.returncode == 0, bridge.log()[-2000:]
            for attack in attacks:
                attack.close()
            assert agent.stop() == 0, agent.log()[-2000:]
            for adapter in adapters:
                assert adapter.stop() == 0, adapter.log()[-2000:]
        return {"agent": json.loads((tmp / "agent.json").read_text()),
                "bridge": json.loads((tmp / "bridge.json").read_text()),
                "links": {pid: json.loads((tmp / f"adapter.{pid}.json").read_text()) for pid in sunspec},
                "sent": {type(a).__name__: dict(a.sent) for a in attacks}}
    finally:
        for attack in attacks:
            attack.close()
        procs.close()
