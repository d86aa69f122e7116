"""The round trip the SunSpec Modbus hop adds to a PV command: command put -> ack received, through the adapter and
a simulated inverter, against the same bus round trip with a responder that acks at once (measured side by side).

A decision sends one command per plant and every plant has its own adapter, so the extra time per decision is
the extra time of one command (the adapters work in parallel). Also reported: the adapter's Modbus part alone (the
704 write and the read back of 701/702/704, ``SunSpecLink.write_var_setpoint``).
"""

from __future__ import annotations

from typing import Any

from benchmarks.hop import FEEDER as F
from benchmarks.hop import Hop, command_fields, hop_bench, stats, timed
from benchmarks.results import SunspecBench

__all__ = ["bench_sunspec"]

D = "pv1"


def _cmd(seq: int) -> Any:
    from schemas import messages as m

    return m.PvCommand(**command_fields(seq, D), plant_id=D, q_kvar=-100.0 - ((seq - 1) % 7))


def bench_sunspec(n: int = 200) -> SunspecBench:
    """Command -> ack round trips [ms] with and without the SunSpec hop, and the Modbus part alone."""
    from adapters.sunspec import SunSpecLink
    from adapters.sunspec_runtime import AdapterConfig, run_adapter
    from schemas import messages as m
    from schemas.bus import free_port
    from simulator_bridge.field.sunspec_sim import SimulatedSunSpecInverter

    hop = Hop(kind="pv", device_id=D, cmd_type=m.PvCommand, make_cmd=_cmd, applied_value=lambda c: c.q_kvar,
              accepted_only=False)
    with hop_bench(hop, n) as (bench, bus_only):
        inv = SimulatedSunSpecInverter(plant_id=D, s_rated_kva=1000.0, v_nominal_v=7200.0, port=free_port())
        inv.set_measurements(p_kw=[200.0] * 3, v_v=[7200.0] * 3)
        with inv:
            config = AdapterConfig(feeder_id=F, device_id=D, modbus=f"tcp/127.0.0.1:{inv.port}", scan_period_s=60.0)
            through_sunspec = bench.through_adapter(run_adapter, config)
            link = SunSpecLink("127.0.0.1", inv.port)
            link.read()
            modbus = timed(n, lambda i: link.write_var_setpoint(-100.0 - (i % 7), 600))
            link.close()
    return SunspecBench(commands=n, bus_only=bus_only, through_sunspec=through_sunspec,
                        modbus_write_read_back=stats(modbus),
                        extra_per_decision_p50_ms=through_sunspec.p50_ms - bus_only.p50_ms,
                        extra_per_decision_p99_ms=through_sunspec.p99_ms - bus_only.p99_ms)
