"""``cvvc run``'s recorder supervisor: a recorder that keeps dying is restarted a bounded number of times.

Real child processes (``python -m cvvc --version``, which exits at once, stands in for a recorder that dies);
the parts they leave (none) are joined into one finished file with a gap per restart.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from cvvc.launch import _RecorderSupervisor
from recordings.info import recording_info

pytestmark = pytest.mark.process  # recorders started as programs


def test_a_recorder_that_keeps_dying_is_restarted_at_most_n_times_then_given_up(tmp_path: Path) -> None:
    path = tmp_path / "session.mcap"
    sup = _RecorderSupervisor(lambda part: ["--version"], path, tmp_path, max_restarts=2)
    children = [sup.child]
    deadline = time.monotonic() + 120
    while not sup.gave_up and time.monotonic() < deadline:
        restarted = sup.check()
        if restarted is not None:
            children.append(restarted)
        time.sleep(0.05)
    assert sup.gave_up and sup.restarts == 2
    assert [c.name for c in children] == ["recorder", "recorder.r1", "recorder.r2"]
    assert all(c.proc.wait(timeout=30) == 0 for c in children)
    assert sup.check() is None  # given up: no more restarts
    assert [p.name for p in sup.parts] == ["session.mcap", "session.r1.mcap", "session.r2.mcap"]
    assert all(f"pid {c.proc.pid}) exited with 0" in r for c, r in zip(children, sup.reasons, strict=False))

    gaps = sup.finish()
    assert [g.restart for g in gaps] == [1, 2] and all(g.from_t_ns == g.to_t_ns == -1 for g in gaps)
    info = recording_info(path)
    assert info.complete and info.gaps == gaps and info.messages == 2  # the gap records alone
    assert sorted(p.name for p in tmp_path.glob("*.mcap")) == ["session.mcap"]
