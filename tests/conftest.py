"""Shared fixtures: free loopback ports, a router-mode Zenoh session, paths to the shared test feeders."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_FEEDERS = (REPO.parent / "shared" / "feeders").resolve()


@pytest.fixture(scope="session", autouse=True)
def _user_cache_in_tmp(tmp_path_factory) -> Iterator[Path]:
    """No test writes into the user's cache: the default cache root (schemas.cache) points into a tmp folder."""
    import os

    folder = tmp_path_factory.mktemp("xdg-cache")
    before = os.environ.get("XDG_CACHE_HOME")
    os.environ["XDG_CACHE_HOME"] = str(folder)
    yield folder
    if before is None:
        os.environ.pop("XDG_CACHE_HOME", None)
    else:
        os.environ["XDG_CACHE_HOME"] = before


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    """A router-mode Zenoh session listening on a free tcp/127.0.0.1 port; yields its endpoint."""
    from schemas.bus import BusConfig, free_port, open_session

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with open_session(BusConfig(mode="router", listen=(endpoint,))):
        yield endpoint


@pytest.fixture
def repo_root() -> Path:
    return REPO


@pytest.fixture
def shared_feeders() -> Path:
    return SHARED_FEEDERS


@pytest.fixture(scope="session")
def ieee13_model(tmp_path_factory) -> Path:
    """A model trained on IEEE 13 (real OpenDSS power flows, ~4 s), once per test session."""
    from regression.model import write_model
    from training.train import train

    out = tmp_path_factory.mktemp("ieee13-model") / "model.json"
    result = train(REPO / "feeders" / "ieee13.toml", year_seed=1, blocks=(3, 3),
                   cache_dir=tmp_path_factory.getbasetemp() / "profiles", progress=False)
    write_model(result.model, out)
    return out


@pytest.fixture(scope="session")
def profile_cache(tmp_path_factory) -> Path:
    """One profile cache for the whole session (profiles of a feeder and seed take seconds to make).

    Files are named by feeder, fingerprint and seed, so every test shares it; its parent is a cache root
    (``cache=`` of a run or evaluation finds it as ``<root>/profiles``).
    """
    folder = tmp_path_factory.getbasetemp() / "profiles"
    folder.mkdir(exist_ok=True)
    return folder
