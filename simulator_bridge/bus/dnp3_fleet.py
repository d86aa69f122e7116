"""The bridge's regulators and capacitor banks behind DNP3 (``cvvc run --field-protocol dnp3``): one outstation each.

With ``BridgeConfig.field_dnp3`` the bridge serves one
:class:`~simulator_bridge.field.dnp3_sim.SimulatedRegulatorControl` per regulator and one
:class:`~simulator_bridge.field.dnp3_sim.SimulatedCapBankController` per bank named there, on the endpoint given, and a
``cvvc adapter dnp3 --clock head`` per device stands between that outstation and the bus, as it would in the field.
The bridge then, as it does for PV plants behind SunSpec (``simulator_bridge.bus.sunspec_fleet``):

* before each step, on the outstations' clock set to the step's time, takes what each device holds in force as the
  device's command (:meth:`Dnp3Fleet.commands`): a regulator's remote set point and band (None: its local set point
  and band), a bank's commanded state (None: its local control). A remote command ends in the device at its hold
  time, so the bridge's own watchdog is not used for these devices. Only changes are handed to the simulation, as
  the bridge's own devices hand each command and each expiry;
* after each step, writes the step's readings into the outstations (:meth:`Dnp3Fleet.measure`), *before* the step's
  head frame is put, so the adapter that reads at that head frame reads this step's values;
* publishes no frame, no ack and no liveliness token for these devices, and takes none of their commands from the
  bus: the adapters do. It still lists them in the step's ``StepEnd`` (the agent waits for their frames), waits,
  bounded, for their frames of each step (``simulator_bridge.bus.adapter_frames``), and counts a command handled
  (lockstep) when its adapter's ack arrives.

The regulator's readout has no load current: its analog input 2 is written as 0 A (no frame carries it).
Measurement noise, drops, latency and clock skew are applied by the bridge to the frames it publishes; for devices
behind DNP3 they are not implemented (the bridge refuses those options with ``field_dnp3``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from schemas import messages as m
from simulator_bridge.errors import BridgeError
from simulator_bridge.field import devices as dv
from simulator_bridge.field.dnp3_sim import (
    Dnp3SimError,
    SimulatedCapBankController,
    SimulatedRegulatorControl,
    parse_dnp3_endpoint,
)

if TYPE_CHECKING:
    from simulator_bridge.opendss.engine import FeederEngine

__all__ = ["Dnp3Fleet", "regulator_phases"]

_V120_MAX = 200.0  # the frames' (and the adapter's) ceiling of a voltage on the 120 V base [V]


def regulator_phases(engine: FeederEngine) -> tuple[m.Phase, ...]:
    """Each map regulator's phase letter (``a``, ``b``, ``c``), from its secondary node (``bus.1`` is phase a)."""
    return tuple(dv.PHASE_NAMES[int(engine.node_names[n].split(".")[1]) - 1] for n in engine.reg_secondary_node)


class Dnp3Fleet:
    """The simulated DNP3 outstations of the regulators and banks behind DNP3, on the simulation's clock.

    Parameters
    ----------
    endpoints : device id (a map regulator or bank) -> ``tcp/127.0.0.1:PORT`` its outstation serves on.
    engine : the feeder (device ids, tap ranges, local set points and bands, bank steps).
    """

    def __init__(self, endpoints: Mapping[str, str], engine: FeederEngine) -> None:
        regs, caps = list(engine.regulator_ids), list(engine.capacitor_ids)
        unknown = sorted(set(endpoints) - set(regs) - set(caps))
        if unknown:
            raise BridgeError(f"--field-dnp3 names devices the feeder has neither as regulator nor as bank: "
                              f"{unknown}; its regulators: {regs}, its banks: {caps}")
        self.clock_ns = 0  # the outstations' clock: the simulation time the bridge is at [ns]
        self.regs: dict[str, tuple[int, SimulatedRegulatorControl]] = {}
        self.caps: dict[str, tuple[int, SimulatedCapBankController]] = {}
        self._reg_in_force: dict[str, tuple[float, float] | None] = {}  # what the simulation was last handed
        self._cap_in_force: dict[str, int | None] = {}
        try:
            for did, endpoint in endpoints.items():
                _, port = parse_dnp3_endpoint(endpoint)
                if did in regs:
                    r = regs.index(did)
                    self.regs[did] = (r, SimulatedRegulatorControl(
                        regulator_id=did, tap_max=int(engine.reg_tap_max[r]),
                        default_setpoint_v120=float(engine.reg_default_setpoint_v120[r]),
                        default_band_v120=float(engine.reg_default_band_v120[r]), port=port, clock_ns=self._clock))
                    self._reg_in_force[did] = None
                else:
                    c = caps.index(did)
                    self.caps[did] = (c, SimulatedCapBankController(capacitor_id=did, port=port,
                                                                    steps=int(engine.cap_steps[c]),
                                                                    clock_ns=self._clock))
                    self._cap_in_force[did] = None
        except Dnp3SimError as e:
            raise BridgeError(f"--field-dnp3: {e}") from e

    def _clock(self) -> int:
        return self.clock_ns

    @property
    def regulator_ids(self) -> tuple[str, ...]:
        """The regulators behind DNP3."""
        return tuple(self.regs)

    @property
    def capacitor_ids(self) -> tuple[str, ...]:
        """The banks behind DNP3."""
        return tuple(self.caps)

    def _outstations(self) -> list[SimulatedRegulatorControl | SimulatedCapBankController]:
        return [sim for _, sim in self.regs.values()] + [sim for _, sim in self.caps.values()]

    def start(self) -> None:
        """Serve every outstation (BridgeError when one cannot listen; those started are stopped)."""
        try:
            for sim in self._outstations():
                sim.start()
        except Exception as e:  # opendnp3 raises plain exceptions when a port is taken
            self.close()
            raise BridgeError(f"a DNP3 outstation could not listen: {e}; pick free ports") from e

    def close(self) -> None:
        """Stop serving."""
        for sim in self._outstations():
            sim.stop()

    def masters_connected(self) -> bool:
        """Whether every outstation has its master (its adapter's) connected."""
        return all(sim.master_connected for sim in self._outstations())

    def set_clock(self, t_ns: int) -> None:
        """Move the outstations' clock to ``t_ns`` [ns] (their hold timers run on it)."""
        self.clock_ns = int(t_ns)

    def commands(self, t_ns: int) -> tuple[dict[int, tuple[float, float] | None], dict[int, int | None]]:
        """At simulation time ``t_ns`` [ns]: what changed since the last call, as ``(regulators, banks)`` by index:
        a regulator's set point and band [V on the 120 V base] in force (None: back on its local ones), a bank's
        commanded closed steps (None: back on its local control).
        """
        self.set_clock(t_ns)
        reg_changes: dict[int, tuple[float, float] | None] = {}
        for did, (r, sim) in self.regs.items():
            remote = sim.setpoint_in_force()
            now = None if remote is None else (remote.setpoint_v120, remote.band_v120)
            if now != self._reg_in_force[did]:
                self._reg_in_force[did] = reg_changes[r] = now
        cap_changes: dict[int, int | None] = {}
        for did, (c, bank) in self.caps.items():
            closed = bank.commanded_closed()
            steps = None if closed is None else int(closed)
            if steps != self._cap_in_force[did]:
                self._cap_in_force[did] = cap_changes[c] = steps
        return reg_changes, cap_changes

    def measure(self, t_ns: int, *, v_compared_120: np.ndarray, v_120: np.ndarray, taps: np.ndarray,
                cap_states: np.ndarray, cap_v_v: np.ndarray, cap_control_value: np.ndarray) -> None:
        """Write the step at ``t_ns`` [ns] into the outstations.

        ``v_compared_120``, ``v_120`` : (R,) each regulator's compared and raw secondary voltage [V on the 120 V base]
        (clipped to the frames' 200 V); ``taps`` : (R,) [steps]; ``cap_states`` : (C,) closed steps;
        ``cap_v_v`` : (C,) bus voltage [V, line-to-neutral]; ``cap_control_value`` : (C,) the local control's
        reading (NaN: none). The arrays are finite (the bridge checked the step), NaN control values apart.
        """
        self.set_clock(t_ns)
        for r, sim in self.regs.values():
            sim.set_measurements(v_compared_120=min(float(v_compared_120[r]), _V120_MAX),
                                 v_120=min(float(v_120[r]), _V120_MAX), tap=int(taps[r]), load_current_a=0.0)
        for c, bank in self.caps.values():
            value = float(cap_control_value[c])
            bank.set_measurements(closed=int(cap_states[c]) > 0, v_v=float(cap_v_v[c]),
                                 control_value=None if np.isnan(value) else value)
