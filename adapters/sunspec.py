"""A PV inverter's SunSpec Modbus link: read models 701/702/704 and write 704's reactive-power set point.

Reads and writes go through pysunspec2 (``SunSpecModbusClientDeviceTCP``) by SunSpec point name, with the scale
factors the device reports: no register addresses are written here. The points used (docs/sunspec.md):

* 701 DER AC measurement: ``W``, ``Var`` (totals), ``WL1..3``, ``VarL1..3``, ``VL1..3`` (per phase L1, L2, L3 =
  a, b, c), with ``W_SF``, ``Var_SF``, ``V_SF``.
* 702 DER capacity: ``VAMax`` (else ``VAMaxRtg``), ``VarMaxInj``, ``VarMaxAbs`` (else their ratings), with
  ``VA_SF``, ``Var_SF``.
* 704 DER AC controls: ``VarSetEna``, ``VarSetMod`` (``VARS`` = 4), ``VarSet`` with ``VarSet_SF``,
  ``VarSetEnaRvrt``, ``VarSetRvrtTms``, ``VarSetRvrtRem``.
* 705 DER volt-var, when the inverter has it: ``Ena`` (also written, to set the plant's local default),
  ``NCrv``, ``NPt``, and curve 1's ``ActPt``, ``DeptRef`` (``VAR_MAX_PCT`` = 1 only), ``VRef``, points ``V``
  (% of ``VRef``) and ``Var`` (% of ``VarMax``), with ``V_SF``, ``DeptRef_SF``: the plant's local default (volt-var
  when enabled, unity power factor otherwise).

Sign convention: ``Var``, ``VarL*`` and ``VarSet`` positive = injecting reactive power (over-excited), the
project's generator convention (docs/conventions.md). Values are checked before use: a point that is not
implemented, a scale factor outside -10..10, a power beyond 1.5 times the rating or a negative voltage raises
:class:`RegisterValueError` naming the point. Link failures raise :class:`LinkDownError`; a write the device
answers with a Modbus exception raises :class:`DeviceRefusedError`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from adapters.errors import DeviceRefusedError, LinkDownError, ModelMissingError, RegisterValueError

__all__ = ["InverterReading", "PhaseReading", "SunSpecLink", "VARS_MODE", "VoltVarCurve"]

VARS_MODE = 4
"""704 ``VarSetMod`` symbol ``VARS``: the reactive power set point is in vars."""
_PHASE_OF = {1: "a", 2: "b", 3: "c"}
_SF_RANGE = (-10, 10)
_OVER_RATING = 1.5  # a power reading beyond this multiple of the rating is refused
_MAX_V = 1e6
_VOLT_VAR = 705
_VAR_MAX_PCT = 1  # 705 DeptRef symbol: the curve's Var in percent of VarMax
_VV_V_PCT = (50.0, 150.0)  # a 705 curve voltage outside this [% of VRef] is refused


@dataclass(frozen=True)
class PhaseReading:
    """One phase's output: active and reactive power [kW], [kvar] (generator convention) and voltage [V, L-N]."""

    phase: str
    p_kw: float
    q_kvar: float
    v_v: float


@dataclass(frozen=True)
class VoltVarCurve:
    """Model 705's curve 1, checked: ``enabled`` (``Ena``), ``v_pu`` its voltages [pu of ``VRef``], strictly
    increasing, and ``q_pu`` its reactive powers [pu of ``VarMaxInj``/``VarMaxAbs``, + injects].
    """

    enabled: bool
    v_pu: tuple[float, ...]
    q_pu: tuple[float, ...]


@dataclass(frozen=True)
class InverterReading:
    """One scan of the inverter's models, checked and in the project's units.

    ``q_setpoint_kvar`` is the 704 set point in force (None: the function is disabled, the local default);
    ``var_set_step_kvar`` the resolution of ``VarSet`` (its scale factor) [kvar]; ``revert_remaining_s`` is
    ``VarSetRvrtRem`` [s] (None if not implemented). ``volt_var``: model 705's curve, None when the inverter has
    no model 705.
    """

    p_kw: float
    q_kvar: float
    phases: tuple[PhaseReading, ...]
    s_rated_kva: float
    var_max_inj_kvar: float
    var_max_abs_kvar: float
    q_setpoint_kvar: float | None
    var_set_step_kvar: float
    revert_remaining_s: float | None
    volt_var: VoltVarCurve | None = None


def _link_errors() -> tuple[type[BaseException], ...]:
    from sunspec2.modbus.client import SunSpecModbusClientError
    from sunspec2.modbus.modbus import ModbusClientError

    return (ModbusClientError, SunSpecModbusClientError, OSError)


class SunSpecLink:
    """The Modbus TCP link to one SunSpec inverter. Not thread safe: one thread does all its I/O.

    Parameters
    ----------
    host, port : the inverter's Modbus TCP address. unit : its Modbus unit (slave) id.
    timeout_s : a request's time-out [s].
    """

    def __init__(self, host: str, port: int, *, unit: int = 1, timeout_s: float = 1.0) -> None:
        self.host = host
        self.port = int(port)
        self.unit = int(unit)
        self.timeout_s = float(timeout_s)
        self._dev: Any = None
        self._models: dict[int, Any] = {}

    @property
    def endpoint(self) -> str:
        """``tcp/host:port`` (the form of the ``--modbus`` flag)."""
        return f"tcp/{self.host}:{self.port}"

    @property
    def connected(self) -> bool:
        """Whether the models were scanned and the link has not failed since."""
        return self._dev is not None

    def connect(self) -> None:
        """Scan the device's models (LinkDownError, ModelMissingError) and keep the connection open."""
        from sunspec2.modbus.client import SunSpecModbusClientDeviceTCP

        self.close()
        dev = SunSpecModbusClientDeviceTCP(slave_id=self.unit, ipaddr=self.host, ipport=self.port,
                                           timeout=self.timeout_s)
        try:
            dev.scan(full_model_read=False)
            dev.connect()
        except _link_errors() as e:
            dev.disconnect()
            raise LinkDownError(f"no SunSpec device at {self.endpoint} unit {self.unit}: {e}") from e
        missing = [mid for mid in (1, 701, 702, 704) if not dev.models.get(mid)]
        if missing:
            dev.disconnect()
            raise ModelMissingError(f"the device at {self.endpoint} has no SunSpec model {missing}; the adapter "
                                    "needs 701 (measurement), 702 (capacity) and 704 (controls)")
        self._dev = dev
        self._models = {mid: dev.models[mid][0] for mid in (701, 702, 704, _VOLT_VAR) if dev.models.get(mid)}

    def close(self) -> None:
        """Close the connection (a later call re-scans)."""
        if self._dev is not None:
            try:
                self._dev.disconnect()
            except _link_errors():
                pass
        self._dev = None
        self._models = {}

    def _io(self, what: str, fn: Any, *args: Any) -> Any:
        if self._dev is None:
            self.connect()
        from sunspec2.modbus.modbus import ModbusClientException

        try:
            return fn(*args)
        except ModbusClientException as e:
            raise DeviceRefusedError(f"{self.endpoint} refused {what}: {e}") from e
        except _link_errors() as e:
            self.close()
            raise LinkDownError(f"{self.endpoint} did not answer {what}: {e}") from e

    def read(self) -> InverterReading:
        """Read 701, 702, 704 (and 705 if the inverter has it) and check them (LinkDownError, RegisterValueError)."""
        if self._dev is None:
            self.connect()
        for mid in self._models:
            try:
                self._io(f"a read of model {mid}", self._models[mid].read)
            except DeviceRefusedError as e:  # an exception answer to a read: the device is not usable
                self.close()
                raise LinkDownError(str(e)) from e
        return self._reading()

    def _reading(self) -> InverterReading:
        m701, m702, m704 = (self._models[k] for k in (701, 702, 704))
        s_va = _first(m702, 702, ("VAMax", "VAMaxRtg"), "VA_SF")
        if s_va <= 0.0:
            raise RegisterValueError("702.VAMax", f"apparent power rating {s_va} VA is not positive")
        inj = abs(_first(m702, 702, ("VarMaxInj", "VarMaxInjRtg"), "Var_SF"))
        absorb = abs(_first(m702, 702, ("VarMaxAbs", "VarMaxAbsRtg"), "Var_SF"))
        lim = _OVER_RATING * s_va
        p_w = _value(m701, 701, "W", "W_SF", -lim, lim)
        q_var = _value(m701, 701, "Var", "Var_SF", -lim, lim)
        phases = []
        for n, ph in _PHASE_OF.items():
            if m701.points[f"VL{n}"].value is None:
                continue  # a phase the inverter is not connected to
            v = _value(m701, 701, f"VL{n}", "V_SF", 0.0, _MAX_V)
            wp = _value(m701, 701, f"WL{n}", "W_SF", -lim, lim)
            qp = _value(m701, 701, f"VarL{n}", "Var_SF", -lim, lim)
            phases.append(PhaseReading(phase=ph, p_kw=wp / 1000.0, q_kvar=qp / 1000.0, v_v=v))
        if not phases:
            raise RegisterValueError("701.VL1", "no phase voltage is implemented (VL1, VL2, VL3)")
        ctl = m704.points
        ena = _enum(m704, 704, "VarSetEna", (0, 1))
        sf = _sf(m704, 704, "VarSet_SF")
        q_set = None
        if ena == 1 and ctl["VarSetMod"].value == VARS_MODE:
            q_set = _value(m704, 704, "VarSet", "VarSet_SF", -lim, lim) / 1000.0
        rem = ctl["VarSetRvrtRem"].value
        vv = _volt_var(self._models[_VOLT_VAR]) if _VOLT_VAR in self._models else None
        return InverterReading(p_kw=p_w / 1000.0, q_kvar=q_var / 1000.0, phases=tuple(phases),
                               s_rated_kva=s_va / 1000.0, var_max_inj_kvar=inj / 1000.0,
                               var_max_abs_kvar=absorb / 1000.0, q_setpoint_kvar=q_set,
                               var_set_step_kvar=10.0**sf / 1000.0,
                               revert_remaining_s=None if rem is None else float(rem), volt_var=vv)

    def write_volt_var_enable(self, enabled: bool) -> InverterReading:
        """Enable or disable model 705's volt-var curve (``Ena``), then read the models back (the returned reading's
        ``volt_var.enabled`` is what the inverter holds). RegisterValueError when the inverter has no model 705.
        """
        if self._dev is None:
            self.connect()
        if _VOLT_VAR not in self._models:
            raise RegisterValueError("705.Ena", f"the device at {self.endpoint} has no model 705 (volt-var)")
        pts = self._models[_VOLT_VAR].points
        pts["Ena"].value = int(bool(enabled))
        self._io("705 Ena", pts["Ena"].write)
        return self.read()

    def write_var_setpoint(self, q_kvar: float, revert_s: int) -> InverterReading:
        """Write a 704 reactive power set point [kvar, + injects] that reverts after ``revert_s`` [s], then read
        the models back (the returned reading's ``q_setpoint_kvar`` is what the inverter holds).

        The set point, its mode and timer are written first, then ``VarSetEna = 1``, so the inverter never
        holds an old ``VarSet`` with a new enable. ``VarSetEnaRvrt = 0``: at the timer's end the function is
        disabled and the inverter is back on its local default.
        """
        if not math.isfinite(q_kvar):
            raise RegisterValueError("704.VarSet", f"set point {q_kvar!r} kvar is not finite")
        if self._dev is None:
            self.connect()
        ctl = self._models[704]
        pts = ctl.points
        _sf(ctl, 704, "VarSet_SF")
        pts["VarSetMod"].value = VARS_MODE
        pts["VarSet"].cvalue = q_kvar * 1000.0
        pts["VarSetEnaRvrt"].value = 0
        pts["VarSetRvrtTms"].value = int(revert_s)
        self._io("the 704 set point", ctl.write)
        pts["VarSetEna"].value = 1
        self._io("704 VarSetEna", pts["VarSetEna"].write)
        return self.read()

    def disable_var_setpoint(self) -> InverterReading:
        """Disable 704's reactive power set point (``VarSetEna = 0``: the inverter back on its local default), then
        read the models back.
        """
        if self._dev is None:
            self.connect()
        pts = self._models[704].points
        pts["VarSetEna"].value = 0
        self._io("704 VarSetEna", pts["VarSetEna"].write)
        return self.read()


def _sf(model: Any, mid: int, name: str) -> int:
    sf = model.points[name].value
    if sf is None or not _SF_RANGE[0] <= int(sf) <= _SF_RANGE[1]:
        raise RegisterValueError(f"{mid}.{name}", f"scale factor {sf!r} is not implemented or outside "
                                 f"{_SF_RANGE[0]}..{_SF_RANGE[1]}")
    return int(sf)


def _value(model: Any, mid: int, name: str, sf_name: str, lo: float, hi: float) -> float:
    """A point's value with its scale factor, in the point's SunSpec unit (W, var, V), checked within lo..hi."""
    sf = _sf(model, mid, sf_name)
    raw = model.points[name].value
    if raw is None:
        raise RegisterValueError(f"{mid}.{name}", "not implemented (the SunSpec unimplemented value)")
    v = float(raw) * 10.0**sf
    if not (math.isfinite(v) and lo <= v <= hi):
        raise RegisterValueError(f"{mid}.{name}", f"{v:g} is outside {lo:g}..{hi:g}")
    return v


def _first(model: Any, mid: int, names: tuple[str, ...], sf_name: str) -> float:
    """The first implemented of ``names`` (a setting, then its rating), scaled; RegisterValueError if none is."""
    for name in names:
        if model.points[name].value is not None:
            return _value(model, mid, name, sf_name, -1e9, 1e9)
    raise RegisterValueError(f"{mid}.{names[0]}", f"none of {', '.join(names)} is implemented")


def _enum(model: Any, mid: int, name: str, allowed: tuple[int, ...]) -> int:
    v = model.points[name].value
    if v not in allowed:
        raise RegisterValueError(f"{mid}.{name}", f"{v!r} is none of {allowed}")
    return int(v)


def _volt_var(model: Any) -> VoltVarCurve:
    """Model 705's curve 1, checked (RegisterValueError naming the point)."""
    enabled = _enum(model, 705, "Ena", (0, 1)) == 1
    n_crv, n_pt = model.points["NCrv"].value, model.points["NPt"].value
    if not n_crv or not n_pt or not model.groups.get("Crv"):
        raise RegisterValueError("705.NCrv", f"{n_crv!r} curves of {n_pt!r} points: no curve")
    crv = model.groups["Crv"][0]
    act = crv.points["ActPt"].value
    if act is None or not 2 <= int(act) <= int(n_pt):
        raise RegisterValueError("705.ActPt", f"{act!r} active points: give 2..{n_pt}")
    if crv.points["DeptRef"].value != _VAR_MAX_PCT:
        raise RegisterValueError("705.DeptRef", f"{crv.points['DeptRef'].value!r}: only VAR_MAX_PCT (1), the "
                                 "curve's Var in percent of VarMax, is understood")
    v_sf, q_sf = _sf(model, 705, "V_SF"), _sf(model, 705, "DeptRef_SF")
    if crv.points["VRef"].value in (None, 0):
        raise RegisterValueError("705.VRef", "the reference voltage is not implemented or 0")
    v, q = [], []
    for i, pt in enumerate(crv.groups["Pt"][:int(act)]):
        rv, rq = pt.points["V"].value, pt.points["Var"].value
        if rv is None or rq is None:
            raise RegisterValueError(f"705.Pt{i + 1}", "a curve point is not implemented")
        v.append(float(rv) * 10.0**v_sf)
        q.append(float(rq) * 10.0**q_sf)
    if not all(_VV_V_PCT[0] <= x <= _VV_V_PCT[1] for x in v) or any(b <= a for a, b in zip(v, v[1:], strict=False)):
        raise RegisterValueError("705.Pt.V", f"curve voltages {v} % of VRef: they must rise strictly within "
                                 f"{_VV_V_PCT[0]:g}..{_VV_V_PCT[1]:g} %")
    if not all(-100.0 <= x <= 100.0 for x in q):
        raise RegisterValueError("705.Pt.Var", f"curve reactive powers {q} % of VarMax: outside -100..100 %")
    return VoltVarCurve(enabled=enabled, v_pu=tuple(x / 100.0 for x in v), q_pu=tuple(x / 100.0 for x in q))
