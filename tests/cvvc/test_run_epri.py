"""One short ``cvvc run`` per EPRI feeder through the real bus (real processes, Zenoh, OpenDSS, MCAP).

Case ``local`` (regulators and capacitors as the model states them, PV on IEEE 1547 volt-var): no model is
trained, so each run takes seconds once the feeder's year profiles are made. epri-m1 runs with its substation
LTC, which senses a remote bus.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader

pytestmark = [pytest.mark.process, pytest.mark.slow]  # every test is a ``cvvc run``

REPO = Path(__file__).resolve().parents[2]
STEPS = 12  # minutes from 11:00 on a summer day


def _cvvc(*args: str, cwd: Path, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ if env is None else env, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", "cvvc", *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=600, check=False)


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("epri-cache")


@pytest.mark.parametrize("name", ["epri-k1", "epri-m1", "epri-ckt5", "epri-ckt24"])
def test_short_local_run(tmp_path, cache, name):
    path = REPO / "feeders" / f"{name}.toml"
    work = tmp_path / "cwd"
    work.mkdir()
    proc = _cvvc("run", "--feeder", str(path), "--case", "local", "--days", str(STEPS / 1440),
                 "--start", "2023-07-10T11:00", "--out", str(tmp_path / "out"), "--cache", str(cache),
                 "--no-baseline", "--json", cwd=work)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout)
    assert summary["steps"] == STEPS and summary["lockstep_misses"] == 0 and summary["model"] is None
    mt = summary["metrics"]
    assert mt["steps"] == STEPS and 0.9 < mt["v_min_pu"] <= mt["v_max_pu"] < 1.1
    heads = 0
    with open(summary["recording"], "rb") as f:
        for _, channel, _ in make_reader(f).iter_messages():
            heads += channel.topic == f"cvvc/{name}/meas/head"
    assert heads == STEPS
    assert list(work.iterdir()) == []  # nothing written into the working directory


def test_a_run_without_cache_flag_writes_into_the_user_cache_not_the_cwd(tmp_path):
    work, xdg = tmp_path / "cwd", tmp_path / "xdg"
    work.mkdir()
    env = dict(os.environ, XDG_CACHE_HOME=str(xdg))
    proc = _cvvc("run", "--feeder", str(REPO / "feeders" / "ieee13.toml"), "--case", "none", "--days", str(3 / 1440),
                 "--out", str(tmp_path / "out"), "--no-baseline", "--json", cwd=work, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert list(work.iterdir()) == []
    assert list((xdg / "cvvc-edge" / "profiles").glob("profiles-ieee13-*.npz"))
    assert (xdg / "cvvc-edge" / "ca" / "ca.key").is_file()  # the first run's local CA, apart from the role keys
    assert (xdg / "cvvc-edge" / "security" / "agent.key").is_file()
