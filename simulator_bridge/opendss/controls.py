"""Local device control as the OpenDSS model states it: every RegControl and CapControl on an event clock.

Pure logic, no OpenDSS: the engine measures (``FeederEngine.sense``), this module decides when which device
acts, and ``qsts.py`` drives the clock inside each 1-minute step. The semantics are OpenDSS's own time-driven
control mode (``set controlmode=time``; sources: ``RegControl.pas`` ``Sample``/``DoPendingAction``,
``CapControl.pas`` ``Sample``/``DoPendingAction``, ``ControlQueue.pas``), restated here:

* After every power flow each control *samples*. A regulator whose compared voltage is out of band
  (``|vreg − v| > band/2``) computes the taps back to ``vreg`` (``round(boost / tap step)``); if it is not
  armed and a tap is possible in that direction, it *arms*: one action is queued at ``t + delay``
  (``delay / min(10, 2|vreg − v|/band)`` with ``inversetime``). Back in band it disarms: the pending change
  is zeroed and the queued action deleted.
* A regulator's action moves one tap toward the pending change; while taps remain pending, the next action
  is queued at ``t + tapdelay`` (that action is not the armed one: disarming does not delete it, and it
  moves a tap if it comes due while a new change is pending, as in OpenDSS).
* A capacitor control decides a pending change (close one step / open one step / none) from its type
  (current, voltage, kvar, PF, time) with ``VoltOverride`` first; it arms at ``t + Delay`` (close; later if
  the bank opened less than ``DeadTime`` ago) or ``t + DelayOFF`` (open), disarms when the pending change
  becomes none, and its action switches one step of whatever change is pending when it comes due.
* Actions due at the same time are done together, then the feeder is solved and every control samples again.

``maxtapchange`` only bounds OpenDSS's static mode (in its time mode a regulator moves one tap per
action); ``maxtapchange=0`` disables a regulator, as in OpenDSS. Forward mode only: reverse/cogeneration
modes, ``vlimit`` and the Beckwith ``LDC_Z`` are not modelled (the engine refuses them). A CapControl of type
``follow`` holds its bank.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

__all__ = ["CapControlSettings", "ControlActions", "LocalControls", "RegControlSettings"]

CapKind = Literal["current", "voltage", "kvar", "pf", "time", "follow"]
_CLOSE, _OPEN, _NONE = 1, -1, 0


@dataclass(frozen=True)
class RegControlSettings:
    """One RegControl's local control as the model states it (read by the engine).

    Attributes
    ----------
    name : the RegControl's name (lower case).
    vreg_v120, band_v120 : set point and band on the PT's base [V on the 120 V base].
    delay_s, tap_delay_s : ``delay`` before the first tap, ``tapdelay`` between further taps [s].
    inverse_time : ``inversetime=yes``.
    enabled : ``enabled`` and ``maxtapchange > 0``.
    tap_max : taps run ``-tap_max..tap_max``.
    taps_per_v120 : tap positions per volt of boost on the 120 V base (``PTratio / (Vbase · tap step)``),
        negative when the tap winding is not the monitored one.
    """

    name: str
    vreg_v120: float
    band_v120: float
    delay_s: float
    tap_delay_s: float
    inverse_time: bool
    enabled: bool
    tap_max: int
    taps_per_v120: float


@dataclass(frozen=True)
class CapControlSettings:
    """One CapControl as the model states it (read by the engine).

    Attributes
    ----------
    name : the CapControl's name (lower case).
    kind : its type. ``on``, ``off`` : ON/OFF settings in the type's unit (V on the PT base, A on the CT
        base, kvar, PF on OpenDSS's 0..2 scale where above 1 is leading, hour of day).
    delay_s, delay_off_s, dead_time_s : ``Delay`` (close), ``DelayOFF`` (open), ``DeadTime`` [s].
    volt_override : ``VoltOverride``; ``vmin_v``, ``vmax_v`` its limits [V on the PT base].
    n_steps : the bank's steps. total_kvar : its rating [kvar]. pct_min_kvar : PF type's ``pctMinkvar`` [%].
    enabled : the control is enabled.
    """

    name: str
    kind: CapKind
    on: float
    off: float
    delay_s: float
    delay_off_s: float
    dead_time_s: float
    volt_override: bool
    vmin_v: float
    vmax_v: float
    n_steps: int
    total_kvar: float
    pct_min_kvar: float
    enabled: bool


@dataclass(frozen=True)
class ControlActions:
    """What comes due at one time: new tap positions and bank states (only the devices that moved)."""

    t_s: float
    taps: dict[int, int]
    cap_states: dict[int, int]


class _Event:
    __slots__ = ("t_s", "seq", "kind", "index", "alive")

    def __init__(self, t_s: float, seq: int, kind: int, index: int) -> None:
        self.t_s, self.seq, self.kind, self.index, self.alive = t_s, seq, kind, index, True

    def __lt__(self, other: _Event) -> bool:
        return (self.t_s, self.seq) < (other.t_s, other.seq)


_REG, _CAP = 0, 1


class LocalControls:
    """The control queue and the armed/pending state of every RegControl and CapControl of a feeder.

    Parameters
    ----------
    regs, caps : the model's controls (``FeederEngine.reg_controls``, ``cap_controls``).

    Commands (``qsts.py``) block a control (``block_reg``/``block_cap``: a device held by the agent) or move
    a regulator's set point and band (``set_reg_band``).
    """

    def __init__(self, regs: tuple[RegControlSettings, ...], caps: tuple[CapControlSettings, ...]) -> None:
        self.regs, self.caps = regs, caps
        self.vreg_v120 = np.array([r.vreg_v120 for r in regs], dtype=float)
        self.band_v120 = np.array([r.band_v120 for r in regs], dtype=float)
        self._reg_on = np.array([r.enabled for r in regs], dtype=bool)
        self._taps_per_v = np.array([r.taps_per_v120 for r in regs], dtype=float)
        self._tap_max = np.array([r.tap_max for r in regs], dtype=int)
        self.reg_blocked = np.zeros(len(regs), dtype=bool)
        self.reg_pending = np.zeros(len(regs), dtype=int)  # signed taps still to move
        self._reg_armed: list[_Event | None] = [None] * len(regs)  # the armed (``delay``) action: the handle
        self._reg_armed_flag = np.zeros(len(regs), dtype=bool)  # OpenDSS's ``Armed``
        self.cap_blocked = np.zeros(len(caps), dtype=bool)
        self.cap_pending = np.zeros(len(caps), dtype=int)  # +1 close a step, -1 open a step, 0 none
        self._cap_armed: list[_Event | None] = [None] * len(caps)
        self._cap_last_open_s = np.full(len(caps), -math.inf)
        self._time_caps = [j for j, c in enumerate(caps) if c.kind == "time" and c.enabled]
        self._queue: list[_Event] = []
        self._seq = 0

    # ------------------------------------------------------------------ queue
    def _push(self, t_s: float, kind: int, index: int) -> _Event:
        self._seq += 1
        ev = _Event(t_s, self._seq, kind, index)
        heapq.heappush(self._queue, ev)
        return ev

    def next_time_s(self, now_s: float) -> float:
        """Time of the next thing that can change a device: a queued action, or a time-type control's ON/OFF
        hour after ``now_s`` (its condition changes then without a power flow) [s]; ``inf`` if none.
        """
        q = self._queue
        while q and not q[0].alive:
            heapq.heappop(q)
        t = q[0].t_s if q else math.inf
        for j in self._time_caps:
            if not self.cap_blocked[j]:
                t = min(t, _next_hour_crossing_s(now_s, (self.caps[j].on, self.caps[j].off)))
        return t

    def pop_due(self, now_s: float, taps: np.ndarray, cap_states: np.ndarray) -> ControlActions:
        """Do every queued action due at or before ``now_s`` on ``taps`` / ``cap_states`` (whole-feeder
        arrays in control order, not modified); returns the devices that moved and their new values.
        """
        new_taps: dict[int, int] = {}
        new_caps: dict[int, int] = {}
        q = self._queue
        while q and (not q[0].alive or q[0].t_s <= now_s):
            ev = heapq.heappop(q)
            if not ev.alive:
                continue
            i = ev.index
            if ev.kind == _REG:
                self._reg_action(i, ev, now_s, taps, new_taps)
            else:
                self._cap_action(i, ev, now_s, cap_states, new_caps)
        return ControlActions(now_s, new_taps, new_caps)

    def _reg_action(self, i: int, ev: _Event, now_s: float, taps: np.ndarray, out: dict[int, int]) -> None:
        pending = int(self.reg_pending[i])
        if self._reg_armed[i] is ev:
            self._reg_armed[i] = None  # executed: a later Delete of this handle does nothing
        if pending == 0:
            self._reg_armed_flag[i] = False
            return
        step = 1 if pending > 0 else -1
        tap = out.get(i, int(taps[i]))
        moved = max(-int(self._tap_max[i]), min(int(self._tap_max[i]), tap + step))
        if moved != int(taps[i]) or i in out:
            out[i] = moved
        self.reg_pending[i] = pending - step
        if self.reg_pending[i] != 0:
            self._push(ev.t_s + self.regs[i].tap_delay_s, _REG, i)
            self._reg_armed_flag[i] = True
        else:
            self._reg_armed_flag[i] = False

    def _cap_action(self, j: int, ev: _Event, now_s: float, states: np.ndarray, out: dict[int, int]) -> None:
        self._cap_armed[j] = None
        n = out.get(j, int(states[j]))
        c = self.caps[j]
        if self.cap_pending[j] == _OPEN and n > 0:
            n -= 1
            if c.n_steps == 1:
                self._cap_last_open_s[j] = ev.t_s
        elif self.cap_pending[j] == _CLOSE and n < c.n_steps:
            n += 1
        if n != int(states[j]) or j in out:
            out[j] = n

    # ------------------------------------------------------------------ sampling
    def sample(self, now_s: float, reg_v120: np.ndarray, taps: np.ndarray, cap_value: np.ndarray,
               cap_v_override: np.ndarray, cap_states: np.ndarray, cap_q_kvar: np.ndarray) -> None:
        """Every control samples the solved state at ``now_s`` [s]: arms, re-arms or disarms.

        Parameters
        ----------
        reg_v120 : (NR,) each regulator's compared voltage [V on the 120 V base].
        taps : (NR,) present taps. cap_states : (NC,) closed steps of each control's bank.
        cap_value : (NC,) each CapControl's controlled quantity in its type's unit (see
            ``CapControlSettings``; the time type's is ignored: it is taken from ``now_s``).
        cap_v_override : (NC,) voltage for ``VoltOverride`` [V on the PT base].
        cap_q_kvar : (NC,) reactive power through the monitored terminal (the PF type's minimum) [kvar].
        """
        if len(self.regs):
            self._sample_regs(now_s, np.asarray(reg_v120, dtype=float), taps)
        if len(self.caps):
            self._sample_caps(now_s, cap_value, cap_v_override, cap_states, cap_q_kvar)

    def _sample_regs(self, now_s: float, v: np.ndarray, taps: np.ndarray) -> None:
        dev = self.vreg_v120 - v
        active = self._reg_on & ~self.reg_blocked
        need = active & (np.abs(dev) > 0.5 * self.band_v120)
        pending = np.where(need, np.round(dev * self._taps_per_v), 0).astype(int)
        armed = self._reg_armed_flag
        # disarm: back in band (or blocked): pending zeroed, the armed action deleted
        for i in np.flatnonzero(~need & (armed | (self.reg_pending != 0))):
            self.reg_pending[i] = 0
            ev = self._reg_armed[i]
            if ev is not None:
                ev.alive = False
                self._reg_armed[i] = None
            armed[i] = False
        self.reg_pending[need] = pending[need]
        can = ((pending > 0) & (taps < self._tap_max)) | ((pending < 0) & (taps > -self._tap_max))
        for i in np.flatnonzero(need & (pending != 0) & ~armed & can):
            r = self.regs[i]
            delay = r.delay_s
            if r.inverse_time:
                delay = r.delay_s / min(10.0, 2.0 * abs(dev[i]) / self.band_v120[i])
            self._reg_armed[i] = self._push(now_s + delay, _REG, int(i))
            armed[i] = True

    def _sample_caps(self, now_s: float, value: np.ndarray, v_over: np.ndarray, states: np.ndarray,
                     q_kvar: np.ndarray) -> None:
        tod_h = (now_s % 86400.0) / 3600.0
        for j, c in enumerate(self.caps):
            if not c.enabled or self.cap_blocked[j] or c.kind == "follow":
                self.cap_pending[j] = _NONE
                self._disarm_cap(j)
                continue
            n = int(states[j])
            closed, available = n > 0, c.n_steps - n
            should = False
            pending = int(self.cap_pending[j])
            if c.volt_override and c.kind != "voltage":
                if not closed and v_over[j] < c.vmin_v:
                    pending, should = _CLOSE, True
                elif closed and v_over[j] > c.vmax_v:
                    pending, should = _OPEN, True
            if not should:
                pending, should = _decide(c, float(value[j]), tod_h, closed, available, pending, float(q_kvar[j]))
            self.cap_pending[j] = pending
            if should and self._cap_armed[j] is None:
                if pending == _CLOSE:
                    since = now_s - self._cap_last_open_s[j]
                    delay = max(c.delay_s, c.dead_time_s + c.delay_s - since) if since < c.dead_time_s \
                        else c.delay_s
                else:
                    delay = c.delay_off_s
                self._cap_armed[j] = self._push(now_s + delay, _CAP, j)
            if self._cap_armed[j] is not None and pending == _NONE:
                self._disarm_cap(j)

    def _disarm_cap(self, j: int) -> None:
        ev = self._cap_armed[j]
        if ev is not None:
            ev.alive = False
            self._cap_armed[j] = None

    # ------------------------------------------------------------------ commands
    def block_reg(self, i: int, blocked: bool) -> None:
        """Take regulator ``i`` out of (or back into) local control; blocking disarms it."""
        self.reg_blocked[i] = blocked
        if blocked:
            self.reg_pending[i] = 0
            ev = self._reg_armed[i]
            if ev is not None:
                ev.alive = False
                self._reg_armed[i] = None
            self._reg_armed_flag[i] = False

    def block_cap(self, j: int, blocked: bool) -> None:
        """Take CapControl ``j`` out of (or back into) local control; blocking disarms it."""
        self.cap_blocked[j] = blocked
        if blocked:
            self.cap_pending[j] = _NONE
            self._disarm_cap(j)

    def set_reg_band(self, i: int, vreg_v120: float, band_v120: float) -> None:
        """Move regulator ``i``'s set point and band [V on the 120 V base]; its delays still apply."""
        self.vreg_v120[i], self.band_v120[i] = float(vreg_v120), float(band_v120)


def _decide(c: CapControlSettings, x: float, tod_h: float, closed: bool, available: int, pending: int,
            q_kvar: float) -> tuple[int, bool]:
    """(pending change, should switch) of one CapControl's own type, as OpenDSS's ``Sample`` decides it.

    A closed multi-step bank whose quantity lies between OFF and ON keeps its previous pending change
    (OpenDSS leaves it unchanged there), without arming.
    """
    if c.kind == "time":
        on_window = (c.on <= tod_h < c.off) if c.off > c.on else (c.on <= tod_h < 24.0)
        off_window = (tod_h >= c.off or tod_h < c.on) if c.off > c.on else (c.off <= tod_h < c.on)
        if not closed:
            return (_CLOSE, True) if on_window else (_NONE, False)
        if off_window:
            return _OPEN, True
        if available > 0:
            return (_CLOSE, True) if on_window else (pending, False)
        return _NONE, False
    if c.kind == "pf":
        if not closed:
            ok = x < c.on and q_kvar > c.total_kvar * c.pct_min_kvar * 0.01
            return (_CLOSE, True) if ok else (_NONE, False)
        if x > c.off:
            return _OPEN, True
        if available > 0:
            ok = x < c.on and q_kvar > c.total_kvar / c.n_steps * 0.5
            return (_CLOSE, True) if ok else (pending, False)
        return _NONE, False
    if c.kind == "voltage":  # low voltage closes, high voltage opens
        if not closed:
            return (_CLOSE, True) if x < c.on else (_NONE, False)
        if x > c.off:
            return _OPEN, True
        if available > 0 and x < c.on:
            return _CLOSE, True
        return _NONE, False
    # current, kvar: a high value closes, a low one opens
    if not closed:
        return (_CLOSE, True) if x > c.on else (_NONE, False)
    if x < c.off:
        return _OPEN, True
    if available > 0:
        return (_CLOSE, True) if x > c.on else (pending, False)
    return _NONE, False


def _next_hour_crossing_s(now_s: float, hours: tuple[float, float]) -> float:
    """The first time after ``now_s`` [s] at which the time of day equals one of ``hours`` [h]."""
    day0 = now_s - now_s % 86400.0
    best = math.inf
    for h in hours:
        for d in (0.0, 86400.0):
            t = day0 + d + h * 3600.0
            if t > now_s + 1e-9:
                best = min(best, t)
                break
    return best
