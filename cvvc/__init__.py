"""The ``cvvc`` program: one command line over every package, and the launchers that compose them."""

from schemas.version import __version__

__all__ = ["__version__"]
