"""The adapters' exceptions: every one a ``CvvcError``, with a message that says what to do."""

from __future__ import annotations

from schemas.errors import CvvcError

__all__ = ["AdapterError", "DeviceRefusedError", "LinkDownError", "ModelMissingError", "RegisterValueError"]


class AdapterError(CvvcError):
    """The root of the adapters' exceptions."""


class LinkDownError(AdapterError):
    """The device does not answer (connection refused, closed or timed out)."""


class ModelMissingError(AdapterError):
    """The device answers but lacks a SunSpec model the adapter needs (1, 701, 702, 704)."""


class RegisterValueError(AdapterError):
    """A register value that is malformed (not implemented, a bad scale factor) or out of range.

    ``point`` names it as ``<model>.<point>`` (``701.W``), the key of the refused-value counts.
    """

    def __init__(self, point: str, detail: str) -> None:
        super().__init__(f"{point}: {detail}")
        self.point = point
        self.detail = detail


class DeviceRefusedError(AdapterError):
    """The device answered a write with a Modbus exception (e.g. 3, illegal value): nothing was applied."""
