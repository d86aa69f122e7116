"""The version of cvvc-edge: one home every package may import (recorded in model files and recordings)."""

__all__ = ["__version__"]

__version__ = "0.1.0"
