"""Simulated field devices, without a bus: command checks, watchdogs, replay protection, acks, measurements.

This module is the device *logic* of the bridge (``bridge.py`` is the only module that knows Zenoh and
clocks). Everything here is a pure function or a small state holder, so it is tested without a bus.

Command handling, the same for every device (:class:`CommandGuard`):

1. **Checks**, in this order, each a :data:`RejectReason`: the payload names the device the key names
   (``wrong_device``); the value is finite (``non_finite``); the command is not already expired at the
   device's present simulation time (``expired``: ``valid_until_t_ns <= now_t_ns``); its times are within
   the device's window (``out_of_window``: ``t_ns`` at most one control period ahead of the device's time,
   ``valid_until_t_ns`` at most :data:`MAX_VALIDITY_PERIODS` periods ahead); its ``seq`` is greater than the
   last applied one from the same sender (``replay``; the sender is the payload's ``source``, or in secure
   mode the authenticated identity every command comes from: see :class:`CommandGuard`), unless its ``t_ns``
   is at least one control period past that sender's last applied command (the sender restarted, or a forged
   huge ``seq`` came earlier: no command locks a sender out for longer than one period); the value is within
   the device's own range (``out_of_range``). ``unknown_device`` and ``wrong_feeder`` are decided by the
   bridge, which owns the key space. A rejected command changes nothing.
2. **Apply**: the command becomes the device's active command until ``valid_until_t_ns``.
3. **Watchdog**: before a step at simulation time ``t_ns`` is simulated, an active command with
   ``valid_until_t_ns < t_ns`` expires; the device returns to its local default and answers an
   ``expired`` ack for that command. A command is therefore in force for every step with
   ``t_ns <= valid_until_t_ns``.

Device limits (beyond the schema bounds checked at decode):

* PV inverter: a reactive power set point beyond the headroom ``sqrt(S² − P²)`` at the present available
  power is **clipped, not rejected**; the ack says ``clipped`` and carries the applied kvar.
* Regulator controller: a tap outside the regulator's own range (``±tap_max``, 16 for a 32-step
  regulator) is rejected; a set point outside :data:`SETPOINT_RANGE_V120` or a band outside
  :data:`BAND_RANGE_V120` is rejected.
* Capacitor bank: more closed steps than the bank has is rejected (``out_of_range``). A release
  (``closed_steps = None``) is accepted and ends the active command at once: the bank is back on its local
  control, as after an expiry.

Measurement realism (:class:`MeasurementNoise`): Gaussian noise per measurement class, off by default.
PMU class (feeder head): magnitudes get relative noise ``σ = pct/100 · |x|``; angles ``σ = pct/100`` rad
(the angle error that gives the same total vector error); P and Q ``σ = pct/100 · |S|`` of the phase.
SCADA class (PV plants, regulators, capacitor banks): voltages relative; P and Q ``σ = pct/100 · S_rated``;
a capacitor control's compared quantity relative. Taps, bank states and set points are exact. Noise never
makes a magnitude negative (clipped at 0).
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Generic, Literal, TypeVar, get_args

import numpy as np

from schemas import messages as m
from simulator_bridge.errors import SimulatorError

__all__ = [
    "BAND_RANGE_V120",
    "REJECT_REASONS",
    "SETPOINT_RANGE_V120",
    "ActiveCommand",
    "CapBankController",
    "CommandGuard",
    "DeviceError",
    "FrameDropper",
    "MAX_VALIDITY_PERIODS",
    "MeasurementNoise",
    "PHASE_NAMES",
    "PvInverter",
    "RegulatorController",
    "RejectReason",
    "DelayLine",
    "Verdict",
    "cap_frame",
    "head_frame",
    "make_ack",
    "pv_frame",
    "pv_verdict",
    "reg_frame",
    "reject",
]

RejectReason = Literal[
    "unknown_device", "wrong_feeder", "wrong_device", "non_finite", "expired", "out_of_window", "replay",
    "out_of_range",
]
REJECT_REASONS: tuple[str, ...] = (
    "unknown_device", "wrong_feeder", "wrong_device", "non_finite", "expired", "out_of_window", "replay",
    "out_of_range",
)
DEFAULT_PERIOD_NS = 300_000_000_000
"""A device's control period when the bridge does not set one (``CommandGuard.period_ns``) [ns]."""
MAX_VALIDITY_PERIODS = 12
"""The furthest a command's ``valid_until_t_ns`` may lie past the device's time, in control periods."""
SETPOINT_RANGE_V120 = m.SETPOINT_RANGE_V120
BAND_RANGE_V120 = m.BAND_RANGE_V120
_CLIP_TOL_KVAR = 1e-6


class DeviceError(SimulatorError):
    """A device asked to do something impossible (a programming error in the bridge, not bad input)."""


@dataclass(frozen=True)
class Verdict:
    """The outcome of one command at a device: what the ack says and why.

    ``status`` is ``accepted`` / ``clipped`` / ``rejected`` / ``expired``; ``applied_value`` is kvar (PV),
    a tap, or volts (set point), None when nothing was applied; ``reason`` is a
    :data:`RejectReason` for rejections (``reason_kind``) plus a sentence for people (``reason``).
    """

    status: Literal["accepted", "clipped", "rejected", "expired"]
    applied_value: float | None = None
    reason: str = ""
    reason_kind: str = ""


def reject(kind: RejectReason, why: str) -> Verdict:
    """A rejection verdict of reason ``kind`` with a human sentence ``why``."""
    return Verdict(status="rejected", reason=f"{kind}: {why}", reason_kind=kind)


@dataclass(frozen=True)
class ActiveCommand:
    """The command a device obeys now: its id, who sent it, until when [ns of simulation time]."""

    cmd_id: str
    source: str
    seq: int
    valid_until_t_ns: int
    value: float


class CommandGuard:
    """Replay protection and the watchdog of one device.

    Keeps the last applied ``seq`` per sender and the active command. Not thread safe: the bridge's
    stepping thread is its only user.

    ``sender_identity``: None keys the replay state on each command's ``source``, which the sender writes
    itself. In secure mode the bus's access policy lets one certificate alone publish commands
    (``schemas.security.COMMAND_ROLE``), so every command that reaches the device was sent under that
    identity: the state is keyed on it, and a command cannot escape the sequence by naming another ``source``.
    """

    def __init__(self, device_id: str, *, period_ns: int = DEFAULT_PERIOD_NS,
                 sender_identity: str | None = None) -> None:
        self.device_id = device_id
        self.period_ns = int(period_ns)  # the feeder's control period [ns]: the unit of the time windows
        self.sender_identity = sender_identity
        self.active: ActiveCommand | None = None
        self._last_seq: dict[str, int] = {}
        self._last_t_ns: dict[str, int] = {}

    def check(self, cmd: m.Command, payload_device_id: str, value: float, *, now_t_ns: int) -> Verdict | None:
        """The rejection of ``cmd`` by the generic checks (see the module docstring), or None if it passes."""
        if payload_device_id != self.device_id:
            return reject("wrong_device", f"command names device {payload_device_id!r} but was sent to "
                          f"{self.device_id!r}; publish on the key of the device it is for")
        if not math.isfinite(value):
            return reject("non_finite", f"value {value!r} is not a finite number")
        if cmd.valid_until_t_ns <= now_t_ns:
            return reject("expired", f"valid_until_t_ns {cmd.valid_until_t_ns} is not after the device's "
                          f"present time {now_t_ns}; send commands valid past the frame they answer")
        if cmd.t_ns > now_t_ns + self.period_ns:
            return reject("out_of_window", f"t_ns {cmd.t_ns} is more than one control period ahead of the "
                          f"device's time {now_t_ns}; stamp commands with the step they answer")
        if cmd.valid_until_t_ns > now_t_ns + MAX_VALIDITY_PERIODS * self.period_ns:
            return reject("out_of_window", f"valid_until_t_ns {cmd.valid_until_t_ns} is more than "
                          f"{MAX_VALIDITY_PERIODS} control periods past the device's time {now_t_ns}")
        sender = self._sender(cmd.source)
        last = self._last_seq.get(sender)
        if last is not None and cmd.seq <= last and cmd.t_ns < self._last_t_ns[sender] + self.period_ns:
            return reject("replay", f"seq {cmd.seq} from {sender!r} is not greater than the last "
                          f"applied {last}; every command needs a new, increasing seq")
        return None

    def _sender(self, source: str) -> str:
        """Who a command counts as sent by: the authenticated identity when there is one, else its ``source``."""
        return self.sender_identity if self.sender_identity is not None else source

    def apply(self, cmd: m.Command, value: float) -> None:
        """Record ``cmd`` as applied: it becomes the active command and its seq the last from its source."""
        self._last_seq[self._sender(cmd.source)] = cmd.seq
        self._last_t_ns[self._sender(cmd.source)] = cmd.t_ns
        self.active = ActiveCommand(cmd_id=cmd.cmd_id, source=cmd.source, seq=cmd.seq,
                                    valid_until_t_ns=cmd.valid_until_t_ns, value=float(value))

    def forget_source(self, source: str) -> None:
        """Forget the last applied ``seq`` of ``source``: that sender's session ended (its liveliness token
        was withdrawn), and a restarted sender counts again from 1. Its active command stays until it expires.
        With an authenticated identity, the identity's state is forgotten: its sessions have one sequence.
        """
        self._last_seq.pop(self._sender(source), None)
        self._last_t_ns.pop(self._sender(source), None)

    def expire(self, t_ns: int) -> ActiveCommand | None:
        """Before simulating time ``t_ns``: drop and return the active command if it has expired."""
        if self.active is not None and self.active.valid_until_t_ns < t_ns:
            gone, self.active = self.active, None
            return gone
        return None


def pv_verdict(requested_kvar: float, applied_kvar: float, headroom_kvar: float) -> Verdict:
    """Accepted when the inverter applies the requested Q, clipped (with the applied value) otherwise.

    Parameters
    ----------
    requested_kvar, applied_kvar : commanded and applied reactive power [kvar, + injects].
    headroom_kvar : ``sqrt(S² − P²)`` at the present available power [kvar] (0 at night).
    """
    if abs(applied_kvar - requested_kvar) <= _CLIP_TOL_KVAR:
        return Verdict(status="accepted", applied_value=float(applied_kvar))
    return Verdict(status="clipped", applied_value=float(applied_kvar),
                   reason=f"{requested_kvar:.3f} kvar is beyond the headroom {headroom_kvar:.3f} kvar at the "
                          "present active power; applied the clipped value")


class PvInverter:
    """A PV plant's inverter: its reactive power command, guarded; local default when none is active.

    Parameters
    ----------
    plant_id : device id (key and ``plant_id``). index : column in the engine's PV arrays.
    s_rated_kva : inverter rating [kVA]. local_mode : its local default.
    """

    def __init__(self, plant_id: str, index: int, s_rated_kva: float,
                 local_mode: Literal["unity_pf", "volt_var"], *, period_ns: int = DEFAULT_PERIOD_NS,
                 sender_identity: str | None = None) -> None:
        self.plant_id = plant_id
        self.index = index
        self.s_rated_kva = float(s_rated_kva)
        self.local_mode = local_mode
        self.guard = CommandGuard(plant_id, period_ns=period_ns, sender_identity=sender_identity)

    def check(self, cmd: m.PvCommand, *, now_t_ns: int) -> Verdict | None:
        """Reject ``cmd`` (see the module docstring) or None: then apply it and build its verdict."""
        return self.guard.check(cmd, cmd.plant_id, cmd.q_kvar, now_t_ns=now_t_ns)

    @property
    def q_setpoint_kvar(self) -> float | None:
        """The commanded Q [kvar] in force, None on the local default."""
        return None if self.guard.active is None else self.guard.active.value


class RegulatorController:
    """A regulator's controller: locked at a commanded tap, or local control around a set point and band.

    Parameters
    ----------
    regulator_id : device id. index : position in the engine's regulator arrays.
    tap_max : the tap range is ``-tap_max..tap_max``.
    default_setpoint_v120, default_band_v120 : the local default from the device map / model [V, 120 V base].
    """

    def __init__(self, regulator_id: str, index: int, tap_max: int,
                 default_setpoint_v120: float, default_band_v120: float, *,
                 period_ns: int = DEFAULT_PERIOD_NS, sender_identity: str | None = None) -> None:
        self.regulator_id = regulator_id
        self.index = index
        self.tap_max = int(tap_max)
        self.default_setpoint_v120 = float(default_setpoint_v120)
        self.default_band_v120 = float(default_band_v120)
        self.guard = CommandGuard(regulator_id, period_ns=period_ns, sender_identity=sender_identity)
        self.action: m.TapAction | m.SetpointAction | None = None

    def check(self, cmd: m.RegCommand, *, now_t_ns: int) -> Verdict | None:
        """Reject ``cmd`` by the generic checks or the device's range, or None (then :meth:`apply` it)."""
        a = cmd.action
        value = float(a.tap) if isinstance(a, m.TapAction) else float(a.setpoint_v120)
        band = 1.0 if isinstance(a, m.TapAction) else float(a.band_v120)
        generic = self.guard.check(cmd, cmd.regulator_id, value if math.isfinite(band) else band,
                                   now_t_ns=now_t_ns)
        if generic is not None:
            return generic
        match a:
            case m.TapAction(tap=tap) if abs(tap) > self.tap_max:
                return reject("out_of_range", f"tap {tap} outside this regulator's -{self.tap_max}.."
                              f"{self.tap_max}")
            case m.SetpointAction(setpoint_v120=sp, band_v120=bw) if not (
                SETPOINT_RANGE_V120[0] <= sp <= SETPOINT_RANGE_V120[1]
                and BAND_RANGE_V120[0] <= bw <= BAND_RANGE_V120[1]
            ):
                return reject("out_of_range", f"set point {sp} V / band {bw} V outside the controller's "
                              f"{SETPOINT_RANGE_V120} V / {BAND_RANGE_V120} V (120 V base)")
        return None

    def apply(self, cmd: m.RegCommand) -> Verdict:
        """Record an accepted command; returns its verdict (applied tap or set point)."""
        a = cmd.action
        value = float(a.tap) if isinstance(a, m.TapAction) else float(a.setpoint_v120)
        self.guard.apply(cmd, value)
        self.action = a
        return Verdict(status="accepted", applied_value=value)

    def expire(self, t_ns: int) -> ActiveCommand | None:
        """Watchdog: the expired command (then the controller is back on its default), or None."""
        gone = self.guard.expire(t_ns)
        if gone is not None:
            self.action = None
        return gone

    @property
    def mode(self) -> Literal["local", "locked"]:
        """``"locked"`` while a tap command holds the regulator, else ``"local"`` (its own control)."""
        return "locked" if isinstance(self.action, m.TapAction) else "local"

    @property
    def setpoint_v120(self) -> float:
        """The set point in force [V on the 120 V base]."""
        return self.action.setpoint_v120 if isinstance(self.action, m.SetpointAction) \
            else self.default_setpoint_v120

    @property
    def band_v120(self) -> float:
        """The band in force [V on the 120 V base]."""
        return self.action.band_v120 if isinstance(self.action, m.SetpointAction) else self.default_band_v120


class CapBankController:
    """A switched capacitor bank as a field device: held at a commanded number of closed steps, or on its
    local control (its ``CapControl``; a bank without one holds its state).

    Parameters
    ----------
    capacitor_id : device id. index : position in the engine's capacitor arrays.
    steps : the bank's number of steps. kvar_rated : its rating with every step closed [kvar].
    control_type : its local control's type (``none``: no control).
    """

    def __init__(self, capacitor_id: str, index: int, steps: int, kvar_rated: float,
                 control_type: m.CapControlType, *, period_ns: int = DEFAULT_PERIOD_NS,
                 sender_identity: str | None = None) -> None:
        self.capacitor_id = capacitor_id
        self.index = index
        self.steps = int(steps)
        self.kvar_rated = float(kvar_rated)
        if control_type not in get_args(m.CapControlType):
            raise DeviceError(f"capacitor bank {capacitor_id!r}: control type {control_type!r} is none of "
                              f"{get_args(m.CapControlType)}; the engine must translate OpenDSS's CapControl type")
        self.control_type: m.CapControlType = control_type
        self.guard = CommandGuard(capacitor_id, period_ns=period_ns, sender_identity=sender_identity)

    def check(self, cmd: m.CapCommand, *, now_t_ns: int) -> Verdict | None:
        """Reject ``cmd`` by the generic checks or the bank's range, or None (then :meth:`apply` it)."""
        value = 0.0 if cmd.closed_steps is None else float(cmd.closed_steps)
        generic = self.guard.check(cmd, cmd.capacitor_id, value, now_t_ns=now_t_ns)
        if generic is not None:
            return generic
        if cmd.closed_steps is not None and cmd.closed_steps > self.steps:
            return reject("out_of_range", f"{cmd.closed_steps} closed steps asked of bank {self.capacitor_id!r}, "
                          f"which has {self.steps}; send 0..{self.steps}, or null to release it")
        return None

    def apply(self, cmd: m.CapCommand, applied_steps: int | None) -> Verdict:
        """Record an accepted command (``applied_steps``: the state the simulator holds the bank at; None for a
        release); returns its verdict.
        """
        if cmd.closed_steps is None:
            self.guard.apply(cmd, 0.0)
            self.guard.active = None  # released: local control from now on, nothing left to expire
            return Verdict(status="accepted", reason=f"released to local control ({self.control_type})")
        value = float(applied_steps if applied_steps is not None else cmd.closed_steps)
        self.guard.apply(cmd, value)
        return Verdict(status="accepted", applied_value=value)

    def expire(self, t_ns: int) -> ActiveCommand | None:
        """Watchdog: the expired command (then the bank is back on its local control), or None."""
        return self.guard.expire(t_ns)

    @property
    def mode(self) -> Literal["local", "commanded"]:
        """``"commanded"`` while a set point is in force, else ``"local"`` (the plant's local default)."""
        return "local" if self.guard.active is None else "commanded"


def make_ack(*, device_id: str, source: str, cmd_id: str, verdict: Verdict, t_ns: int, seq: int) -> m.Ack:
    """The ack of one command (``cmd_id`` is truncated to the schema's 96 characters)."""
    return m.Ack(t_ns=int(t_ns), seq=int(seq), source=source, cmd_id=cmd_id[:96], device_id=device_id,
                 status=verdict.status, applied_value=verdict.applied_value, reason=verdict.reason[:500])


# ----------------------------------------------------------------------------------- measurement model
class MeasurementNoise:
    """Seeded Gaussian measurement noise per class (see the module docstring). Zero percent: exact copies.

    Parameters
    ----------
    pmu_pct : PMU class (feeder head) [% of the reading]. scada_pct : SCADA class (PV plants, regulators) [%].
    seed : seed of the noise stream.
    """

    def __init__(self, *, pmu_pct: float, scada_pct: float, seed: int) -> None:
        if not (0.0 <= pmu_pct <= 100.0 and 0.0 <= scada_pct <= 100.0):
            raise DeviceError(f"noise percentages must be within 0..100, got {pmu_pct}, {scada_pct}")
        self.pmu = pmu_pct / 100.0
        self.scada = scada_pct / 100.0
        self._rng = np.random.default_rng([seed, 0x5EED])

    def _gauss(self, shape: tuple[int, ...], sigma: float) -> np.ndarray:
        return self._rng.standard_normal(shape) * sigma if sigma > 0 else np.zeros(shape)

    def head(self, v_mag_v: np.ndarray, v_ang_deg: np.ndarray, i_mag_a: np.ndarray, i_ang_deg: np.ndarray,
             p_kw: np.ndarray, q_kvar: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Noisy feeder-head phasors and powers, each (3,); PMU class. Returns new arrays."""
        e = self.pmu
        s_kva = np.hypot(p_kw, q_kvar)
        ang = math.degrees(e)
        return (
            np.maximum(v_mag_v * (1 + self._gauss(v_mag_v.shape, e)), 0.0),
            v_ang_deg + self._gauss(v_ang_deg.shape, ang),
            np.maximum(i_mag_a * (1 + self._gauss(i_mag_a.shape, e)), 0.0),
            i_ang_deg + self._gauss(i_ang_deg.shape, ang),
            p_kw + s_kva * self._gauss(p_kw.shape, e),
            q_kvar + s_kva * self._gauss(q_kvar.shape, e),
        )

    def pv(self, p_kw: np.ndarray, q_kvar: np.ndarray, v_v: np.ndarray, s_rated_kva: float
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Noisy per-phase P [kW], Q [kvar] and voltage [V] of one plant; SCADA class."""
        e = self.scada
        per_phase_kva = s_rated_kva / max(int(np.count_nonzero(v_v)), 1)
        return (
            p_kw + per_phase_kva * self._gauss(p_kw.shape, e),
            q_kvar + per_phase_kva * self._gauss(q_kvar.shape, e),
            np.maximum(v_v * (1 + self._gauss(v_v.shape, e)), 0.0),
        )

    def capacitor(self, v_v: float, control_value: float | None) -> tuple[float, float | None]:
        """Noisy bus voltage [V] and control reading (its own unit; None stays None) of one bank; SCADA class."""
        n = self._gauss((2,), self.scada)
        return (max(float(v_v * (1 + n[0])), 0.0),
                None if control_value is None else float(control_value * (1 + n[1])))

    def meter(self, v_pu: float) -> float:
        """Noisy AMI meter reading [pu]; PMU class (revenue meters measure voltage to about 0.1 %)."""
        return max(float(v_pu * (1 + self._gauss((1,), self.pmu)[0])), 0.0)

    def regulator(self, v120: float, v_compared_120: float) -> tuple[float, float]:
        """Noisy raw and compared secondary voltages [V on the 120 V base]; SCADA class."""
        n = self._gauss((2,), self.scada)
        return max(v120 * (1 + n[0]), 0.0), max(v_compared_120 * (1 + n[1]), 0.0)


class FrameDropper:
    """Drops frames with a long-run share ``p``: each frame independently, or in bursts per source (seeded).

    ``burst_s`` = 0: every frame is dropped independently with probability ``p``. ``burst_s`` > 0: each source
    (a device) loses its link for ``burst_s`` at a time: a frame of a source that is up starts an outage with
    probability ``q = p / (L (1 - p) + p)``, ``L = burst_s / step_s`` frames, and every frame of that source
    stamped before the outage's end is dropped. Up runs are geometric, outages last ``L`` frames, so the share of
    frames lost is ``L / (L + (1 - q) / q) = p``. ``step_s`` [s] is the frames' cadence.
    """

    def __init__(self, *, p: float, seed: int, burst_s: float = 0.0, step_s: float = 60.0) -> None:
        if not 0.0 <= p <= 1.0:
            raise DeviceError(f"drop probability must be within 0..1, got {p}")
        if not (math.isfinite(burst_s) and 0.0 <= burst_s <= 86_400.0):
            raise DeviceError(f"drop burst must be within 0..86400 s, got {burst_s}")
        if not (math.isfinite(step_s) and step_s > 0.0):
            raise DeviceError(f"frame cadence must be > 0 s, got {step_s}")
        self.p = float(p)
        self.burst_s = float(burst_s)
        n_burst = max(1.0, burst_s / step_s)
        self.q_start = self.p / (n_burst * (1.0 - self.p) + self.p) if self.p > 0.0 else 0.0
        self._burst_ns = int(round(burst_s * 1e9))
        self._until_ns: dict[str, int] = {}  # per source: the end of its outage (frames stamped before it drop)
        self._rng = np.random.default_rng([seed, 0xD50])

    def drop(self, source: str = "", t_ns: int = 0) -> bool:
        """Whether the frame of ``source`` stamped ``t_ns`` [ns] is lost (both ignored without bursts)."""
        if self.p <= 0.0:
            return False
        if self._burst_ns <= 0:
            return bool(self._rng.random() < self.p)
        if t_ns < self._until_ns.get(source, t_ns):
            return True
        if self._rng.random() < self.q_start:
            self._until_ns[source] = t_ns + self._burst_ns
            return True
        return False


_Item = TypeVar("_Item")


class DelayLine(Generic[_Item]):
    """Fixed latency: items put at wall time ``now_s`` come out at ``now_s + latency_s``, in order.

    Times are the caller's monotonic clock [s]; with ``latency_s = 0`` every item is due at once.
    """

    def __init__(self, latency_s: float) -> None:
        if not (math.isfinite(latency_s) and 0.0 <= latency_s <= 3600.0):
            raise DeviceError(f"latency must be within 0..3600 s, got {latency_s}")
        self.latency_s = float(latency_s)
        self._heap: list[tuple[float, int, _Item]] = []
        self._n = 0

    def put(self, item: _Item, now_s: float) -> None:
        """Hold ``item`` until ``now_s + latency_s`` [s, the caller's monotonic clock]."""
        self._n += 1
        heapq.heappush(self._heap, (now_s + self.latency_s, self._n, item))

    def due(self, now_s: float) -> list[_Item]:
        """Remove and return every item due at ``now_s``, oldest first."""
        out: list[_Item] = []
        while self._heap and self._heap[0][0] <= now_s:
            out.append(heapq.heappop(self._heap)[2])
        return out

    def next_due_s(self) -> float | None:
        """When the next item is due [s, caller's clock], None when empty."""
        return self._heap[0][0] if self._heap else None

    def __len__(self) -> int:
        return len(self._heap)


# ---------------------------------------------------------------------------------------- frames
PHASE_NAMES: tuple[m.Phase, m.Phase, m.Phase] = ("a", "b", "c")  # phases 1, 2, 3 as the messages name them
_Values = Sequence[float] | np.ndarray  # per-phase readings: a list (the bridge) or an array


def head_frame(*, feeder_id: str, t_ns: int, seq: int, v_mag_v: _Values, v_ang_deg: _Values, i_mag_a: _Values,
               i_ang_deg: _Values, p_kw: _Values, q_kvar: _Values) -> m.HeadFrame:
    """The feeder-head meter's frame from its per-phase readings, each (3,); absent phases (V = 0) left out.

    Powers are into the feeder [kW], [kvar]; the totals are the sums over the phases present. The readings
    may be arrays or lists (the bridge passes lists: indexing them is cheaper than making NumPy scalars).
    """
    present = [ph for ph in range(3) if v_mag_v[ph] > 0.0] or [0, 1, 2]
    phases = [m.HeadPhase(phase=PHASE_NAMES[ph], v_mag_v=float(v_mag_v[ph]), v_ang_deg=_wrap(v_ang_deg[ph]),
                          i_mag_a=float(i_mag_a[ph]), i_ang_deg=_wrap(i_ang_deg[ph]), p_kw=float(p_kw[ph]),
                          q_kvar=float(q_kvar[ph])) for ph in present]
    return m.HeadFrame(t_ns=t_ns, seq=seq, source="head", feeder_id=feeder_id, phases=phases,
                       p_kw=float(sum([p.p_kw for p in phases])), q_kvar=float(sum([p.q_kvar for p in phases])))


def pv_q_headroom_kvar(s_rated_kva: float, p_kw: float, q_at_night: bool) -> float:
    """The reactive power an inverter can give at active power ``p_kw`` [kvar], either way: ``sqrt(S² − P²)``, or 0
    when it has no active power and gives no reactive power at night (``q_at_night`` false). The simulated plants'
    frames and acks, the simulated SunSpec inverter and the SunSpec adapter all judge a set point by it.
    """
    if p_kw <= 0.0 and not q_at_night:
        return 0.0
    return math.sqrt(max(s_rated_kva**2 - p_kw**2, 0.0))


def pv_frame(*, plant: PvInverter, t_ns: int, seq: int, p_kw: _Values, q_kvar: _Values, v_v: _Values,
             available_p_kw: float, q_setpoint_kvar: float | None, q_at_night: bool = False) -> m.PvFrame:
    """A PV inverter's frame from its per-phase output (generator convention) and voltages, each (3,).

    ``q_available_kvar`` is the headroom ``sqrt(S² − P²)`` at the available active power [kvar]; 0 when there
    is no active power and the inverter gives no reactive power at night (``q_at_night`` false). The readings
    may be arrays or lists. ``q_setpoint_kvar`` is the commanded Q in force at the step (``plant.q_setpoint_kvar``
    then): passed, not read from ``plant``, because a publisher may build the frame after the state moved on.
    The frame reports the set point as the inverter applies it: clipped to ``±q_available_kvar`` (a request of
    1,000,000 kvar on a 1,860 kVA inverter reads as its headroom, not as the request).
    """
    present = [ph for ph in range(3) if v_v[ph] > 0.0] or [0, 1, 2]
    phases = [m.PvPhase(phase=PHASE_NAMES[ph], p_kw=float(p_kw[ph]), q_kvar=float(q_kvar[ph]),
                        v_mag_v=float(v_v[ph])) for ph in present]
    s_rated = plant.s_rated_kva
    p_avail = min(max(float(available_p_kw), 0.0), s_rated)
    q_avail = pv_q_headroom_kvar(s_rated, p_avail, q_at_night)
    q_applied = None if q_setpoint_kvar is None else min(max(float(q_setpoint_kvar), -q_avail), q_avail)
    return m.PvFrame(t_ns=t_ns, seq=seq, source=plant.plant_id, plant_id=plant.plant_id, phases=phases,
                     p_kw=float(sum([p.p_kw for p in phases])), q_kvar=float(sum([p.q_kvar for p in phases])),
                     s_rated_kva=s_rated,
                     q_available_kvar=q_avail, q_setpoint_kvar=q_applied, local_mode=plant.local_mode)


def reg_frame(*, reg: RegulatorController, t_ns: int, seq: int, phase: m.Phase, v120: float,
              v_compared_120: float, tap: int, setpoint_v120: float, band_v120: float,
              mode: Literal["local", "locked"]) -> m.RegFrame:
    """A regulator controller's frame: raw and compared secondary voltage [V, 120 V base], tap, and the
    settings in force at the step (``reg.setpoint_v120``, ``reg.band_v120``, ``reg.mode`` then).
    """
    return m.RegFrame(t_ns=t_ns, seq=seq, source=reg.regulator_id, regulator_id=reg.regulator_id,
                      phases=[m.RegPhase(phase=phase, v_120=float(v120))],
                      v_compared_120=float(v_compared_120), tap=int(tap), setpoint_v120=setpoint_v120,
                      band_v120=band_v120, mode=mode)


def cap_frame(*, cap: CapBankController, t_ns: int, seq: int, closed_steps: int, v_v: float,
              control_value: float | None, active: ActiveCommand | None) -> m.CapFrame:
    """A capacitor bank's frame: closed steps, bus voltage [V], its control's reading (None without a control or
    when not finite) and the command in force at the step (``cap.guard.active`` then; None: local control).
    """
    cv = (None if control_value is None or not math.isfinite(control_value)
          else min(max(float(control_value), -1e9), 1e9))
    return m.CapFrame(t_ns=t_ns, seq=seq, source=cap.capacitor_id, capacitor_id=cap.capacitor_id,
                      closed_steps=min(max(int(closed_steps), 0), cap.steps), steps=cap.steps,
                      kvar_rated=cap.kvar_rated, v_v=min(max(float(v_v), 0.0), 1e6), control_type=cap.control_type,
                      control_value=cv, mode="local" if active is None else "commanded",
                      cmd_id=None if active is None else active.cmd_id[:96],
                      valid_until_t_ns=None if active is None else active.valid_until_t_ns)


def _wrap(angle_deg: float) -> float:
    """An angle in (-180, 180] [deg] (noise may push a reading past ±180)."""
    a = (float(angle_deg) + 180.0) % 360.0 - 180.0
    return 180.0 if a == -180.0 else a
