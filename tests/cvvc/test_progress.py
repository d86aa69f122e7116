"""Progress bars (on a real pseudo-terminal, off elsewhere and with ``--quiet``) and bad arguments refused before
the heavy imports."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from cvvc.cli import build_parser
from cvvc.progress import progress_bar, progress_wanted

REPO = Path(__file__).resolve().parents[2]
HEAVY = ("numpy", "zenoh", "matplotlib", "opendssdirect", "scipy", "mcap", "dask", "tqdm", "pandas")


def _terminal() -> tuple[int, int]:
    """A pseudo-terminal of 24 x 120 characters: (master, slave) file descriptors."""
    import fcntl
    import struct
    import termios

    master, slave = os.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 120, 0, 0))
    return master, slave


def _drain(master: int, deadline_s: float = 5.0) -> str:
    """Everything written to the pseudo-terminal so far: a loaded machine hands it over in several reads."""
    import select
    import time

    chunks, end = [], time.monotonic() + deadline_s
    while time.monotonic() < end:
        ready, _, _ = select.select([master], [], [], 0.2)
        if not ready:
            break
        chunks.append(os.read(master, 65536))
    return b"".join(chunks).decode(errors="replace")


def test_the_bar_shows_rate_and_time_left_on_a_terminal(monkeypatch):
    master, slave = _terminal()
    with os.fdopen(slave, "w") as tty:
        monkeypatch.setattr(sys, "stderr", tty)
        bar = progress_bar(100, desc="no control", unit="min")
        assert not bar.disable
        bar.update(40)
        bar.refresh()
        bar.close()
        tty.flush()
        shown = _drain(master)
    os.close(master)
    assert "no control" in shown and "40/100" in shown and "min/s" in shown
    assert "<" in shown  # tqdm's "elapsed<remaining": the time left


def test_the_bar_shows_on_a_terminal_that_gives_no_size(monkeypatch):
    """A pseudo-terminal nobody sized (0 x 0, as under ``script`` or a container's -t): tqdm alone drew nothing."""
    master, slave = os.openpty()
    with os.fdopen(slave, "w") as tty:
        assert os.get_terminal_size(tty.fileno()).columns == 0
        monkeypatch.setattr(sys, "stderr", tty)
        bar = progress_bar(10, desc="training", unit="pf")
        bar.update(3)
        bar.refresh()
        bar.close()
        tty.flush()
        shown = _drain(master)
    os.close(master)
    assert "training" in shown and "3/10" in shown


def test_the_bar_is_off_without_a_terminal_or_when_not_wanted(monkeypatch, tmp_path):
    with (tmp_path / "stderr.txt").open("w") as f:
        monkeypatch.setattr(sys, "stderr", f)
        bar = progress_bar(10, desc="x")
        assert bar.disable
        bar.update(5)
        bar.close()
    assert (tmp_path / "stderr.txt").read_text() == ""
    master, slave = _terminal()
    with os.fdopen(slave, "w") as tty:
        monkeypatch.setattr(sys, "stderr", tty)
        assert progress_bar(10, enabled=False).disable
    os.close(master)


@pytest.mark.parametrize("argv", [["run", "--quiet"], ["run", "--json"], ["evaluate", "--out", "o", "--quiet"],
                                  ["train", "--out", "m.json", "--quiet"]])
def test_quiet_turns_the_bars_off(argv):
    args = build_parser().parse_args(argv)
    assert not progress_wanted(args)
    assert progress_wanted(build_parser().parse_args([a for a in argv if a not in ("--quiet", "--json")]))


_PROBE = """
import sys
from cvvc.cli import main
try:
    code = main(sys.argv[1:])
except SystemExit as e:
    code = e.code
print("EXIT", code, "LOADED", ",".join(m for m in {heavy!r} if m in sys.modules))
"""


@pytest.mark.process  # a fresh interpreter: what a command line imports before it refuses its arguments
@pytest.mark.parametrize(("argv", "says"), [
    (["run", "--case", "nonsense"], "invalid choice: 'nonsense'"),
    (["run", "--bogus"], "unrecognized arguments: --bogus"),
    (["evaluate", "--out", "o", "--jobs", "two"], "invalid int value: 'two'"),
    (["train", "--out", "m.json", "--bogus"], "unrecognized arguments: --bogus"),
    (["record", "--zenoh-mode", "mesh"], "invalid choice: 'mesh'"),
])
def test_bad_arguments_are_refused_before_the_heavy_imports(argv, says, tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-c", _PROBE.format(heavy=HEAVY), *argv], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=60, check=False)
    assert says in proc.stderr, proc.stderr[-2000:]
    assert "EXIT 2 LOADED \n" in proc.stdout, proc.stdout  # nothing heavy was imported to say so
