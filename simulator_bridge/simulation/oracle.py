"""The case-A oracle: every feeder node's true voltage and its perturbation sensitivities at the present state.

It exists only in simulation, only when a run asks for it (``BridgeConfig.oracle``); the bridge rate-limits it
and, in secure mode, the access policy admits only the agent. The voltages are the stepping engine's own
solution. The perturbation power flows run on a *twin*: a second engine of the same device map, compiled when the
oracle is made, put in the stepping engine's state (loads, PV, every tap and bank) before each answer. The
simulation is never disturbed, so its next step solves from exactly the state it left. (Perturbing the stepping
engine and undoing the moves does not restore it on the EPRI feeders: on epri-ckt24 the voltages came back 3.3e-4 pu
away after a +100 kvar move and 6.8e-4 pu after a tap, both solves converged; on epri-ckt5 the node that moved most
sat at 1.0514 pu, just above the loads' ``Vmaxpu`` of 1.05, where their model changes.)

Replies carry only the feeder zone's nodes (the head meter's side): the transmission side of the substation is
no control target. Sensitivities are clipped to ±1 pu per unit moved and NaN (a plant with no headroom) sent as 0.
"""

from __future__ import annotations

import numpy as np

from schemas import messages as m
from simulator_bridge.opendss.engine import FeederEngine

__all__ = ["Oracle"]


class Oracle:
    """Answers oracle requests from the present state of ``engine`` (the bridge's stepping engine)."""

    def __init__(self, engine: FeederEngine) -> None:
        self.engine = engine
        self.twin = FeederEngine(engine.device_map, tolerance=engine.tolerance)
        self._zone = np.flatnonzero(engine.node_in_feeder)
        self._names = [engine.node_names[i] for i in self._zone]

    def reply(self, *, t_ns: int, seq: int, feeder_id: str, include_sensitivities: bool) -> m.OracleReply:
        """The reply for the engine's last solved state (call with the step's own loads set, not the next's)."""
        e, zone = self.engine, self._zone
        v = e.node_voltages_pu()[zone]
        dq: list[list[float]] = []
        dtap: list[list[float]] = []
        dp: list[list[float]] = []
        if include_sensitivities:
            self.twin.set_state(e.state())
            s = self.twin.perturbation_sensitivities(restore=False)  # the twin is put in state at every answer
            dq, dtap, dp = (np.clip(np.nan_to_num(a[zone], nan=0.0), -1.0, 1.0).tolist()
                            for a in (s.dv_dq, s.dv_dtap, s.dv_dp))
        return m.OracleReply(t_ns=max(t_ns, 0), seq=seq, source="bridge", feeder_id=feeder_id,
                             node_names=self._names, v_pu=np.clip(v, 0.0, 3.0).tolist(), dv_dq_pu_per_kvar=dq,
                             dv_dtap_pu=dtap, taps=[int(t) for t in e.taps()], dv_dp_pu_per_kw=dp)

    def close(self) -> None:
        """Release the twin engine."""
        self.twin.close()
