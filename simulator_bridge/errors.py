"""The base of every ``simulator_bridge`` exception, under ``schemas.errors.CvvcError``."""

from schemas.errors import CvvcError

__all__ = ["BridgeError", "EngineError", "SimulatorError"]


class SimulatorError(CvvcError):
    """Base of every exception raised by the ``simulator_bridge`` package."""


class EngineError(SimulatorError):
    """OpenDSS could not compile or solve the feeder, or was asked for something impossible."""


class BridgeError(SimulatorError):
    """The bridge cannot run as configured (bad dates, step counts, speeds, feeders)."""
