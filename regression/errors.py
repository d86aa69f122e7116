"""The exceptions of the ``regression`` package: one hierarchy under ``schemas.errors.CvvcError``."""

from schemas.errors import CvvcError

__all__ = ["ModelError", "ModelInputError", "RegressionError"]


class RegressionError(CvvcError):
    """Base of every exception raised by the ``regression`` package."""


class ModelError(RegressionError):
    """A model file that is missing, corrupt, of another version, or for another feeder."""


class ModelInputError(RegressionError):
    """Estimator inputs of the wrong shape, non-finite, or inconsistent with the model; the message says which."""
