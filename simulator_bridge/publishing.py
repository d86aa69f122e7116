"""Publishing one simulated step: device frames, streaming metrics and truth, inline or from a publisher process.

:class:`StepFramer` builds, encodes and puts a step's messages (the head meter's, PV, regulator and capacitor bank
frames with noise, drops and latency; the metrics update; the truth frame) and the metrics frames. The bridge's stepping
thread calls it directly (``publisher="inline"``), or hands each step to a :class:`PublisherProcess`
(``publisher="process"``), a child process with its own Zenoh session and its own :class:`StepFramer`: the
Python work of publishing then runs beside the power flow, on the other core, instead of under the stepping
process's GIL (``docs/bridge.md``, Speed).

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

import dataclasses
import logging
import math
import multiprocessing as mp
import os
import signal
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import msgspec
import numpy as np
import zenoh

from schemas import keys
from schemas import messages as m
from schemas.bus import BusConfig, open_session, wait_for
from simulator_bridge import devices as dv
from simulator_bridge.engine import FieldReadings
from simulator_bridge.errors import SimulatorError
from simulator_bridge.metrics import Metrics

__all__ = [
    "DeviceSettings",
    "FramePublisher",
    "FramerSpec",
    "PublisherError",
    "PublisherProcess",
    "PublisherReport",
    "FINITE_READING_FIELDS",
    "READING_FIELDS",
    "StepFramer",
    "StepPacker",
    "metrics_frame",
]

log = logging.getLogger(__name__)

_NS = 1_000_000_000
READING_FIELDS = tuple(f.name for f in dataclasses.fields(FieldReadings))
"""The fields of ``FieldReadings``, in order (the slot layout)."""
FINITE_READING_FIELDS = tuple(name for name in READING_FIELDS if name != "cap_control_value")
"""The readings that must be finite (the bridge's check): a bank without a CapControl reads NaN."""
_CMD_ID_WORDS = 12  # a cmd_id (at most 96 bytes of ASCII) packed into int64 words
_POLL_S = 0.05  # longest a wait goes without looking at the other process [s]
_WAIT_S = 60.0  # longest the stepping process waits for the child to take a step or answer [s]
_START_S = 60.0  # longest the child may take to start (a fresh interpreter, imports, a Zenoh session) [s]
_CTRL_RING = 64  # control-step head publication times kept for the round trip


class PublisherError(SimulatorError):
    """The publisher process cannot start, failed, or is gone: the run stops."""


class FramePublisher:
    """Publisher of the bridge's own messages, whose numbers are already known to be finite.

    ``TypedPublisher`` walks every field of every message for NaN (about 60 µs a frame, more than a power
    flow of IEEE 13). Frames and truth come from arrays that were checked in one vectorised pass; metrics from
    the accumulator, which refuses non-finite inputs and clips what it reports; the status holds no float.
    Same Zenoh settings and JSON as ``TypedPublisher``.
    """

    def __init__(self, session: zenoh.Session, key: str, *, reliable: bool = False) -> None:
        self._enc = msgspec.json.Encoder()
        self._pub = session.declare_publisher(
            key, encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.REAL_TIME if reliable else zenoh.Priority.DATA, express=reliable)

    def put(self, msg: msgspec.Struct) -> None:
        self._pub.put(self._enc.encode(msg))

    def wait_matched(self, timeout_s: float) -> bool:
        """Wait until a subscriber exists (a put right after a remote declaration is often lost)."""
        return wait_for(lambda: bool(self._pub.matching_status.matching), timeout_s)


@dataclass(frozen=True)
class FramerSpec:
    """What a :class:`StepFramer` needs to know of the run: static, picklable (sent to the publisher process).

    Attributes
    ----------
    feeder_id : id in the key space. step_s : step length [s]. control_every : steps per control step.
    profile_start_t_ns : time of profile step 0 (control steps are aligned to it). run_start_t_ns : the first
    simulated step's time (metrics frames). truth_every : truth decimation (0: none). node_names : the engine's.
    pvs : (plant_id, index, s_rated_kva, local_mode) per plant. regs : (regulator_id, index, tap_max,
    default set point, default band) per regulator. reg_phase : each regulator's phase letter.
    q_at_night : PV gives Q without P. noise_pmu_pct, noise_scada_pct, drop_prob, latency_s, noise_seed :
    measurement realism (``BridgeConfig``). metrics : the run's metrics accumulator, empty at the start, the
    one mutable part: the framer updates it (inline, the runtime's own; in the process, the pickled copy).
    caps : (capacitor_id, index, steps, kvar_rated, control_type) per capacitor bank.
    drop_burst_s : with ``drop_prob``, each device loses its frames in outages of this long [s] (0: each frame
    independently). clock_skew_s : the devices' clocks are this far off the bridge's [s]: every frame and scan
    end marker is stamped ``t + clock_skew_s`` (the truth, metrics and command checks keep the bridge's time).
    """

    feeder_id: str
    step_s: int
    control_every: int
    profile_start_t_ns: int
    run_start_t_ns: int
    truth_every: int
    node_names: tuple[str, ...]
    pvs: tuple[tuple[str, int, float, Literal["unity_pf", "volt_var"]], ...]
    regs: tuple[tuple[str, int, int, float, float], ...]
    reg_phase: tuple[str, ...]
    q_at_night: bool
    noise_pmu_pct: float
    noise_scada_pct: float
    drop_prob: float
    latency_s: float
    noise_seed: int
    metrics: Any  # simulator_bridge.metrics.MetricsAccumulator
    caps: tuple[tuple[str, int, int, float, str], ...] = ()
    drop_burst_s: float = 0.0
    clock_skew_s: float = 0.0

    def is_control_t(self, t_ns: int) -> bool:
        return ((t_ns - self.profile_start_t_ns) // (self.step_s * _NS)) % self.control_every == 0


@dataclass(frozen=True)
class DeviceSettings:
    """The devices' command state at one step, as its frames show it.

    pv_q_setpoint_kvar : per plant, the commanded Q in force [kvar] or None (local default). reg_setpoint_v120,
    reg_band_v120, reg_mode : per regulator, the set point and band in force [V, 120 V base] and its mode.
    cap_command : per capacitor bank, the command in force as (cmd_id, valid_until_t_ns), or None (local control).
    """

    pv_q_setpoint_kvar: tuple[float | None, ...]
    reg_setpoint_v120: tuple[float, ...]
    reg_band_v120: tuple[float, ...]
    reg_mode: tuple[Literal["local", "locked"], ...]
    cap_command: tuple[tuple[str, int] | None, ...] = ()


class StepFramer:
    """Builds, encodes and puts the messages of simulated steps on one Zenoh session (see the module docstring).

    ``on_control_head(t_ns, wall_ns)`` is called just before a control step's head frame is put.
    """

    def __init__(self, spec: FramerSpec, session: zenoh.Session,
                 on_control_head: Callable[[int, int], None] | None = None) -> None:
        s, f = spec, spec.feeder_id
        self.spec = spec
        self.pvs = [dv.PvInverter(pid, k, kva, local) for pid, k, kva, local in s.pvs]
        self.regs = [dv.RegulatorController(rid, r, tmax, sp, bw) for rid, r, tmax, sp, bw in s.regs]
        self.caps = [dv.CapBankController(cid, c, steps, kvar, kind) for cid, c, steps, kvar, kind in s.caps]  # type: ignore[arg-type]
        self.noise = (dv.MeasurementNoise(pmu_pct=s.noise_pmu_pct, scada_pct=s.noise_scada_pct, seed=s.noise_seed)
                      if s.noise_pmu_pct > 0 or s.noise_scada_pct > 0 else None)
        self.dropper = dv.FrameDropper(p=s.drop_prob, seed=s.noise_seed, burst_s=s.drop_burst_s, step_s=s.step_s)
        self.skew_ns = int(round(s.clock_skew_s * 1e9))
        self.delay = dv.DelayLine(s.latency_s)
        self.metrics = s.metrics
        self.on_control_head = on_control_head
        self._truth_v = np.empty(len(s.node_names))  # the clipped truth voltages, rewritten every step
        self.pub_head = FramePublisher(session, keys.meas_head(f))
        self.pub_pv = [FramePublisher(session, keys.meas_pv(f, pv.plant_id)) for pv in self.pvs]
        self.pub_vr = [FramePublisher(session, keys.meas_vr(f, reg.regulator_id)) for reg in self.regs]
        self.pub_cap = [FramePublisher(session, keys.meas_cap(f, cap.capacitor_id)) for cap in self.caps]
        self.pub_step = FramePublisher(session, keys.meas_step(f))  # same QoS as the frames: queued behind them
        self.pub_truth = FramePublisher(session, keys.sim_truth(f), reliable=True)
        self.pub_metrics = FramePublisher(session, keys.sim_metrics(f), reliable=True)
        self.seqs: Counter[str] = Counter()
        self.frames_published = self.frames_dropped = self.truth_frames = 0

    # ---------------------------------------------------------------- one step
    def publish_step(self, res: Any, n_step: int, v_lo_pu: float, v_hi_pu: float, settings: DeviceSettings,
                     now_s: float) -> None:
        """Frames, metrics update and truth of the ``n_step``-th step of the run (from 1); ``res`` a
        ``StepResult`` whose numbers are finite, ``v_lo_pu``/``v_hi_pu`` the extremes of ``res.v_pu``. The
        device frames go out first, so that on a control step the agent works while the rest is done.
        """
        self.publish_frames(res, settings, now_s)
        self.metrics.update(res.v_pu, res.tap_changes, res.pv_q_kvar, res.cap_switches)
        self.publish_truth(res, n_step, v_lo_pu, v_hi_pu)

    def flush(self, now_s: float) -> None:
        """Put the frames the latency line holds that are due at ``now_s``."""
        for pub, msg in self.delay.due(now_s):  # type: ignore[misc]
            self._publish(pub, msg)

    def _publish(self, pub: FramePublisher, msg: msgspec.Struct) -> None:
        if pub is self.pub_head and self.on_control_head is not None:
            t_ns = msg.t_ns - self.skew_ns  # type: ignore[attr-defined]  # the bridge's time of the step
            if self.spec.is_control_t(t_ns):
                self.on_control_head(t_ns, time.time_ns())  # before put: the answer may beat put's return
        pub.put(msg)
        self.frames_published += pub is not self.pub_step  # a scan's end marker is not a frame

    def _send(self, pub: FramePublisher, msg: msgspec.Struct, now_s: float) -> bool:
        """Drop ``msg`` (False) or put it, through the latency line if any (True)."""
        if self.dropper.drop(msg.source, msg.t_ns):  # type: ignore[attr-defined]
            self.frames_dropped += 1
            return False
        if self.delay.latency_s > 0.0:
            self.delay.put((pub, msg), now_s)
        else:
            self._publish(pub, msg)
        return True

    def _send_now(self, pub: FramePublisher, msg: msgspec.Struct, now_s: float) -> bool:
        """:meth:`_send` without drops or latency configured."""
        self._publish(pub, msg)
        return True

    def _step_end(self, t_ns: int, head: bool, sent: dict[str, list[str]], now_s: float) -> None:
        """The scan's end marker after its frames (through the latency line too, so it stays behind them)."""
        self.seqs["step_end"] += 1
        msg = m.StepEnd(t_ns=t_ns, seq=self.seqs["step_end"], source="bridge", feeder_id=self.spec.feeder_id,
                        head=head, pv=sent["pv"], vr=sent["vr"], cap=sent["cap"])
        if self.delay.latency_s > 0.0:
            self.delay.put((self.pub_step, msg), now_s)
        else:
            self.pub_step.put(msg)

    def publish_frames(self, res: Any, settings: DeviceSettings, now_s: float) -> None:
        """Schedule the frames of one step (noise, drops, latency applied).

        The readings are turned into Python numbers once per step (``tolist``), so the frame builders index
        lists rather than making a NumPy scalar of every value; the numbers, hence the frames, are the same.
        """
        rd, t, seqs, noise = res.readings, int(res.t_ns) + self.skew_ns, self.seqs, self.noise
        send = self._send if self.dropper.p > 0.0 or self.delay.latency_s > 0.0 else self._send_now
        head = (rd.head_v_mag_v, rd.head_v_ang_deg, rd.head_i_mag_a, rd.head_i_ang_deg, rd.head_p_kw,
                rd.head_q_kvar)
        if noise is not None:
            head = noise.head(*head)
        hv, ha, hi, hia, hp, hq = (x.tolist() for x in head)
        seqs["head"] += 1
        sent: dict[str, list[str]] = {"pv": [], "vr": [], "cap": []}
        head = dv.head_frame(feeder_id=self.spec.feeder_id, t_ns=t, seq=seqs["head"], v_mag_v=hv, v_ang_deg=ha,
                             i_mag_a=hi, i_ang_deg=hia, p_kw=hp, q_kvar=hq)
        head_sent = send(self.pub_head, head, now_s)
        pv_p, pv_q, pv_v = rd.pv_p_kw, rd.pv_q_kvar, rd.pv_v_v
        if noise is None:
            pv_p, pv_q, pv_v = pv_p.tolist(), pv_q.tolist(), pv_v.tolist()
        available, q_at_night = np.asarray(res.pv_p_kw, dtype=float).tolist(), self.spec.q_at_night
        for pv, pub, q_set in zip(self.pvs, self.pub_pv, settings.pv_q_setpoint_kvar, strict=True):
            k = pv.index
            p, q, v = pv_p[k], pv_q[k], pv_v[k]
            if noise is not None:
                p, q, v = (x.tolist() for x in noise.pv(p, q, v, pv.s_rated_kva))
            seqs[pv.plant_id] += 1
            if send(pub, dv.pv_frame(plant=pv, t_ns=t, seq=seqs[pv.plant_id], p_kw=p, q_kvar=q, v_v=v,
                                     available_p_kw=available[k], q_setpoint_kvar=q_set, q_at_night=q_at_night),
                    now_s):
                sent["pv"].append(pv.plant_id)
        v120s = np.asarray(rd.reg_v120, dtype=float).tolist()
        vcs = np.asarray(rd.reg_v120_compared, dtype=float).tolist()
        taps = np.asarray(res.taps).tolist()
        for reg, pub, sp, bw, mode in zip(self.regs, self.pub_vr, settings.reg_setpoint_v120,
                                          settings.reg_band_v120, settings.reg_mode, strict=True):
            r = reg.index
            v120, vc = v120s[r], vcs[r]
            if noise is not None:
                v120, vc = noise.regulator(v120, vc)
            seqs[reg.regulator_id] += 1
            if send(pub, dv.reg_frame(reg=reg, t_ns=t, seq=seqs[reg.regulator_id], phase=self.spec.reg_phase[r],
                                      v120=min(v120, 200.0), v_compared_120=min(vc, 200.0), tap=int(taps[r]),
                                      setpoint_v120=sp, band_v120=bw, mode=mode), now_s):
                sent["vr"].append(reg.regulator_id)
        if self.caps:
            sent["cap"] = self._cap_frames(rd, t, settings, send, now_s)
        self._step_end(t, head_sent, sent, now_s)
        if len(self.delay):
            self.flush(now_s)

    def _cap_frames(self, rd: Any, t: int, settings: DeviceSettings, send: Any, now_s: float) -> list[str]:
        """The capacitor banks' frames of one step (states exact; voltage and control reading SCADA class); the
        ids of the banks whose frame was sent.
        """
        sent = []
        states = np.asarray(rd.cap_states).tolist()
        volts = np.asarray(rd.cap_v_v, dtype=float).tolist()
        values = np.asarray(rd.cap_control_value, dtype=float).tolist()
        commands = settings.cap_command or (None,) * len(self.caps)
        for cap, pub, command in zip(self.caps, self.pub_cap, commands, strict=True):
            c = cap.index
            v, cv = volts[c], values[c]
            cv = None if math.isnan(cv) else cv
            if self.noise is not None:
                v, cv = self.noise.capacitor(v, cv)
            active = None if command is None else dv.ActiveCommand(
                cmd_id=command[0], source="", seq=0, valid_until_t_ns=command[1], value=float(states[c]))
            self.seqs[f"cap:{cap.capacitor_id}"] += 1
            if send(pub, dv.cap_frame(cap=cap, t_ns=t, seq=self.seqs[f"cap:{cap.capacitor_id}"],
                                      closed_steps=int(states[c]), v_v=v, control_value=cv, active=active), now_s):
                sent.append(cap.capacitor_id)
        return sent

    def publish_truth(self, res: Any, n_step: int, v_lo_pu: float, v_hi_pu: float) -> None:
        """The TruthFrame of the ``n_step``-th step of the run (from 1), if it has one.

        The voltages are clipped to the schema's 0..3 pu into a buffer kept across steps; the extremes of the
        clipped voltages are the clipped extremes (clipping is monotonic).
        """
        every = self.spec.truth_every
        if every == 0 or (n_step - 1) % every != 0:
            return
        self.seqs["truth"] += 1
        v = np.clip(res.v_pu, 0.0, 3.0, out=self._truth_v)
        self.pub_truth.put(m.TruthFrame(
            t_ns=int(res.t_ns), seq=self.seqs["truth"], source="bridge", feeder_id=self.spec.feeder_id,
            v_pu=v.tolist(), v_min_pu=min(max(v_lo_pu, 0.0), 3.0), v_max_pu=min(max(v_hi_pu, 0.0), 3.0),
            node_names=list(self.spec.node_names) if self.truth_frames == 0 else None,
            taps=np.asarray(res.taps).tolist(), pv_q_kvar=np.asarray(res.pv_q_kvar, dtype=float).tolist(),
            cap_states=np.asarray(res.cap_states).tolist()))
        self.truth_frames += 1

    def metrics_frame(self, t_ns: int, *, final: bool) -> m.MetricsFrame:
        """Cumulative paper IV.F metrics since the first step (``simulator_bridge.metrics``), at ``t_ns``."""
        self.seqs["metrics"] += 1
        return metrics_frame(self.metrics.result(), t_ns=t_ns, seq=self.seqs["metrics"],
                             feeder_id=self.spec.feeder_id, start_t_ns=self.spec.run_start_t_ns, final=final)

    def publish_metrics(self, t_ns: int, *, final: bool) -> m.MetricsFrame:
        frame = self.metrics_frame(t_ns, final=final)
        self.pub_metrics.put(frame)
        return frame


def metrics_frame(r: Metrics, *, t_ns: int, seq: int, feeder_id: str, start_t_ns: int,
                  final: bool) -> m.MetricsFrame:
    """The bus's form of metrics ``r`` (values clipped to the message's ranges); ``t_ns`` [ns] its time."""
    return m.MetricsFrame(
        t_ns=max(t_ns, 0), seq=seq, source="bridge", feeder_id=feeder_id,
        start_t_ns=start_t_ns, steps=r.n_steps,
        mvvm_pu=min(float(r.mvvm_pu), 3.0), nvv=int(r.nvv),
        minutes_in_violation=int(round(r.minutes_in_violation)), ntc=int(r.ntc), q_cost=float(r.q_cost),
        t_cost=float(r.t_cost), total_cost=float(r.total_cost),
        v_min_pu=min(max(r.v_min_pu if r.v_min_pu is not None else 0.0, 0.0), 3.0),
        v_max_pu=min(max(r.v_max_pu if r.v_max_pu is not None else 0.0, 0.0), 3.0),
        taps_changes=dict(zip(r.regulator_ids, r.tap_changes_per_regulator, strict=True)),
        q_mvar_intervals=dict(zip(r.pv_ids, r.q_mvar_intervals_per_plant, strict=True)),
        final=final, cap_switches=int(r.cap_switches), cap_cost=float(r.cap_cost),
        cap_switches_per_bank=dict(zip(r.capacitor_ids, r.cap_switches_per_bank, strict=True)))


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
        shapes = {name: (3,) for name in READING_FIELDS if name.startswith("head_")}
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
        from simulator_bridge.qsts import StepResult

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
