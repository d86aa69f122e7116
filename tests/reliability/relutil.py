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
