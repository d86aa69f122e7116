"""The publisher process: a step's results handed over through shared memory to a child that publishes them.

:class:`PublisherProcess` starts a child process with its own Zenoh session and its own
:class:`~simulator_bridge.bus.publishing.StepFramer` (``publisher="process"``): the Python work of publishing then
runs beside the power flow, on the other core, instead of under the stepping process's GIL (``docs/bridge.md``,
Speed).

The hand-over is a ring of ``depth`` slots in shared memory (:class:`StepPacker`: the step's readings, node
voltages, taps and the device settings in force, a few µs to write) and two semaphores (slots free, slots
ready). The child publishes the steps in order with the same code, hence the same messages, byte for byte per
key, as inline publishing; it writes when it put each control step's head frame (the decision round trip
starts there) into shared memory. It never touches the simulation, so the stepping process never waits for
it, except for a free slot (``depth`` steps behind) and at the end (:meth:`PublisherProcess.close`, which
returns the child's counters and final metrics frame). A child that fails or dies fails the run with a
``PublisherError`` at the next hand-over; every wait is bounded.
"""

from __future__ import annotations

import logging
import math
import multiprocessing as mp
import os
import signal
import time
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np

from schemas import messages as m
from schemas.bus import BusConfig, open_session
from simulator_bridge.bus.publishing import READING_FIELDS, DeviceSettings, FramerSpec, PublisherError, StepFramer
from simulator_bridge.opendss.readout import FieldReadings

__all__ = [
    "PublisherProcess",
    "PublisherReport",
    "StepPacker",
    "child_bus",
]

log = logging.getLogger(__name__)

_CMD_ID_WORDS = 12  # a cmd_id (at most 96 bytes of ASCII) packed into int64 words
_POLL_S = 0.05  # longest a wait goes without looking at the other process [s]
_WAIT_S = 60.0  # longest the stepping process waits for the child to take a step or answer [s]
_START_S = 60.0  # longest the child may take to start (a fresh interpreter, imports, a Zenoh session) [s]
_CTRL_RING = 64  # control-step head publication times kept for the round trip

# ------------------------------------------------------------------------------------------ packing
@dataclass(frozen=True)
class _Field:
    name: str
    shape: tuple[int, ...]
    start: int
    stop: int


class StepPacker:
    """The layout of one step in a shared-memory slot: floats and int64s, written and read as NumPy views.

    The *checked* floats (readings, node voltages, PV P and Q) come first, so one sum over them tells
    whether the step is finite; the device settings follow (a NaN set point is "none").
    """

    def __init__(self, n_nodes: int, n_pv: int, n_reg: int, n_cap: int = 0) -> None:
        shapes: dict[str, tuple[int, ...]] = {name: (3,) for name in READING_FIELDS if name.startswith("head_")}
        shapes |= {"pv_p_kw": (n_pv, 3), "pv_q_kvar": (n_pv, 3), "pv_v_v": (n_pv, 3), "reg_v120": (n_reg,),
                   "reg_v120_compared": (n_reg,), "reg_tap": (n_reg,), "cap_states": (n_cap,),
                   "cap_v_v": (n_cap,), "cap_control_value": (n_cap,)}
        fields, at = [], 0
        for name in READING_FIELDS:  # FieldReadings' shapes (see its docstring)
            size = int(np.prod(shapes[name], dtype=np.int64))
            fields.append(_Field(name, shapes[name], at, at + size))
            at += size
        for name, n in (("v_pu", n_nodes), ("pv_q_kvar", n_pv), ("pv_p_kw", n_pv)):  # StepResult's own
            fields.append(_Field(name, (n,), at, at + n))
            at += n
        self.n_checked = at
        self.readings = tuple(fields[:len(READING_FIELDS)])
        self.step_fields = tuple(fields[len(READING_FIELDS):])
        self.n_pv, self.n_reg, self.n_cap = n_pv, n_reg, n_cap
        self.n_float = at + n_pv + 2 * n_reg  # + PV set points, regulator set points and bands
        # kind, t_ns, step, n_step; taps, changes, modes; caps, switches; per bank the command in force: valid until
        # (-1: none) and its cmd_id's bytes
        self._cap_cmd_at = 4 + 3 * n_reg + 2 * n_cap
        self.n_int = self._cap_cmd_at + (1 + _CMD_ID_WORDS) * n_cap
        # a bank without a CapControl reads NaN: that field is left out of the finiteness check
        cv = next(f for f in self.readings if f.name == "cap_control_value")
        self._nan_ok = (cv.start, cv.stop)
        self._last: DeviceSettings | None = None  # the settings last packed, and their packed form
        self._settings_f = np.zeros(n_pv + 2 * n_reg)
        self._modes = np.zeros(n_reg, np.int64)
        self._cap_cmds = np.full((n_cap, 1 + _CMD_ID_WORDS), -1, np.int64)

    def pack(self, fs: np.ndarray, ints: np.ndarray, res: Any, n_step: int, settings: DeviceSettings) -> bool:
        """Write ``res`` and ``settings`` into the slot ``fs`` (floats), ``ints``; returns whether every checked
        number is finite (their sum is: NaN and inf never leave a float sum; an overflowing sum is re-checked).
        """
        rd = res.readings
        checked = fs[:self.n_checked]
        np.concatenate([getattr(rd, f.name).ravel() for f in self.readings]
                       + [res.v_pu, res.pv_q_kvar, res.pv_p_kw], out=checked)
        if settings is not self._last:  # the settings change a few times a day: packed once per change
            self._last = settings
            r = self.n_reg
            self._settings_f = np.array([math.nan if q is None else q for q in settings.pv_q_setpoint_kvar]
                                        + list(settings.reg_setpoint_v120) + list(settings.reg_band_v120), float)
            self._modes = np.array([mode == "locked" for mode in settings.reg_mode], np.int64).reshape(r)
            self._cap_cmds = _pack_cap_commands(settings.cap_command, self.n_cap)
        fs[self.n_checked:] = self._settings_f
        r = self.n_reg
        ints[1], ints[2], ints[3] = int(res.t_ns), int(res.step), n_step
        ints[4:4 + r] = res.taps
        ints[4 + r:4 + 2 * r] = res.tap_changes
        ints[4 + 2 * r:4 + 3 * r] = self._modes
        c = self.n_cap
        ints[4 + 3 * r:4 + 3 * r + c] = res.cap_states
        ints[4 + 3 * r + c:self._cap_cmd_at] = res.cap_switches
        ints[self._cap_cmd_at:] = self._cap_cmds.ravel()
        a, b = self._nan_ok
        if a == b:
            return math.isfinite(float(checked.sum())) or bool(np.isfinite(checked).all())
        rest = float(checked[:a].sum()) + float(checked[b:].sum())
        return math.isfinite(rest) or bool(np.isfinite(checked[:a]).all() and np.isfinite(checked[b:]).all())

    def unpack(self, fs: np.ndarray, ints: np.ndarray) -> tuple[Any, int, DeviceSettings]:
        """(a ``StepResult`` with copies of the arrays, the step's number in the run, its device settings)."""
        from simulator_bridge.simulation.qsts import StepResult

        r, k, at = self.n_reg, self.n_pv, self.n_checked
        fields = {f.name: fs[f.start:f.stop].reshape(f.shape).copy() for f in self.readings}
        fields["cap_states"] = fields["cap_states"].astype(int)
        readings = FieldReadings(**fields)
        c = self.n_cap
        v_pu, pv_q, pv_p = (fs[f.start:f.stop].copy() for f in self.step_fields)
        res = StepResult(step=int(ints[2]), t_ns=int(ints[1]), readings=readings, v_pu=v_pu,
                         taps=ints[4:4 + r].copy(), tap_changes=ints[4 + r:4 + 2 * r].copy(), pv_q_kvar=pv_q,
                         pv_p_kw=pv_p, cap_states=ints[4 + 3 * r:4 + 3 * r + c].copy(),
                         cap_switches=ints[4 + 3 * r + c:4 + 3 * r + 2 * c].copy())
        q_set = fs[at:at + k].tolist()
        settings = DeviceSettings(
            pv_q_setpoint_kvar=tuple(None if math.isnan(q) else q for q in q_set),
            reg_setpoint_v120=tuple(fs[at + k:at + k + r].tolist()),
            reg_band_v120=tuple(fs[at + k + r:at + k + 2 * r].tolist()),
            reg_mode=tuple("locked" if x else "local" for x in ints[4 + 2 * r:4 + 3 * r].tolist()),
            cap_command=_unpack_cap_commands(ints[self._cap_cmd_at:], self.n_cap))
        return res, int(ints[3]), settings


def _pack_cap_commands(commands: tuple[tuple[str, int] | None, ...], n_cap: int) -> np.ndarray:
    """(n_cap, 1 + words) int64: per bank its command's valid_until_t_ns (-1: none) and its cmd_id, NUL padded."""
    out = np.full((n_cap, 1 + _CMD_ID_WORDS), -1, np.int64)
    for c, command in enumerate(commands or (None,) * n_cap):
        if command is not None:
            raw = command[0].encode("ascii")[:8 * _CMD_ID_WORDS].ljust(8 * _CMD_ID_WORDS, b"\0")
            out[c, 0] = command[1]
            out[c, 1:] = np.frombuffer(raw, dtype=np.int64)
    return out


def _unpack_cap_commands(words: np.ndarray, n_cap: int) -> tuple[tuple[str, int] | None, ...]:
    rows = np.asarray(words, dtype=np.int64).reshape(n_cap, 1 + _CMD_ID_WORDS)
    return tuple(None if row[0] < 0 else (row[1:].tobytes().rstrip(b"\0").decode("ascii"), int(row[0]))
                 for row in rows)


# ------------------------------------------------------------------------------------------ the process
_STEP, _STEP_THEN_METRICS, _MATCH, _CLOSE = 1, 2, 3, 4


class PublisherReport(msgspec.Struct, frozen=True, kw_only=True):
    """What the publisher process did (returned by :meth:`PublisherProcess.close`)."""

    steps: int
    frames_published: int
    frames_dropped: int
    truth_frames: int
    cpu_s: float  # from its first step on
    final_metrics: m.MetricsFrame | None


class PublisherProcess:
    """The parent's handle on a publisher process (see the module docstring).

    Parameters
    ----------
    spec : the run (``FramerSpec``). packer : the slot layout. bus : how the child joins the bus (its own
    session: see :func:`child_bus`). depth : steps handed over and not yet published, at most.
    """

    def __init__(self, spec: FramerSpec, packer: StepPacker, bus: BusConfig, *, depth: int = 8) -> None:
        ctx = mp.get_context("spawn")  # a fresh interpreter: never fork a process holding OpenDSS and Zenoh
        self.packer, self.depth = packer, depth
        self._floats = ctx.RawArray("d", depth * packer.n_float)
        self._ints = ctx.RawArray("q", depth * packer.n_int)
        self._ctrl = ctx.RawArray("q", 2 * _CTRL_RING)  # (t_ns, wall ns of the head put) of control steps
        self._state = ctx.RawArray("q", 2)  # [items of the ring done (steps and commands), failed]
        self._fs = np.frombuffer(self._floats, dtype=np.float64).reshape(depth, packer.n_float)
        self._is = np.frombuffer(self._ints, dtype=np.int64).reshape(depth, packer.n_int)
        self._ctrl_view = np.frombuffer(self._ctrl, dtype=np.int64).reshape(_CTRL_RING, 2)
        self._state_view = np.frombuffer(self._state, dtype=np.int64)
        self._free, self._ready = ctx.Semaphore(depth), ctx.Semaphore(0)
        self._conn, child_conn = ctx.Pipe(duplex=False)
        self._submitted = 0
        self._closed = False
        self._proc = ctx.Process(
            target=_child_main, name="cvvc-bridge-publisher", daemon=True,
            args=(spec, packer, bus, depth, self._floats, self._ints, self._ctrl, self._state, self._free,
                  self._ready, child_conn))
        self._proc.start()
        child_conn.close()
        try:
            self._expect("ready", _START_S)
        except PublisherError:
            self._kill()
            raise

    # ---------------------------------------------------------------- the stepping process's side
    def _check(self) -> None:
        if self._state_view[1]:
            why = self._conn.recv() if self._conn.poll(1.0) else ("error", "no reason received")
            raise PublisherError(f"the publisher process failed: {why[1]}; the run stops")
        if not self._proc.is_alive():
            raise PublisherError(f"the publisher process is gone (exit code {self._proc.exitcode}); the run stops")

    def _slot(self) -> int:
        """Wait for a free slot (bounded) and return its index."""
        deadline = time.monotonic() + _WAIT_S
        while not self._free.acquire(timeout=_POLL_S):
            self._check()
            if time.monotonic() > deadline:
                raise PublisherError(f"the publisher process took no step for {_WAIT_S:.0f} s; the run stops")
        return self._submitted % self.depth

    def submit(self, res: Any, n_step: int, settings: DeviceSettings, *, metrics_after: bool) -> bool:
        """Hand one step over; ``metrics_after``: publish a metrics frame after it. Returns False (and hands
        nothing over) when the step holds a NaN or inf.
        """
        if self._state_view[1]:
            self._check()
        i = self._slot()
        if not self.packer.pack(self._fs[i], self._is[i], res, n_step, settings):
            self._free.release()
            return False
        self._is[i, 0] = _STEP_THEN_METRICS if metrics_after else _STEP
        self._submitted += 1
        self._ready.release()
        return True

    def _command(self, kind: int, *, seconds: float = 0.0, t_ns: int = 0) -> None:
        i = self._slot()
        self._is[i, 0], self._is[i, 1], self._fs[i, 0] = kind, t_ns, seconds
        self._submitted += 1
        self._ready.release()

    def wait_matched(self, timeout_s: float) -> bool:
        """Wait (in the child) until the head frames have a subscriber, at most ``timeout_s``."""
        self._command(_MATCH, seconds=timeout_s)
        return bool(self._expect("matched", timeout_s + _WAIT_S)[1])

    def control_head_wall_ns(self, t_ns: int) -> int | None:
        """When the child put the head frame of the control step ``t_ns`` [wall ns], if it was one of the last
        ``_CTRL_RING``.
        """
        hit = np.flatnonzero(self._ctrl_view[:, 0] == t_ns)
        return int(self._ctrl_view[hit[0], 1]) if len(hit) else None

    @property
    def published(self) -> int:
        """Steps the publisher process has published so far."""
        return int(self._state_view[0])

    def drain(self) -> None:
        """Return once every step handed over is published (bounded)."""
        deadline = time.monotonic() + _WAIT_S
        while self._state_view[0] < self._submitted:
            self._check()
            if time.monotonic() > deadline:
                raise PublisherError(f"the publisher process published {self.published} of {self._submitted} "
                                     f"steps in {_WAIT_S:.0f} s; the run stops")
            time.sleep(0.0005)

    def close(self, final_t_ns: int | None) -> PublisherReport | None:
        """Stop the child after it published every step handed over and, with ``final_t_ns``, a final metrics
        frame at that time (None: an error path, no final frame). Returns its report, None if it gave none.
        """
        if self._closed:
            return None
        self._closed = True
        report = None
        try:
            if self._proc.is_alive() and not self._state_view[1]:
                self._command(_CLOSE, t_ns=-1 if final_t_ns is None else final_t_ns)
                _, report = self._expect("closed", _WAIT_S)
        except PublisherError as e:
            log.warning("the publisher process did not close cleanly: %s", e)
        finally:
            self._proc.join(5.0)
            self._kill()
            self._conn.close()
        return report

    def _expect(self, what: str, timeout_s: float) -> tuple[str, Any]:
        deadline = time.monotonic() + timeout_s
        while not self._conn.poll(_POLL_S):
            if not self._proc.is_alive():
                raise PublisherError(f"the publisher process exited (code {self._proc.exitcode}) before "
                                     f"{what!r}")
            if time.monotonic() > deadline:
                raise PublisherError(f"the publisher process sent no {what!r} within {timeout_s:.0f} s")
        msg = self._conn.recv()
        if msg[0] == "error":
            raise PublisherError(f"the publisher process failed: {msg[1]}")
        if msg[0] != what:
            raise PublisherError(f"the publisher process sent {msg[0]!r}, expected {what!r}")
        return msg

    def _kill(self) -> None:
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(5.0)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(5.0)


def child_bus(bus: BusConfig) -> BusConfig | None:
    """How the publisher process joins the bus: the bridge's settings, connecting to every endpoint the bridge
    connects to or listens on (it cannot listen there itself). None when that reaches nobody, or with a Zenoh
    config file (whose endpoints this cannot rewrite).
    """
    if bus.config_file is not None:
        return None
    connect = tuple(bus.connect) + tuple(ep for ep in bus.listen if not ep.endswith(":0"))
    if not connect:
        return None
    return msgspec.structs.replace(bus, listen=(), connect=connect)


def _child_main(spec: FramerSpec, packer: StepPacker, bus: BusConfig, depth: int, floats: Any, ints: Any,
                ctrl: Any, state: Any, free: Any, ready: Any, conn: Any) -> None:
    """The publisher process: publish every step handed over, in order, until told to close."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the bridge decides when this ends (a Ctrl-C reaches both)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    fs = np.frombuffer(floats, dtype=np.float64).reshape(depth, packer.n_float)
    ins = np.frombuffer(ints, dtype=np.int64).reshape(depth, packer.n_int)
    ctrl_view = np.frombuffer(ctrl, dtype=np.int64).reshape(_CTRL_RING, 2)
    st = np.frombuffer(state, dtype=np.int64)
    parent = mp.parent_process()
    n_ctrl = [0]

    def on_control_head(t_ns: int, wall_ns: int) -> None:
        row = ctrl_view[n_ctrl[0] % _CTRL_RING]
        row[1], row[0] = wall_ns, t_ns  # wall first: the parent matches on t_ns
        n_ctrl[0] += 1

    try:
        with open_session(bus) as session:
            framer = StepFramer(spec, session, on_control_head)
            conn.send(("ready", os.getpid()))
            i, cpu0 = 0, None
            while True:
                if not ready.acquire(timeout=_POLL_S):
                    if parent is not None and not parent.is_alive():
                        return
                    continue
                slot = i % depth
                kind = int(ins[slot, 0])
                i += 1
                if kind in (_STEP, _STEP_THEN_METRICS):
                    if cpu0 is None:
                        cpu0 = time.process_time()  # from the first step on: the start is no publishing
                    res, n_step, settings = packer.unpack(fs[slot], ins[slot])
                    free.release()
                    framer.publish_step(res, n_step, float(res.v_pu.min()), float(res.v_pu.max()), settings,
                                        time.monotonic())
                    if kind == _STEP_THEN_METRICS:
                        framer.publish_metrics(res.t_ns, final=False)
                    st[0] += 1
                elif kind == _MATCH:
                    timeout_s = float(fs[slot, 0])
                    free.release()
                    conn.send(("matched", framer.pub_head.wait_matched(timeout_s)))
                    st[0] += 1
                elif kind == _CLOSE:
                    final_t_ns = int(ins[slot, 1])
                    final = None if final_t_ns < 0 else framer.publish_metrics(final_t_ns, final=True)
                    conn.send(("closed", PublisherReport(
                        steps=framer.metrics.n_steps, frames_published=framer.frames_published,
                        frames_dropped=framer.frames_dropped, truth_frames=framer.truth_frames,
                        cpu_s=time.process_time() - (cpu0 or 0.0), final_metrics=final)))
                    free.release()
                    return
    except BaseException as e:  # the parent raises it as PublisherError at its next hand-over
        st[1] = 1
        try:
            conn.send(("error", f"{type(e).__name__}: {e}"))
        except Exception:  # the parent is gone
            pass
        raise
