"""One valid example of every message type: for tests, schema docs, fuzzing seeds and benchmarks."""

from __future__ import annotations

import msgspec
import numpy as np

from schemas import messages as m

__all__ = ["example", "examples"]

T0_NS = 1_672_549_200_000_000_000  # 2023-01-01T00:00-05:00
_PHASES: tuple[m.Phase, ...] = ("a", "b", "c")


def examples(t_ns: int = T0_NS, seq: int = 1) -> dict[type[msgspec.Struct], msgspec.Struct]:
    """A valid, physically plausible instance of every type in ``MESSAGE_TYPES``."""
    head_phases = [
        m.HeadPhase(phase=ph, v_mag_v=7200.0 + i, v_ang_deg=ang, i_mag_a=120.0, i_ang_deg=ang - 20.0,
                    p_kw=800.0 + 10 * i, q_kvar=200.0 - 5 * i)
        for i, (ph, ang) in enumerate(zip(_PHASES, (0.0, -120.0, 120.0), strict=True))
    ]
    return {
        m.HeadFrame: m.HeadFrame(t_ns=t_ns, seq=seq, source="head", feeder_id="rural", phases=head_phases,
                                 p_kw=2430.0, q_kvar=585.0),
        m.PvFrame: m.PvFrame(
            t_ns=t_ns, seq=seq, source="pv1", plant_id="pv1",
            phases=[m.PvPhase(phase=ph, p_kw=300.0, q_kvar=-20.0, v_mag_v=7250.0) for ph in _PHASES],
            p_kw=900.0, q_kvar=-60.0, s_rated_kva=1000.0, q_available_kvar=435.9, q_setpoint_kvar=-60.0),
        m.RegFrame: m.RegFrame(t_ns=t_ns, seq=seq, source="vr1a", regulator_id="vr1a",
                               phases=[m.RegPhase(phase="a", v_120=122.1)], v_compared_120=121.4, tap=3,
                               setpoint_v120=122.0, band_v120=2.0, mode="local"),
        m.PvCommand: m.PvCommand(t_ns=t_ns, seq=seq, source="agent", cmd_id=f"agent:{seq}:pv1", in_reply_to=seq,
                                 valid_until_t_ns=t_ns + 600_000_000_000, plant_id="pv1", q_kvar=-120.0),
        m.RegCommand: m.RegCommand(t_ns=t_ns, seq=seq, source="agent", cmd_id=f"agent:{seq}:vr1a",
                                   in_reply_to=seq, valid_until_t_ns=t_ns + 600_000_000_000,
                                   regulator_id="vr1a",
                                   action=m.SetpointAction(setpoint_v120=122.5, band_v120=4.0)),
        m.Ack: m.Ack(t_ns=t_ns, seq=seq, source="pv1", cmd_id=f"agent:{seq}:pv1", device_id="pv1",
                     status="clipped", applied_value=-110.0, reason="clipped to headroom 110.0 kvar"),
        m.Decision: m.Decision(
            t_ns=t_ns, seq=seq, source="agent", feeder_id="rural", step_t_ns=t_ns, in_reply_to=seq,
            status="optimal",
            commands=[m.PvCommand(t_ns=t_ns, seq=seq, source="agent", cmd_id=f"agent:{seq}:pv1",
                                  in_reply_to=seq, valid_until_t_ns=t_ns + 600_000_000_000, plant_id="pv1",
                                  q_kvar=-120.0),
                      m.RegCommand(t_ns=t_ns, seq=seq, source="agent", cmd_id=f"agent:{seq}:vr1a",
                                   in_reply_to=seq, valid_until_t_ns=t_ns + 600_000_000_000,
                                   regulator_id="vr1a", action=m.TapAction(tap=4))],
            estimates=[m.NodeEstimate(node="b0001.1", v_pu=1.021, v_predicted_pu=1.018)],
            dv_dq_pu_per_kvar=[[1.2e-5]], dv_dtap_pu=[[0.00625]],
            solver=m.SolverStats(status="solved", iterations=25, objective=0.12),
            timings=m.Timings(estimate_s=1e-5, solve_s=1e-3, total_s=1.2e-3), corrected=True),
        m.AgentStatus: m.AgentStatus(t_ns=t_ns, seq=seq, source="agent", feeder_id="rural", state="ok",
                                     last_frame_t_ns=t_ns, decisions=3, rejected={"out_of_range": 1}),
        m.TruthFrame: m.TruthFrame(t_ns=t_ns, seq=seq, source="bridge", feeder_id="rural",
                                   v_pu=[1.01, 0.99, 1.03], v_min_pu=0.99, v_max_pu=1.03,
                                   node_names=["b0001.1", "b0001.2", "b0001.3"], taps=[3], pv_q_kvar=[0.0],
                                   cap_states=[1]),
        m.TruthPack: m.TruthPack(t_ns=t_ns, seq=seq, source="bridge", feeder_id="rural", n_nodes=3,
                                 v_pu_f32=m.pack_v_pu(np.array([1.01, 0.99, 1.03])), v_min_pu=0.99, v_max_pu=1.03,
                                 node_names=["b0001.1", "b0001.2", "b0001.3"], taps=[3], pv_q_kvar=[0.0],
                                 cap_states=[1]),
        m.MetricsFrame: m.MetricsFrame(t_ns=t_ns, seq=seq, source="bridge", feeder_id="rural", start_t_ns=t_ns,
                                       steps=60, mvvm_pu=0.0, nvv=0, minutes_in_violation=0, ntc=2,
                                       q_cost=1.5, t_cost=0.28, total_cost=2.78, v_min_pu=0.98, v_max_pu=1.03,
                                       taps_changes={"vr1a": 2}, q_mvar_intervals={"pv1": 1.5},
                                       cap_switches=1, cap_cost=1.0, cap_switches_per_bank={"cap1": 1}),
        m.BridgeStatus: m.BridgeStatus(t_ns=t_ns, seq=seq, source="bridge", feeder_id="rural", step=10,
                                       steps_total=1440, clock="lockstep", agent_alive=True),
        m.CapFrame: m.CapFrame(t_ns=t_ns, seq=seq, source="cap1", capacitor_id="cap1", closed_steps=1, steps=1,
                               kvar_rated=600.0, v_v=2450.0, control_type="voltage", control_value=121.3,
                               mode="commanded", cmd_id=f"agent:{seq}:cap1",
                               valid_until_t_ns=t_ns + 600_000_000_000),
        m.CapCommand: m.CapCommand(t_ns=t_ns, seq=seq, source="agent", cmd_id=f"agent:{seq}:cap1", in_reply_to=seq,
                                   valid_until_t_ns=t_ns + 600_000_000_000, capacitor_id="cap1", closed_steps=1),
        m.MeterFrame: m.MeterFrame(t_ns=t_ns, seq=seq, source="ami1", meter_id="ami1", node="b0042.1", v_pu=1.012,
                                   interval_s=900),
        m.OracleRequest: m.OracleRequest(t_ns=t_ns),
        m.OracleReply: m.OracleReply(t_ns=t_ns, seq=seq, source="bridge", feeder_id="rural",
                                     node_names=["b0001.1"], v_pu=[1.01], dv_dq_pu_per_kvar=[[1e-5]],
                                     dv_dtap_pu=[[0.00625]], taps=[3],
                                     dv_dp_pu_per_kw=[[3e-5]]),
        m.StepEnd: m.StepEnd(t_ns=t_ns, seq=seq, source="bridge", feeder_id="rural", head=True, pv=["pv1"],
                             vr=["vr1a"], cap=[]),
        m.LinkStatus: m.LinkStatus(t_ns=t_ns, seq=seq, source="sunspec-pv1", feeder_id="rural", device_id="pv1",
                                   endpoint="tcp/127.0.0.1:1502", state="ok", scans=10, frames=9,
                                   refused={"701.W": 1}, commands=2, last_ok_t_ns=t_ns),
    }


def example(msg_type: type[msgspec.Struct], t_ns: int = T0_NS, seq: int = 1) -> msgspec.Struct:
    """One valid example of ``msg_type`` stamped ``t_ns`` [ns] and ``seq``."""
    return examples(t_ns, seq)[msg_type]
