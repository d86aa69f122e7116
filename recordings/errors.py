"""The exceptions of the recordings package: every one says what went wrong and what to do."""

from __future__ import annotations

from schemas.errors import CvvcError

__all__ = ["NotMcapError", "OfflineError", "RecordingError", "ReplayError", "UnreadableError"]


class RecordingError(CvvcError):
    """Base of the recordings errors."""


class NotMcapError(RecordingError):
    """The file is empty, missing, or does not start with the MCAP magic bytes."""


class UnreadableError(RecordingError):
    """An MCAP file whose index cannot be used (cut short, corrupt): ``cvvc recordings recover`` it first."""


class ReplayError(RecordingError):
    """A replay that cannot start: no matching messages, no subscriber, bad time bounds."""


class OfflineError(RecordingError):
    """An offline re-run that cannot start: no model, no recorded decisions, agent runtime unavailable."""
