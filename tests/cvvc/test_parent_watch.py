"""A process `cvvc run` starts ends when its launcher is killed outright, and finishes cleanly."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader

from cvvc.parent_watch import PARENT_ENV, watch_parent
from schemas.bus import free_port

REPO = Path(__file__).resolve().parents[2]

# a launcher standing in for `cvvc run`: starts a recorder as its child, as cvvc.launch does, prints its pid, waits
_LAUNCHER = """
import os, subprocess, sys, time
out, endpoint = sys.argv[1], sys.argv[2]
child = subprocess.Popen([sys.executable, "-m", "cvvc", "record", "--out", out, "--listen", endpoint, "--insecure"],
                         env=dict(os.environ, CVVC_PARENT_PID=str(os.getpid())), stdin=subprocess.DEVNULL)
print(child.pid, flush=True)
time.sleep(600)
"""


def _ended(pid: int) -> bool:
    """Gone, or a zombie nobody has reaped yet."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except FileNotFoundError:
        return True


@pytest.mark.process
def test_a_child_ends_cleanly_once_its_launcher_is_killed(tmp_path: Path) -> None:
    out = tmp_path / "session.mcap"
    launcher = subprocess.Popen([sys.executable, "-c", _LAUNCHER, str(out), f"tcp/127.0.0.1:{free_port()}"],
                                stdout=subprocess.PIPE, text=True, cwd=REPO,
                                env=dict(os.environ, PYTHONPATH=str(REPO)))
    child = None
    try:
        child = int(launcher.stdout.readline())
        deadline = time.monotonic() + 30
        while not out.exists() and time.monotonic() < deadline:  # the recorder is up once its file is open
            time.sleep(0.1)
        assert out.exists(), "the recorder did not start"
        assert not _ended(child)
        launcher.kill()  # SIGKILL: the launcher cannot stop its child
        launcher.wait(timeout=10)
        deadline = time.monotonic() + 20
        while not _ended(child) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert _ended(child), "the recorder outlived its launcher"
    finally:
        if launcher.poll() is None:
            launcher.kill()
            launcher.wait(timeout=10)
        launcher.stdout.close()
        if child is not None and not _ended(child):
            os.kill(child, 9)
    with open(out, "rb") as f:  # ended on SIGTERM: the file is finished (summary and footer written)
        assert make_reader(f).get_summary() is not None


def test_the_launchers_id_is_taken_out_of_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """A process the child starts must not take the child's launcher for its own."""
    assert watch_parent() is None  # no launcher named: nothing watched
    monkeypatch.setenv(PARENT_ENV, str(os.getppid()))
    thread = watch_parent(period_s=0.05)
    assert thread is not None and PARENT_ENV not in os.environ
    time.sleep(0.2)
    assert thread.is_alive()  # still this process's parent: no signal
