"""A PV plant behind SunSpec Modbus as a device of the cvvc bus, without the bus: scans -> frames, commands -> acks.

The command contract is the simulated plants' (``simulator_bridge.field.devices``: the same checks, in the same order,
by the same :class:`~simulator_bridge.field.devices.PvInverter` guard), then the SunSpec hop:

1. The generic checks (wrong device, non-finite, expired, out of window, replay) at the adapter's present time.
2. The link is down: ``rejected`` with reason ``link_down`` (nothing is written).
3. The set point is clipped to what the inverter can give: its headroom ``sqrt(S² − P²)`` at the last scan's
   active power (0 at night unless ``q_at_night``) and 702's ``VarMaxInj``/``VarMaxAbs``.
4. It is written as a 704 ``VarSet`` whose revert timer ``VarSetRvrtTms`` is the time left until the command's
   ``valid_until_t_ns``, rounded up to a whole second: an expired command reverts *in the inverter*.
5. The models are read back: the ack carries what the inverter holds (``VarSet`` with its scale factor):
   ``accepted`` when that is the request within half a ``VarSet`` step, ``clipped`` otherwise; a Modbus exception
   answer is ``rejected`` with reason ``device_refused``; a link failure ``rejected`` with ``link_down``.

A scan reads 701/702/704 (and 705, the local volt-var curve, if the inverter has it) and makes a ``PvFrame``
stamped with the scan's time; its ``local_mode`` is 705's (volt-var when enabled) or, without 705, the setting's.
Refused register values (``adapters.sunspec``) give no frame: they are counted by point and the link's state
becomes ``refusing``.
A command whose ``valid_until_t_ns`` has passed at a scan is answered ``expired`` (the inverter reverted itself).

Each scan also verifies what the inverter does: the 704 set point in force must be the one this adapter wrote for
the command in force (none without one). Another value was written by someone else (a second Modbus master): a
*foreign write*, counted (``foreign_writes``, in ``LinkStatus``), logged (the first one), and ours written again
(with the command's remaining revert time, or the function disabled when no command is in force); the frame reports
the set point the inverter holds after that. Within ``_EXPIRY_MARGIN_NS`` of the command's end the inverter's own
revert timer and the adapter's clock may disagree, and nothing is judged.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Literal

from adapters.device import LinkedDevice
from adapters.device import rejected as _rejected
from adapters.errors import DeviceRefusedError, LinkDownError, ModelMissingError, RegisterValueError
from adapters.sunspec import InverterReading, SunSpecLink
from schemas import messages as m
from simulator_bridge.field import devices as dv

__all__ = ["PlantSettings", "SunSpecPlant"]

log = logging.getLogger(__name__)
_ROUNDING_TOL_KVAR = 1e-9
_EXPIRY_MARGIN_NS = 5_000_000_000  # the revert timer is whole seconds, rounded up, on the inverter's own clock


@dataclass(frozen=True)
class PlantSettings:
    """What the adapter knows of the plant beyond its registers.

    Parameters
    ----------
    feeder_id, device_id : where it is on the bus (``cvvc/<feeder_id>/.../pv/<device_id>``).
    control_period_ns : the feeder's control period [ns]: the unit of the command windows (as the bridge's).
    local_mode : the plant's local default, reported in its frames when the inverter has no model 705 (with 705,
        its ``Ena`` says: volt-var or unity power factor).
    q_at_night : whether the inverter gives reactive power at zero active power.
    set_local_mode : write ``local_mode`` into the inverter's model 705 (``Ena``: volt-var on or off) whenever a scan
        finds it otherwise (at the first scan, and after the inverter changed it); nothing without 705.
    """

    feeder_id: str
    device_id: str
    control_period_ns: int = dv.DEFAULT_PERIOD_NS
    local_mode: Literal["unity_pf", "volt_var"] = "unity_pf"
    q_at_night: bool = False
    set_local_mode: bool = False


class SunSpecPlant(LinkedDevice):
    """One inverter's scans and commands. Not thread safe: the adapter's loop is its only user."""

    def __init__(self, settings: PlantSettings, link: SunSpecLink) -> None:
        super().__init__(settings.feeder_id, settings.device_id, "pv", "sunspec", log)
        self.settings = settings
        self.link = link
        self.plant = dv.PvInverter(settings.device_id, 0, 1.0, settings.local_mode,
                                   period_ns=settings.control_period_ns)
        self.last: InverterReading | None = None
        self.local_mode_writes = self.local_mode_failures = 0  # 705 Ena written to set the local mode (failed)

    @property
    def guard(self) -> dv.CommandGuard:
        """The inverter's command guard."""
        return self.plant.guard

    @property
    def endpoint(self) -> str:
        """The inverter's Modbus endpoint."""
        return self.link.endpoint

    # ------------------------------------------------------------------------------------------- scans
    def scan(self, t_ns: int) -> m.PvFrame | None:
        """Read the inverter for the scan at ``t_ns`` [ns]; its frame, or None (link down, values refused)."""
        self.scans += 1
        try:
            reading = self.link.read()
        except (LinkDownError, ModelMissingError) as e:
            self._fail("down", str(e))
            return None
        except RegisterValueError as e:
            self.refused[e.point] += 1
            self._fail("refusing", f"refused register value {e}")
            return None
        reading = self._set_local_mode(reading)
        self.state, self.reason, self.last_ok_t_ns = "ok", "", int(t_ns)
        reading = self._verify_setpoint(reading, int(t_ns))
        self.last = reading
        return self._frame(reading, t_ns)

    def _set_local_mode(self, r: InverterReading) -> InverterReading:
        """With ``set_local_mode``: write 705 ``Ena`` when the inverter's local default is not the configured one;
        the reading after it (the one given when nothing is written or the write fails: the frame says what the
        inverter does, and the failure is counted in ``local_mode_failures`` and logged).
        """
        want = self.settings.local_mode == "volt_var"
        if not self.settings.set_local_mode or r.volt_var is None or r.volt_var.enabled == want:
            return r
        try:
            back = self.link.write_volt_var_enable(want)
        except (LinkDownError, DeviceRefusedError, RegisterValueError) as e:
            self.local_mode_failures += 1
            self.rlog.warning("local_mode", "%s: could not set the local mode %s in 705: %s",
                              self.settings.device_id, self.settings.local_mode, e)
            return r
        self.local_mode_writes += 1
        return back

    def _verify_setpoint(self, r: InverterReading, t_ns: int) -> InverterReading:
        """The reading after making sure the set point in force is ours (module docstring); a foreign one is counted,
        logged and overwritten with ours.
        """
        active = self.plant.guard.active
        if active is not None and abs(active.valid_until_t_ns - t_ns) < _EXPIRY_MARGIN_NS:
            return r
        ours = None if active is None or active.valid_until_t_ns < t_ns else active.value
        held = r.q_setpoint_kvar
        if (ours is None) == (held is None) and (
                ours is None or held is None or abs(held - ours) <= r.var_set_step_kvar / 2 + _ROUNDING_TOL_KVAR):
            return r
        self.foreign_writes += 1
        what = "its local default" if ours is None else f"{ours:.3f} kvar"
        self.reason = (f"foreign write: the inverter held {'no set point' if held is None else f'{held:.3f} kvar'} "
                       f"where this adapter wrote {what}; re-asserted")
        if self.foreign_writes == 1:  # logged once; LinkStatus counts every one and says the latest
            log.warning("%s: %s (counted in its LinkStatus.foreign_writes)", self.settings.device_id, self.reason)
        try:
            if ours is None or active is None:
                return self.link.disable_var_setpoint()
            return self.link.write_var_setpoint(ours, max(1, math.ceil((active.valid_until_t_ns - t_ns) / 1e9)))
        except (LinkDownError, DeviceRefusedError, RegisterValueError) as e:
            self.rlog.warning("foreign_write_fix", "%s: could not write the set point again: %s",
                              self.settings.device_id, e)
            return r

    def _frame(self, r: InverterReading, t_ns: int) -> m.PvFrame:
        by_phase = {p.phase: p for p in r.phases}
        p = [by_phase[ph].p_kw if ph in by_phase else 0.0 for ph in "abc"]
        q = [by_phase[ph].q_kvar if ph in by_phase else 0.0 for ph in "abc"]
        v = [by_phase[ph].v_v if ph in by_phase else 0.0 for ph in "abc"]
        self.plant.s_rated_kva = r.s_rated_kva
        if r.volt_var is not None:  # the inverter says what it does on its own (705); else the configured mode
            self.plant.local_mode = "volt_var" if r.volt_var.enabled else "unity_pf"
        self._seq += 1
        self.frames += 1
        return dv.pv_frame(plant=self.plant, t_ns=int(t_ns), seq=self._seq, p_kw=p, q_kvar=q, v_v=v,
                           available_p_kw=max(r.p_kw, 0.0), q_setpoint_kvar=r.q_setpoint_kvar,
                           q_at_night=self.settings.q_at_night)

    def expired(self, t_ns: int) -> m.Ack | None:
        """The ``expired`` ack of the command whose validity ended before ``t_ns`` [ns], or None."""
        gone = self.plant.guard.expire(t_ns)
        if gone is None:
            return None
        return self._ack(gone.cmd_id, dv.Verdict(status="expired", applied_value=None,
                                                 reason="valid_until_t_ns passed: the inverter's revert timer "
                                                        "returned it to its local default"), t_ns)

    # ---------------------------------------------------------------------------------------- commands
    def headroom_kvar(self) -> tuple[float, float]:
        """What the inverter can inject and absorb now [kvar] (both >= 0), from the last scan."""
        r = self.last
        if r is None:
            return 0.0, 0.0
        p = max(r.p_kw, 0.0)
        h = dv.pv_q_headroom_kvar(r.s_rated_kva, p, self.settings.q_at_night)
        return min(h, r.var_max_inj_kvar), min(h, r.var_max_abs_kvar)

    def _verdict(self, cmd: m.PvCommand, now_t_ns: int) -> dv.Verdict:
        return self.plant.check(cmd, now_t_ns=now_t_ns) or self._apply(cmd, now_t_ns)

    def _apply(self, cmd: m.PvCommand, now_t_ns: int) -> dv.Verdict:
        if self.state == "down" or self.last is None:
            what = "no answer from" if self.state != "refusing" else "no valid scan yet of"
            return _rejected("link_down", f"{what} the inverter at {self.link.endpoint}"
                             + (f" ({self.reason})" if self.reason else "") + "; the command was not written")
        inj, absorb = self.headroom_kvar()
        q = min(max(float(cmd.q_kvar), -absorb), inj)
        revert_s = max(1, math.ceil((cmd.valid_until_t_ns - now_t_ns) / 1e9))
        try:
            back = self.link.write_var_setpoint(q, revert_s)
        except LinkDownError as e:
            self.state, self.reason = "down", str(e)
            return _rejected("link_down", f"{e}; the set point may not have been written")
        except DeviceRefusedError as e:
            return _rejected("device_refused", str(e))
        except RegisterValueError as e:
            self.refused[e.point] += 1
            return _rejected("device_refused", f"read-back value refused: {e}")
        self.last = back
        applied = back.q_setpoint_kvar
        if applied is None:
            return _rejected("device_refused", "the inverter did not enable the reactive power set point "
                             "(704 VarSetEna or VarSetMod read back otherwise)")
        self.plant.guard.apply(cmd, applied)
        if abs(applied - float(cmd.q_kvar)) <= back.var_set_step_kvar / 2 + _ROUNDING_TOL_KVAR:
            return dv.Verdict(status="accepted", applied_value=applied)
        return dv.Verdict(status="clipped", applied_value=applied,
                          reason=f"{cmd.q_kvar:.3f} kvar is beyond what the inverter gives now (inject "
                                 f"{inj:.3f}, absorb {absorb:.3f} kvar); it applied {applied:.3f} kvar")
