"""The exception hierarchy of the ``training`` package."""

from schemas.errors import CvvcError

__all__ = ["TrainingError"]


class TrainingError(CvvcError):
    """Training cannot produce a trustworthy model; the message says what to change."""
