"""Shared fixtures: free loopback ports, a router-mode Zenoh session, paths to the shared test feeders."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_FEEDERS = (REPO.parent / "shared" / "feeders").resolve()


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
