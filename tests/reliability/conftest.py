"""Fixtures of the reliability tests: a trained IEEE 13 model, its profiles, real processes, a bus watcher.

Every process is ``python -m cvvc ...`` started with ``subprocess`` (a fresh interpreter, never a fork),
connected to the router of the root ``router_endpoint`` fixture, logging to a file under ``tmp_path``, and
stopped by its pid (SIGINT, then SIGKILL) when the test ends. The watcher is a plain-zenoh peer that
decodes everything under ``cvvc/ieee13/**`` with the typed codecs; tests wait on it with deadlines.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from relutil import FEEDER_MAP, REPO, Procs, Watcher

from tests.yearcache import cache_year_profiles


@pytest.fixture(scope="session")
def rel_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """IEEE 13 profiles (year seed 1) generated once per session into a temporary cache."""
    return cache_year_profiles(FEEDER_MAP, tmp_path_factory.mktemp("rel-cache"))


@pytest.fixture(scope="session")
def model13(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A model of IEEE 13 trained once per session with ``cvvc train`` (about 5 s)."""
    out = tmp_path_factory.mktemp("rel-model") / "ieee13-model.json"
    proc = subprocess.run([sys.executable, "-m", "cvvc", "train", "--feeder", str(FEEDER_MAP), "--out", str(out),
                           "--json", "--workers", "1"], cwd=REPO, capture_output=True, text=True, timeout=300)
    if proc.returncode != 0 or not out.is_file():
        raise RuntimeError(f"cvvc train failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    return out


@pytest.fixture(scope="session")
def secure_certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A CA and the role certificates it issued (agent, devices, recorder, router), made once per session."""
    from schemas.security import init_ca, init_security_dir

    tmp = tmp_path_factory.mktemp("rel-security")
    init_ca(tmp / "ca")
    init_security_dir(tmp / "security", ca_dir=tmp / "ca")
    return tmp / "security"


@pytest.fixture
def procs(tmp_path: Path, router_endpoint: str, model13: Path, rel_cache: Path) -> Iterator[Procs]:
    p = Procs(tmp_path, router_endpoint, model13, rel_cache)
    try:
        yield p
    finally:
        p.close()


@pytest.fixture
def watcher(router_endpoint: str) -> Iterator[Watcher]:
    w = Watcher(router_endpoint)
    try:
        yield w
    finally:
        w.close()
