"""The ``cvvc`` program: one command line over every package, and the launchers that compose them."""

__all__ = ["__version__"]

__version__ = "0.1.0"
