"""Fixtures of the simulator bridge's tests: IEEE 123's device map (the engine, Qsts and oracle tests), and for the
bridge's bus tests (test_bridge.py, test_publisher_process.py) IEEE 13 on the session's profile cache and the
hand-played agent (``busclient``). A test module's own fixture of the same name wins (test_capbus.py)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from bridgeutil import FEEDER
from busclient import BusClient as Client

from schemas.devicemap import DeviceMap, load_device_map
from tests.yearcache import cache_year_profiles

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="session")
def map123() -> DeviceMap:
    """IEEE 123's device map (a frozen struct: one decode serves every module)."""
    return load_device_map(REPO / "feeders" / "ieee123.toml")


@pytest.fixture(scope="module")
def device_map_path(repo_root_module: Path) -> Path:
    return repo_root_module / "feeders" / "ieee13.toml"


@pytest.fixture(scope="module")
def repo_root_module() -> Path:
    return Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def cache_dir(profile_cache: Path, device_map_path: Path) -> Path:
    """The session's profile cache (shared with training's tests: same file names), with IEEE 13's year made
    once (about 5 s) and then loaded from .npz by every bridge run."""
    from simulator_bridge.simulation.profiles import profiles_cache_path

    cache_year_profiles(device_map_path, profile_cache)
    # the cache is shared: training's tests add maps of IEEE 13 with other fingerprints beside this one
    assert profiles_cache_path(load_device_map(device_map_path), 1, profile_cache).is_file()
    return profile_cache


@pytest.fixture
def client(router_endpoint: str) -> Iterator[Client]:
    c = Client(router_endpoint, FEEDER, also=("cvvc/otherfeeder/ack/**",))
    try:
        yield c
    finally:
        c.close()
