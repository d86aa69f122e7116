"""End to end: the live agent on a real Zenoh bus, recorded by the Recorder; the offline re-run of that
recording reproduces every decision exactly (``agent.runtime.decide_offline``)."""

from __future__ import annotations

import math
import threading
from pathlib import Path

import msgspec
import zenoh

from agent.runtime import AgentSettings, run_agent
from benchmarks.synthetic import synthetic_model
from cvvc.cli import main as cvvc_main
from recordings.info import recording_info
from recordings.offline import run_offline
from recordings.recorder import Recorder, RecorderConfig
from regression.model import write_model
from schemas import keys
from schemas import messages as m
from schemas.bus import BusConfig, codec_for, open_session, wait_for
from schemas.examples import T0_NS, examples

FEEDER = "rural"
STEPS = 30  # simulated minutes; a decision every 5 minutes
CONTROL_STEPS = STEPS // 5


def _step_frames(model, i: int) -> list[tuple[str, msgspec.Struct]]:
    ex = examples()
    t_ns, seq = T0_NS + i * 60_000_000_000, i + 1
    head_kw = 600.0 + 300.0 * math.sin(i / 5.0)
    phases = [msgspec.structs.replace(p, p_kw=head_kw) for p in ex[m.HeadFrame].phases]
    out: list[tuple[str, msgspec.Struct]] = [(keys.meas_head(FEEDER), msgspec.structs.replace(
        ex[m.HeadFrame], t_ns=t_ns, seq=seq, phases=phases, p_kw=3 * head_kw, q_kvar=sum(p.q_kvar for p in phases)))]
    for pv in model.pv:
        out.append((keys.meas_pv(FEEDER, pv.id), msgspec.structs.replace(
            ex[m.PvFrame], t_ns=t_ns, seq=seq, source=pv.id, plant_id=pv.id, s_rated_kva=pv.kva,
            q_available_kvar=0.4 * pv.kva, p_kw=0.6 * pv.kva, q_kvar=0.0,
            phases=[msgspec.structs.replace(p, p_kw=0.2 * pv.kva, q_kvar=0.0) for p in ex[m.PvFrame].phases])))
    for reg in model.regulators:
        out.append((keys.meas_vr(FEEDER, reg.id), msgspec.structs.replace(
            ex[m.RegFrame], t_ns=t_ns, seq=seq, source=reg.id, regulator_id=reg.id, tap=i % 3)))
    return out


def _decisions_in(path: Path) -> int:
    if not path.exists() or path.stat().st_size < 8:
        return 0
    info = recording_info(path)
    return sum(c.messages for c in info.channels if c.topic == keys.agent_decision(FEEDER))


def test_offline_rerun_of_a_recorded_live_session_is_identical(router_endpoint: str, tmp_path: Path,
                                                                capsys) -> None:
    model = synthetic_model(seed=3)
    model_path = tmp_path / "model.json"
    write_model(model, model_path)
    settings = AgentSettings(feeder_id=FEEDER)
    bus = BusConfig(mode="peer", connect=(router_endpoint,))
    out = tmp_path / "session.mcap"
    stop = threading.Event()
    decisions: list[m.Decision] = []
    statuses: list[bytes] = []
    lock = threading.Lock()

    def on_decision(sample: zenoh.Sample) -> None:
        with lock:
            decisions.append(codec_for(m.Decision).decode(sample.payload.to_bytes()))

    with open_session(bus) as rec_session, open_session(bus) as session:
        config = RecorderConfig(out_path=str(out), keys=(f"cvvc/{FEEDER}/**",), flush_period_s=0.1,
                                model_path=str(model_path), agent_settings_json=msgspec.json.encode(settings).decode())
        with Recorder(rec_session, config):
            dec_sub = session.declare_subscriber(keys.agent_decision(FEEDER), on_decision)
            status_sub = session.declare_subscriber(keys.agent_status(FEEDER),
                                                    lambda s: statuses.append(s.payload.to_bytes()))
            agent = threading.Thread(target=run_agent, args=(model, settings, bus),
                                     kwargs={"stop": stop, "install_signals": False}, daemon=True)
            agent.start()
            try:
                assert wait_for(lambda: len(statuses) > 0, 20.0), "the agent never published its status"
                pubs: dict[str, zenoh.Publisher] = {}
                for i in range(STEPS):  # lockstep: on a control step, wait for its decision
                    for key, frame in _step_frames(model, i):
                        if key not in pubs:
                            pubs[key] = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
                        pubs[key].put(codec_for(type(frame)).encode(frame))
                    if i % 5 == 0:
                        assert wait_for(lambda i=i: len(decisions) == i // 5 + 1, 10.0), f"no decision at step {i}"
            finally:
                stop.set()
                agent.join(15.0)
            dec_sub.undeclare()
            status_sub.undeclare()
            assert wait_for(lambda: _decisions_in(out) == CONTROL_STEPS, 10.0, poll_s=0.05)
    assert not agent.is_alive()
    assert len(decisions) == CONTROL_STEPS and all(d.commands for d in decisions)

    res = run_offline(out)  # model and settings from the recording's metadata
    assert res.model_path == str(model_path)
    assert res.frames == STEPS * (1 + len(model.pv) + len(model.regulators)) and res.frames_rejected == 0
    assert res.diff.recorded == res.diff.identical == CONTROL_STEPS and res.diff.all_identical

    # another model changes decisions, and the diff says so
    other = tmp_path / "other.json"
    write_model(synthetic_model(seed=4), other)
    assert cvvc_main(["replay", "--offline", "--json", "--model", str(other), str(out)]) == 1
    diff = msgspec.json.decode(capsys.readouterr().out)["diff"]
    assert diff["recorded"] == CONTROL_STEPS and diff["identical"] < CONTROL_STEPS
