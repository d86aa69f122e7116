"""The exceptions of the ``cvvc`` package (the command line and the launchers): one base under ``CvvcError``."""

from schemas.errors import CvvcError

__all__ = ["CliError", "CommandError"]


class CommandError(CvvcError):
    """Base of every exception raised by the ``cvvc`` package (launchers, evaluation, reports, command line)."""


class CliError(CommandError):
    """A user-facing error of the command line itself."""
