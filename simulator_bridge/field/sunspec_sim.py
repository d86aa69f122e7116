"""A simulated SunSpec inverter: a Modbus TCP server (pymodbus) holding SunSpec models 1, 701, 702 and 704.

The register image is made by pysunspec2 from the SunSpec model definitions (no hand-written register map): the
``SunS`` marker at 40000, then common (1), DER AC measurement (701), DER capacity (702), DER AC controls (704)
and the end model. Whoever drives the inverter (a test, or the bridge) sets its per-phase P [kW], voltage [V]
and optionally Q [kvar] with :meth:`SimulatedSunSpecInverter.set_measurements`; a Modbus client reads them as
SunSpec points with scale factors, and writes the 704 reactive-power controls.

The inverter's own logic (its "firmware"), run on every Modbus request:

* **Writes** are taken only on the read-write points of model 704 and on 705's ``Ena`` (0 or 1) when it has
  model 705 (anything else: Modbus exception 2, *illegal address*). A write that leaves 704 inconsistent is
  refused with exception 3 (*illegal value*) and changes nothing: ``VarSetEna``/``VarSetEnaRvrt`` not 0/1,
  ``VarSetMod`` other than ``VARS`` (4) while enabled, ``VarSet`` beyond ``-VarMaxAbs..VarMaxInj`` of model 702,
  a reversion time beyond one day. Refused writes are counted (:attr:`refused_writes`).
* **Set point**: with ``VarSetEna = 1`` and ``VarSetMod = VARS`` the inverter holds ``VarSet`` [var] (positive:
  injecting, over-excited: the project's generator convention), clipped to its headroom ``sqrt(VAMax² − P²)``
  (0 at night, as the simulated plants); otherwise it is on its local default (:meth:`q_command_kvar` is None).
* **Revert timer**: writing ``VarSetRvrtTms`` > 0 (or a new ``VarSet`` while it is > 0) starts the timer on the
  inverter's own clock; ``VarSetRvrtRem`` counts down. Once it has run out (the set point is in force up to and
  including the deadline, as a bus command up to its ``valid_until_t_ns``), the set point reverts: to
  ``VarSetRvrt`` if ``VarSetEnaRvrt = 1``, else the function is disabled (``VarSetEna = 0``: the local default).
  So a command that expires reverts *in the inverter*, whether or not anyone is still talking to it.
* **One master**: as a plant controller configured for one Modbus master, the inverter takes writes only from its
  registered master: the first connection opened while no master is connected (in a run, its adapter's), until that
  connection closes. A write from any other connection is refused with Modbus exception 1 (*illegal function*),
  changes nothing, is counted (:attr:`foreign_master_writes`) and logged once; reads are open to every connection.

The inverter's clock is ``clock_ns`` (default ``time.monotonic_ns``): the bridge passes its simulation time.
Link loss is simulated by :meth:`stop` (the server goes away) and :meth:`start` again on the same port.
"""

from __future__ import annotations

import asyncio
import contextvars
import itertools
import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

from simulator_bridge.errors import SimulatorError
from simulator_bridge.field.devices import pv_q_headroom_kvar

__all__ = ["SUNSPEC_BASE_ADDR", "SimulatedSunSpecInverter", "SunSpecSimError"]

log = logging.getLogger(__name__)

SUNSPEC_BASE_ADDR = 40000
"""Where the ``SunS`` marker is (the usual SunSpec base address; pysunspec2 also tries 0 and 50000)."""
_MODELS = (1, 701, 702, 704)
_VOLT_VAR = 705
# 705's curve: IEEE 1547-2018 category B default (the simulated plants' own, simulator_bridge.simulation.qsts), in
# 705's units:
# V in percent of VRef (V_SF 0: whole percents), Var in percent of VarMax (DeptRef VAR_MAX_PCT, DeptRef_SF -2)
_VV_V_PCT = (92, 98, 102, 108)
_VV_VAR_PCT = (44.0, 0.0, 0.0, -44.0)
_VAR_MAX_PCT = 1  # 705 DeptRef symbol VAR_MAX_PCT
_VV_RESPONSE_S = 5  # 705 RspTms: the open-loop response time of the category B default [s]
_PHASES = ("a", "b", "c")
_VARS_MODE = 4  # 704 VarSetMod symbol VARS: the set point is in vars
_MAX_REVERT_S = 86_400
_INT16_MAX = 32767
_ILLEGAL_FUNCTION = 1  # Modbus exception to a write from a connection that is not the registered master
#: The connection a request came on, set in its handler's task (each request is handled in a task of its own)
_CONNECTION: contextvars.ContextVar[int | None] = contextvars.ContextVar("sunspec_connection", default=None)


def _close_all(transports: list[Any]) -> None:
    """Close every transport not closed yet (pymodbus closes those it saw connected; not one accepted late)."""
    for transport in transports:
        if not transport.is_closing():
            transport.close()
    transports.clear()


class SunSpecSimError(SimulatorError):
    """The simulated inverter cannot be built or started (bad rating, port in use)."""


def _sf_for(max_abs: float, lowest: int) -> int:
    """The smallest scale factor >= ``lowest`` that puts ``max_abs`` within an int16."""
    sf = lowest
    while max_abs / 10.0**sf > _INT16_MAX:
        sf += 1
    return sf


class SimulatedSunSpecInverter:
    """One PV inverter behind SunSpec Modbus TCP on ``host:port``, unit id ``unit``.

    Parameters
    ----------
    plant_id : the serial number it reports (model 1 ``SN``).
    s_rated_kva : its rating [kVA] (702 ``VAMaxRtg``/``VAMax``; also ``WMaxRtg`` and the var ratings).
    v_nominal_v : nominal line-to-neutral voltage [V] (702 ``VNomRtg``).
    phases : the phases it is connected to, of ``a``, ``b``, ``c`` (701 L1, L2, L3).
    port : TCP port on ``host``; ``unit`` the Modbus unit id it answers (others too: a single device).
    clock_ns : the inverter's clock [ns] for its revert timer.
    q_at_night : whether it gives reactive power at zero active power.
    volt_var : model 705 (DER volt-var) with one curve, the IEEE 1547-2018 category B default, enabled (True: the
        plant's local default is volt-var) or disabled (False: unity power factor); None: no model 705. Of its
        points only ``Ena`` takes writes (0 or 1; the curve is fixed here: other writes are refused as outside
        704); :meth:`volt_var_enabled` is what the plant's driver applies.
    single_master : writes only from the registered master's connection (module docstring); False: from any
        connection (an inverter without that setting, where a second master can overwrite the set point).
    """

    def __init__(self, *, plant_id: str, s_rated_kva: float, v_nominal_v: float, port: int,
                 phases: Sequence[str] = _PHASES, unit: int = 1, host: str = "127.0.0.1",
                 clock_ns: Callable[[], int] = time.monotonic_ns, q_at_night: bool = False,
                 volt_var: bool | None = None, single_master: bool = True) -> None:
        from sunspec2 import device

        if not (math.isfinite(s_rated_kva) and 0.0 < s_rated_kva <= 1e6):
            raise SunSpecSimError(f"rating {s_rated_kva!r} kVA is not within (0, 1e6]")
        if not (math.isfinite(v_nominal_v) and 0.0 < v_nominal_v <= 1e5):
            raise SunSpecSimError(f"nominal voltage {v_nominal_v!r} V is not within (0, 1e5]")
        if not phases or any(p not in _PHASES for p in phases) or len(set(phases)) != len(phases):
            raise SunSpecSimError(f"phases {tuple(phases)!r}: give distinct phases of a, b, c")
        self.plant_id = plant_id
        self.s_rated_kva = float(s_rated_kva)
        self.v_nominal_v = float(v_nominal_v)
        self.phases = tuple(phases)
        self.port = int(port)
        self.unit = int(unit)
        self.host = host
        self.q_at_night = q_at_night
        self._clock = clock_ns
        self._lock = threading.Lock()
        self.refused_writes = 0
        self.foreign_master_writes = 0  # writes refused because they came on another connection than the master's
        self.writes = 0
        self.single_master = bool(single_master)
        self._master: int | None = None  # the connection that may write (see the module docstring)
        self._conn_ids = itertools.count(1)
        self.reverts = 0
        self._deadline_ns: int | None = None
        self._p_kw = [0.0, 0.0, 0.0]
        self._models: dict[int, Any] = {}
        self._model_ids = _MODELS if volt_var is None else (*_MODELS, _VOLT_VAR)
        for mid in _MODELS:
            md = device.Model(model_id=mid)
            md.points["ID"].value = mid
            md.points["L"].value = md.len - 2
            self._models[mid] = md
        if volt_var is not None:
            self._models[_VOLT_VAR] = self._volt_var_model(bool(volt_var))
        self._addr: dict[int, int] = {}
        addr = SUNSPEC_BASE_ADDR + 2
        for mid in self._model_ids:
            self._addr[mid] = addr
            addr += self._models[mid].len
        self._end_addr = addr
        self._init_points()
        self._image: list[int] = self._build_image()
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: Any = None
        self._conns: list[Any] = []

    # ---------------------------------------------------------------------------------- register image
    def _init_points(self) -> None:
        s_va = self.s_rated_kva * 1000.0
        p1 = self._models[1].points
        for name, value in (("Mn", "cvvc-edge"), ("Md", "simulated PV inverter"), ("Vr", "1"),
                            ("SN", self.plant_id[:32]), ("DA", self.unit)):
            p1[name].value = value
        pw_sf = _sf_for(1.5 * s_va, 0)
        v_sf = _sf_for(1.5 * self.v_nominal_v * math.sqrt(3.0), -2)
        m701 = self._models[701].points
        for name, value in (("W_SF", pw_sf), ("VA_SF", pw_sf), ("Var_SF", pw_sf), ("V_SF", v_sf),
                            ("Hz_SF", -2), ("PF_SF", -3)):
            m701[name].value = value
        m701["ACType"].value = 2 if len(self.phases) == 3 else 0
        for name, value in (("St", 1), ("InvSt", 3), ("ConnSt", 1)):
            m701[name].value = value
        m701["Hz"].cvalue = 60.0
        m702 = self._models[702].points
        for name, value in (("W_SF", pw_sf), ("VA_SF", pw_sf), ("Var_SF", pw_sf), ("V_SF", v_sf), ("PF_SF", -3)):
            m702[name].value = value
        for name in ("WMaxRtg", "VAMaxRtg", "VarMaxInjRtg", "VarMaxAbsRtg", "WMax", "VAMax", "VarMaxInj",
                     "VarMaxAbs"):
            m702[name].cvalue = s_va
        for name in ("VNomRtg", "VNom"):
            m702[name].cvalue = self.v_nominal_v
        m704 = self._models[704].points
        for name, value in (("VarSet_SF", 0), ("VarSetEna", 0), ("VarSetMod", _VARS_MODE), ("VarSetPri", 1),
                            ("VarSet", 0), ("VarSetRvrt", 0), ("VarSetEnaRvrt", 0), ("VarSetRvrtTms", 0),
                            ("VarSetRvrtRem", 0)):
            m704[name].value = value
        self._set_measure_points([0.0] * 3, [self.v_nominal_v] * 3, [0.0] * 3)

    def _volt_var_model(self, enabled: bool) -> Any:
        """Model 705 with one curve of ``len(_VV_V_PCT)`` points (its repeating groups need their counts first)."""
        from sunspec2 import device, mb

        n_pt = len(_VV_V_PCT)
        head = [_VOLT_VAR, 0, 0, 0, 1, n_pt, 1]  # ID, L (below), Ena, AdptCrvReq, AdptCrvRslt, NPt, NCrv
        # the rest zero, long enough for any curve of up to 16 points (the length follows from the counts)
        md = device.Model(model_id=_VOLT_VAR, data=b"".join(mb.u16_to_data(r) for r in head) + bytes(2 * 64))
        pts = md.points
        v_ref = int(round(self.v_nominal_v))
        for name, value in (("L", md.len - 2), ("Ena", int(enabled)), ("AdptCrvRslt", 1), ("RvrtTms", 0),
                            ("RvrtRem", 0), ("RvrtCrv", 0), ("V_SF", 0), ("DeptRef_SF", -2), ("RspTms_SF", 0)):
            pts[name].value = value
        crv = md.groups["Crv"][0]
        for name, value in (("ActPt", n_pt), ("DeptRef", _VAR_MAX_PCT), ("Pri", 1), ("VRef", v_ref),
                            ("VRefAuto", v_ref), ("VRefAutoEna", 0), ("VRefAutoTms", 0), ("RspTms", _VV_RESPONSE_S),
                            ("ReadOnly", 0)):
            crv.points[name].value = value
        for pt, v, q in zip(crv.groups["Pt"], _VV_V_PCT, _VV_VAR_PCT, strict=True):
            pt.points["V"].value = v
            pt.points["Var"].cvalue = q
        return md

    def _build_image(self) -> list[int]:
        from sunspec2 import mb

        data = b"SunS" + b"".join(self._models[mid].get_mb() for mid in self._model_ids)
        data += mb.u16_to_data(0xFFFF) + mb.u16_to_data(0)
        return [int.from_bytes(data[i:i + 2], "big") for i in range(0, len(data), 2)]

    def _set_measure_points(self, p_kw: Sequence[float], v_v: Sequence[float], q_kvar: Sequence[float]) -> None:
        pts = self._models[701].points
        lim = 1.5 * self.s_rated_kva * 1000.0
        total_p = total_q = 0.0
        for i, ph in enumerate(_PHASES):
            n = i + 1
            on = ph in self.phases
            p_w = min(max(1000.0 * float(p_kw[i]), -lim), lim) if on else None
            q_var = min(max(1000.0 * float(q_kvar[i]), -lim), lim) if on else None
            v = min(max(float(v_v[i]), 0.0), 1.5 * self.v_nominal_v) if on else None
            for name, value in ((f"WL{n}", p_w), (f"VarL{n}", q_var), (f"VL{n}", v),
                                (f"VAL{n}", None if p_w is None or q_var is None else math.hypot(p_w, q_var))):
                if value is None:
                    pts[name].value = None
                else:
                    pts[name].cvalue = value
            total_p += p_w or 0.0
            total_q += q_var or 0.0
        pts["W"].cvalue = min(max(total_p, -lim), lim)
        pts["Var"].cvalue = min(max(total_q, -lim), lim)
        pts["VA"].cvalue = min(math.hypot(total_p, total_q), lim)
        vs = [float(v_v[i]) for i, ph in enumerate(_PHASES) if ph in self.phases]
        pts["LNV"].cvalue = min(max(sum(vs) / len(vs), 0.0), 1.5 * self.v_nominal_v)

    # ---------------------------------------------------------------------------------- inverter logic
    def _tick(self) -> None:
        """Run the revert timer to the inverter's present time (lock held)."""
        if self._deadline_ns is None:
            return
        ctl = self._models[704].points
        now = self._clock()
        if now > self._deadline_ns:
            self._deadline_ns = None
            self.reverts += 1
            if ctl["VarSetEnaRvrt"].value == 1:
                ctl["VarSet"].value = ctl["VarSetRvrt"].value
            else:
                ctl["VarSetEna"].value = 0
            ctl["VarSetRvrtRem"].value = 0
        else:
            ctl["VarSetRvrtRem"].value = int(math.ceil((self._deadline_ns - now) / 1e9))
        self._image = self._build_image()

    def _headroom_kvar(self) -> float:
        return pv_q_headroom_kvar(self.s_rated_kva, sum(self._p_kw), self.q_at_night)

    def _q_command_locked(self) -> float | None:
        ctl = self._models[704].points
        if ctl["VarSetEna"].value != 1 or ctl["VarSetMod"].value != _VARS_MODE:
            return None
        q = float(ctl["VarSet"].cvalue) / 1000.0
        h = self._headroom_kvar()
        return min(max(q, -h), h)

    def q_command_kvar(self) -> float | None:
        """The reactive power set point in force [kvar, + injects], clipped to the headroom; None: local default."""
        with self._lock:
            self._tick()
            return self._q_command_locked()

    def var_setpoint_kvar(self) -> float | None:
        """The 704 set point in force [kvar, + injects], not clipped; None: the function is off (local default).

        What a plant model takes as its command: the plant clips it to the headroom at its own output at each
        instant (``simulator_bridge.simulation.qsts``), as the inverter does at its present P (:meth:`q_command_kvar`).
        """
        with self._lock:
            self._tick()
            ctl = self._models[704].points
            if ctl["VarSetEna"].value != 1 or ctl["VarSetMod"].value != _VARS_MODE:
                return None
            return float(ctl["VarSet"].cvalue) / 1000.0

    def control_state(self) -> dict[str, Any]:
        """Model 704's reactive-power points as they stand now (raw register values, after the timer)."""
        with self._lock:
            self._tick()
            pts = self._models[704].points
            return {k: pts[k].value for k in ("VarSetEna", "VarSetMod", "VarSet", "VarSetRvrt", "VarSetEnaRvrt",
                                              "VarSetRvrtTms", "VarSetRvrtRem", "VarSet_SF")}

    def set_measurements(self, *, p_kw: Sequence[float], v_v: Sequence[float],
                         q_kvar: Sequence[float] | None = None) -> None:
        """Set the output the inverter reports, per phase a, b, c (values of absent phases are ignored).

        Parameters
        ----------
        p_kw : active power per phase [kW, generator convention]. v_v : line-to-neutral voltage per phase [V].
        q_kvar : reactive power per phase [kvar, + injects]; None: the set point in force (or 0 on the local
            default), shared equally by the phases.
        """
        if len(p_kw) != 3 or len(v_v) != 3 or (q_kvar is not None and len(q_kvar) != 3):
            raise SunSpecSimError("give p_kw, v_v (and q_kvar) for the three phases a, b, c")
        values = [*p_kw, *v_v, *(q_kvar or ())]
        if not all(math.isfinite(float(x)) for x in values):
            raise SunSpecSimError(f"non-finite measurement in {values!r}")
        with self._lock:
            self._p_kw = [float(p) if ph in self.phases else 0.0 for p, ph in zip(p_kw, _PHASES, strict=True)]
            self._tick()
            if q_kvar is None:
                q = self._q_command_locked() or 0.0
                q_kvar = [q / len(self.phases) if ph in self.phases else 0.0 for ph in _PHASES]
            self._set_measure_points(p_kw, v_v, q_kvar)
            self._image = self._build_image()

    def set_raw(self, model_id: int, point: str, raw: int | None) -> None:
        """Put a raw register value into a point (None: the SunSpec "not implemented" value); for tests of bad
        values. The next :meth:`set_measurements` overwrites measurement points again. 705's curve points are
        named ``Crv.<point>`` (curve 1) and ``Crv.Pt.<i>.<point>`` (its point ``i`` from 0).
        """
        with self._lock:
            group = self._models[model_id]
            *path, name = point.split(".")  # 705's curve: "Crv.<name>" (curve 1) or "Crv.Pt.<i>.<name>" (its point i)
            if path[:1] == ["Crv"]:
                group = group.groups["Crv"][0]
                if path[1:2] == ["Pt"]:
                    group = group.groups["Pt"][int(path[2])]
            group.points[name].value = raw
            self._image = self._build_image()

    # ---------------------------------------------------------------------------------------- Modbus side
    def _rw_704(self) -> set[int]:
        """Register addresses of model 704's read-write points."""
        out: set[int] = set()
        md = self._models[704]
        base = self._addr[704]

        def walk(group: Any) -> None:
            for p in group.points.values():
                if p.pdef.get("access") == "RW":
                    out.update(range(base + p.offset, base + p.offset + p.len))
            for g in group.groups.values():
                for sub in g if isinstance(g, list) else [g]:
                    walk(sub)

        walk(md)
        return out

    def _ena_705_addr(self) -> int | None:
        """The register of 705's ``Ena`` (its only point this inverter takes writes on), None without 705."""
        if _VOLT_VAR not in self._models:
            return None
        return self._addr[_VOLT_VAR] + self._models[_VOLT_VAR].points["Ena"].offset

    def _write_705_ena(self, values: list[int]) -> int | None:
        """Enable (1) or disable (0) the volt-var curve; the Modbus exception code if refused (lock held)."""
        if values[0] not in (0, 1):
            self.refused_writes += 1
            return 3  # illegal value
        self._models[_VOLT_VAR].points["Ena"].value = values[0]
        self.writes += 1
        self._image = self._build_image()
        return None

    def volt_var_enabled(self) -> bool | None:
        """Whether model 705's volt-var curve is enabled (the plant's local default); None without model 705."""
        with self._lock:
            if _VOLT_VAR not in self._models:
                return None
            return self._models[_VOLT_VAR].points["Ena"].value == 1

    def _write_704(self, start: int, address: int, values: list[int]) -> int | None:
        """Apply a write of ``values`` at ``address``; the Modbus exception code if refused (lock held)."""
        from sunspec2 import device

        rw = self._rw_704()
        if any(a not in rw for a in range(address, address + len(values))):
            self.refused_writes += 1
            return 2  # illegal address: only 704's read-write points take writes
        image = list(self._image)
        off = address - start
        image[off:off + len(values)] = [int(v) & 0xFFFF for v in values]
        lo = self._addr[704] - start
        data = b"".join(r.to_bytes(2, "big") for r in image[lo:lo + self._models[704].len])
        trial = device.Model(model_id=704, data=data)
        pts = trial.points
        cap = self._models[702].points
        ena, mod, ena_rv, tms = (pts[k].value for k in ("VarSetEna", "VarSetMod", "VarSetEnaRvrt",
                                                          "VarSetRvrtTms"))
        try:
            var_set = float(pts["VarSet"].cvalue) if pts["VarSet"].value is not None else None
            inj, absorb = float(cap["VarMaxInj"].cvalue), float(cap["VarMaxAbs"].cvalue)
        except (TypeError, ValueError):
            var_set, inj, absorb = None, 0.0, 0.0
        if (ena not in (0, 1) or ena_rv not in (0, 1) or (ena == 1 and mod != _VARS_MODE)
                or (ena == 1 and var_set is None) or (var_set is not None and not -absorb <= var_set <= inj)
                or tms is None or tms > _MAX_REVERT_S):
            self.refused_writes += 1
            return 3  # illegal value: the controls stay as they were
        touched = set(range(address, address + len(values)))
        old = self._models[704]
        base = self._addr[704]
        timer_regs = {base + old.points[k].offset + i for k in ("VarSet", "VarSetRvrtTms", "VarSetEna")
                      for i in range(old.points[k].len)}
        self._models[704] = trial
        trial.points["VarSetRvrtRem"].value = 0
        if touched & timer_regs:
            self._deadline_ns = self._clock() + int(tms) * 1_000_000_000 if tms and ena == 1 else None
        self.writes += 1
        self._tick()
        self._image = self._build_image()
        return None

    async def _action(self, func_code: int, start: int, address: int, count: int, registers: list[int],
                      values: list[int] | list[bool] | None) -> Any:
        from pymodbus.constants import ExcCodes

        with self._lock:
            self._tick()
            if values is not None and func_code in (6, 16):
                conn = _CONNECTION.get()
                if self.single_master and (conn is None or conn != self._master):
                    self._refuse_foreign_master(conn, address, len(values))
                    return ExcCodes(_ILLEGAL_FUNCTION)
                ena = self._ena_705_addr()
                code = (self._write_705_ena([int(v) for v in values]) if ena is not None and address == ena
                        and len(values) == 1 else self._write_704(start, address, [int(v) for v in values]))
                if code is not None:
                    return ExcCodes(code)
            registers[:len(self._image)] = self._image
        return None

    def _refuse_foreign_master(self, conn: int | None, address: int, count: int) -> None:
        """Count a write from a connection that is not the master's; the first is logged (lock held)."""
        self.foreign_master_writes += 1
        if self.foreign_master_writes == 1:
            log.warning("%s: refused a write of %d register(s) at %d from Modbus connection %s, not the registered "
                        "master's (%s); further ones are counted in foreign_master_writes", self.plant_id, count,
                        address, conn, self._master)

    def _on_connect(self) -> int:
        """A new connection's id; it becomes the master when none is connected."""
        with self._lock:
            conn = next(self._conn_ids)
            if self._master is None:
                self._master = conn
            return conn

    def _on_disconnect(self, conn: int) -> None:
        """A connection closed: when it was the master's, the next connection to open becomes the master."""
        with self._lock:
            if self._master == conn:
                self._master = None

    def start(self) -> SimulatedSunSpecInverter:
        """Serve on ``host:port`` from a background thread; returns when it listens (SunSpecSimError if not)."""
        from pymodbus.server import ModbusTcpServer
        from pymodbus.simulator import DataType, SimData, SimDevice

        if self._thread is not None:
            return self
        n = self._end_addr + 2 - SUNSPEC_BASE_ADDR
        dev = SimDevice(id=0, simdata=[SimData(SUNSPEC_BASE_ADDR, values=[0] * n, datatype=DataType.REGISTERS)],
                        action=self._action)
        loop = asyncio.new_event_loop()
        ready = threading.Event()
        failure: list[BaseException] = []

        conns: list[Any] = []
        self._conns = conns

        async def serve() -> None:
            server = ModbusTcpServer(dev, address=(self.host, self.port))
            make = server.callback_new_connection

            def tracked() -> Any:  # every connection's transport, so stop() can close what pymodbus left open
                proto = make()
                made, lost, handle = proto.connection_made, proto.connection_lost, proto.handle_request
                conn: list[int] = []

                def connection_made(transport: Any) -> None:
                    conns.append(transport)
                    conn.append(self._on_connect())
                    made(transport)

                def connection_lost(exc: Exception | None) -> None:
                    if conn:
                        self._on_disconnect(conn[0])
                    lost(exc)

                async def handle_request() -> None:  # in the request's own task: the action sees its connection
                    _CONNECTION.set(conn[0] if conn else None)
                    await handle()

                proto.connection_made = connection_made
                proto.connection_lost = connection_lost
                proto.handle_request = handle_request
                return proto

            server.callback_new_connection = tracked  # type: ignore[method-assign]
            self._server = server
            await server.serve_forever(background=True)

        def run() -> None:
            asyncio.set_event_loop(loop)
            try:
                loop.run_until_complete(serve())
            except BaseException as e:  # reported to start(), which raises SunSpecSimError
                failure.append(e)
                ready.set()
                return
            ready.set()
            loop.run_forever()

        self._loop = loop
        self._thread = threading.Thread(target=run, name=f"sunspec-sim-{self.plant_id}", daemon=True)
        self._thread.start()
        if not ready.wait(10.0) or failure:
            self._join()
            raise SunSpecSimError(f"cannot serve SunSpec Modbus on {self.host}:{self.port}: "
                                  f"{failure[0] if failure else 'no answer in 10 s'}")
        return self

    def stop(self) -> None:
        """Stop serving (a lost link, seen from the client); :meth:`start` serves again."""
        if self._thread is None or self._loop is None:
            return
        loop = self._loop
        server = self._server

        conns = self._conns

        async def shutdown() -> None:
            # accept what the kernel has queued first: asyncio fails (and leaks the socket of) a connection
            # whose accept is still on its way when the listener closes
            for _ in range(3):
                await asyncio.sleep(0.01)
            await server.shutdown()
            for _ in range(3):  # a connection accepted just before: its connection_made is still queued
                await asyncio.sleep(0.005)
            _close_all(conns)
            for _ in range(3):  # let the closed transports close their sockets
                await asyncio.sleep(0.005)

        if server is not None and loop.is_running():
            fut = asyncio.run_coroutine_threadsafe(shutdown(), loop)
            try:
                fut.result(5.0)
            except Exception:  # already closing: stop the loop anyway
                pass
        self._join()

    def _join(self) -> None:
        loop, thread = self._loop, self._thread
        if loop is not None and thread is not None:
            if loop.is_running():
                loop.call_soon_threadsafe(loop.stop)
            thread.join(10.0)
            if not loop.is_running():
                # a connection accepted while the loop was stopping: let its connection_made run, then close it
                loop.run_until_complete(asyncio.sleep(0.01))
                _close_all(self._conns)
                loop.run_until_complete(asyncio.sleep(0.01))
                loop.close()
        self._loop = self._thread = self._server = None
        with self._lock:
            self._master = None  # every connection is gone

    def __enter__(self) -> SimulatedSunSpecInverter:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
