"""What every adapter's device does alike, without the bus: its link state, counts, acks and ``LinkStatus``.

:class:`LinkedDevice` is the base of :class:`~adapters.sunspec_plant.SunSpecPlant` and
:class:`~adapters.dnp3_device.Dnp3Device`: a protocol's device makes the verdict of a command
(``_verdict``: the generic checks, the write and the read back); the base counts it, logs a rejection and numbers
its ack, and reports the link.
"""

from __future__ import annotations

import logging
from collections import Counter
from typing import Any, Literal

from schemas import messages as m
from schemas.logs import RateLimitedLog
from simulator_bridge.field import devices as dv

__all__ = ["LinkedDevice", "rejected"]


def rejected(kind: str, why: str) -> dv.Verdict:
    """A ``rejected`` verdict of reason kind ``kind`` (``link_down``, ``device_refused``, ...) saying ``why``."""
    return dv.Verdict(status="rejected", reason=f"{kind}: {why}", reason_kind=kind)


class LinkedDevice:
    """One device behind a field protocol: its link's state and counts. Not thread safe (one loop uses it).

    Parameters
    ----------
    feeder_id, device_id : where it is on the bus. kind : ``pv``, ``vr`` or ``cap``.
    protocol : ``sunspec`` or ``dnp3``. log : the protocol module's logger (rate-limited here).
    """

    def __init__(self, feeder_id: str, device_id: str, kind: Literal["pv", "vr", "cap"],
                 protocol: Literal["sunspec", "dnp3"], log: logging.Logger) -> None:
        self._feeder_id, self._device_id, self._kind, self._protocol = feeder_id, device_id, kind, protocol
        self.state: Literal["starting", "ok", "down", "refusing"] = "starting"
        self.reason = ""
        self.last_ok_t_ns = 0
        self.scans = self.scan_failures = self.frames = 0
        self.commands = self.commands_failed = 0
        self.refused: Counter[str] = Counter()
        self.acks: Counter[str] = Counter()
        self.foreign_writes = 0  # scans that found a set point this adapter did not write (re-asserted)
        self._seq = self._ack_seq = self._status_seq = 0
        self.rlog = RateLimitedLog(log, period_s=10.0)

    @property
    def endpoint(self) -> str:
        """The link's endpoint, as ``LinkStatus`` says it."""
        raise NotImplementedError

    @property
    def guard(self) -> dv.CommandGuard:
        """The guard of the commands in force."""
        raise NotImplementedError

    def scan(self, t_ns: int) -> Any:
        """Read the device for the scan at ``t_ns`` [ns]; its frame, or None (link down, values refused)."""
        raise NotImplementedError

    def expired(self, t_ns: int) -> m.Ack | None:
        """The ``expired`` ack of the command whose validity ended before ``t_ns`` [ns], or None."""
        raise NotImplementedError

    def _verdict(self, cmd: Any, now_t_ns: int) -> dv.Verdict:
        """Check, write and read back ``cmd`` at ``now_t_ns`` [ns]: the protocol's part of a command."""
        raise NotImplementedError

    def command(self, cmd: Any, now_t_ns: int) -> m.Ack:
        """Check, write and read back one command at the adapter's time ``now_t_ns`` [ns]; its ack."""
        self.commands += 1
        verdict = self._verdict(cmd, now_t_ns)
        if verdict.status == "rejected":
            self.commands_failed += 1
            self.rlog.info("command_rejected", "%s: rejected command %s: %s", self._device_id,
                           cmd.cmd_id, verdict.reason)
        return self._ack(cmd.cmd_id, verdict, now_t_ns)

    def _fail(self, state: Literal["down", "refusing"], why: str) -> None:
        self.scan_failures += 1
        self.state, self.reason = state, why
        self.rlog.warning(state, "%s: no frame: %s", self._device_id, why)

    def _ack(self, cmd_id: str, verdict: dv.Verdict, t_ns: int) -> m.Ack:
        self._ack_seq += 1
        self.acks[verdict.status] += 1
        return dv.make_ack(device_id=self._device_id, source=self._device_id, cmd_id=cmd_id,
                           verdict=verdict, t_ns=max(int(t_ns), 0), seq=self._ack_seq)

    def status(self, t_ns: int) -> m.LinkStatus:
        """The link's ``LinkStatus`` at ``t_ns`` [ns]."""
        self._status_seq += 1
        return m.LinkStatus(t_ns=max(int(t_ns), 0), seq=self._status_seq, source=self._device_id,
                            feeder_id=self._feeder_id, device_id=self._device_id, kind=self._kind,
                            protocol=self._protocol, endpoint=self.endpoint[:200], state=self.state,
                            scans=self.scans, scan_failures=self.scan_failures, frames=self.frames,
                            refused=dict(self.refused), commands=self.commands,
                            commands_failed=self.commands_failed, last_ok_t_ns=self.last_ok_t_ns,
                            reason=self.reason[:500], foreign_writes=self.foreign_writes)
