"""The frames of one simulated step: device frames, streaming metrics and truth, and the metrics frames.

:class:`StepFramer` builds, encodes and puts a step's messages (the head meter's, PV, regulator and capacitor bank
frames with noise, drops and latency; the metrics update; the truth frame) and the metrics frames. The bridge's stepping
thread calls it directly (``publisher="inline"``), or hands each step to a
:class:`~simulator_bridge.bus.publisher_process.PublisherProcess` (``publisher="process"``), a child process with its
own Zenoh session and its own :class:`StepFramer` (``publisher_process.py``: the shared-memory hand-over). The
messages are the same either way.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import zenoh

from schemas import keys
from schemas import messages as m
from schemas.bus import has_subscribers, wait_for, zenoh_encoding
from schemas.wire import typed_encoder
from simulator_bridge.errors import SimulatorError
from simulator_bridge.field import devices as dv
from simulator_bridge.opendss.readout import FieldReadings
from simulator_bridge.simulation.metrics import Metrics

__all__ = [
    "DeviceSettings",
    "FramePublisher",
    "FramerSpec",
    "PublisherError",
    "FINITE_READING_FIELDS",
    "READING_FIELDS",
    "StepFramer",
    "metrics_frame",
]

log = logging.getLogger(__name__)

_NS = 1_000_000_000
READING_FIELDS = tuple(f.name for f in dataclasses.fields(FieldReadings))
"""The fields of ``FieldReadings``, in order (the slot layout)."""
FINITE_READING_FIELDS = tuple(name for name in READING_FIELDS if name != "cap_control_value")
"""The readings that must be finite (the bridge's check): a bank without a CapControl reads NaN."""


class PublisherError(SimulatorError):
    """The publisher process cannot start, failed, or is gone: the run stops."""


class FramePublisher:
    """Publisher of the bridge's own messages, whose numbers are already known to be finite.

    ``TypedPublisher`` walks every field of every message for NaN (about 60 µs a frame, more than a power
    flow of IEEE 13). Frames and truth come from arrays that were checked in one vectorised pass; metrics from
    the accumulator, which refuses non-finite inputs and clips what it reports; the status holds no float.
    Same Zenoh settings and encoding as ``TypedPublisher``: the wire of ``msg_type`` (JSON; Protobuf for the truth,
    ``TruthPack``).
    """

    def __init__(self, session: zenoh.Session, key: str, *, reliable: bool = False,
                 msg_type: type[m.Message] = m.Message) -> None:
        self._enc = typed_encoder(msg_type)
        self._pub = session.declare_publisher(
            key, encoding=zenoh_encoding(m.wire_of(msg_type)),
            congestion_control=zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.REAL_TIME if reliable else zenoh.Priority.DATA, express=reliable)

    def put(self, msg: m.Message) -> None:
        """Encode ``msg`` and put it (no finiteness check: see the class docstring)."""
        self._pub.put(self._enc.encode(msg))

    def wait_matched(self, timeout_s: float) -> bool:
        """Wait until a subscriber exists (a put right after a remote declaration is often lost)."""
        return wait_for(lambda: has_subscribers(self._pub), timeout_s)


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
    q_at_night : per plant (by index), whether it gives Q without P. noise_pmu_pct, noise_scada_pct, drop_prob,
    latency_s, noise_seed : measurement realism (``BridgeConfig``). metrics : the run's metrics accumulator, empty
    at the start, the one mutable part: the framer updates it (inline, the runtime's own; in the process, the
    pickled copy).
    caps : (capacitor_id, index, steps, kvar_rated, control_type) per capacitor bank.
    drop_burst_s : with ``drop_prob``, each device loses its frames in outages of this long [s] (0: each frame
    independently). clock_skew_s : the devices' clocks are this far off the bridge's [s]: every frame and scan
    end marker is stamped ``t + clock_skew_s`` (the truth, metrics and command checks keep the bridge's time).
    pv_external : plants whose frames an adapter publishes (``simulator_bridge.bus.sunspec_fleet``): no frame here, but
    listed in the step's ``StepEnd``, so the agent waits for the adapter's. meters : AMI meters (``MeterSpec``):
    each puts a ``MeterFrame`` of its node's voltage at the steps whose time is a multiple of its interval.
    vr_external, cap_external : regulators and banks whose frames an adapter publishes
    (``simulator_bridge.bus.dnp3_fleet``): as ``pv_external``.
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
    reg_phase: tuple[m.Phase, ...]
    q_at_night: tuple[bool, ...]
    noise_pmu_pct: float
    noise_scada_pct: float
    drop_prob: float
    latency_s: float
    noise_seed: int
    metrics: Any  # simulator_bridge.simulation.metrics_stream.MetricsAccumulator
    caps: tuple[tuple[str, int, int, float, m.CapControlType], ...] = ()
    drop_burst_s: float = 0.0
    clock_skew_s: float = 0.0
    pv_external: tuple[str, ...] = ()
    meters: tuple[tuple[str, int, int], ...] = ()  # AMI meters (explicit option): (meter_id, node index, interval_s)
    vr_external: tuple[str, ...] = ()
    cap_external: tuple[str, ...] = ()

    def is_control_t(self, t_ns: int) -> bool:
        """Whether the step at ``t_ns`` [ns since the UTC epoch] is a control step.

        Control steps are every ``control_every``-th step from profile step 0.
        """
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
        self.caps = [dv.CapBankController(cid, c, steps, kvar, kind) for cid, c, steps, kvar, kind in s.caps]
        self.noise = (dv.MeasurementNoise(pmu_pct=s.noise_pmu_pct, scada_pct=s.noise_scada_pct, seed=s.noise_seed)
                      if s.noise_pmu_pct > 0 or s.noise_scada_pct > 0 else None)
        self.dropper = dv.FrameDropper(p=s.drop_prob, seed=s.noise_seed, burst_s=s.drop_burst_s, step_s=s.step_s)
        self.skew_ns = int(round(s.clock_skew_s * 1e9))
        self.delay: dv.DelayLine[tuple[FramePublisher, m.Message]] = dv.DelayLine(s.latency_s)
        self.metrics = s.metrics
        self.on_control_head = on_control_head
        self._truth_v = np.empty(len(s.node_names))  # the clipped truth voltages, rewritten every step
        self.pub_head = FramePublisher(session, keys.meas_head(f))
        self.pub_pv = [None if pv.plant_id in s.pv_external else FramePublisher(session, keys.meas_pv(f, pv.plant_id))
                       for pv in self.pvs]  # an external plant's frames are its adapter's
        self.pub_vr = [None if reg.regulator_id in s.vr_external else FramePublisher(session, keys.meas_vr(
            f, reg.regulator_id)) for reg in self.regs]  # an external device's frames are its adapter's
        self.pub_cap = [None if cap.capacitor_id in s.cap_external else FramePublisher(session, keys.meas_cap(
            f, cap.capacitor_id)) for cap in self.caps]
        self.pub_ami = [FramePublisher(session, keys.meas_ami(f, mid)) for mid, _, _ in s.meters]
        self.pub_step = FramePublisher(session, keys.meas_step(f))  # same QoS as the frames: queued behind them
        self.pub_truth = FramePublisher(session, keys.sim_truth(f), reliable=True, msg_type=m.TruthPack)
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
        for pub, msg in self.delay.due(now_s):
            self._publish(pub, msg)

    def _publish(self, pub: FramePublisher, msg: m.Message) -> None:
        if pub is self.pub_head and self.on_control_head is not None:
            t_ns = msg.t_ns - self.skew_ns  # the bridge's time of the step
            if self.spec.is_control_t(t_ns):
                self.on_control_head(t_ns, time.time_ns())  # before put: the answer may beat put's return
        pub.put(msg)
        self.frames_published += pub is not self.pub_step  # a scan's end marker is not a frame

    def _send(self, pub: FramePublisher, msg: m.Message, now_s: float) -> bool:
        """Drop ``msg`` (False) or put it, through the latency line if any (True)."""
        if self.dropper.drop(msg.source, msg.t_ns):
            self.frames_dropped += 1
            return False
        if self.delay.latency_s > 0.0:
            self.delay.put((pub, msg), now_s)
        else:
            self._publish(pub, msg)
        return True

    def _send_now(self, pub: FramePublisher, msg: m.Message, now_s: float) -> bool:
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
        head_values = (rd.head_v_mag_v, rd.head_v_ang_deg, rd.head_i_mag_a, rd.head_i_ang_deg, rd.head_p_kw,
                       rd.head_q_kvar)
        if noise is not None:
            head_values = noise.head(*head_values)
        hv, ha, hi, hia, hp, hq = (x.tolist() for x in head_values)
        seqs["head"] += 1
        sent: dict[str, list[str]] = {"pv": [], "vr": [], "cap": []}
        head = dv.head_frame(feeder_id=self.spec.feeder_id, t_ns=t, seq=seqs["head"], v_mag_v=hv, v_ang_deg=ha,
                             i_mag_a=hi, i_ang_deg=hia, p_kw=hp, q_kvar=hq)
        head_sent = send(self.pub_head, head, now_s)
        if self.spec.meters:  # before the device frames: the agent has a reading before the step's group completes
            self._meter_frames(res, t, send, now_s)
        pv_p, pv_q, pv_v = rd.pv_p_kw, rd.pv_q_kvar, rd.pv_v_v
        if noise is None:
            pv_p, pv_q, pv_v = pv_p.tolist(), pv_q.tolist(), pv_v.tolist()
        available, q_at_night = np.asarray(res.pv_p_kw, dtype=float).tolist(), self.spec.q_at_night
        external = self.spec.pv_external
        for pv, pub, q_set in zip(self.pvs, self.pub_pv, settings.pv_q_setpoint_kvar, strict=True):
            if pub is None or pv.plant_id in external:
                sent["pv"].append(pv.plant_id)
                continue
            k = pv.index
            p, q, v = pv_p[k], pv_q[k], pv_v[k]
            if noise is not None:
                p, q, v = (x.tolist() for x in noise.pv(p, q, v, pv.s_rated_kva))
            seqs[pv.plant_id] += 1
            if send(pub, dv.pv_frame(plant=pv, t_ns=t, seq=seqs[pv.plant_id], p_kw=p, q_kvar=q, v_v=v,
                                     available_p_kw=available[k], q_setpoint_kvar=q_set, q_at_night=q_at_night[k]),
                    now_s):
                sent["pv"].append(pv.plant_id)
        v120s = np.asarray(rd.reg_v120, dtype=float).tolist()
        vcs = np.asarray(rd.reg_v120_compared, dtype=float).tolist()
        taps = np.asarray(res.taps).tolist()
        for reg, pub, sp, bw, mode in zip(self.regs, self.pub_vr, settings.reg_setpoint_v120,
                                          settings.reg_band_v120, settings.reg_mode, strict=True):
            if pub is None:
                sent["vr"].append(reg.regulator_id)
                continue
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

    def _meter_frames(self, res: Any, t: int, send: Any, now_s: float) -> None:
        """The AMI meters' frames of one step: a meter reads when the step's time is a multiple of its interval."""
        t_s = int(res.t_ns) // _NS
        for (meter_id, node, interval_s), pub in zip(self.spec.meters, self.pub_ami, strict=True):
            if t_s % interval_s:
                continue
            v = float(res.v_pu[node])
            if self.noise is not None:
                v = self.noise.meter(v)
            self.seqs[f"ami:{meter_id}"] += 1
            send(pub, m.MeterFrame(t_ns=t, seq=self.seqs[f"ami:{meter_id}"], source=meter_id, meter_id=meter_id,
                                   node=self.spec.node_names[node], v_pu=min(v, 3.0), interval_s=interval_s), now_s)

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
            if pub is None:
                sent.append(cap.capacitor_id)
                continue
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
        """The truth frame (``TruthPack``) of the ``n_step``-th step of the run (from 1), if it has one.

        The voltages are clipped to the schema's 0..3 pu into a buffer kept across steps, then packed as float32
        (``schemas.messages.pack_v_pu``); the extremes of the clipped voltages are the clipped extremes (clipping is
        monotonic), sent exact.
        """
        every = self.spec.truth_every
        if every == 0 or (n_step - 1) % every != 0:
            return
        self.seqs["truth"] += 1
        v = np.clip(res.v_pu, 0.0, 3.0, out=self._truth_v)
        self.pub_truth.put(m.TruthPack(
            t_ns=int(res.t_ns), seq=self.seqs["truth"], source="bridge", feeder_id=self.spec.feeder_id,
            n_nodes=len(v), v_pu_f32=m.pack_v_pu(v),
            v_min_pu=min(max(v_lo_pu, 0.0), 3.0), v_max_pu=min(max(v_hi_pu, 0.0), 3.0),
            node_names=list(self.spec.node_names) if self.truth_frames == 0 else None,
            taps=np.asarray(res.taps).tolist(), pv_q_kvar=np.asarray(res.pv_q_kvar, dtype=float).tolist(),
            cap_states=np.asarray(res.cap_states).tolist()))
        self.truth_frames += 1

    def metrics_frame(self, t_ns: int, *, final: bool) -> m.MetricsFrame:
        """Cumulative paper IV.F metrics since the first step (``simulator_bridge.simulation.metrics``), at ``t_ns``."""
        self.seqs["metrics"] += 1
        return metrics_frame(self.metrics.result(), t_ns=t_ns, seq=self.seqs["metrics"],
                             feeder_id=self.spec.feeder_id, start_t_ns=self.spec.run_start_t_ns, final=final)

    def publish_metrics(self, t_ns: int, *, final: bool) -> m.MetricsFrame:
        """Put and return the metrics frame of the run so far at ``t_ns`` [ns since the UTC epoch].

        ``final`` marks the run's last frame.
        """
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
        cap_switches_per_bank=dict(zip(r.capacitor_ids, r.cap_switches_per_bank, strict=True)),
        node_minutes_outside_opt=int(round(r.node_minutes_outside_opt)),
        minutes_outside_opt=int(round(r.minutes_outside_opt)),
        node_minutes_outside_ansi=int(round(r.node_minutes_outside_ansi)),
        minutes_outside_ansi=int(round(r.minutes_outside_ansi)),
        steps_over_tap_rate={} if not r.steps_over_tap_rate_per_regulator
        else dict(zip(r.regulator_ids, r.steps_over_tap_rate_per_regulator, strict=True)),
        opt_limits_pu=(float(r.opt_limits_pu[0]), float(r.opt_limits_pu[1])))
