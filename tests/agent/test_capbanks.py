"""Capacitor banks as controlled devices: golden cases against the exact MILP, and the controller's bank decisions.

The banks enter the CVVC problem as integer devices after the regulators (closed steps within 0..steps, a cost
per switching, their per-step voltage effect): the solver relaxes them in OSQP and rounds them with the taps;
``solve_milp_reference`` solves the same problem exactly with them integer.
"""

import dataclasses

import msgspec
import numpy as np
import pytest

from agent.aligner import AlignedFrames
from agent.controller import CvvcController, MeasurementSnapshot
from agent.cvvc_qp import CvvcInputs
from agent.runtime import AgentSettings, DecisionMaker
from agent.solve import V_TOL_PU, solve_cvvc, solve_milp_reference
from benchmarks.synthetic import synthetic_model
from regression.capbanks import bank_voltage_pu, head_q_at_training_banks
from regression.estimator import estimate_voltages_pu
from regression.model import CapacitorInfo, ModelArrays, ModelError, features, read_model, write_model
from schemas import messages as m
from schemas.settings import AgentOptions

# Bank A: 600 kvar, +0.006 / +0.004 pu per step at nodes 0 / 1; bank B: 300 kvar, +0.003 / +0.002 pu.
DV_BANK = np.array([[0.006, 0.003], [0.004, 0.002]])


def _feeder(v0, *, closed=(0, 0), cost_per_kvar=1e-4, q_limit=1000.0, reg: bool = False) -> CvvcInputs:
    """2 nodes, 1 plant (1000 kVA, dV/dQ 2e-5 / 1e-5 pu/kvar), two binary banks at 1.0 per switching.

    With ``reg`` a regulator (0.625 %/step, 1.0 per tap) comes first, as the controller orders them.
    """
    taps, lo, hi, mx, cost, dv = list(closed), [0, 0], [1, 1], [1, 1], [1.0, 1.0], DV_BANK
    if reg:
        taps, lo, hi, mx, cost = [0, *taps], [-16, *lo], [16, *hi], [4, *mx], [1.0, *cost]
        dv = np.hstack([np.full((2, 1), 0.00625), DV_BANK])
    return CvvcInputs(
        v0_pu=np.array(v0, float),
        dv_dq_pu_per_kvar=np.array([[2e-5], [1e-5]]),
        dv_dtap_pu=dv,
        q0_kvar=np.array([0.0]),
        q_min_kvar=np.array([-q_limit]),
        q_max_kvar=np.array([q_limit]),
        q_rating_kvar=np.array([1000.0]),
        taps=np.array(taps),
        tap_min=np.array(lo),
        tap_max=np.array(hi),
        max_taps_per_interval=np.array(mx),
        cost_per_tap=np.array(cost),
        cost_per_kvar=np.array([cost_per_kvar]),
        v_min_pu=0.975,
        v_max_pu=1.04,
    )


# Hand-computed optima (banks' closed steps after, Q [kvar], cost):
# not_worth: node 0 0.005 pu low; 250 kvar cost 0.025 < one switching (1.0): no bank switched.
# worth: Q at 1e-2/kvar: 250 kvar = 2.5; bank B + 100 kvar = 2.0; bank A alone covers 0.006 >= 0.005 for 1.0.
# both: Q within +-100 kvar, 0.010 pu low: A + B give 0.009, the last 0.001 pu = 50 kvar (0.005): 2.005;
#   A + 100 kvar gives only 0.008.
# open: both closed, node 0 0.0061 pu high, Q at 1e-2: opening A (-0.006) + 5 kvar absorbed = 1.05 beats
#   opening both (2.0), B + 155 kvar (2.55) and Q alone (305 kvar, 3.05).
GOLDEN = {
    "not_worth": (dict(v0=[0.970, 0.99]), [0, 0], 250.0, 0.025),
    "worth": (dict(v0=[0.970, 0.99], cost_per_kvar=1e-2), [1, 0], 0.0, 1.0),
    "both": (dict(v0=[0.965, 0.99], q_limit=100.0), [1, 1], 50.0, 2.005),
    "open": (dict(v0=[1.0461, 1.03], closed=(1, 1), cost_per_kvar=1e-2), [0, 1], -5.0, 1.05),
}


@pytest.mark.parametrize("name", GOLDEN)
def test_golden_bank_decisions_match_the_exact_milp(name):
    kwargs, banks, q_kvar, cost = GOLDEN[name]
    inputs = _feeder(**kwargs)
    milp = solve_milp_reference(inputs)
    assert milp.status == "optimal"
    assert milp.taps_new.tolist() == banks
    assert milp.cost == pytest.approx(cost, abs=1e-6)
    sol = solve_cvvc(inputs)
    assert sol.status == "optimal", sol.reason
    assert sol.taps_new.tolist() == banks  # the rounding takes the MILP's switching decisions
    np.testing.assert_allclose(sol.q_new_kvar, [q_kvar], atol=0.05)
    assert sol.cost == pytest.approx(cost, abs=1e-3)
    assert sol.max_violation_pu <= V_TOL_PU


def test_random_bank_problems_round_to_the_milp_decisions():
    """Random 2-node problems with a regulator and two banks: same switchings as the MILP, same cost."""
    rng = np.random.default_rng(16)
    agree = compared = 0
    for _ in range(40):
        v0 = rng.uniform(0.955, 1.06, 2)
        inputs = _feeder(v0, closed=tuple(rng.integers(0, 2, 2)), cost_per_kvar=float(rng.choice([1e-4, 3e-3, 1e-2])),
                         q_limit=float(rng.uniform(50, 1000)), reg=True)
        milp, sol = solve_milp_reference(inputs), solve_cvvc(inputs)
        if milp.status != "optimal":
            continue
        assert sol.status == "optimal", sol.reason
        compared += 1
        assert sol.cost >= milp.cost * (1 - 1e-4) - 1e-6  # nothing feasible beats the exact optimum
        assert sol.cost <= milp.cost * 1.02 + 1e-3
        agree += sol.taps_new[1:].tolist() == milp.taps_new[1:].tolist()
    assert compared >= 25
    assert agree >= compared - 1  # ties (equal costs) may at most once pick another bank


# ------------------------------------------------------------------------------------------- controller
BASE = synthetic_model(0)
K, R = len(BASE.pv), len(BASE.regulators)
N = len(BASE.critical_nodes)
BANKS = [CapacitorInfo(id="cap1", steps=1, kvar_rated=600.0, phases=[1, 2, 3], closed0=0, cost_per_switch=1.0),
         CapacitorInfo(id="cap2", steps=2, kvar_rated=300.0, phases=[3], closed0=1, cost_per_switch=2.0,
                       max_switches_per_interval=2)]
# regulators frozen (0 taps per interval), as on a feeder without any: banks and plants are the levers
MODEL = msgspec.structs.replace(
    BASE, capacitors=BANKS, dv_dcap_pu=np.tile([0.012, 0.002], (N, 1)).tolist(),
    regulators=[msgspec.structs.replace(r, max_taps_per_interval=0) for r in BASE.regulators])
ARRAYS = ModelArrays.of(MODEL)


def _snapshot(t_ns: int = 0, *, head_p_kw: float = 800.0, cap_steps=(0, 1), **changes) -> MeasurementSnapshot:
    taps = np.zeros(R, int)
    head_q = np.full(3, 200.0)
    pv_p, pv_q = np.full(K, 900.0), np.zeros(K)
    v_hat = estimate_voltages_pu(ARRAYS, features(np.full(3, head_p_kw), head_q, pv_p, pv_q), taps)
    raw = v_hat[ARRAYS.reg_secondary_node] / ARRAYS.reg_pu_per_v120
    snap = MeasurementSnapshot(
        t_ns=t_ns, head_p_kw=np.full(3, head_p_kw), head_q_kvar=head_q, pv_p_kw=pv_p, pv_q_kvar=pv_q,
        pv_kva_available=np.full(K, 900.0), pv_q_setpoint_kvar=np.full(K, np.nan), reg_v120=raw,
        reg_v120_compared=raw, reg_tap=taps, head_valid=True, pv_valid=np.ones(K, bool), reg_valid=np.ones(R, bool),
        cap_steps=np.array(cap_steps), cap_valid=np.ones(len(BANKS), bool))
    return dataclasses.replace(snap, **changes)


def _shift_to(v_min_target: float, snap: MeasurementSnapshot) -> MeasurementSnapshot:
    """The same snapshot with the head's P raised until the estimate's lowest node sits at ``v_min_target``."""
    names = MODEL.feature_names
    dv_dp_head = ARRAYS.alpha[:, [names.index(f"head_p_kw_{p}") for p in "abc"]].sum(axis=1)
    v_now = estimate_voltages_pu(ARRAYS, features(snap.head_p_kw, snap.head_q_kvar, snap.pv_p_kw, snap.pv_q_kvar),
                                 snap.reg_tap) + bank_voltage_pu(ARRAYS, snap.cap_steps)
    i = int(np.argmin(v_now))
    dp = (v_min_target - v_now[i]) / dv_dp_head[i]
    return dataclasses.replace(snap, head_p_kw=snap.head_p_kw + dp)


def test_banks_stay_on_local_control_unless_the_agent_is_told_to_control_them():
    """Off by default (``AgentSettings.control_banks``): the same low-voltage snapshot switches nothing and sends no
    bank command; the measured bank state still enters the estimate."""
    lo, _ = MODEL.optimization_limits_pu
    snap = _shift_to(lo - 0.008, _snapshot())
    frozen = dataclasses.replace(snap, pv_kva_available=snap.pv_p_kw.copy())  # no Q headroom
    d = CvvcController(MODEL, AgentOptions(bandwidth_v120=4.0), mode="taps", correction=False).decide(frozen)
    assert not d.cap_command.any()
    assert d.cap_steps is None or d.cap_steps.tolist() == list(frozen.cap_steps)
    assert AgentSettings(feeder_id=MODEL.feeder_name).control_banks is False


def test_a_low_voltage_decision_closes_a_bank_and_sends_its_command():
    ctl = CvvcController(MODEL, AgentOptions(bandwidth_v120=4.0, control_banks=True), mode="taps", correction=False)
    lo, _ = MODEL.optimization_limits_pu
    snap = _shift_to(lo - 0.008, _snapshot())
    frozen = dataclasses.replace(snap, pv_kva_available=snap.pv_p_kw.copy())  # no Q headroom
    d = ctl.decide(frozen)
    assert d.status == "optimal", d.reason
    assert d.cap_steps is not None and d.cap_steps.tolist()[0] == 1  # cap1 closes (+0.012 pu)
    assert d.cap_command.tolist() == [True, True]
    assert d.v_pred_pu.min() >= lo - 1e-5
    maker = DecisionMaker(MODEL, AgentSettings(feeder_id=MODEL.feeder_name, mode="taps", correction=False))
    maker.controller = ctl
    msg = maker.to_message(AlignedFrames(t_ns=0, head=None, pv={}, vr={}, missing=()), d)
    caps = [c for c in msg.commands if isinstance(c, m.CapCommand)]
    assert [(c.capacitor_id, c.closed_steps) for c in caps] == [("cap1", 1), ("cap2", d.cap_steps[1])]
    assert all(c.valid_until_t_ns > c.t_ns and c.source == maker.settings.agent_id for c in caps)
    assert msgspec.json.decode(msgspec.json.encode(msg), type=m.Decision) == msg


def test_without_need_no_bank_switches():
    ctl = CvvcController(MODEL, AgentOptions(bandwidth_v120=4.0, control_banks=True), mode="taps", correction=False)
    lo, _ = MODEL.optimization_limits_pu
    d = ctl.decide(_shift_to(lo + 0.01, _snapshot()))
    assert d.status == "optimal", d.reason
    assert d.cap_steps.tolist() == [0, 1]  # as they are: switching costs and nothing needs it


@pytest.mark.parametrize("why", ["stale", "refused"])
def test_a_stale_or_refused_bank_is_held_without_a_command(why):
    ctl = CvvcController(MODEL, AgentOptions(bandwidth_v120=4.0, control_banks=True), mode="taps", correction=False)
    lo, _ = MODEL.optimization_limits_pu
    snap = _shift_to(lo - 0.008, _snapshot(t_ns=300_000_000_000))
    snap = dataclasses.replace(snap, pv_kva_available=snap.pv_p_kw.copy())
    if why == "stale":
        snap = dataclasses.replace(snap, cap_valid=np.array([False, True]))
    else:
        assert ctl.refuse_bank("cap1", 0) and not ctl.refuse_bank("nope", 0)
    d = ctl.decide(snap)
    assert d.cap_steps is not None and d.cap_steps[0] == 0  # held open
    assert not d.cap_command[0] and d.cap_command[1]
    assert ("cap1" in d.missing) == (why == "stale")
    later = ctl.decide(dataclasses.replace(snap, t_ns=snap.t_ns + 3 * 300_000_000_000,
                                           cap_valid=np.ones(2, bool)))
    assert later.cap_steps[0] == 1 and later.cap_command[0]  # usable again: switched


def test_estimate_accounts_for_banks_switched_since_training():
    head_q = np.array([100.0, 100.0, 100.0])
    adj = head_q_at_training_banks(ARRAYS, head_q, np.array([1, 2]))
    np.testing.assert_allclose(adj, [300.0, 300.0, 450.0])  # cap1 +600 over 3 phases, cap2 +150 on phase c
    np.testing.assert_allclose(bank_voltage_pu(ARRAYS, np.array([1, 2])), np.full(N, 0.014))


def test_model_with_banks_round_trips_and_a_bad_grid_fails_clearly(tmp_path):
    path = tmp_path / "model.json"
    write_model(MODEL, path)
    back = read_model(path)
    assert back.capacitors == BANKS and back.dv_dcap_pu == MODEL.dv_dcap_pu
    old = tmp_path / "old.json"
    write_model(BASE, old)
    assert read_model(old).capacitors == [] and ModelArrays.of(read_model(old)).dv_dcap_pu.shape == (N, 0)
    bad = tmp_path / "bad.json"
    write_model(msgspec.structs.replace(MODEL, dv_dcap_pu=MODEL.dv_dcap_pu[:-1]), bad)
    with pytest.raises(ModelError, match="dv_dcap_pu has shape"):
        read_model(bad)


# ------------------------------------------------------------------------------------------- aligner
PERIOD_NS = 300_000_000_000
T0 = 1_672_549_200_000_000_000  # a control step


def _frames(t_ns: int, seq: int, *, bank: str = "cap1", closed: int = 1, steps: int = 1):
    from schemas import keys
    from schemas.examples import examples

    ex = examples()
    return [
        (keys.meas_head("rural"), msgspec.structs.replace(ex[m.HeadFrame], t_ns=t_ns, seq=seq)),
        (keys.meas_pv("rural", "pv1"), msgspec.structs.replace(ex[m.PvFrame], t_ns=t_ns, seq=seq, plant_id="pv1",
                                                               source="pv1")),
        (keys.meas_cap("rural", bank), m.CapFrame(t_ns=t_ns, seq=seq, source=bank, capacitor_id=bank,
                                                  closed_steps=closed, steps=steps, kvar_rated=600.0, v_v=7200.0)),
    ]


def test_aligner_waits_for_the_banks_and_rejects_unknown_or_impossible_ones():
    from agent.aligner import FrameAligner

    al = FrameAligner(feeder_id="rural", pv_ids=("pv1",), regulator_ids=(), control_period_ns=PERIOD_NS,
                      capacitor_ids=("cap1",))
    head, plant, bank = _frames(T0, 1)
    assert al.add(*head) == [] and al.add(*plant) == []  # not complete without the bank
    out = al.add(*bank)
    assert len(out) == 1 and out[0].complete and out[0].cap["cap1"].closed_steps == 1
    assert al.add(*_frames(T0 + PERIOD_NS, 2, bank="capX")[2]) == []
    assert al.rejected["unknown_device"] == 1
    assert al.add(*_frames(T0 + PERIOD_NS, 2, closed=2, steps=1)[2]) == []
    assert al.rejected["implausible"] == 1
    for key, frame in _frames(T0 + PERIOD_NS, 2)[:2]:
        al.add(key, frame)
    late = al.close_pending()
    assert len(late) == 1 and late[0].missing == ("cap1",)  # a stale bank is named missing
    without = FrameAligner(feeder_id="rural", pv_ids=("pv1",), regulator_ids=(), control_period_ns=PERIOD_NS)
    assert without.add(*bank) == [] and without.ignored == 1  # a model without banks ignores their frames


def _predicted(dq: list[float]) -> object:
    """MODEL with cap2 (partially closed) on a current control: ON 300 A, OFF 200 A, ``dq`` A per kvar of each
    plant's Q (injecting Q lowers the current the control monitors)."""
    banks = [BANKS[0], msgspec.structs.replace(BANKS[1], control_kind="current", control_on=300.0, control_off=200.0,
                                               control_dq=dq, control_dtap=[0.0] * R)]
    return msgspec.structs.replace(MODEL, capacitors=banks)


def test_a_bank_on_local_control_is_not_pushed_across_its_setting():
    """A low-voltage snapshot: the plants inject Q. Plant 0's Q lowers the current cap2's local control monitors
    (0.2 A/kvar, 215 A now, OFF at 200 A): unpredicted, the decision injects enough to open the bank; predicted, it
    keeps the current at or above 210 A (OFF plus 10 % of the ON-OFF gap) and takes the rest from the other plants."""
    dq = [-0.2] + [0.0] * (K - 1)
    model = _predicted(dq)
    lo, _ = model.optimization_limits_pu
    snap = dataclasses.replace(_shift_to(lo - 0.004, _snapshot()), cap_control_value=np.array([np.nan, 215.0]),
                               pv_kva_available=np.full(K, 1500.0))  # Q headroom: 1200 kvar each

    def after(predict: bool) -> tuple[float, object]:
        d = CvvcController(model, AgentOptions(bandwidth_v120=4.0, predict_banks=predict), mode="taps",
                           correction=False).decide(snap)
        assert d.status == "optimal", d.reason
        return 215.0 + float(np.dot(dq, d.pv_q_kvar - snap.pv_q_kvar)), d

    free, _ = after(False)
    kept, d = after(True)
    assert free < 200.0  # the bank's own control would open it
    assert kept >= 210.0 - 1e-6 and d.v_pred_pu.min() >= lo - 1e-5 and d.v_pred_pu.size == N
    # a bank already past its setting switches whatever the decision: no row binds for it
    past = dataclasses.replace(snap, cap_control_value=np.array([np.nan, 195.0]))
    d_past = CvvcController(model, AgentOptions(bandwidth_v120=4.0, predict_banks=True), mode="taps",
                            correction=False).decide(past)
    np.testing.assert_allclose(d_past.pv_q_kvar, CvvcController(model, AgentOptions(bandwidth_v120=4.0), mode="taps",
                                                                correction=False).decide(past).pv_q_kvar, atol=1e-6)


def test_bank_rows_keep_the_quantity_where_the_control_would_not_switch():
    from agent.bank_rows import BANK_MARGIN_SHARE, ROW_SPAN_PU, local_bank_rows, predicted_banks

    volt = CapacitorInfo(id="v", steps=1, kvar_rated=600.0, phases=[1], closed0=0, control_kind="voltage",
                         control_on=118.0, control_off=126.0, control_dq=[0.01], control_dtap=[0.8])
    kvar = CapacitorInfo(id="k", steps=2, kvar_rated=600.0, phases=[1], closed0=1, control_kind="kvar",
                         control_on=150.0, control_off=-225.0, control_dq=[-1.0], control_dtap=[0.0])
    plain = CapacitorInfo(id="p", steps=1, kvar_rated=300.0, phases=[1], closed0=0)
    banks = [volt, plain, kvar]
    assert predicted_banks(banks).tolist() == [0, 2]
    rows = local_bank_rows(banks, np.array([121.0, np.nan, 0.0]), np.array([0, 0, 1]), np.zeros(3, bool), 1, 1)
    gain_v, gain_k = ROW_SPAN_PU / 8.0, ROW_SPAN_PU / 375.0
    # the open voltage bank: kept above ON + margin (118.8 V), no upper limit (it cannot open)
    assert rows.lo[0] == pytest.approx(1.0 + gain_v * (118.0 + BANK_MARGIN_SHARE * 8.0 - 122.0))
    assert rows.hi[0] > 5.0 and rows.u0[0] == pytest.approx(1.0 + gain_v * (121.0 - 122.0))
    # the partially closed kvar bank: between OFF + margin and ON - margin
    assert rows.lo[1] == pytest.approx(1.0 + gain_k * (-225.0 + 37.5 + 37.5))
    assert rows.hi[1] == pytest.approx(1.0 + gain_k * (150.0 - 37.5 + 37.5))
    np.testing.assert_allclose(rows.du_dq[:, 0], [0.01 * gain_v, -1.0 * gain_k])
    np.testing.assert_allclose(rows.du_dtap[:, :2], [[0.8 * gain_v, 0.0], [0.0, 0.0]])  # banks' own columns: 0
    assert rows.binding.tolist() == [True, True]
    # within the margin already: the limit half-way to the setting; past a setting, held or unknown: no limit
    near = local_bank_rows(banks, np.array([118.2, np.nan, 160.0]), np.array([0, 0, 1]), np.zeros(3, bool), 1, 1)
    assert near.lo[0] == pytest.approx(1.0 + gain_v * (118.1 - 122.0)) and near.binding.tolist() == [True, False]
    held = local_bank_rows(banks, np.array([121.0, np.nan, np.nan]), np.array([0, 0, 1]),
                           np.array([True, False, False]), 1, 1)
    assert held.binding.tolist() == [False, False] and held.lo.max() < -5.0 and held.hi.min() > 5.0


def test_a_volt_override_gets_a_row_on_the_voltage_it_tests():
    """A kvar bank whose control closes it below Vmin: an open bank's tested voltage is kept OVERRIDE_MARGIN above
    Vmin even when it is already below (the override would close it, and its kvar rule open it, at every decision);
    a closed one's below Vmax; held or unread, free."""
    from agent.bank_rows import OVERRIDE_MARGIN, ROW_SPAN_PU, bank_row_names, local_bank_rows

    bank = CapacitorInfo(id="k", steps=1, kvar_rated=300.0, phases=[1], closed0=0, control_kind="kvar",
                         control_on=150.0, control_off=-225.0, control_dq=[-0.4], control_dtap=[-20.0],
                         override_vmin_v=7110.0, override_vmax_v=7740.0, override_per_v=1.01, override_dq=[0.05],
                         override_dtap=[40.0])
    gain, mid = ROW_SPAN_PU / 630.0, 7425.0
    rows = local_bank_rows([bank], np.array([-400.0]), np.array([0]), np.zeros(1, bool), 1, 1, v_v=np.array([7000.0]))
    assert rows.u0.shape == (2,) and rows.binding.tolist() == [True, True]
    assert rows.u0[1] == pytest.approx(1.0 + gain * (7070.0 - mid))  # 7000 V read, 7070 V tested: under Vmin
    assert rows.lo[1] == pytest.approx(1.0 + gain * (7110.0 * (1 + OVERRIDE_MARGIN) - mid)) and rows.hi[1] > 5.0
    np.testing.assert_allclose(rows.du_dq[1], [0.05 * gain])
    np.testing.assert_allclose(rows.du_dtap[1], [40.0 * gain, 0.0])
    closed = local_bank_rows([bank], np.array([-400.0]), np.array([1]), np.zeros(1, bool), 1, 1,
                             v_v=np.array([7300.0]))
    assert closed.hi[1] == pytest.approx(1.0 + gain * (7740.0 * (1 - OVERRIDE_MARGIN) - mid)) and closed.lo[1] < -5.0
    for held, v in ((np.ones(1, bool), 7000.0), (np.zeros(1, bool), np.nan)):
        free = local_bank_rows([bank], np.array([-400.0]), np.array([0]), held, 1, 1, v_v=np.array([v]))
        assert not free.binding[1] and free.lo[1] < -5.0 and free.hi[1] > 5.0
    plain = local_bank_rows([msgspec.structs.replace(bank, override_vmin_v=0.0)], np.array([-400.0]), np.array([0]),
                            np.zeros(1, bool), 1, 1, v_v=np.array([7000.0]))
    assert plain.u0.shape == (1,)  # no override: no second row
    # the rows named in their order (what `cvvc report decision` prints)
    assert bank_row_names([bank]) == ["bank k", "bank k override"]
    assert bank_row_names([msgspec.structs.replace(bank, override_vmin_v=0.0)]) == ["bank k"]
