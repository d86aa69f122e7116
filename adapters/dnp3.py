"""Dnp3Master: a DNP3 (IEEE 1815) master on one outstation over TCP, through opendnp3 (PyPI ``yadnp3``).

Reads with explicit headers (g30v6 analog inputs, g1v2 binary inputs, g40v4 analog output status, g10v2 binary
output status: double-precision analog values, whatever static variations the outstation defaults to), operates
analog outputs (g41v4, double precision) and CROBs (g12v1) by select-before-operate or direct operate, and returns the
outstation's answer per point. opendnp3 runs its callbacks on its own threads; every call here waits for its
result on an event with a deadline, and one call runs at a time. docs/dnp3.md.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any

import opendnp3 as dnp3

from simulator_bridge.field.dnp3_sim import MASTER_ADDR, OUTSTATION_ADDR, parse_dnp3_endpoint

__all__ = ["Dnp3LinkError", "Dnp3Master", "Dnp3Reading", "OperateOutcome"]

_READ_HEADERS = ((30, 6), (1, 2), (40, 4), (10, 2))
_ONLINE = 0x01  # the ONLINE bit of a point's flags (IEEE 1815 quality flags)


class Dnp3LinkError(ConnectionError):
    """The outstation did not answer (no link, a timeout, a bad response): the reason in words."""


@dataclass(frozen=True)
class Dnp3Reading:
    """One read of the outstation: values by point index, and the indices whose ONLINE flag was not set."""

    analog_inputs: dict[int, float] = field(default_factory=dict)
    binary_inputs: dict[int, bool] = field(default_factory=dict)
    analog_outputs: dict[int, float] = field(default_factory=dict)
    binary_outputs: dict[int, bool] = field(default_factory=dict)
    offline: tuple[str, ...] = ()


@dataclass(frozen=True)
class OperateOutcome:
    """The outstation's answer to one operate: ``status`` is its CommandStatus name (``SUCCESS``,
    ``OUT_OF_RANGE``, ``NOT_SUPPORTED``, ...), ``state`` how far the master got (``SUCCESS``, ``SELECT_FAIL``,
    ``OPERATE_FAIL``, ...).
    """

    status: str
    state: str

    @property
    def ok(self) -> bool:
        """Whether the outstation took it."""
        return self.status == "SUCCESS" and self.state == "SUCCESS"


class _Collector(dnp3.ISOEHandler):
    """Collects one read's values (called on opendnp3's thread)."""

    def __init__(self) -> None:
        super().__init__()
        self.lock = threading.Lock()
        self.values: dict[str, dict[int, Any]] = {"ai": {}, "bi": {}, "ao": {}, "bo": {}}
        self.offline: list[str] = []

    def BeginFragment(self, info: Any) -> None:  # noqa: N802 - opendnp3's interface
        pass

    def EndFragment(self, info: Any) -> None:  # noqa: N802
        pass

    def Process(self, info: Any, values: Any) -> None:  # noqa: N802
        with self.lock:
            for v in values:
                m = v.value
                kind = ("ai" if isinstance(m, dnp3.Analog) else "bi" if isinstance(m, dnp3.Binary)
                        else "ao" if isinstance(m, dnp3.AnalogOutputStatus)
                        else "bo" if isinstance(m, dnp3.BinaryOutputStatus) else None)
                if kind is None:
                    continue
                self.values[kind][int(v.index)] = m.value
                if not int(m.flags.value) & _ONLINE:
                    self.offline.append(f"{kind}{int(v.index)}")


class _App(dnp3.IMasterApplication):
    """Counts the user tasks (reads and operates) started and completed, and keeps the last one's result.

    Tasks complete in the order they were started, so a read waits until the completions reach its own number: an
    operate's completion, or a read that timed out and completes later, cannot end the next read (whose values go
    to its own collector).
    """

    def __init__(self) -> None:
        super().__init__()
        self._cond = threading.Condition()
        self._started = self._completed = 0
        self.result: Any = None

    def OnTaskComplete(self, info: Any) -> None:  # noqa: N802
        if info.type == dnp3.MasterTaskType.USER_TASK:
            with self._cond:
                self._completed += 1
                self.result = info.result
                self._cond.notify_all()

    def start(self) -> int:
        """Count a user task about to start; its number."""
        with self._cond:
            self._started += 1
            return self._started

    def wait(self, number: int, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for task ``number`` to complete; whether it did (its result is ``result``)."""
        with self._cond:
            return self._cond.wait_for(lambda: self._completed >= number, timeout_s)

    def AssignClassDuringStartup(self) -> bool:  # noqa: N802
        return False


class _Listener(dnp3.IChannelListener):
    def __init__(self) -> None:
        super().__init__()
        self.state: Any = dnp3.ChannelState.CLOSED
        self.opened = threading.Event()

    def OnStateChange(self, state: Any) -> None:  # noqa: N802
        self.state = state
        if state == dnp3.ChannelState.OPEN:
            self.opened.set()
        else:
            self.opened.clear()


class Dnp3Master:
    """A master on the outstation at ``endpoint`` (``tcp/127.0.0.1:PORT``); a context manager.

    ``timeout_s`` bounds each read and operate [s]; the channel reconnects by itself after a lost link
    (every ``retry_s``).
    """

    def __init__(self, endpoint: str, *, address: int = MASTER_ADDR, outstation_address: int = OUTSTATION_ADDR,
                 timeout_s: float = 2.0, retry_s: float = 0.5) -> None:
        self.host, self.port = parse_dnp3_endpoint(endpoint)
        self.endpoint = endpoint
        self.address = int(address)
        self.outstation_address = int(outstation_address)
        self.timeout_s = float(timeout_s)
        self.retry_s = float(retry_s)
        self._call = threading.Lock()
        self._manager: Any = None
        self._master: Any = None
        self._listener = _Listener()
        self._app = _App()

    def open(self) -> None:
        """Start the channel (it connects, and reconnects, by itself)."""
        if self._manager is not None:
            return
        self._manager = dnp3.DNP3Manager(1)
        retry_ms = max(1, int(self.retry_s * 1000))
        retry = dnp3.ChannelRetry(dnp3.TimeDuration.Milliseconds(retry_ms), dnp3.TimeDuration.Milliseconds(retry_ms))
        channel = self._manager.AddTCPClient(f"master-{self.port}", dnp3.LogLevels(), retry,
                                             [dnp3.IPEndpoint(self.host, self.port)], "127.0.0.1", self._listener)
        cfg = dnp3.MasterStackConfig()
        cfg.link.LocalAddr = self.address
        cfg.link.RemoteAddr = self.outstation_address
        cfg.master.disableUnsolOnStartup = True
        cfg.master.responseTimeout = dnp3.TimeDuration.Milliseconds(max(1, int(self.timeout_s * 1000)))
        self._master = channel.AddMaster(f"master-{self.port}", _Collector(), self._app, cfg)
        self._master.Enable()

    def close(self) -> None:
        """Stop the channel and the library's threads."""
        manager, self._manager, self._master = self._manager, None, None
        if manager is not None:
            manager.Shutdown()

    def __enter__(self) -> Dnp3Master:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def link_up(self) -> bool:
        """Whether the TCP channel is open now."""
        return self._listener.opened.is_set()

    def wait_open(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for the channel to be open; whether it is."""
        return self._listener.opened.wait(timeout_s)

    def read(self) -> Dnp3Reading:
        """Read every point of the map's types; raises Dnp3LinkError when the outstation does not answer."""
        if self._master is None:
            raise Dnp3LinkError("the master is not open")
        with self._call:
            collector = _Collector()
            headers = [dnp3.Header.AllObjects(g, v) for g, v in _READ_HEADERS]
            task = self._app.start()
            self._master.Scan(headers, collector)
            if not self._app.wait(task, self.timeout_s * 2 + 1.0):
                raise Dnp3LinkError(f"no answer from {self.endpoint} within {self.timeout_s * 2 + 1.0:.1f} s")
            if self._app.result != dnp3.TaskCompletion.SUCCESS:
                raise Dnp3LinkError(f"read of {self.endpoint} failed: {self._app.result.name}")
            with collector.lock:
                v = collector.values
                return Dnp3Reading(analog_inputs={i: float(x) for i, x in v["ai"].items()},
                                   binary_inputs={i: bool(x) for i, x in v["bi"].items()},
                                   analog_outputs={i: float(x) for i, x in v["ao"].items()},
                                   binary_outputs={i: bool(x) for i, x in v["bo"].items()},
                                   offline=tuple(collector.offline))

    def operate_analog(self, index: int, value: float, *, select: bool = True) -> OperateOutcome:
        """Write ``value`` to analog output ``index`` (g41v4, double precision), by select-before-operate or direct
        operate.
        """
        return self._operate(dnp3.AnalogOutputDouble64(float(value)), index, select=select)

    def operate_crob(self, index: int, *, close: bool, select: bool = True) -> OperateOutcome:
        """A CROB on binary output ``index``: ``PULSE_ON`` with ``CLOSE`` (close) or ``TRIP``."""
        tcc = dnp3.TripCloseCode.CLOSE if close else dnp3.TripCloseCode.TRIP
        return self._operate(dnp3.ControlRelayOutputBlock(dnp3.OperationType.PULSE_ON, tcc), index, select=select)

    def _operate(self, command: Any, index: int, *, select: bool) -> OperateOutcome:
        if self._master is None:
            raise Dnp3LinkError("the master is not open")
        with self._call:
            done = threading.Event()
            out: list[OperateOutcome] = []

            def on_result(result: Any) -> None:  # on opendnp3's thread; the result is valid only here
                points = [(p.state.name, p.status.name) for p in result.to_list()]
                if result.summary != dnp3.TaskCompletion.SUCCESS or not points:
                    out.append(OperateOutcome(status=result.summary.name, state="NO_RESPONSE"))
                else:
                    out.append(OperateOutcome(status=points[0][1], state=points[0][0]))
                done.set()

            self._app.start()  # an operate is a user task too: counted, so that no read takes its completion
            if select:
                self._master.SelectAndOperate(command, int(index), on_result)
            else:
                self._master.DirectOperate(command, int(index), on_result)
            wait_s = self.timeout_s * 2 + 1.0
            if not done.wait(wait_s):
                raise Dnp3LinkError(f"no answer to an operate from {self.endpoint} within {wait_s:.1f} s")
            if out[0].state == "NO_RESPONSE":
                raise Dnp3LinkError(f"operate on {self.endpoint} failed: {out[0].status}")
            return out[0]
