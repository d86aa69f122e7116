"""Year profiles of a feeder made once into a test cache (what every bridge run then loads from ``.npz``)."""

from __future__ import annotations

from pathlib import Path


def cache_year_profiles(map_path: Path, cache_dir: Path, *, seed: int = 1) -> Path:
    """Make (or load) the year profiles of the feeder of ``map_path`` for ``seed`` in ``cache_dir``; returns it."""
    from schemas.devicemap import load_device_map
    from simulator_bridge.bus.bridge import cached_profiles
    from simulator_bridge.opendss.engine import FeederEngine

    dm = load_device_map(map_path)
    engine = FeederEngine(dm)
    try:
        cached_profiles(dm, engine, seed=seed, cache_dir=cache_dir)
    finally:
        engine.close()
    return cache_dir
