"""The exceptions of the ``cvvc`` package (the command line and the launchers) under ``CvvcError``."""

from schemas.errors import CvvcError

__all__ = ["CliError"]


class CliError(CvvcError):
    """A user-facing error of the command line itself."""
