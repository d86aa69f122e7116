"""The bridge's PV plants behind SunSpec Modbus (``cvvc run --pv-protocol sunspec``): one simulated inverter each.

With ``BridgeConfig.pv_sunspec`` the bridge serves one
:class:`~simulator_bridge.field.sunspec_sim.SimulatedSunSpecInverter`
per plant named there, on the Modbus TCP endpoint given, and a ``cvvc adapter sunspec`` (``--clock head``) per plant
stands between that inverter and the bus, as it would in the field. The bridge then:

* before each step takes each inverter's model 705 ``Ena`` as the plant's local default (volt-var or unity power
  factor: the adapter sets it, ``--set-local-mode``; :meth:`SunSpecFleet.local_modes`), and, on the inverter's clock
  set to the step's time, its 704 set point as the plant's command (:meth:`SunSpecFleet.commands`; None, the
  function disabled or reverted by its timer: the plant's local default). The plant clips it to its headroom at its
  own output, as for a command from the bus. The bridge's own PV watchdog is not used for these plants: the
  inverter reverts itself;
* after each step, writes the plant's simulated output per phase (P, Q, voltage) into the inverter's 701 registers
  (:meth:`SunSpecFleet.measure`), *before* the step's head frame is put, so the adapter that scans at that head
  frame reads this step's values;
* publishes no frame, no ack and no liveliness token for these plants, and takes none of their commands from the
  bus: the adapters do. It still lists them in the step's ``StepEnd`` (the agent waits for their frames);
* waits, bounded, for every adapter's frame of a step before the next step
  (:class:`~simulator_bridge.bus.adapter_frames.AdapterFrames`), so a lagging adapter never reads the next step's
  values and the agent gets the step's PV frames before the next head frame; a PV command counts as handled
  (lockstep) when its adapter's ack arrives.

Measurement noise, drops, latency and clock skew are applied by the bridge to the frames it publishes; for plants
behind SunSpec they are not implemented (the bridge refuses those options with ``pv_sunspec``).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence

import numpy as np

from schemas.devicemap import DeviceMap
from simulator_bridge.errors import BridgeError
from simulator_bridge.field.sunspec_sim import SimulatedSunSpecInverter, SunSpecSimError

__all__ = ["SunSpecFleet", "plant_phases"]

_PHASE_OF_NODE = {"1": "a", "2": "b", "3": "c"}
_ENDPOINT = re.compile(r"^tcp/(?P<host>[A-Za-z0-9_.\-]+):(?P<port>[0-9]{1,5})$")


class SunSpecFleet:
    """The simulated inverters of the plants behind SunSpec, on the simulation's clock.

    Parameters
    ----------
    endpoints : plant id -> ``tcp/HOST:PORT`` the plant's inverter serves on (unit id 1).
    dm : the device map (ratings, nominal voltages). pv_ids : the engine's plant ids, in its order (the index of a
    plant in the step's arrays). pv_phases : per plant, the phases it is connected to (``a``, ``b``, ``c``).
    q_at_night : per plant (in ``pv_ids`` order), whether it gives reactive power at zero active power.
    volt_var : whether the plants' local default is the IEEE 1547 volt-var curve (the bridge's ``pv_local``): each
    inverter's model 705 holds that curve, enabled or not, so its adapter reports the plant's local mode from it.
    """

    def __init__(self, endpoints: Mapping[str, str], dm: DeviceMap, pv_ids: tuple[str, ...],
                 pv_phases: tuple[tuple[str, ...], ...], *, q_at_night: Sequence[bool],
                 volt_var: bool = False) -> None:
        unknown = sorted(set(endpoints) - set(pv_ids))
        if unknown:
            raise BridgeError(f"--pv-sunspec names plants the feeder does not have: {unknown}; its plants: "
                              f"{list(pv_ids)}")
        specs = {p.id: p for p in dm.pv}
        self.clock_ns = 0  # the inverters' clock: the simulation time the bridge is at [ns]
        self.index: dict[str, int] = {}
        self.inverters: dict[str, SimulatedSunSpecInverter] = {}
        for pid, endpoint in endpoints.items():
            port = _loopback_port(pid, endpoint)
            k = pv_ids.index(pid)
            spec = specs[pid]
            v_nominal_v = spec.kv_ll * 1000.0 / (math.sqrt(3.0) if spec.phases == 3 else 1.0)
            try:
                self.inverters[pid] = SimulatedSunSpecInverter(
                    plant_id=pid, s_rated_kva=float(spec.kva), v_nominal_v=v_nominal_v, port=port,
                    phases=pv_phases[k], host="127.0.0.1", clock_ns=self._clock, q_at_night=bool(q_at_night[k]),
                    volt_var=volt_var)
            except SunSpecSimError as e:
                raise BridgeError(f"plant {pid}: {e}") from e
            self.index[pid] = k

    def _clock(self) -> int:
        return self.clock_ns

    @property
    def plant_ids(self) -> tuple[str, ...]:
        """The plants behind SunSpec."""
        return tuple(self.inverters)

    def start(self) -> None:
        """Serve every inverter (BridgeError when one cannot listen; those started are stopped)."""
        try:
            for inv in self.inverters.values():
                inv.start()
        except SunSpecSimError as e:
            self.close()
            raise BridgeError(f"{e}; pick free ports") from e

    def close(self) -> None:
        """Stop serving."""
        for inv in self.inverters.values():
            inv.stop()

    def set_clock(self, t_ns: int) -> None:
        """Move the inverters' clock to ``t_ns`` [ns] (their revert timers run on it)."""
        self.clock_ns = int(t_ns)

    def commands(self, t_ns: int) -> dict[int, float | None]:
        """At simulation time ``t_ns`` [ns]: each plant's command (by its index) from its inverter's 704 set point
        [kvar, + injects], None when the function is off (timer run out, never enabled).
        """
        self.set_clock(t_ns)
        return {self.index[pid]: inv.var_setpoint_kvar() for pid, inv in self.inverters.items()}

    def local_modes(self) -> dict[int, bool]:
        """Each plant's local default (by its index) as its inverter's model 705 holds it: volt-var enabled (True) or
        not (False), as the adapter may have set it (``cvvc adapter sunspec --set-local-mode``).
        """
        return {self.index[pid]: bool(inv.volt_var_enabled()) for pid, inv in self.inverters.items()}

    def measure(self, t_ns: int, p_kw: np.ndarray, q_kvar: np.ndarray, v_v: np.ndarray) -> None:
        """Write the step at ``t_ns`` [ns] into the inverters' 701 registers.

        ``p_kw``, ``q_kvar`` : (K, 3) output per plant and phase [kW], [kvar] (generator convention); ``v_v`` : (K, 3)
        line-to-neutral voltage [V] (``FieldReadings``); the arrays are finite (the bridge checked the step).
        """
        self.set_clock(t_ns)
        for pid, inv in self.inverters.items():
            k = self.index[pid]
            inv.set_measurements(p_kw=p_kw[k].tolist(), v_v=v_v[k].tolist(), q_kvar=q_kvar[k].tolist())

    def foreign_master_writes(self) -> dict[str, int]:
        """Writes each inverter refused because they came from another connection than its adapter's (its one Modbus
        master), by plant; plants without any left out.
        """
        return {pid: inv.foreign_master_writes for pid, inv in self.inverters.items() if inv.foreign_master_writes}


def _loopback_port(plant_id: str, endpoint: str) -> int:
    """The port of ``tcp/127.0.0.1:PORT``; BridgeError for any other form or host (the inverters are local)."""
    match = _ENDPOINT.match(endpoint)
    if match is None:
        raise BridgeError(f"--pv-sunspec {plant_id}={endpoint}: not tcp/HOST:PORT; write PV_ID=tcp/127.0.0.1:PORT")
    if match.group("host") not in ("127.0.0.1", "localhost"):
        raise BridgeError(f"--pv-sunspec {plant_id}={endpoint}: the simulated inverters serve on 127.0.0.1 only")
    port = int(match.group("port"))
    if not 0 < port < 65536:
        raise BridgeError(f"--pv-sunspec {plant_id}={endpoint}: port {port} is not within 1..65535")
    return port


def plant_phases(node_names: tuple[str, ...],
                 pv_node_index: tuple[tuple[int, ...], ...]) -> tuple[tuple[str, ...], ...]:
    """Per plant, its phases (``a``, ``b``, ``c``) from the engine's node names (``bus.1`` is phase a)."""
    out = []
    for nodes in pv_node_index:
        suffixes = {node_names[n].rsplit(".", 1)[-1] for n in nodes}
        phases = tuple(sorted(_PHASE_OF_NODE[s] for s in suffixes if s in _PHASE_OF_NODE))
        out.append(phases or ("a", "b", "c"))
    return tuple(out)
