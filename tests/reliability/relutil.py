"""Helpers of the reliability tests: real child processes, a bus watcher, plain sessions, /proc memory."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh

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
        p = Proc(f"{self._n:02d}-{name}", [*args, "--connect", self.endpoint], self.log_dir)
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


class Watcher:
    """A plain-zenoh peer that decodes every sample of the feeder (and its liveliness) as it arrives."""

    def __init__(self, endpoint: str) -> None:
        from schemas.bus import BadMessage, codec_for
        from schemas.keys import message_type_for_key

        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        self.session = zenoh.open(conf)
        self._cond = threading.Condition()
        self.seen: list[tuple[str, Any, float]] = []
        self.alive: dict[str, bool] = {}
        self.undecodable = 0
        self.skip: tuple[str, ...] = ()  # key substrings not to keep (floods that tests send themselves)

        def on_sample(s: zenoh.Sample) -> None:
            key = str(s.key_expr)
            mtype = message_type_for_key(key)
            if mtype is None or any(part in key for part in self.skip):
                return
            try:
                msg = codec_for(mtype).decode(s.payload.to_bytes())
            except BadMessage:  # the fuzzers' own garbage, seen here too
                with self._cond:
                    self.undecodable += 1
                return
            with self._cond:
                self.seen.append((key, msg, time.monotonic()))
                self._cond.notify_all()

        def on_alive(s: zenoh.Sample) -> None:
            with self._cond:
                self.alive[str(s.key_expr)] = s.kind == zenoh.SampleKind.PUT
                self._cond.notify_all()

        self._sub = self.session.declare_subscriber(f"cvvc/{FEEDER}/**", on_sample)
        self._live = self.session.liveliness().declare_subscriber(f"cvvc/{FEEDER}/alive/**", on_alive,
                                                                  history=True)

    def messages(self, msg_type: type, pred: Callable[[Any], bool] = lambda x: True) -> list[Any]:
        with self._cond:
            return [x for _, x, _ in self.seen if isinstance(x, msg_type) and pred(x)]

    def wait(self, pred: Callable[[], Any], timeout_s: float, what: str) -> Any:
        """Wait until ``pred()`` is truthy (re-checked on every sample); its value, or AssertionError."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                value = pred()
                if value:
                    return value
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
                self._cond.wait(min(remaining, 0.1))

    def first(self, msg_type: type, pred: Callable[[Any], bool], timeout_s: float, what: str) -> Any:
        """The first message of ``msg_type`` (seen so far or to come) for which ``pred`` holds."""
        def find() -> Any:
            for _, x, _ in self.seen:
                if isinstance(x, msg_type) and pred(x):
                    return x
            return None
        return self.wait(find, timeout_s, what)

    def is_alive(self, key: str) -> bool:
        with self._cond:
            return self.alive.get(key, False)

    def close(self) -> None:
        self._sub.undeclare()
        self._live.undeclare()
        self.session.close()


def plain_session(endpoint: str, mode: str = "peer") -> zenoh.Session:
    """A plain-zenoh session (what an attacker or a broken device would use); a client routes everything
    through the router (one link: no route change while it sends).
    """
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if mode != "client":
        conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    return zenoh.open(conf)


def rss_kib(pid: int, field: str = "VmRSS") -> int:
    """``VmRSS`` / ``VmHWM`` of a process from /proc [KiB]."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"no {field} in /proc/{pid}/status")
