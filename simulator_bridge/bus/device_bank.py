"""The bridge's device bank: every field device of the feeder on the bus, and what it does with commands.

One :class:`DeviceBank` holds the PV inverters, regulator controllers and capacitor bank controllers of a feeder
(their logic is ``devices.py``'s), their liveliness tokens and ack publishers. It checks each command, applies it
to the simulation (:class:`~simulator_bridge.simulation.qsts.Qsts`), acks it, expires commands past their validity (the
watchdogs), and remembers which ``cmd_id`` it handled, for the lockstep's decision matching. Used only by the
bridge's stepping thread (``bridge_runtime.py``); the counters it keeps are the run's (:class:`BridgeCounters`).
"""

from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal, cast

import zenoh

from schemas import keys
from schemas import messages as m
from schemas.bus import LivelinessWatcher, TypedPublisher, codec_for
from schemas.errors import CvvcError
from schemas.logs import RateLimitedLog
from simulator_bridge.bus.publishing import DeviceSettings
from simulator_bridge.field import devices as dv

if TYPE_CHECKING:
    from simulator_bridge.opendss.engine import FeederEngine
    from simulator_bridge.simulation.qsts import Qsts

__all__ = ["BridgeCounters", "DeviceBank"]


_HANDLED_MEMORY = 10_000  # cmd_ids remembered for matching decisions


@dataclass
class BridgeCounters:
    """What a bridge run counts, shared by its parts (stepping thread only).

    Attributes
    ----------
    rlog : every log line a peer can provoke, rate limited.
    seqs : the sequence numbers of the bridge's own messages, by key (``ack:<source>``, ``oracle``, ``status``).
    acks : acks sent, by status. rejected : rejected commands and queries, by reason.
    """

    rlog: RateLimitedLog
    seqs: Counter[str] = field(default_factory=Counter)
    acks: Counter[str] = field(default_factory=Counter)
    rejected: Counter[str] = field(default_factory=Counter)


def _ack_kind(kind: str) -> keys.DeviceKind:
    """The ack key kind of a command key's kind (``vr`` for kinds this bridge does not know)."""
    return "pv" if kind == "pv" else "cap" if kind == "cap" else "vr"


class DeviceBank:
    """The feeder's field devices on the bus: their tokens, acks, command handling and watchdogs.

    Parameters
    ----------
    session : the bridge's Zenoh session. feeder_id : the feeder's id in the key space.
    engine : the feeder (device ids, ratings, defaults). qsts : the simulation the commands act on.
    local : the PV inverters' local default. period_ns : the control period, the unit of the commands' time windows
        [ns]. sender : in secure mode the command role's identity (replay protection is keyed on it), else None.
    counters : the run's counters.
    external_pv : plants behind a field-protocol adapter (``simulator_bridge.bus.sunspec_fleet``): no token, ack,
        command or watchdog here; the adapter does all that, and its acks mark the commands handled
        (:meth:`remember`).
    external_vr, external_cap : regulators and banks behind a field-protocol adapter
        (``simulator_bridge.bus.dnp3_fleet``), the same way.
    """

    def __init__(self, session: zenoh.Session, feeder_id: str, engine: FeederEngine, qsts: Qsts, *,
                 local: Literal["unity_pf", "volt_var"], period_ns: int, sender: str | None,
                 counters: BridgeCounters, external_pv: frozenset[str] = frozenset(),
                 external_vr: frozenset[str] = frozenset(), external_cap: frozenset[str] = frozenset()) -> None:
        self.session, self.fid, self.qsts, self.counters = session, feeder_id, qsts, counters
        self.external = {"pv": external_pv, "vr": external_vr, "cap": external_cap}  # by kind: the adapters' devices
        self.external_pv = external_pv
        self.now_t_ns = 0  # the simulation time of the step just simulated (set by the runtime)
        self.pv_p_kw = engine.pv_setpoints()[0]  # the plants' available power at that step [kW]
        self.pvs = {pid: dv.PvInverter(pid, k, float(engine.pv_kva[k]), local, period_ns=period_ns,
                                       sender_identity=sender)
                    for k, pid in enumerate(engine.pv_ids)}
        self.regs = {rid: dv.RegulatorController(rid, r, int(engine.reg_tap_max[r]),
                                                 float(engine.reg_default_setpoint_v120[r]),
                                                 float(engine.reg_default_band_v120[r]), period_ns=period_ns,
                                                 sender_identity=sender)
                     for r, rid in enumerate(engine.regulator_ids)}
        self.caps = {cid: dv.CapBankController(cid, c, int(engine.cap_steps[c]), float(engine.cap_kvar[c]),
                                               cast(m.CapControlType, engine.cap_control_type[c]),  # checked there
                                               period_ns=period_ns,
                                               sender_identity=sender)
                     for c, cid in enumerate(engine.capacitor_ids)}
        self._handled: set[str] = set()
        self._handled_order: deque[str] = deque()
        self._settings: DeviceSettings | None = None  # the devices' settings, until the next change

    def declare(self) -> list[zenoh.LivelinessToken]:
        """Declare every device's ack publisher and the watcher of other feeders' bridges; return the devices'
        liveliness tokens (the caller withdraws them).
        """
        s, f = self.session, self.fid
        lv = s.liveliness()
        tokens = [lv.declare_token(keys.alive(f, "pv", p)) for p in self.pvs if p not in self.external_pv]
        tokens += [lv.declare_token(keys.alive(f, "vr", r)) for r in self.regs if r not in self.external["vr"]]
        tokens += [lv.declare_token(keys.alive(f, "cap", k)) for k in self.caps if k not in self.external["cap"]]
        # a decision's acks come in a burst that nobody waits for: batched by Zenoh, not one write each
        self.ack_pv = {p: TypedPublisher(s, keys.ack(f, "pv", p), m.Ack, reliable=True, express=False)
                       for p in self.pvs if p not in self.external_pv}
        self.ack_vr = {r: TypedPublisher(s, keys.ack(f, "vr", r), m.Ack, reliable=True, express=False)
                       for r in self.regs if r not in self.external["vr"]}
        self.ack_cap = {k: TypedPublisher(s, keys.ack(f, "cap", k), m.Ack, reliable=True, express=False)
                        for k in self.caps if k not in self.external["cap"]}
        self.bridges = LivelinessWatcher(s, f"{keys.ROOT}/*/alive/bridge/*")
        return tokens

    # ---------------------------------------------------------------- decisions' commands
    def remember(self, cmd_id: str) -> None:
        """Remember that a command with ``cmd_id`` was handled (the last ``_HANDLED_MEMORY`` are kept)."""
        if cmd_id in self._handled:
            return
        self._handled.add(cmd_id)
        self._handled_order.append(cmd_id)
        if len(self._handled_order) > _HANDLED_MEMORY:
            self._handled.discard(self._handled_order.popleft())

    def handled(self, cmd_id: str) -> bool:
        """Whether a command with ``cmd_id`` was handled (applied, clipped or rejected)."""
        return cmd_id in self._handled

    def forget_source(self, source: str) -> None:
        """An agent's liveliness token was withdrawn: every device forgets its command sequence."""
        guards = [pv.guard for pv in self.pvs.values()] + [r.guard for r in self.regs.values()] + [
            k.guard for k in self.caps.values()]
        for guard in guards:
            guard.forget_source(source)

    # ---------------------------------------------------------------- commands
    def _ack(self, pub_or_key: TypedPublisher | str, device_id: str, source: str, cmd_id: str,
             verdict: dv.Verdict) -> None:
        c = self.counters
        c.seqs[f"ack:{source}"] += 1
        ack = dv.make_ack(device_id=device_id, source=source, cmd_id=cmd_id, verdict=verdict,
                          t_ns=max(self.now_t_ns, 0), seq=c.seqs[f"ack:{source}"])
        c.acks[verdict.status] += 1
        if verdict.status != "rejected":
            self._settings = None  # accepted, clipped or expired: a device's settings changed
        if verdict.status == "rejected":
            c.rejected[verdict.reason_kind] += 1
            c.rlog.info("command_rejected", "rejected command %s for %s: %s", cmd_id, device_id, verdict.reason)
        if isinstance(pub_or_key, TypedPublisher):
            pub_or_key.put(ack)
        else:
            self.session.put(pub_or_key, codec_for(m.Ack).encode(ack), encoding=zenoh.Encoding.APPLICATION_JSON,
                             congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.REAL_TIME)

    def on_command(self, key: str, cmd: m.PvCommand | m.RegCommand | m.CapCommand) -> None:
        """Handle one command received on ``key``: check, apply and ack it, or reject it with a reason.

        A command to a device behind an adapter (``external_pv``, ``external_vr``, ``external_cap``) is the adapter's:
        left alone.
        """
        parts = keys.parse_device_key(key)
        if parts is not None and parts[0] == self.fid and parts[3] in self.external.get(parts[2], ()):
            return
        self.remember(cmd.cmd_id)
        if parts is None:
            self.counters.rejected["unknown_device"] += 1  # no device key to answer on
            return
        feeder, _, kind, device = parts
        if feeder != self.fid:
            self._wrong_feeder(feeder, kind, device, cmd)
            return
        ack_key = keys.ack(self.fid, _ack_kind(kind), device)
        if kind == "pv" and device in self.pvs and isinstance(cmd, m.PvCommand):
            self._pv_command(self.pvs[device], cmd)
        elif kind == "vr" and device in self.regs and isinstance(cmd, m.RegCommand):
            self._reg_command(self.regs[device], cmd)
        elif kind == "cap" and device in self.caps and isinstance(cmd, m.CapCommand):
            self._cap_command(self.caps[device], cmd)
        else:
            known = sorted(self.pvs) if kind == "pv" else sorted(self.caps) if kind == "cap" else sorted(self.regs)
            self._ack(ack_key, device, "bridge", cmd.cmd_id, dv.reject(
                "unknown_device", f"feeder {self.fid!r} has no {kind} device {device!r}; devices: {known}"))

    def _wrong_feeder(self, feeder: str, kind: str, device: str, cmd: m.Command) -> None:
        """A command addressed to another feeder: ignored when that feeder has a live bridge (it is its
        business), otherwise rejected and acked on that feeder's ack key, so the sender learns of it.
        """
        if any(k.startswith(f"{keys.ROOT}/{feeder}/alive/bridge/") for k in self.bridges.alive()):
            return
        try:
            ack_key = keys.ack(feeder, _ack_kind(kind), device)
        except CvvcError:
            self.counters.rejected["wrong_feeder"] += 1
            return
        self._ack(ack_key, device, "bridge", cmd.cmd_id, dv.reject(
            "wrong_feeder", f"no bridge runs feeder {feeder!r}; this bridge runs {self.fid!r}"))

    def _pv_command(self, pv: dv.PvInverter, cmd: m.PvCommand) -> None:
        bad = pv.check(cmd, now_t_ns=self.now_t_ns)
        if bad is not None:
            self._ack(self.ack_pv[pv.plant_id], pv.plant_id, pv.plant_id, cmd.cmd_id, bad)
            return
        applied = self.qsts.command_pv_q(pv.index, cmd.q_kvar)
        p = float(self.pv_p_kw[pv.index])
        headroom = dv.pv_q_headroom_kvar(pv.s_rated_kva, p, bool(self.qsts.pv_q_at_night[pv.index]))
        pv.guard.apply(cmd, cmd.q_kvar)
        self._ack(self.ack_pv[pv.plant_id], pv.plant_id, pv.plant_id, cmd.cmd_id,
                  dv.pv_verdict(cmd.q_kvar, applied, headroom))

    def _reg_command(self, reg: dv.RegulatorController, cmd: m.RegCommand) -> None:
        bad = reg.check(cmd, now_t_ns=self.now_t_ns)
        if bad is not None:
            self._ack(self.ack_vr[reg.regulator_id], reg.regulator_id, reg.regulator_id, cmd.cmd_id, bad)
            return
        match cmd.action:
            case m.TapAction(tap=tap):
                self.qsts.command_tap(reg.index, tap)
                self.qsts.command_setpoint(reg.index, None, None)
            case m.SetpointAction(setpoint_v120=sp, band_v120=bw):
                self.qsts.command_tap(reg.index, None)
                self.qsts.command_setpoint(reg.index, sp, bw)
        self._ack(self.ack_vr[reg.regulator_id], reg.regulator_id, reg.regulator_id, cmd.cmd_id, reg.apply(cmd))

    def _cap_command(self, cap: dv.CapBankController, cmd: m.CapCommand) -> None:
        bad = cap.check(cmd, now_t_ns=self.now_t_ns)
        if bad is not None:
            self._ack(self.ack_cap[cap.capacitor_id], cap.capacitor_id, cap.capacitor_id, cmd.cmd_id, bad)
            return
        applied = self.qsts.command_cap(cap.index, cmd.closed_steps)
        self._ack(self.ack_cap[cap.capacitor_id], cap.capacitor_id, cap.capacitor_id, cmd.cmd_id,
                  cap.apply(cmd, None if cmd.closed_steps is None else applied))

    # ---------------------------------------------------------------- watchdogs and settings
    def run_watchdogs(self, t_ns: int) -> None:
        """Before simulating ``t_ns``: expire commands past their validity; devices go back to default."""
        for pv in self.pvs.values():
            if pv.plant_id in self.external_pv:  # its inverter reverts itself; its adapter acks the expiry
                continue
            gone = pv.guard.expire(t_ns)
            if gone is not None:
                self.qsts.command_pv_q(pv.index, None)
                self._ack(self.ack_pv[pv.plant_id], pv.plant_id, pv.plant_id, gone.cmd_id, dv.Verdict(
                    status="expired", reason=f"valid until {gone.valid_until_t_ns}; back to local "
                                             f"{pv.local_mode}"))
        for reg in self.regs.values():
            if reg.regulator_id in self.external["vr"]:  # its outstation's hold timer ends it; its adapter acks
                continue
            gone = reg.expire(t_ns)
            if gone is not None:
                self.qsts.command_tap(reg.index, None)
                self.qsts.command_setpoint(reg.index, None, None)
                self._ack(self.ack_vr[reg.regulator_id], reg.regulator_id, reg.regulator_id, gone.cmd_id,
                          dv.Verdict(status="expired", applied_value=reg.default_setpoint_v120,
                                     reason=f"valid until {gone.valid_until_t_ns}; back to local control at "
                                            f"{reg.default_setpoint_v120:.2f} V, band {reg.default_band_v120:.2f} V"))
        for cap in self.caps.values():
            if cap.capacitor_id in self.external["cap"]:
                continue
            gone = cap.expire(t_ns)
            if gone is not None:
                self.qsts.command_cap(cap.index, None)
                self._ack(self.ack_cap[cap.capacitor_id], cap.capacitor_id, cap.capacitor_id, gone.cmd_id,
                          dv.Verdict(status="expired", reason=f"valid until {gone.valid_until_t_ns}; back to local "
                                                              f"control ({cap.control_type})"))

    def settings(self) -> DeviceSettings:
        """The devices' command state now, as the frames of the step just simulated show it (kept until a
        command is applied or expires: every such change is acked, see :meth:`_ack`).
        """
        if self._settings is None:
            self._settings = self._read_settings()
        return self._settings

    def _read_settings(self) -> DeviceSettings:
        regs = self.regs.values()
        return DeviceSettings(pv_q_setpoint_kvar=tuple(pv.q_setpoint_kvar for pv in self.pvs.values()),
                              reg_setpoint_v120=tuple(r.setpoint_v120 for r in regs),
                              reg_band_v120=tuple(r.band_v120 for r in regs), reg_mode=tuple(r.mode for r in regs),
                              cap_command=tuple(None if k.guard.active is None else
                                                (k.guard.active.cmd_id, k.guard.active.valid_until_t_ns)
                                                for k in self.caps.values()))
