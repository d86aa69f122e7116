"""A simulated regulator control and capacitor bank controller, each a DNP3 (IEEE 1815) outstation on TCP.

The DNP3 stack is opendnp3 (PyPI ``yadnp3``, docs/dnp3.md): this module only holds the devices' points and their
logic ("firmware"); it builds no DNP3 frame. The point maps are docs/dnp3.md's tables.

Whoever simulates the feeder drives a device: it sets its measurements (``set_measurements``) and asks what is in
force (:meth:`SimulatedRegulatorControl.setpoint_in_force`, :meth:`SimulatedCapBankController.commanded_closed`;
None: the device is on its local control, as the simulated controls are without a command).

The devices' logic, run on the DNP3 stack's thread for every select and operate:

* **Checks**: a value outside the point's range (set point, band, hold time; NaN too) is refused with
  ``OUT_OF_RANGE``, a point the map does not hold or an operation it does not take with ``NOT_SUPPORTED``, the
  bank's CROB by direct operate (select-before-operate only) with ``NOT_SUPPORTED``, a set point or CROB while the
  hold time is 0 with ``BLOCKED``. Each refusal is counted (:attr:`refused_operates`) and changes nothing.
* **Hold timer**: a remote set point (or bank state) holds for the hold time written before it (analog output 2 of
  the regulator, 0 of the bank) on the device's own clock (``clock_ns``), then the device is back on its local
  control; a hold time of 0 releases it at once. So a command ends *in the device*, whether a master is still
  there or not. The timer is checked by a ticker thread, at every operate and at every ``set_measurements``.
* **One master**: a second TCP connection while the master's is open is closed by the outstation (opendnp3's
  server channel in ``ServerAcceptMode.CloseNew``); the master keeps its link.

:meth:`stop` and :meth:`start` simulate a lost and restored link (the outstation goes away, its state stays).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import opendnp3 as dnp3

from simulator_bridge.errors import SimulatorError
from simulator_bridge.field.devices import BAND_RANGE_V120, SETPOINT_RANGE_V120

__all__ = ["HOLD_MAX_S", "MASTER_ADDR", "OUTSTATION_ADDR", "CapBankPoints", "Dnp3SimError", "RegulatorPoints",
           "RemoteSetpoint", "SimulatedCapBankController", "SimulatedRegulatorControl", "parse_dnp3_endpoint"]

log = logging.getLogger(__name__)

OUTSTATION_ADDR = 10
"""The outstation's DNP3 link address (default)."""
MASTER_ADDR = 1
"""The master's DNP3 link address (default)."""
HOLD_MAX_S = 86_400
"""The longest hold time a device takes [s]."""
_TICK_S = 0.1  # how often the ticker thread checks the hold timer [s of wall time]


class Dnp3SimError(SimulatorError):
    """A simulated DNP3 device cannot be built or started (bad endpoint, bad rating, a bank of several steps)."""


class RegulatorPoints:
    """The regulator control's point indices (docs/dnp3.md, "Regulator control")."""

    AI_V_COMPARED_120 = 0
    AI_TAP = 1
    AI_LOAD_CURRENT_A = 2
    AI_SETPOINT_120 = 3
    AI_BAND_120 = 4
    AI_V_120 = 5
    BI_REMOTE = 0
    AO_SETPOINT_120 = 0
    AO_BAND_120 = 1
    AO_HOLD_S = 2


class CapBankPoints:
    """The capacitor bank controller's point indices (docs/dnp3.md, "Capacitor bank controller")."""

    BI_CLOSED = 0
    BI_REMOTE = 1
    AI_V = 0
    AI_CONTROL_VALUE = 1
    BO_SWITCH = 0
    AO_HOLD_S = 0


@dataclass(frozen=True)
class RemoteSetpoint:
    """A regulator's remote set point in force: set point and band [V on the 120 V base], until ``until_ns``."""

    setpoint_v120: float
    band_v120: float
    until_ns: int


def parse_dnp3_endpoint(text: str) -> tuple[str, int]:
    """``tcp/127.0.0.1:PORT`` -> (host, port); anything else (another host, a bad port) raises Dnp3SimError.

    DNP3 runs on loopback only in this project (docs/security.md).
    """
    prefix = "tcp/127.0.0.1:"
    if not text.startswith(prefix):
        raise Dnp3SimError(f"DNP3 endpoint {text!r}: give tcp/127.0.0.1:PORT (loopback only)")
    port_text = text[len(prefix):]
    if not port_text.isdecimal() or not 0 < int(port_text) < 65536:
        raise Dnp3SimError(f"DNP3 endpoint {text!r}: the port must be 1..65535")
    return "127.0.0.1", int(port_text)


def _hold_ok(value: float) -> bool:
    return math.isfinite(value) and 0.0 <= value <= HOLD_MAX_S


class _Outstation(ABC):
    """One opendnp3 outstation on a TCP server channel, with the ticker for the device's hold timer.

    Its database holds ``_DB_SIZE`` points of every type (the binding sizes them all alike); those past the
    device's map are never written and read with their ONLINE flag cleared.
    """

    _DB_SIZE = 5

    def __init__(self, *, name: str, port: int, host: str, clock_ns: Callable[[], int], address: int,
                 master_address: int) -> None:
        if host != "127.0.0.1":
            raise Dnp3SimError(f"host {host!r}: DNP3 outstations listen on 127.0.0.1 only")
        if not 0 < int(port) < 65536:
            raise Dnp3SimError(f"port {port!r} is not 1..65535")
        self.name = name
        self.host = host
        self.port = int(port)
        self.address = int(address)
        self.master_address = int(master_address)
        self._clock = clock_ns
        self._lock = threading.RLock()
        self._manager: Any = None
        self._outstation: Any = None
        self._ticker: threading.Thread | None = None
        self._stop = threading.Event()
        self._listener = _ChannelListener()
        self.operates = 0  # operates taken
        self.refused_operates = 0  # selects and operates refused (out of range, not supported, blocked)
        self._refusals_logged = 0

    # ------------------------------------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Listen on ``tcp/host:port`` (again, after :meth:`stop`) and start the hold timer's ticker."""
        with self._lock:
            if self._manager is not None:
                return
            manager = dnp3.DNP3Manager(1)
            channel = manager.AddTCPServer(self.name, dnp3.LogLevels(), dnp3.ServerAcceptMode.CloseNew,
                                           dnp3.IPEndpoint(self.host, self.port), self._listener)
            cfg = dnp3.OutstationStackConfig(dnp3.DatabaseConfig(self._DB_SIZE))
            cfg.link.LocalAddr = self.address
            cfg.link.RemoteAddr = self.master_address
            cfg.outstation.params.allowUnsolicited = False
            self._outstation = channel.AddOutstation(self.name, _CommandHandler(self), dnp3.IOutstationApplication(),
                                                     cfg)
            self._manager = manager
            self._publish()
            self._outstation.Enable()
        self._stop.clear()
        self._ticker = threading.Thread(target=self._tick_loop, name=f"dnp3-{self.name}-hold", daemon=True)
        self._ticker.start()

    def stop(self) -> None:
        """Take the outstation off the network (a lost link); its state and timers stay."""
        self._stop.set()
        if self._ticker is not None:
            self._ticker.join(timeout=5.0)
            self._ticker = None
        with self._lock:
            manager, self._manager, self._outstation = self._manager, None, None
        if manager is not None:
            manager.Shutdown()

    def __enter__(self) -> _Outstation:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def endpoint(self) -> str:
        """``tcp/host:port``."""
        return f"tcp/{self.host}:{self.port}"

    @property
    def master_connected(self) -> bool:
        """Whether a master's TCP connection is open now."""
        return self._listener.opened.is_set()

    # -------------------------------------------------------------------------------------------- the device
    def _tick_loop(self) -> None:
        while not self._stop.wait(_TICK_S):
            self.tick()

    def tick(self) -> None:
        """Check the hold timer on the device's clock (the device is back on local control once it ran out)."""
        with self._lock:
            if self._expire(self._clock()):
                self._publish()

    def _refuse(self, status: Any, why: str) -> Any:
        self.refused_operates += 1
        if self._refusals_logged == 0:
            log.warning("%s: %s refused: %s (further refusals are counted only)", self.name, status.name, why)
        self._refusals_logged += 1
        return status

    def _apply(self, builder: Any) -> None:
        if self._outstation is not None:
            self._outstation.Apply(builder.Build())

    @abstractmethod
    def check(self, command: Any, index: int, *, direct: bool) -> Any:
        """The status a select (or an operate) of ``command`` on ``index`` gets, without acting [CommandStatus]."""

    def operate(self, command: Any, index: int, *, direct: bool) -> Any:
        """Check and act on ``command`` at ``index`` (``_act``, after dropping a hold that ran out); the status for
        the master [CommandStatus].
        """
        status = self.check(command, index, direct=direct)
        if status != dnp3.CommandStatus.SUCCESS:
            return status
        now = self._clock()
        self._expire(now)
        self._act(command, index, now)
        self.operates += 1
        self._publish()
        return dnp3.CommandStatus.SUCCESS

    @abstractmethod
    def _act(self, command: Any, index: int, now_ns: int) -> None:
        """Apply an accepted ``command`` on ``index`` at ``now_ns`` to the device's state."""

    @abstractmethod
    def _expire(self, now_ns: int) -> bool:
        """Drop a remote command whose hold ran out at ``now_ns``; whether one was dropped."""

    @abstractmethod
    def _publish(self) -> None:
        """Put the device's state into the outstation's database."""


class _ChannelListener(dnp3.IChannelListener):
    """The server channel's state, on opendnp3's thread: ``opened`` is set while a master's connection is open."""

    def __init__(self) -> None:
        super().__init__()
        self.opened = threading.Event()

    def OnStateChange(self, state: Any) -> None:  # noqa: N802 - opendnp3's interface
        if state == dnp3.ChannelState.OPEN:
            self.opened.set()
        else:
            self.opened.clear()


class _CommandHandler(dnp3.ICommandHandler):
    """opendnp3's command callbacks, on its thread, handed to the device under its lock.

    No Python exception is let back into the C++ stack (whose thread has no handler for it): an unexpected one is
    logged, counted as a refusal and answered ``HARDWARE_ERROR``, so bad input never takes the device down.
    """

    def __init__(self, device: _Outstation) -> None:
        super().__init__()
        self._device = device

    def Begin(self) -> None:  # noqa: N802 - opendnp3's interface
        pass

    def End(self) -> None:  # noqa: N802
        pass

    def Select(self, command: Any, index: int) -> Any:  # noqa: N802
        try:
            with self._device._lock:
                return self._device.check(command, int(index), direct=False)
        except Exception:  # the C++ caller cannot take a Python exception (see the class docstring)
            log.exception("%s: select failed", self._device.name)
            self._device.refused_operates += 1
            return dnp3.CommandStatus.HARDWARE_ERROR

    def Operate(self, command: Any, index: int, handler: Any, op_type: Any) -> Any:  # noqa: N802
        try:
            with self._device._lock:
                return self._device.operate(command, int(index),
                                            direct=op_type != dnp3.OperateType.SelectBeforeOperate)
        except Exception:  # the C++ caller cannot take a Python exception (see the class docstring)
            log.exception("%s: operate failed", self._device.name)
            self._device.refused_operates += 1
            return dnp3.CommandStatus.HARDWARE_ERROR


class SimulatedRegulatorControl(_Outstation):
    """A regulator control behind DNP3 on ``tcp/127.0.0.1:port``.

    Its database holds 6 points of every type (analog inputs 0..5).

    Parameters
    ----------
    regulator_id : the device id (the outstation's name in logs).
    tap_max : the tap range is ``-tap_max..tap_max``.
    default_setpoint_v120, default_band_v120 : its local set point and band [V, 120 V base].
    setpoint_range_v120 : the set points it takes [V, 120 V base]: the command contract's by default; a control
        configured with narrower limits refuses the others with ``OUT_OF_RANGE``.
    port : TCP port on 127.0.0.1. clock_ns : the device's clock [ns] for the hold timer.
    address, master_address : the DNP3 link addresses of the outstation and of its master.
    """

    _DB_SIZE = 6

    def __init__(self, *, regulator_id: str, tap_max: int, default_setpoint_v120: float, default_band_v120: float,
                 port: int, host: str = "127.0.0.1", clock_ns: Callable[[], int] = time.monotonic_ns,
                 setpoint_range_v120: tuple[float, float] = SETPOINT_RANGE_V120,
                 address: int = OUTSTATION_ADDR, master_address: int = MASTER_ADDR) -> None:
        lo, hi = float(setpoint_range_v120[0]), float(setpoint_range_v120[1])
        if not SETPOINT_RANGE_V120[0] <= lo < hi <= SETPOINT_RANGE_V120[1]:
            raise Dnp3SimError(f"regulator {regulator_id!r}: set point range {setpoint_range_v120!r} is not within "
                               f"{SETPOINT_RANGE_V120}")
        if not (lo <= default_setpoint_v120 <= hi
                and BAND_RANGE_V120[0] <= default_band_v120 <= BAND_RANGE_V120[1]):
            raise Dnp3SimError(f"regulator {regulator_id!r}: local set point {default_setpoint_v120!r} V / band "
                               f"{default_band_v120!r} V outside {(lo, hi)} / {BAND_RANGE_V120}")
        if int(tap_max) <= 0:
            raise Dnp3SimError(f"regulator {regulator_id!r}: tap_max {tap_max!r} must be positive")
        super().__init__(name=regulator_id, port=port, host=host, clock_ns=clock_ns, address=address,
                         master_address=master_address)
        self.regulator_id = regulator_id
        self.tap_max = int(tap_max)
        self.default_setpoint_v120 = float(default_setpoint_v120)
        self.default_band_v120 = float(default_band_v120)
        self.setpoint_range_v120 = (lo, hi)
        self._v_compared_120 = 0.0
        self._v_120 = 0.0
        self._tap = 0
        self._i_a = 0.0
        # analog outputs as last written (what the master reads back, g40)
        self._ao = {RegulatorPoints.AO_SETPOINT_120: self.default_setpoint_v120,
                    RegulatorPoints.AO_BAND_120: self.default_band_v120, RegulatorPoints.AO_HOLD_S: 0.0}
        self._remote: RemoteSetpoint | None = None
        self.expiries = 0

    def set_measurements(self, *, v_compared_120: float, v_120: float, tap: int, load_current_a: float) -> None:
        """The control's readings: compared voltage and the secondary voltage without line-drop compensation
        [V, 120 V base], tap [steps], load current [A].
        """
        with self._lock:
            self._v_compared_120 = float(v_compared_120)
            self._v_120 = float(v_120)
            self._tap = int(tap)
            self._i_a = float(load_current_a)
            self._expire(self._clock())
            self._publish()

    def setpoint_in_force(self) -> RemoteSetpoint | None:
        """The remote set point in force, or None (the control is on its local set point and band)."""
        with self._lock:
            if self._expire(self._clock()):
                self._publish()
            return self._remote

    @property
    def analog_outputs(self) -> dict[int, float]:
        """The analog outputs as last written (index -> value)."""
        with self._lock:
            return dict(self._ao)

    def check(self, command: Any, index: int, *, direct: bool) -> Any:
        """The regulator's checks (module docstring): range, hold time, the map's analog outputs only."""
        if isinstance(command, dnp3.ControlRelayOutputBlock):
            return self._refuse(dnp3.CommandStatus.NOT_SUPPORTED, f"a CROB on index {index}: the regulator has "
                                "no binary output")
        value = float(command.value)
        match index:
            case RegulatorPoints.AO_SETPOINT_120:
                lo, hi = self.setpoint_range_v120
                if not lo <= value <= hi:
                    return self._refuse(dnp3.CommandStatus.OUT_OF_RANGE, f"set point {value} V outside {lo}..{hi} V")
                if self._ao[RegulatorPoints.AO_HOLD_S] <= 0.0:
                    return self._refuse(dnp3.CommandStatus.BLOCKED, "set point with a hold time of 0: write "
                                        f"analog output {RegulatorPoints.AO_HOLD_S} first")
            case RegulatorPoints.AO_BAND_120:
                if not BAND_RANGE_V120[0] <= value <= BAND_RANGE_V120[1]:
                    return self._refuse(dnp3.CommandStatus.OUT_OF_RANGE, f"band {value} V outside {BAND_RANGE_V120} V")
            case RegulatorPoints.AO_HOLD_S:
                if not _hold_ok(value):
                    return self._refuse(dnp3.CommandStatus.OUT_OF_RANGE, f"hold time {value} s outside 0..{HOLD_MAX_S}")
            case _:
                return self._refuse(dnp3.CommandStatus.NOT_SUPPORTED, f"analog output {index} is not in the map")
        return dnp3.CommandStatus.SUCCESS

    def _act(self, command: Any, index: int, now_ns: int) -> None:
        """Write an analog output; a set point write puts the remote set point in force for the hold time."""
        value = float(command.value)
        self._ao[index] = value
        if index == RegulatorPoints.AO_SETPOINT_120:
            hold_ns = int(round(self._ao[RegulatorPoints.AO_HOLD_S] * 1e9))
            self._remote = RemoteSetpoint(setpoint_v120=value, band_v120=self._ao[RegulatorPoints.AO_BAND_120],
                                          until_ns=now_ns + hold_ns)
        elif index == RegulatorPoints.AO_HOLD_S and value == 0.0:
            self._remote = None

    def _expire(self, now_ns: int) -> bool:
        if self._remote is not None and now_ns > self._remote.until_ns:
            self._remote = None
            self.expiries += 1
            return True
        return False

    def _publish(self) -> None:
        remote = self._remote
        b = dnp3.UpdateBuilder()
        b.Update(dnp3.Analog(self._v_compared_120), RegulatorPoints.AI_V_COMPARED_120)
        b.Update(dnp3.Analog(float(self._tap)), RegulatorPoints.AI_TAP)
        b.Update(dnp3.Analog(self._i_a), RegulatorPoints.AI_LOAD_CURRENT_A)
        b.Update(dnp3.Analog(self._v_120), RegulatorPoints.AI_V_120)
        b.Update(dnp3.Analog(self.default_setpoint_v120 if remote is None else remote.setpoint_v120),
                 RegulatorPoints.AI_SETPOINT_120)
        b.Update(dnp3.Analog(self.default_band_v120 if remote is None else remote.band_v120),
                 RegulatorPoints.AI_BAND_120)
        b.Update(dnp3.Binary(remote is not None), RegulatorPoints.BI_REMOTE)
        for index, value in self._ao.items():
            b.Update(dnp3.AnalogOutputStatus(value), index)
        self._apply(b)


class SimulatedCapBankController(_Outstation):
    """A capacitor bank controller (one step) behind DNP3 on ``tcp/127.0.0.1:port``.

    Parameters
    ----------
    capacitor_id : the device id. steps : the bank's steps (1 only: docs/dnp3.md).
    port, clock_ns, address, master_address : as :class:`SimulatedRegulatorControl`.
    """

    _DB_SIZE = 2

    def __init__(self, *, capacitor_id: str, port: int, steps: int = 1, host: str = "127.0.0.1",
                 clock_ns: Callable[[], int] = time.monotonic_ns, address: int = OUTSTATION_ADDR,
                 master_address: int = MASTER_ADDR) -> None:
        if int(steps) != 1:
            raise Dnp3SimError(f"capacitor bank {capacitor_id!r} has {steps} steps: the DNP3 map serves banks of "
                               "one step (docs/dnp3.md)")
        super().__init__(name=capacitor_id, port=port, host=host, clock_ns=clock_ns, address=address,
                         master_address=master_address)
        self.capacitor_id = capacitor_id
        self._closed = False
        self._v_v = 0.0
        self._control_value = 0.0
        self._hold_s = 0.0
        self._commanded: tuple[bool, int] | None = None  # (closed, until_ns)
        self._last_crob: bool | None = None
        self.expiries = 0

    def set_measurements(self, *, closed: bool, v_v: float, control_value: float | None) -> None:
        """The bank's state (closed or not), bus voltage [V] and its control's reading (None: no control)."""
        with self._lock:
            self._closed = bool(closed)
            self._v_v = float(v_v)
            self._control_value = 0.0 if control_value is None else float(control_value)
            self._expire(self._clock())
            self._publish()

    def commanded_closed(self) -> bool | None:
        """The commanded state in force (True: closed), or None (the bank is on its local control)."""
        with self._lock:
            if self._expire(self._clock()):
                self._publish()
            return None if self._commanded is None else self._commanded[0]

    @staticmethod
    def _crob_close(command: Any) -> bool | None:
        """True: close, False: trip, None: a code the controller does not take."""
        op, tcc = command.opType, command.tcc
        if op == dnp3.OperationType.LATCH_ON and tcc == dnp3.TripCloseCode.NUL:
            return True
        if op == dnp3.OperationType.LATCH_OFF and tcc == dnp3.TripCloseCode.NUL:
            return False
        if op == dnp3.OperationType.PULSE_ON and tcc == dnp3.TripCloseCode.CLOSE:
            return True
        if op == dnp3.OperationType.PULSE_ON and tcc == dnp3.TripCloseCode.TRIP:
            return False
        return None

    def check(self, command: Any, index: int, *, direct: bool) -> Any:
        """The bank's checks (module docstring): the switch by select-before-operate, the hold time's range."""
        if isinstance(command, dnp3.ControlRelayOutputBlock):
            if index != CapBankPoints.BO_SWITCH:
                return self._refuse(dnp3.CommandStatus.NOT_SUPPORTED, f"binary output {index} is not in the map")
            if direct:
                return self._refuse(dnp3.CommandStatus.NOT_SUPPORTED, "the switch takes select-before-operate only")
            if command.clear or self._crob_close(command) is None:
                return self._refuse(dnp3.CommandStatus.NOT_SUPPORTED,
                                    f"CROB {command.opType.name}/{command.tcc.name}: give LATCH_ON/LATCH_OFF or "
                                    "PULSE_ON with CLOSE/TRIP")
            if self._hold_s <= 0.0:
                return self._refuse(dnp3.CommandStatus.BLOCKED, "switch with a hold time of 0: write analog output "
                                    f"{CapBankPoints.AO_HOLD_S} first")
            return dnp3.CommandStatus.SUCCESS
        if index != CapBankPoints.AO_HOLD_S:
            return self._refuse(dnp3.CommandStatus.NOT_SUPPORTED, f"analog output {index} is not in the map")
        value = float(command.value)
        if not _hold_ok(value):
            return self._refuse(dnp3.CommandStatus.OUT_OF_RANGE, f"hold time {value} s outside 0..{HOLD_MAX_S}")
        return dnp3.CommandStatus.SUCCESS

    def _act(self, command: Any, index: int, now_ns: int) -> None:
        """Switch the bank (held for the hold time) or write the hold time (0 releases it)."""
        if isinstance(command, dnp3.ControlRelayOutputBlock):
            close = bool(self._crob_close(command))
            self._commanded = (close, now_ns + int(round(self._hold_s * 1e9)))
            self._last_crob = close
        else:
            self._hold_s = float(command.value)
            if self._hold_s == 0.0:
                self._commanded = None

    def _expire(self, now_ns: int) -> bool:
        if self._commanded is not None and now_ns > self._commanded[1]:
            self._commanded = None
            self.expiries += 1
            return True
        return False

    def _publish(self) -> None:
        b = dnp3.UpdateBuilder()
        b.Update(dnp3.Binary(self._closed), CapBankPoints.BI_CLOSED)
        b.Update(dnp3.Binary(self._commanded is not None), CapBankPoints.BI_REMOTE)
        b.Update(dnp3.Analog(self._v_v), CapBankPoints.AI_V)
        b.Update(dnp3.Analog(self._control_value), CapBankPoints.AI_CONTROL_VALUE)
        b.Update(dnp3.BinaryOutputStatus(bool(self._last_crob)), CapBankPoints.BO_SWITCH)
        b.Update(dnp3.AnalogOutputStatus(self._hold_s), CapBankPoints.AO_HOLD_S)
        self._apply(b)
