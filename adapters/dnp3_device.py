"""A regulator control or capacitor bank controller behind DNP3 as a device of the cvvc bus, without the bus.

Reads -> frames (``RegFrame``, ``CapFrame``), commands -> DNP3 operates -> acks, on one :class:`~adapters.dnp3.
Dnp3Master`; the point maps are docs/dnp3.md's. The command contract is the simulated devices'
(``simulator_bridge.field.devices``: the same checks, in the same order, by the same ``RegulatorController`` /
``CapBankController`` guard), then the DNP3 hop:

1. The generic checks (wrong device, non-finite, expired, out of window, replay) and the device's range, at the
   adapter's present time. A tap command (``TapAction``) is refused: the map has no point for it.
2. The link is down (or no valid read came yet): ``rejected`` with reason ``link_down``; nothing is operated.
3. Select-before-operate of the hold time (the seconds left until the command's ``valid_until_t_ns``, rounded
   up), then of the band and the set point (regulator) or of the switch (bank, a CROB). The command therefore
   ends *in the device* at its validity, whether the adapter is still there or not.
4. An operate the outstation refuses (its ``CommandStatus``: ``OUT_OF_RANGE``, ``NOT_SUPPORTED``, ``BLOCKED``, ...)
   is ``rejected`` with reason ``device_refused`` and counted by point (``refused``: ``ao0:OUT_OF_RANGE``); no
   answer is ``rejected`` with ``link_down``.
5. Read back: the ack is ``accepted`` when the device holds what was written (the analog outputs as written, in
   double precision, and the "remote in force" input set; for the bank, the switch's output status), else
   ``rejected``, ``device_refused``.

Each read also verifies what the device does (as the SunSpec adapter): with a command in force the device must
hold it, without one it must be on local control. Anything else was done by someone else (another master):
a *foreign write*, counted (``foreign_writes``), logged once, and undone (ours operated again, or the device
released with a hold of 0). Within ``_EXPIRY_MARGIN_NS`` of the command's end nothing is judged.

Values read are checked before a frame is made: a map point read without its ONLINE flag, a voltage or current
that is negative, not finite or beyond its type's range, a tap that is not a whole step within the range, are
refused by point (``refused``: ``ai1``), the state becomes ``refusing`` and no frame is sent.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Literal

from adapters.device import LinkedDevice
from adapters.device import rejected as _rejected
from adapters.dnp3 import Dnp3LinkError, Dnp3Master, Dnp3Reading, OperateOutcome
from schemas import messages as m
from simulator_bridge.field import devices as dv
from simulator_bridge.field.dnp3_sim import HOLD_MAX_S, CapBankPoints, RegulatorPoints

__all__ = ["Dnp3Device", "Dnp3DeviceSettings"]

log = logging.getLogger(__name__)
_EXPIRY_MARGIN_NS = 2_000_000_000  # the hold is whole seconds, rounded up, on the device's own clock
_READ_BACK_TOL = 1e-9  # a value written and read back (g41v4 / g40v4, double precision) [V, s]
_V120_MAX = 200.0
_TAP_MAX = 16
_V_MAX_V = 1e6


class _Refused(ValueError):
    """A value read is refused (the point's name in ``point``)."""

    def __init__(self, point: str, why: str) -> None:
        super().__init__(f"{point}: {why}")
        self.point = point


@dataclass(frozen=True)
class Dnp3DeviceSettings:
    """What the adapter knows of the device beyond its points.

    Parameters
    ----------
    feeder_id, device_id : where it is on the bus. kind : ``vr`` (regulator control) or ``cap`` (bank).
    control_period_ns : the feeder's control period [ns], the unit of the command windows.
    phase : the regulator's phase (its frame's). kvar_rated, control_type : the bank's rating [kvar] and its local
    control's type (frames).
    """

    feeder_id: str
    device_id: str
    kind: Literal["vr", "cap"]
    control_period_ns: int = dv.DEFAULT_PERIOD_NS
    phase: m.Phase = "a"
    kvar_rated: float = 600.0
    control_type: m.CapControlType = "none"


class Dnp3Device(LinkedDevice):
    """One outstation's reads and commands. Not thread safe: the adapter's loop is its only user."""

    def __init__(self, settings: Dnp3DeviceSettings, master: Dnp3Master) -> None:
        super().__init__(settings.feeder_id, settings.device_id, settings.kind, "dnp3", log)
        self.settings = settings
        self.master = master
        d = settings.device_id
        self.reg = dv.RegulatorController(d, 0, _TAP_MAX, 120.0, 2.0, period_ns=settings.control_period_ns)
        self.cap = dv.CapBankController(d, 0, 1, settings.kvar_rated, settings.control_type,
                                        period_ns=settings.control_period_ns)
        self.last: Dnp3Reading | None = None

    @property
    def guard(self) -> dv.CommandGuard:
        """The command guard of the device's kind."""
        return self.reg.guard if self.settings.kind == "vr" else self.cap.guard

    @property
    def endpoint(self) -> str:
        """The outstation's endpoint."""
        return self.master.endpoint

    # ------------------------------------------------------------------------------------------- reads
    def scan(self, t_ns: int) -> m.RegFrame | m.CapFrame | None:
        """Read the outstation for the scan at ``t_ns`` [ns]; its frame, or None (link down, values refused)."""
        self.scans += 1
        try:
            reading = self.master.read()
            self._check(reading)
        except Dnp3LinkError as e:
            self._fail("down", str(e))
            return None
        except _Refused as e:
            self.refused[e.point] += 1
            self._fail("refusing", f"refused value {e}")
            return None
        self.state, self.reason, self.last_ok_t_ns = "ok", "", int(t_ns)
        reading = self._verify(reading, int(t_ns))
        self.last = reading
        return self._frame(reading, int(t_ns))

    def _check(self, r: Dnp3Reading) -> None:
        if self.settings.kind == "vr":
            p = RegulatorPoints
            ai = [p.AI_V_COMPARED_120, p.AI_TAP, p.AI_LOAD_CURRENT_A, p.AI_SETPOINT_120, p.AI_BAND_120, p.AI_V_120]
            bi = [p.BI_REMOTE]
        else:
            c = CapBankPoints
            ai, bi = [c.AI_V, c.AI_CONTROL_VALUE], [c.BI_CLOSED, c.BI_REMOTE]
        for name in [f"ai{i}" for i in ai] + [f"bi{i}" for i in bi]:
            if name in r.offline:
                raise _Refused(name, "read without its ONLINE flag")
        for i in ai:
            if i not in r.analog_inputs or not math.isfinite(r.analog_inputs[i]):
                raise _Refused(f"ai{i}", f"missing or not finite ({r.analog_inputs.get(i)!r})")
        for i in bi:
            if i not in r.binary_inputs:
                raise _Refused(f"bi{i}", "missing")
        a = r.analog_inputs
        if self.settings.kind == "vr":
            p = RegulatorPoints
            for i in (p.AI_V_COMPARED_120, p.AI_SETPOINT_120, p.AI_V_120):
                if not 0.0 <= a[i] <= _V120_MAX:
                    raise _Refused(f"ai{i}", f"{a[i]} V outside 0..{_V120_MAX} V (120 V base)")
            if not (a[p.AI_TAP] == round(a[p.AI_TAP]) and abs(a[p.AI_TAP]) <= _TAP_MAX):
                raise _Refused(f"ai{p.AI_TAP}", f"tap {a[p.AI_TAP]} is not a whole step within ±{_TAP_MAX}")
            if a[p.AI_LOAD_CURRENT_A] < 0.0:
                raise _Refused(f"ai{p.AI_LOAD_CURRENT_A}", f"negative current {a[p.AI_LOAD_CURRENT_A]} A")
            if not 0.0 < a[p.AI_BAND_120] <= 12.0:
                raise _Refused(f"ai{p.AI_BAND_120}", f"band {a[p.AI_BAND_120]} V outside (0, 12] V")
        elif not 0.0 <= a[CapBankPoints.AI_V] <= _V_MAX_V:
            raise _Refused(f"ai{CapBankPoints.AI_V}", f"{a[CapBankPoints.AI_V]} V outside 0..{_V_MAX_V:g} V")

    def _holds(self, r: Dnp3Reading, t_ns: int) -> bool | None:
        """Whether the device holds the command in force (or local control without one); None: not judged."""
        active = self.guard.active
        if active is not None and abs(active.valid_until_t_ns - t_ns) < _EXPIRY_MARGIN_NS:
            return None
        ours = active is not None and active.valid_until_t_ns >= t_ns
        if self.settings.kind == "vr":
            remote = r.binary_inputs[RegulatorPoints.BI_REMOTE]
            if not ours:
                return not remote
            a = self.reg.action
            return (remote and isinstance(a, m.SetpointAction)
                    and abs(r.analog_inputs[RegulatorPoints.AI_SETPOINT_120] - a.setpoint_v120) <= _READ_BACK_TOL
                    and abs(r.analog_inputs[RegulatorPoints.AI_BAND_120] - a.band_v120) <= _READ_BACK_TOL)
        remote = r.binary_inputs[CapBankPoints.BI_REMOTE]
        if not ours or active is None:
            return not remote
        return remote and r.binary_outputs.get(CapBankPoints.BO_SWITCH) == (active.value > 0.0)

    def _verify(self, r: Dnp3Reading, t_ns: int) -> Dnp3Reading:
        if self._holds(r, t_ns) is not False:
            return r
        self.foreign_writes += 1
        active = self.guard.active
        self.reason = ("foreign write: the device held another command than this adapter's "
                       f"({'none' if active is None else active.cmd_id}); re-asserted")
        if self.foreign_writes == 1:  # logged once; LinkStatus counts every one
            log.warning("%s: %s (counted in its LinkStatus.foreign_writes)", self.settings.device_id, self.reason)
        try:
            if active is None or active.valid_until_t_ns < t_ns:
                self._operate_ok(self._hold_index(), 0.0)
                return self.master.read()
            if self.settings.kind == "vr" and isinstance(self.reg.action, m.SetpointAction):
                return self.write_setpoint(self.reg.action, active.valid_until_t_ns, t_ns)  # its read-back
            return self._write_switch(active.value > 0.0, active.valid_until_t_ns, t_ns)
        except (Dnp3LinkError, _Refused) as e:
            self.rlog.warning("foreign_write_fix", "%s: could not operate again: %s", self.settings.device_id, e)
            return r

    def _frame(self, r: Dnp3Reading, t_ns: int) -> m.RegFrame | m.CapFrame:
        self._seq += 1
        self.frames += 1
        a = r.analog_inputs
        if self.settings.kind == "vr":
            p = RegulatorPoints
            return dv.reg_frame(reg=self.reg, t_ns=t_ns, seq=self._seq, phase=self.settings.phase,
                                v120=a[p.AI_V_120], v_compared_120=a[p.AI_V_COMPARED_120],
                                tap=int(a[p.AI_TAP]), setpoint_v120=a[p.AI_SETPOINT_120],
                                band_v120=a[p.AI_BAND_120], mode="local")
        c = CapBankPoints
        control = None if self.settings.control_type == "none" else a[c.AI_CONTROL_VALUE]
        remote = r.binary_inputs[c.BI_REMOTE]
        return dv.cap_frame(cap=self.cap, t_ns=t_ns, seq=self._seq, closed_steps=int(r.binary_inputs[c.BI_CLOSED]),
                            v_v=a[c.AI_V], control_value=control, active=self.guard.active if remote else None)

    def expired(self, t_ns: int) -> m.Ack | None:
        """The ``expired`` ack of the command whose validity ended before ``t_ns`` [ns], or None."""
        gone = self.reg.expire(t_ns) if self.settings.kind == "vr" else self.cap.expire(t_ns)
        if gone is None:
            return None
        return self._ack(gone.cmd_id, dv.Verdict(status="expired", reason="valid_until_t_ns passed: the device's "
                                                 "hold timer returned it to its local control"), t_ns)

    # ---------------------------------------------------------------------------------------- commands
    def _verdict(self, cmd: m.RegCommand | m.CapCommand, now: int) -> dv.Verdict:
        match cmd:
            case m.RegCommand() if self.settings.kind == "vr":
                verdict = self.reg.check(cmd, now_t_ns=now)
                if verdict is None and isinstance(cmd.action, m.TapAction):
                    verdict = _rejected("device_refused", "a tap command: this regulator control takes a voltage "
                                        "set point and band over DNP3 (docs/dnp3.md)")
            case m.CapCommand() if self.settings.kind == "cap":
                verdict = self.cap.check(cmd, now_t_ns=now)
                if verdict is None and cmd.closed_steps is not None and cmd.closed_steps > 1:
                    verdict = _rejected("out_of_range", f"{cmd.closed_steps} closed steps asked of a one-step bank")
            case _:
                verdict = _rejected("wrong_device", f"a {type(cmd).__name__} sent to the {self.settings.kind} "
                                    f"adapter of {self.settings.device_id!r}")
        if verdict is not None:
            return verdict
        if self.state == "down" or self.last is None:
            return _rejected("link_down", f"no valid read yet of the outstation at {self.master.endpoint}"
                             + (f" ({self.reason})" if self.reason else "") + "; nothing was operated")
        try:
            if isinstance(cmd, m.RegCommand):
                if not isinstance(cmd.action, m.SetpointAction):  # a TapAction was refused above
                    return _rejected("device_refused", "a tap command")
                back = self.write_setpoint(cmd.action, cmd.valid_until_t_ns, now)
                a, tol = back.analog_outputs, _READ_BACK_TOL
                if not (back.binary_inputs.get(RegulatorPoints.BI_REMOTE)
                        and abs(a.get(RegulatorPoints.AO_SETPOINT_120, math.nan) - cmd.action.setpoint_v120) <= tol
                        and abs(a.get(RegulatorPoints.AO_BAND_120, math.nan) - cmd.action.band_v120) <= tol):
                    return _rejected("device_refused", f"read back: the device holds set point "
                                     f"{a.get(RegulatorPoints.AO_SETPOINT_120)} V, band "
                                     f"{a.get(RegulatorPoints.AO_BAND_120)} V, remote "
                                     f"{back.binary_inputs.get(RegulatorPoints.BI_REMOTE)}")
                self.last = back
                return self.reg.apply(cmd)
            if cmd.closed_steps is None:
                self._operate_ok(CapBankPoints.AO_HOLD_S, 0.0)
                self.last = self.master.read()
                return self.cap.apply(cmd, None)
            close = cmd.closed_steps > 0
            back = self._write_switch(close, cmd.valid_until_t_ns, now)
            if not (back.binary_inputs.get(CapBankPoints.BI_REMOTE)
                    and back.binary_outputs.get(CapBankPoints.BO_SWITCH) == close):
                return _rejected("device_refused", "read back: the bank's switch or remote state is not the one "
                                 "operated")
            self.last = back
            return self.cap.apply(cmd, cmd.closed_steps)
        except Dnp3LinkError as e:
            self.state, self.reason = "down", str(e)
            return _rejected("link_down", f"{e}; the command may be partly operated")
        except _Refused as e:
            return _rejected("device_refused", str(e))

    def _hold_index(self) -> int:
        return RegulatorPoints.AO_HOLD_S if self.settings.kind == "vr" else CapBankPoints.AO_HOLD_S

    def _hold_s(self, valid_until_t_ns: int, now: int) -> float:
        return float(min(max(1, math.ceil((valid_until_t_ns - now) / 1e9)), HOLD_MAX_S))

    def _operate_ok(self, index: int, value: float) -> OperateOutcome:
        out = self.master.operate_analog(index, value)
        if not out.ok:
            self.refused[f"ao{index}:{out.status}"] += 1
            raise _Refused(f"ao{index}", f"the outstation answered {out.status} ({out.state}) to {value}")
        return out

    def write_setpoint(self, a: m.SetpointAction, valid_until_t_ns: int, now: int) -> Dnp3Reading:
        """Operate the hold time (until ``valid_until_t_ns`` from ``now`` [ns]), band and set point; the read back.

        Raises Dnp3LinkError without an answer, and a ValueError naming the point the outstation refused.
        """
        p = RegulatorPoints
        self._operate_ok(p.AO_HOLD_S, self._hold_s(valid_until_t_ns, now))
        self._operate_ok(p.AO_BAND_120, a.band_v120)
        self._operate_ok(p.AO_SETPOINT_120, a.setpoint_v120)
        return self.master.read()

    def _write_switch(self, close: bool, valid_until_t_ns: int, now: int) -> Dnp3Reading:
        self._operate_ok(CapBankPoints.AO_HOLD_S, self._hold_s(valid_until_t_ns, now))
        out = self.master.operate_crob(CapBankPoints.BO_SWITCH, close=close)
        if not out.ok:
            self.refused[f"bo{CapBankPoints.BO_SWITCH}:{out.status}"] += 1
            raise _Refused(f"bo{CapBankPoints.BO_SWITCH}", f"the outstation answered {out.status} ({out.state})")
        return self.master.read()
