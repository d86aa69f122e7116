"""The embedded rural feeder as a cached default: generated once into the cache root, then reused.

``cvvc run``, ``cvvc train``, ``cvvc bridge`` and ``cvvc feeder info`` use it when no ``--feeder`` is given.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

__all__ = ["GENERATOR_VERSION", "default_feeder_dir", "ensure_default_feeder"]

#: Bump when generator.py changes its output, so cached default feeders are regenerated.
GENERATOR_VERSION = 1


def default_feeder_dir(cache_root: Path, seed: int = 1) -> Path:
    """Folder of the embedded rural feeder for ``seed`` inside ``cache_root``."""
    return Path(cache_root) / "feeders" / f"rural-v{GENERATOR_VERSION}-s{seed}"


def ensure_default_feeder(cache_root: Path, seed: int = 1) -> Path:
    """Return the device map path of the embedded rural feeder, generating it first if absent.

    The feeder is written into a temporary sibling folder and renamed into place, so two processes
    starting together never see a half-written feeder.
    """
    from simulator_bridge.rural.generator import DEVICE_MAP_FILE, GeneratorError, generate_rural_feeder

    folder = default_feeder_dir(cache_root, seed)
    path = folder / DEVICE_MAP_FILE
    if path.is_file():
        return path
    try:
        folder.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}-", dir=folder.parent))
    except OSError as e:
        raise GeneratorError(f"cannot create the feeder cache under {cache_root}: {e}") from e
    try:
        generate_rural_feeder(seed, tmp)
        try:
            os.rename(tmp, folder)
        except OSError:
            if not path.is_file():  # not a concurrent writer that got there first
                raise
    except OSError as e:
        raise GeneratorError(f"cannot store the generated feeder in {folder}: {e}") from e
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return path
