"""``cvvc run --pv-protocol sunspec`` against the plain run: real processes, real Zenoh, real Modbus TCP, real OpenDSS.

One simulated hour of case D on IEEE 13 (three plants, PV producing), lockstep, twice: every plant's frames from the
bridge (``bus``), and every plant behind a simulated SunSpec inverter and its own ``cvvc adapter sunspec``
(``sunspec``). The two runs are started together (the machine has two cores; each waits on its own processes).

Tolerance, and why: through SunSpec the agent sees its PV inputs as the inverter's registers hold them, rounded to
the scale factors' steps (701 ``W``/``Var`` per phase on 100 W / 100 var for these 0.8-1.2 MVA plants, ``V`` on
1 V of 2.4 kV, about 4e-4 pu), and its set points reach the plant on 704 ``VarSet``'s 1 var step. Its decisions
are continuous in those inputs, so each PV set point may move by a small fraction of a kvar (0.09 kvar at most when
this test was written): allowed 1 kvar per command (0.1 % of the smallest rating here) and 1e-3 of the reactive
power cost. Everything discrete must be the same: the number of decisions, NVV, NTC and the tap cost.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.closed_loop import run_side_by_side
from tests.recorded import messages_by_topic

PLANTS = ("pv675", "pv680", "pv633")
STEP_KW = 0.1  # 701 W_SF = 2 for these plants (1.5 x rating within an int16): 100 W per phase
Q_TOL_KVAR = 1.0
COST_REL = 1e-3


@pytest.fixture(scope="module")
def both_runs(tmp_path_factory, ieee13_model) -> dict[str, tuple[Path, dict]]:
    return run_side_by_side(tmp_path_factory.mktemp("pvloop"), ieee13_model,
                            {p: ["--pv-protocol", p] for p in ("bus", "sunspec")}, days=1 / 24,
                            start="2023-07-10T11:00")


def test_the_same_decisions_and_metrics_within_the_scale_factors_rounding(both_runs):
    (_, bus), (_, ss) = both_runs["bus"], both_runs["sunspec"]
    assert (bus["pv_protocol"], ss["pv_protocol"]) == ("bus", "sunspec")
    assert ss["decisions"] == bus["decisions"] == 12  # every 5 simulated minutes
    assert ss["lockstep_misses"] == bus["lockstep_misses"] == 0 and ss["sunspec_frame_misses"] == 0
    a, b = bus["metrics"], ss["metrics"]
    assert b["nvv"] == a["nvv"] and b["ntc"] == a["ntc"] and b["t_cost"] == a["t_cost"]
    assert b["minutes_in_violation"] == a["minutes_in_violation"]
    assert b["q_cost"] == pytest.approx(a["q_cost"], rel=COST_REL)
    assert b["total_cost"] == pytest.approx(a["total_cost"], rel=COST_REL)
    assert a["q_cost"] > 0  # the agent did use the plants
    rec_a, rec_b = messages_by_topic(bus["recording"]), messages_by_topic(ss["recording"])
    q_a = {(d["step_t_ns"], c["plant_id"]): c["q_kvar"] for d in rec_a["cvvc/ieee13/agent/decision"]
           for c in d["commands"] if "q_kvar" in c}
    q_b = {(d["step_t_ns"], c["plant_id"]): c["q_kvar"] for d in rec_b["cvvc/ieee13/agent/decision"]
           for c in d["commands"] if "q_kvar" in c}
    assert q_a.keys() == q_b.keys() and len(q_a) == 36
    assert max(abs(q_a[k] - q_b[k]) for k in q_a) <= Q_TOL_KVAR


def test_the_sunspec_run_counts_no_foreign_write_and_is_not_degraded(both_runs):
    """The adapters' own summaries (``--summary-out``) are summed into the run's integrity: nobody else wrote."""
    (out, ss) = both_runs["sunspec"]
    g = ss["integrity"]
    assert g["foreign_writes"] == {} and g["foreign_master_writes"] == {} and g["degraded"] == ""
    for pid in PLANTS:
        link = json.loads((out / f"adapter.{pid}-summary.json").read_text())
        assert link["device_id"] == pid and link["foreign_writes"] == 0 and link["commands"] > 0


def test_the_plants_frames_and_acks_come_from_the_adapters(both_runs):
    _, ss = both_runs["sunspec"]
    rec = messages_by_topic(ss["recording"])
    commands = {c["cmd_id"]: c for d in rec["cvvc/ieee13/agent/decision"] for c in d["commands"] if "q_kvar" in c}
    truth = rec["cvvc/ieee13/sim/truth"]
    truth_q = {t["t_ns"]: t["pv_q_kvar"] for t in truth}
    for k, plant in enumerate(PLANTS):
        frames = rec[f"cvvc/ieee13/meas/pv/{plant}"]
        assert len(frames) == ss["steps"] == 60  # one per step: the adapter's, none from the bridge
        # the 701 registers' values: each phase on the 100 W step, the total within the phases' rounding of the truth
        assert all(abs(ph["p_kw"] / STEP_KW - round(ph["p_kw"] / STEP_KW)) < 1e-6 for f in frames
                   for ph in f["phases"])
        assert all(abs(f["q_kvar"] - truth_q[f["t_ns"]][k]) <= 3 * STEP_KW / 2 + 1e-9 for f in frames)
        status = rec[f"cvvc/ieee13/link/pv/{plant}"]
        assert status and all(s["state"] in ("starting", "ok") for s in status) and status[-1]["refused"] == {}
        assert status[-1]["foreign_writes"] == 0  # every scan read back the set point the adapter wrote
        acks = rec[f"cvvc/ieee13/ack/pv/{plant}"]
        answered = [a for a in acks if a["status"] in ("accepted", "clipped", "rejected")]
        assert len(answered) == sum(c["plant_id"] == plant for c in commands.values())  # one each, the adapter's
        for a in answered:
            assert a["status"] == "accepted", a
            # read back from 704: the request on VarSet's 1 var step; and the simulated plant applied it next step
            assert a["applied_value"] == pytest.approx(commands[a["cmd_id"]]["q_kvar"], abs=0.0005 + 1e-9)
            nxt = commands[a["cmd_id"]]["t_ns"] + 60 * 10**9
            if nxt in truth_q:
                assert truth_q[nxt][k] == pytest.approx(a["applied_value"], abs=1e-6)
