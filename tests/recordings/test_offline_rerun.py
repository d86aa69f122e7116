"""Offline re-run: recorded frames fed in log-time order, decisions paired by step and diffed."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import msgspec
import pytest
from recutil import EXAMPLE_KEYS, head_frame, write_recording

from cvvc.cli import main as cvvc_main
from recordings.offline import command_values, diff_decisions, recorded_decisions, run_offline
from schemas import messages as m
from schemas.bus import Received
from schemas.examples import examples

STEPS = 12


def _decision(frame_t_ns: int, seq: int, *, q_kvar: float = -120.0, tap: int = 4,
              status: str = "optimal", total_s: float = 1e-3) -> m.Decision:
    base = examples(t_ns=frame_t_ns, seq=seq)[m.Decision]
    pv, vr = base.commands
    commands = [] if status == "hold" else [msgspec.structs.replace(pv, q_kvar=q_kvar),
                                            msgspec.structs.replace(vr, action=m.TapAction(tap=tap))]
    return msgspec.structs.replace(base, status=status, commands=commands, timings=m.Timings(total_s=total_s))


def _decisions(**changes: dict[str, object]) -> list[m.Decision]:
    out = []
    for i in range(STEPS):
        kw = dict(changes.get(str(i), {}))
        if kw.pop("drop", False):
            continue
        out.append(_decision(head_frame(i).t_ns, i + 1, **kw))  # type: ignore[arg-type]
    return out


def _write(path: Path, decisions: list[m.Decision], frames: bool = True, **meta: str) -> Path:
    items: list[tuple[str, msgspec.Struct]] = []
    for i, d in enumerate(decisions):
        if frames:
            items.append((EXAMPLE_KEYS[m.HeadFrame], head_frame(i, p_kw=2000.0 + i)))
        items.append((EXAMPLE_KEYS[m.Decision], d))
    return write_recording(path, items, flush_every=5, metadata={"model_path": "", **meta})


def test_same_decisions_are_identical_even_with_other_timings(tmp_path: Path) -> None:
    a = recorded_decisions(_write(tmp_path / "a.mcap", _decisions()))
    b = recorded_decisions(_write(tmp_path / "b.mcap", _decisions(**{str(i): {"total_s": 0.5} for i in range(STEPS)})))
    assert len(a) == STEPS and a != b  # timings differ ...
    d = diff_decisions(a, b)
    assert d.all_identical and d.identical == STEPS and d.changed == d.missing == d.extra == 0  # ... and are ignored


def test_changed_missing_and_extra_decisions(tmp_path: Path) -> None:
    recorded = recorded_decisions(_write(tmp_path / "a.mcap", _decisions()))
    rerun_list = _decisions(**{
        "2": {"q_kvar": -115.0},              # 5 kvar less absorption
        "5": {"q_kvar": -118.0, "tap": 6},    # 2 kvar, and 2 tap steps
        "7": {"status": "hold"},              # held: no commands at all
        "9": {"drop": True},                  # not decided by the re-run
    })
    extra = _decision(head_frame(100).t_ns, 101)
    rerun = recorded_decisions(_write(tmp_path / "b.mcap", rerun_list + [extra], frames=False))
    d = diff_decisions(recorded, rerun)
    assert (d.recorded, d.rerun) == (STEPS, STEPS)
    assert d.identical == STEPS - 4 and d.changed == 3 and d.missing == 1 and d.extra == 1
    assert d.status_changed == 1 and d.changed_identity_only == 0 and not d.all_identical
    assert d.changed_steps_ns == [head_frame(i).t_ns for i in (2, 5, 7)]
    assert d.missing_steps_ns == [head_frame(9).t_ns]
    pv, tap = d.largest_change["pv/pv1/q_kvar"], d.largest_change["vr/vr1a/tap"]
    assert (pv.step_t_ns, pv.recorded, pv.rerun, pv.abs_change) == (head_frame(2).t_ns, -120.0, -115.0, 5.0)
    assert (tap.step_t_ns, tap.recorded, tap.rerun, tap.abs_change) == (head_frame(5).t_ns, 4.0, 6.0, 2.0)
    assert d.appeared_or_vanished == {"pv/pv1/q_kvar": 1, "vr/vr1a/tap": 1}


def test_counter_only_differences_are_told_apart() -> None:
    recorded = _decisions()
    shifted = [msgspec.structs.replace(
        d, seq=d.seq + 1000, in_reply_to=d.in_reply_to + 1000,
        commands=[msgspec.structs.replace(c, seq=c.seq + 1000, cmd_id=f"agent:{c.seq + 1000}:x") for c in d.commands])
        for d in recorded]
    d = diff_decisions(recorded, shifted)
    assert d.changed == d.changed_identity_only == STEPS and not d.largest_change


def test_duplicate_recorded_steps_are_counted() -> None:
    recorded = _decisions()
    d = diff_decisions(recorded + recorded[:2], recorded)
    assert d.duplicate_recorded == 2 and d.identical == STEPS and d.recorded == STEPS + 2


def _rule(q_per_kw: float) -> Callable[[Iterable[Received]], Iterator[m.Decision]]:
    """A stand-in for agent.runtime.decide_offline: one decision per head frame, q from the head's p_kw."""

    def decide(frames: Iterable[Received]) -> Iterator[m.Decision]:
        last_t = -1
        for r in frames:
            assert isinstance(r, Received) and r.key == EXAMPLE_KEYS[m.HeadFrame]
            assert isinstance(r.msg, m.HeadFrame) and r.msg.t_ns > last_t  # typed, in log-time order
            last_t = r.msg.t_ns
            yield _decision(r.msg.t_ns, r.msg.seq, q_kvar=round(-r.msg.p_kw * q_per_kw, 3))

    return decide


def test_run_offline_feeds_recorded_frames_and_diffs(tmp_path: Path) -> None:
    recorded = list(_rule(0.05)(Received(EXAMPLE_KEYS[m.HeadFrame], head_frame(i, p_kw=2000.0 + i), 0, b"")
                                for i in range(STEPS)))
    path = _write(tmp_path / "run.mcap", recorded)
    same = run_offline(path, decide=_rule(0.05))
    assert same.frames == STEPS and same.frames_rejected == 0
    assert same.simulated_s == (STEPS - 1) * 60.0 and same.sim_minutes_per_wall_s > 0
    assert same.diff.all_identical
    other = run_offline(path, decide=_rule(0.06))
    assert other.diff.changed == STEPS and other.diff.identical == 0
    worst = other.diff.largest_change["pv/pv1/q_kvar"]
    assert worst.step_t_ns == head_frame(STEPS - 1).t_ns
    assert worst.abs_change == pytest.approx((2000.0 + STEPS - 1) * 0.01)


def test_cli_offline_needs_a_model(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = _write(tmp_path / "run.mcap", _decisions())
    assert cvvc_main(["replay", "--offline", str(path)]) == 2
    assert "names no model in its metadata: pass --model" in capsys.readouterr().err
    assert cvvc_main(["replay", "--offline", "--model", str(tmp_path / "none.json"), str(path)]) == 2
    assert "not found" in capsys.readouterr().err
    no_decisions = write_recording(tmp_path / "frames.mcap", [(EXAMPLE_KEYS[m.HeadFrame], head_frame(0))])
    assert cvvc_main(["replay", "--offline", str(no_decisions)]) == 2
    assert "no decodable agent decisions" in capsys.readouterr().err


def test_cli_offline_refuses_case_a(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from benchmarks.synthetic import synthetic_model
    from regression.model import write_model

    model = tmp_path / "model.json"
    write_model(synthetic_model(seed=3), model)
    path = _write(tmp_path / "run.mcap", _decisions(), model_path=str(model),
                  agent_settings='{"feeder_id": "rural", "full_visibility": true}')
    assert cvvc_main(["replay", "--offline", str(path)]) == 2
    assert "case A (full visibility)" in capsys.readouterr().err
    assert cvvc_main(["replay", "--offline", "--agent-settings", '{"nonsense": 1}', str(path)]) == 2
    assert "do not decode as AgentSettings" in capsys.readouterr().err


def test_bank_commands_are_command_quantities_and_a_release_has_none():
    ex = examples()
    cap = ex[m.CapCommand]
    d = msgspec.structs.replace(ex[m.Decision], commands=[ex[m.PvCommand], msgspec.structs.replace(cap, closed_steps=1),
                                                         msgspec.structs.replace(cap, capacitor_id="cap2",
                                                                                 closed_steps=None)])
    values = command_values(d)
    assert values[f"cap/{cap.capacitor_id}/closed_steps"] == 1.0 and not any(k.startswith("cap/cap2") for k in values)
    assert f"pv/{ex[m.PvCommand].plant_id}/q_kvar" in values
