"""Fixtures of the training tests: one IEEE 123 model trained once per session (3x3 blocks, ~2 s) on the session's
profile cache (tests/conftest.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
IEEE123 = REPO / "feeders" / "ieee123.toml"


@pytest.fixture(scope="session")
def trained_123(profile_cache):
    from schemas.settings import TrainingOptions
    from training.train import train

    return train(IEEE123, TrainingOptions(blocks=(3, 3)), workers=1, cache_dir=profile_cache, progress=False)
