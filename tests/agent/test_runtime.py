"""The agent's decision maker: frames in, decision messages out, the same live and offline."""

from __future__ import annotations

import msgspec
import pytest

from agent.runtime import AgentSettings, DecisionMaker, decide_offline
from benchmarks.synthetic import synthetic_model
from schemas import keys
from schemas import messages as m
from schemas.bus import codec_for
from schemas.examples import examples

PERIOD_NS = 300_000_000_000
T0 = 1_672_549_200_000_000_000
EX = examples()


@pytest.fixture(scope="module")
def model():
    return synthetic_model(seed=3)


def _frames(model, t_ns: int, seq: int, *, head_p_kw: float = 900.0, drop: tuple[str, ...] = ()):
    fid = "rural"
    out = []
    if "head" not in drop:
        phases = [msgspec.structs.replace(p, p_kw=head_p_kw) for p in EX[m.HeadFrame].phases]
        out.append((keys.meas_head(fid), msgspec.structs.replace(
            EX[m.HeadFrame], t_ns=t_ns, seq=seq, phases=phases, p_kw=3 * head_p_kw,
            q_kvar=sum(p.q_kvar for p in phases))))
    for pv in model.pv:
        if pv.id in drop:
            continue
        out.append((keys.meas_pv(fid, pv.id), msgspec.structs.replace(
            EX[m.PvFrame], t_ns=t_ns, seq=seq, source=pv.id, plant_id=pv.id, s_rated_kva=pv.kva,
            q_available_kvar=0.4 * pv.kva, p_kw=0.6 * pv.kva, q_kvar=0.0,
            phases=[msgspec.structs.replace(p, p_kw=0.2 * pv.kva, q_kvar=0.0) for p in EX[m.PvFrame].phases])))
    for reg in model.regulators:
        if reg.id in drop:
            continue
        out.append((keys.meas_vr(fid, reg.id), msgspec.structs.replace(
            EX[m.RegFrame], t_ns=t_ns, seq=seq, source=reg.id, regulator_id=reg.id, tap=0)))
    return out


def test_one_decision_per_control_step_with_expiring_commands(model):
    maker = DecisionMaker(model, AgentSettings(feeder_id="rural"))
    msgs = []
    for i, t in enumerate(range(T0, T0 + 11 * 60_000_000_000, 60_000_000_000)):
        for key, frame in _frames(model, t, i + 1):
            msgs += [maker.to_message(a, d) for a, d in maker.on_frame(key, frame)]
    assert [d.step_t_ns for d in msgs] == [T0, T0 + PERIOD_NS, T0 + 2 * PERIOD_NS]
    for d in msgs:
        assert d.status in ("optimal", "soft")
        assert len(d.commands) == len(model.pv) + len(model.regulators)
        assert all(c.valid_until_t_ns == d.step_t_ns + 2 * PERIOD_NS for c in d.commands)
        assert all(c.cmd_id.startswith(f"agent:{d.step_t_ns}:") for c in d.commands)
        assert len(d.estimates) == len(model.critical_nodes)
        codec_for(m.Decision).decode(codec_for(m.Decision).encode(d))  # valid on the wire


def test_missing_head_holds_with_no_commands(model):
    maker = DecisionMaker(model, AgentSettings(feeder_id="rural"))
    for key, frame in _frames(model, T0, 1, drop=("head",)):
        assert maker.on_frame(key, frame) == []
    ((aligned, d),) = maker.close_pending()
    msg = maker.to_message(aligned, d)
    assert msg.status == "hold" and msg.commands == [] and "head" in msg.missing
    assert "feeder-head" in msg.reason


def test_offline_decisions_are_bit_identical_across_runs(model):
    frames = []
    for i, t in enumerate(range(T0, T0 + 30 * 60_000_000_000, 60_000_000_000)):
        frames += _frames(model, t, i + 1, head_p_kw=600.0 + 40.0 * i)
    settings = AgentSettings(feeder_id="rural")
    a = [msgspec.structs.replace(d, timings=m.Timings()) for d in decide_offline(model, settings, frames)]
    b = [msgspec.structs.replace(d, timings=m.Timings()) for d in decide_offline(model, settings, frames)]
    assert len(a) == 6
    assert [msgspec.json.encode(x) for x in a] == [msgspec.json.encode(x) for x in b]


def test_full_visibility_cannot_run_offline(model):
    with pytest.raises(ValueError, match="oracle"):
        list(decide_offline(model, AgentSettings(feeder_id="rural", full_visibility=True), []))
