"""What the field devices and the local controls read at one solved state, in one batch read per solve.

:class:`Readout` batches the measured elements of one engine (the feeder head, PV plants, regulator windings,
capacitor banks and the elements CapControls monitor), reads their conductor voltages and currents once per
solution, and turns them into :class:`FieldReadings` and into what every RegControl and CapControl samples. Conventions
as in ``engine.py``'s table; used only by ``engine.py``, which owns the OpenDSS context.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.devicemap import DeviceMapError
from simulator_bridge.opendss.circuit_tables import RegulatorWiring, conductor_range, terminal_index
from simulator_bridge.opendss.controls import CapControlSettings

__all__ = ["FieldReadings", "Readout"]


@dataclass(frozen=True)
class FieldReadings:
    """What the field devices measure at one solved state.

    Attributes
    ----------
    head_v_mag_v, head_v_ang_deg : (3,) line-to-neutral voltage phasor on terminal 1 of the head
        element, phases a, b, c [V], [deg]; 0 on absent phases.
    head_i_mag_a, head_i_ang_deg : (3,) current phasor into the feeder through the head element [A], [deg].
    head_p_kw, head_q_kvar : (3,) active / reactive power into the feeder per phase [kW], [kvar].
    pv_p_kw, pv_q_kvar : (K, 3) output per phase of each PV plant, generator convention [kW], [kvar].
    pv_v_v : (K, 3) line-to-neutral voltage magnitude at each PV plant per phase [V].
    reg_v120 : (R,) raw secondary line-to-neutral voltage / PT ratio [V on the 120 V base].
    reg_v120_compared : (R,) the voltage the controller compares with its band: ``reg_v120`` with
        line-drop compensation applied [V on the 120 V base].
    reg_tap : (R,) tap positions, -16..16 for a 32-step regulator.
    cap_states : (C,) int, closed steps of each map capacitor bank (0..its ``numsteps``).
    cap_v_v : (C,) mean line-to-neutral voltage magnitude at the bank's bus [V].
    cap_control_value : (C,) the quantity the bank's CapControl compares with its ON/OFF settings, in the
        control's own unit (V on its PT base, kvar, A, PF, hour of day); NaN when the bank has none.
    """

    head_v_mag_v: np.ndarray
    head_v_ang_deg: np.ndarray
    head_i_mag_a: np.ndarray
    head_i_ang_deg: np.ndarray
    head_p_kw: np.ndarray
    head_q_kvar: np.ndarray
    pv_p_kw: np.ndarray
    pv_q_kvar: np.ndarray
    pv_v_v: np.ndarray
    reg_v120: np.ndarray
    reg_v120_compared: np.ndarray
    reg_tap: np.ndarray
    cap_states: np.ndarray
    cap_v_v: np.ndarray
    cap_control_value: np.ndarray


class Readout:
    """The measured elements of one engine and the index tables that turn their batch read into readings.

    Parameters
    ----------
    d : the engine's OpenDSS context. node_names, node_index : the engine's nodes and their indices.
    head_element : the feeder-head meter's element (``Class.name``). pv_names : the PVSystems, map order.
    reg_wiring : every RegControl's wiring (the map's first). cap_names : the map's Capacitors.
    cc_monitored, cap_controls : every CapControl's monitored terminal (``BankTable.monitored``) and settings.
    where : names the device map in error messages.

    Raises
    ------
    DeviceMapError
        A measured element is not in the model.
    """

    def __init__(self, d, node_names: tuple[str, ...], node_index: dict[str, int], head_element: str,
                 pv_names: tuple[str, ...], reg_wiring: tuple[RegulatorWiring, ...], cap_names: tuple[str, ...],
                 cc_monitored: tuple[tuple[str, int, int, int, float, float, bool], ...],
                 cap_controls: tuple[CapControlSettings, ...], where: str) -> None:
        self._dss, self.node_names, self._node_index, self._where = d, node_names, node_index, where
        self._pv_names, self._regs, self._cap_names = pv_names, reg_wiring, cap_names
        self._cc_monitored, self.cap_controls = cc_monitored, cap_controls
        self._cap_value = np.full(len(cap_controls), np.nan)  # last sensed, for readings
        lib, ffi = self._lib, self._ffi = d.dss_lib, d.dss_ffi
        cc_elements = [m[0] for m in self._cc_monitored]
        elements = [head_element] + [f"PVSystem.{n}" for n in self._pv_names] + [
            f"Transformer.{r.transformer}" for r in self._regs] + [f"Capacitor.{c}" for c in self._cap_names] \
            + cc_elements
        terminals = [1] * (1 + len(self._pv_names)) + [r.winding for r in self._regs] + [1] * len(
            self._cap_names) + [m[1] for m in self._cc_monitored]
        handles, terms, offsets, offset = [], [], [], 0
        for element, terminal in zip(elements, terminals, strict=True):
            cls, name = element.split(".", 1)
            handle = lib.Obj_GetHandleByName(lib._ctx, lib.DSS_SetActiveClass(cls.encode()), name.encode())
            if handle == ffi.NULL:
                raise DeviceMapError(f"{self._where}: element {element!r} not found")
            handles.append(handle)
            t, size = terminal_index(self._dss, self._node_index, element, terminal, offset, self._where)
            terms.append(t)
            offsets.append(offset)
            offset += size
        self._ce_handles = ffi.new("void*[]", handles)
        self._n_ce = len(handles)
        self._ce_result = ffi.new("double**")
        self._ce_dims = ffi.new("int32_t[4]")
        n_pv, n_reg, n_cap = len(self._pv_names), len(self._regs), len(self._cap_names)
        head, pvs = terms[0], terms[1:1 + n_pv]
        regs = terms[1 + n_pv:1 + n_pv + n_reg]
        caps = terms[1 + n_pv + n_reg:1 + n_pv + n_reg + n_cap]
        self._head_cond, self._head_neutral = np.array(head.conductor), head.neutral
        self._pv_cond = np.array([t.conductor for t in pvs], dtype=int).reshape(-1, 3)
        self._pv_neutral = np.array([t.neutral for t in pvs], dtype=int)
        # regulators: the winding's phase conductors in the transformer's own order (PT phase 1..n)
        reg_cond = np.full((n_reg, 3), -1, dtype=int)
        for r, (reg, off) in enumerate(zip(self._regs, offsets[1 + n_pv:1 + n_pv + n_reg], strict=True)):
            first, nph = conductor_range(self._dss, f"Transformer.{reg.transformer}", reg.winding, off)
            reg_cond[r, :nph] = np.arange(first, first + nph)
        self._reg_cond_all = reg_cond
        self._reg_phase_mask = reg_cond >= 0
        self._reg_neutral = np.array([t.neutral for t in regs], dtype=int)
        self._reg_ratio = np.array([r.pt_ratio for r in self._regs], dtype=float)
        self._reg_ldc = np.array([complex(r.ldc_r_v, r.ldc_x_v) / r.ct_primary_a if r.remote_node < 0 else 0j
                                  for r in self._regs])
        self._reg_pt_mode = np.array([r.pt_mode for r in self._regs], dtype=int)
        self._reg_rows = np.arange(n_reg)
        self._reg_sel_fixed = self._reg_pt_mode - 1 if np.all(self._reg_pt_mode > 0) else None
        self._reg_v: tuple[np.ndarray, np.ndarray] | None = None  # this solution's, once computed
        self._reg_fixed = np.flatnonzero(self._reg_pt_mode > 0)
        self._reg_remote = np.flatnonzero(np.array([r.remote_node >= 0 for r in self._regs], dtype=bool))
        # a bank's voltage: mean over its phases of |V(phase) - V(neutral)|; absent phases are masked out
        self._cap_cond = np.array([t.conductor for t in caps], dtype=int).reshape(-1, 3)
        self._cap_neutral = np.array([t.neutral for t in caps], dtype=int)
        self._cap_phase_mask = self._cap_cond >= 0
        self._cap_n_phases = np.maximum(self._cap_phase_mask.sum(axis=1), 1)
        # CapControls: the monitored terminal's phase conductors (PT/CT phase 1..n) and all its conductors
        n_cc = len(self._cc_monitored)
        cc_ph = np.full((n_cc, 3), -1, dtype=int)
        cc_all = np.full((n_cc, 8), -1, dtype=int)
        for j, (m, off) in enumerate(zip(self._cc_monitored, offsets[1 + n_pv + n_reg + n_cap:], strict=True)):
            first, nph, ncond = conductor_range(self._dss, m[0], m[1], off, with_conductors=True)
            cc_ph[j, :min(nph, 3)] = np.arange(first, first + min(nph, 3))
            cc_all[j, :min(ncond, 8)] = np.arange(first, first + min(ncond, 8))
        self._cc_ph, self._cc_all, self._cc_mask = cc_ph, cc_all, cc_ph >= 0
        self._cc_nph = np.maximum(self._cc_mask.sum(axis=1), 1)
        self._cc_pt = np.array([m[2] for m in self._cc_monitored], dtype=int)
        self._cc_ct = np.array([m[3] for m in self._cc_monitored], dtype=int)
        self._cc_ptratio = np.array([m[4] for m in self._cc_monitored], dtype=float)
        self._cc_ctratio = np.array([m[5] for m in self._cc_monitored], dtype=float)
        self._cc_delta = np.array([m[6] for m in self._cc_monitored], dtype=bool)
        kinds = [c.kind for c in self.cap_controls]
        self._cc_kind = {k: np.array([x == k for x in kinds], dtype=bool) for k in ("current", "voltage", "kvar",
                                                                                      "pf", "time")}
        self._cc_is_v = self._cc_kind["voltage"]
        self._cc_any = {k: bool(m.any()) for k, m in self._cc_kind.items()}
        self._batch: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def cap_conductors(self) -> np.ndarray:
        """(C, 3) each bank's node index per phase a, b, c (-1 where the bank has no conductor on it)."""
        return self._cap_cond

    def invalidate(self) -> None:
        """Forget the batch read: the circuit was solved again."""
        self._batch = self._reg_v = None

    def _batch_read(self, func) -> np.ndarray:
        """One batch read (voltages [V] or currents into the element [A]) of every conductor of every
        measured element, as complex, plus a trailing 0.
        """
        func(self._ce_result, self._ce_dims, self._ce_handles, self._n_ce)
        n = int(self._ce_dims[0])
        out = np.zeros(n // 2 + 1, dtype=complex)
        out[:-1] = np.frombuffer(self._ffi.buffer(self._ce_result[0], n * 8), dtype=complex)  # (re, im) pairs
        return out

    def _read(self) -> tuple[np.ndarray, np.ndarray]:
        """The batch voltages and currents of the present solution (read once per solve)."""
        if self._batch is None:
            self._batch = (self._batch_read(self._lib.Alt_CEBatch_Get_Voltages),
                           self._batch_read(self._lib.Alt_CEBatch_Get_Currents))
        return self._batch

    def _reg_voltages(self, v: np.ndarray, i: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(raw, compared) voltage of every RegControl [V on the 120 V base], as its ``Sample`` computes it:
        the PT phase's winding voltage (MAX/MIN: the highest/lowest phase) over PTratio plus ``(R + jX)·I/CTprim``
        (current into the winding, same phase); a remote bus: that node's voltage over its PT ratio, no LDC.
        """
        if self._reg_v is not None:
            return self._reg_v
        rows = self._reg_rows
        if self._reg_sel_fixed is not None:  # every PT reads one fixed phase: no phase comparison needed
            sel = self._reg_sel_fixed
            cond = self._reg_cond_all[rows, sel]
            v_sec = (v[cond] - v[self._reg_neutral]) / self._reg_ratio
        else:
            w = (v[self._reg_cond_all] - v[self._reg_neutral][:, None]) * self._reg_phase_mask
            sel = _select_phase_index(np.abs(w), self._reg_phase_mask, self._reg_pt_mode)
            cond = self._reg_cond_all[rows, sel]
            v_sec = w[rows, sel] / self._reg_ratio
        compared = np.abs(v_sec + self._reg_ldc * i[cond])
        raw = np.abs(v_sec)
        for r in self._reg_remote:
            reg = self._regs[r]
            bus, node = self.node_names[reg.remote_node].split(".")
            self._dss.Circuit.SetActiveBus(bus)
            pos = list(self._dss.Bus.Nodes()).index(int(node))
            raw[r] = compared[r] = self._dss.Bus.VMagAngle()[2 * pos] / reg.remote_pt_ratio
        self._reg_v = (raw, compared)
        return raw, compared

    def sense(self, tod_h: float = float("nan")) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What every RegControl and CapControl of the model samples at the present solution, ``tod_h`` [h] the
        time of day (see ``FeederEngine.sense`` for the returned arrays and their units).
        """
        v, i = self._read()
        reg = self._reg_voltages(v, i)[1]
        if not len(self._cc_ph):
            z = np.zeros(0)
            return reg, z, z, z
        vph = v[self._cc_ph] * self._cc_mask
        vm = np.abs(vph)
        volts = _select_phase(vm, self._cc_mask, self._cc_pt, self._cc_nph)
        if self._cc_delta.any():  # a delta bank with one PT phase reads the line-to-line voltage
            for j in np.flatnonzero(self._cc_delta & (self._cc_pt > 0)):
                k = self._cc_pt[j] - 1
                volts[j] = abs(vph[j, k] - vph[j, (k + 1) % self._cc_nph[j]])
        volts = volts / self._cc_ptratio
        amps = _select_phase(np.abs(i[self._cc_ph]) * self._cc_mask, self._cc_mask, self._cc_ct, self._cc_nph)
        amps = amps / self._cc_ctratio
        s = (v[self._cc_all] * np.conj(i[self._cc_all])).sum(axis=1)
        q_kvar = s.imag / 1000.0
        s_abs = np.abs(s)
        pf = np.where(s_abs > 0, np.abs(s.real) / np.where(s_abs > 0, s_abs, 1.0), 1.0)
        pf = np.where(s.imag < 0, 2.0 - pf, pf)  # OpenDSS's 0..2 scale: above 1 is leading
        value = np.where(self._cc_is_v, volts, np.nan)
        for kind, x in (("current", amps), ("kvar", q_kvar), ("pf", pf)):
            if self._cc_any[kind]:
                value = np.where(self._cc_kind[kind], x, value)
        if self._cc_any["time"]:
            value = np.where(self._cc_kind["time"], tod_h, value)
        self._cap_value = value
        return reg, value, volts, q_kvar

    def readings(self, taps: np.ndarray, cap_states: np.ndarray, cap_control_index: np.ndarray) -> FieldReadings:
        """What the field devices measure at the present solution (see ``FeederEngine.readings``), with the map
        regulators' ``taps``, the map banks' ``cap_states`` and each map bank's CapControl (``cap_control_index``).
        """
        v, i = self._read()
        hv = v[self._head_cond] - v[self._head_neutral]  # index -1 reads the trailing 0
        hi = i[self._head_cond]
        hs = hv * np.conj(hi) / 1000.0
        pv_v = np.where(self._pv_cond >= 0, v[self._pv_cond] - v[self._pv_neutral][:, None], 0)  # absent: 0
        pv_s = -pv_v * np.conj(i[self._pv_cond]) / 1000.0
        n = len(taps)
        raw, compared = self._reg_voltages(v, i)
        cap_v = np.abs(v[self._cap_cond] - v[self._cap_neutral][:, None]) * self._cap_phase_mask
        cap_v_v = cap_v.sum(axis=1) / self._cap_n_phases
        cc = cap_control_index
        value = np.where(cc >= 0, self._cap_value[cc] if len(self._cap_value) else np.nan, np.nan)
        return FieldReadings(
            head_v_mag_v=np.abs(hv), head_v_ang_deg=np.degrees(np.angle(hv)),
            head_i_mag_a=np.abs(hi), head_i_ang_deg=np.degrees(np.angle(hi)),
            head_p_kw=hs.real, head_q_kvar=hs.imag,
            pv_p_kw=pv_s.real, pv_q_kvar=pv_s.imag, pv_v_v=np.abs(pv_v),
            reg_v120=raw[:n], reg_v120_compared=compared[:n], reg_tap=taps.copy(),
            cap_states=cap_states.copy(), cap_v_v=cap_v_v, cap_control_value=value,
        )

    def close(self) -> None:
        """Release the batch read's result buffer."""
        if getattr(self, "_ce_result", None) is not None and self._ce_result[0] != self._ffi.NULL:
            self._lib.DSS_Dispose_PDouble(self._ce_result)
            self._ce_result = None


def _select_phase_index(mag: np.ndarray, mask: np.ndarray, mode: np.ndarray) -> np.ndarray:
    """(n,) column of each row: the fixed phase ``mode`` (1..3), the highest (-2) or lowest (-3) present one."""
    fixed = np.clip(mode - 1, 0, 2)
    hi = np.argmax(np.where(mask, mag, -np.inf), axis=1)
    lo = np.argmin(np.where(mask, mag, np.inf), axis=1)
    return np.where(mode > 0, fixed, np.where(mode == -2, hi, lo))


def _select_phase(mag: np.ndarray, mask: np.ndarray, mode: np.ndarray, n_phases: np.ndarray) -> np.ndarray:
    """(n,) per row: a fixed phase (``mode`` 1..3), the average (-1), maximum (-2) or minimum (-3) over phases."""
    if not len(mag):
        return np.zeros(0)
    rows = np.arange(len(mag))
    avg = (mag * mask).sum(axis=1) / n_phases
    pick = mag[rows, _select_phase_index(mag, mask, np.where(mode == -1, 1, mode))]
    return np.where(mode == -1, avg, pick)
