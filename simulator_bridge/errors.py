"""The base of every ``simulator_bridge`` exception, under ``schemas.errors.CvvcError``."""

from schemas.errors import CvvcError

__all__ = ["EngineError", "SimulatorError"]


class SimulatorError(CvvcError):
    """Base of every exception raised by the ``simulator_bridge`` package."""


class EngineError(SimulatorError):
    """OpenDSS could not compile or solve the feeder, or was asked for something impossible."""
