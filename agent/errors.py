"""The agent package's exceptions: one hierarchy under ``schemas.errors.CvvcError``."""

from schemas.errors import CvvcError

__all__ = ["AgentError", "AgentInputError"]


class AgentError(CvvcError):
    """Base of every exception raised by the ``agent`` package."""


class AgentInputError(AgentError):
    """Inputs of the wrong shape, non-finite, or inconsistent; the message says which and what to fix."""
