"""Where cvvc-edge caches generated feeders, year profiles, trained models and certificates.

One place says it, so that every package (agent/, training/, simulator_bridge/, cvvc/) may import it without an
upward or sideways import. Nothing is written into the working directory unless the user points ``--cache``
there: the default is a per-user cache folder, ``$XDG_CACHE_HOME/cvvc-edge`` (``~/.cache/cvvc-edge`` when
``XDG_CACHE_HOME`` is unset), read when a command runs, never at import time.

Layout under the cache root::

    feeders/rural-v<generator version>-s<seed>/    the embedded rural feeder (simulator_bridge.rural.default_feeder)
    profiles/profiles-<feeder>-<fingerprint>-<seed>.npz   year profiles (simulator_bridge.simulation.profiles)
    models/                                         models trained by ``cvvc run`` / ``cvvc evaluate``
    security/                                       the role certificates and keys of the bus (mTLS, the default)
    ca/                                             the local certificate authority that issues them, made on the
                                                    first run (its key is never copied into security/)
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["CACHE_FOLDER_NAME", "CACHE_HELP", "ca_dir", "cache_root", "default_cache_root", "profiles_dir",
           "security_dir"]

#: Name of the project's folder inside the user's cache folder.
CACHE_FOLDER_NAME = "cvvc-edge"

#: Help text of every ``--cache`` flag.
CACHE_HELP = ("cache folder of generated feeders, year profiles and models (default: $XDG_CACHE_HOME/cvvc-edge, "
              "else ~/.cache/cvvc-edge)")


def default_cache_root() -> Path:
    """The default cache root: ``$XDG_CACHE_HOME/cvvc-edge``, else ``~/.cache/cvvc-edge`` (absolute)."""
    xdg = os.environ.get("XDG_CACHE_HOME", "").strip()
    base = Path(xdg) if xdg and Path(xdg).is_absolute() else Path.home() / ".cache"  # XDG: relative paths ignored
    return base / CACHE_FOLDER_NAME


def cache_root(given: str | os.PathLike[str] | None) -> Path:
    """The cache root a command uses: ``given`` (a ``--cache`` value) when set, else :func:`default_cache_root`."""
    if given is None or str(given) == "":
        return default_cache_root()
    return Path(given)


def profiles_dir(given: str | os.PathLike[str] | None) -> Path:
    """The year-profile cache folder under the cache root of ``given`` (see :func:`cache_root`)."""
    return cache_root(given) / "profiles"


def security_dir(given: str | os.PathLike[str] | None) -> Path:
    """The folder of the bus's role certificates and keys under the cache root of ``given``."""
    return cache_root(given) / "security"


def ca_dir(given: str | os.PathLike[str] | None) -> Path:
    """The folder of the local certificate authority under the cache root of ``given``: a sibling of
    :func:`security_dir`, never inside it (the CA's key signs every certificate of the bus).
    """
    return cache_root(given) / "ca"
