"""The round trip the DNP3 hop adds to a regulator command: command put -> ack received, through ``cvvc adapter
dnp3``'s loop and a simulated regulator control, against the same bus round trip with a responder that acks at
once (measured side by side). Also reported: the DNP3 part alone (select-before-operate of the hold time, the band
and the set point, then the read back: ``Dnp3Device``'s operate of one set point).
"""

from __future__ import annotations

import time
from typing import Any

from benchmarks.hop import FEEDER as F
from benchmarks.hop import VALID_S, Hop, command_fields, hop_bench, stats, timed
from benchmarks.results import Dnp3Bench

__all__ = ["bench_dnp3"]

D = "reg1"


def _cmd(seq: int) -> Any:
    from schemas import messages as m

    return m.RegCommand(**command_fields(seq, D), regulator_id=D,
                        action=m.SetpointAction(setpoint_v120=118.0 + (seq % 7), band_v120=2.0))


def bench_dnp3(n: int = 200) -> Dnp3Bench:
    """Command -> ack round trips [ms] with and without the DNP3 hop, and the DNP3 part alone."""
    from adapters.dnp3 import Dnp3Master
    from adapters.dnp3_device import Dnp3Device, Dnp3DeviceSettings
    from adapters.dnp3_runtime import Dnp3AdapterConfig, run_dnp3_adapter
    from schemas import messages as m
    from schemas.bus import free_port
    from simulator_bridge.field.dnp3_sim import SimulatedRegulatorControl

    hop = Hop(kind="vr", device_id=D, cmd_type=m.RegCommand, make_cmd=_cmd,
              applied_value=lambda c: c.action.setpoint_v120, accepted_only=True)
    with hop_bench(hop, n) as (bench, bus_only):
        sim = SimulatedRegulatorControl(regulator_id=D, tap_max=16, default_setpoint_v120=120.0,
                                        default_band_v120=2.0, port=free_port(), clock_ns=time.time_ns)
        with sim:
            sim.set_measurements(v_compared_120=121.0, v_120=121.0, tap=0, load_current_a=100.0)
            config = Dnp3AdapterConfig(feeder_id=F, device_id=D, kind="vr", dnp3=sim.endpoint, scan_period_s=60.0)
            through_dnp3 = bench.through_adapter(run_dnp3_adapter, config)
            with Dnp3Master(sim.endpoint) as master:
                if not master.wait_open(20.0):
                    raise RuntimeError(f"no DNP3 channel to {sim.endpoint}")
                dev = Dnp3Device(Dnp3DeviceSettings(feeder_id=F, device_id=D, kind="vr"), master)

                def operate(i: int) -> None:
                    now = time.time_ns()
                    dev.write_setpoint(m.SetpointAction(setpoint_v120=118.0 + (i % 7), band_v120=2.0),
                                       now + VALID_S * 1_000_000_000, now)

                dnp3_part = timed(n, operate)
    return Dnp3Bench(commands=n, bus_only=bus_only, through_dnp3=through_dnp3,
                     dnp3_operates_read_back=stats(dnp3_part),
                     extra_per_decision_p50_ms=through_dnp3.p50_ms - bus_only.p50_ms,
                     extra_per_decision_p99_ms=through_dnp3.p99_ms - bus_only.p99_ms)
