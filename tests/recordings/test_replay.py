"""Replay onto a real Zenoh bus: spacing scaled by the speed, log-time order, bytes unchanged, bounds."""

from __future__ import annotations

import threading
from pathlib import Path

import msgspec
import pytest
import zenoh
from recutil import EXAMPLE_KEYS, encode, head_frame, write_recording

from cvvc.cli import main as cvvc_main
from recordings.errors import ReplayError, UnreadableError
from recordings.replay import ReplayConfig, parse_time_ns, replay
from schemas import messages as m
from schemas.bus import BusConfig, open_session
from schemas.examples import T0_NS, examples


class _Collector:
    """Subscriber callback: every sample in arrival order; ``done`` is set once ``expected`` have arrived, and
    ``stop`` (when given) once ``stop_after`` have."""

    def __init__(self, expected: int, stop: threading.Event | None = None, stop_after: int = 0) -> None:
        self.lock = threading.Lock()
        self.items: list[tuple[str, bytes]] = []
        self.expected = expected
        self.done = threading.Event()
        self.stop, self.stop_after = stop, stop_after

    def __call__(self, sample: zenoh.Sample) -> None:
        item = (str(sample.key_expr), sample.payload.to_bytes())
        with self.lock:
            self.items.append(item)
            n = len(self.items)
        if n >= self.expected:
            self.done.set()
        if self.stop is not None and n >= self.stop_after:
            self.stop.set()


def _with_decisions(frames: list[m.HeadFrame]) -> list[tuple[str, msgspec.Struct]]:
    items: list[tuple[str, msgspec.Struct]] = []
    for f in frames:
        items.append((EXAMPLE_KEYS[m.HeadFrame], f))
        items.append((EXAMPLE_KEYS[m.Decision], examples(t_ns=f.t_ns, seq=f.seq)[m.Decision]))
    return items


def test_replay_paced_by_speed(router_endpoint: str, tmp_path: Path) -> None:
    """Every frame once, in order, bytes unchanged; the schedule (59 s of frames at 20x) is a floor on the replay's
    duration, and a stop after a few frames ends a replay at 1x long before its end (counts, not timings)."""
    frames = [head_frame(i, step_s=1.0) for i in range(60)]  # 60 frames 1 s apart
    path = write_recording(tmp_path / "day.mcap", _with_decisions(frames), flush_every=7)
    bus = BusConfig(mode="peer", connect=(router_endpoint,))
    expected = [(EXAMPLE_KEYS[m.HeadFrame], encode(f)) for f in frames]
    got = _Collector(expected=60)
    with open_session(bus) as sub_session, open_session(bus) as pub_session:
        sub = sub_session.declare_subscriber("cvvc/**", got)
        res = replay(pub_session, ReplayConfig(path=str(path), speed=20.0, bus=bus, wait_subscriber_s=10.0))
        assert got.done.wait(10.0), got.items  # everything is put before replay returns; bounded wait
        sub.undeclare()
    assert res.messages == 60 and res.by_topic == {EXAMPLE_KEYS[m.HeadFrame]: 60}  # decisions not replayed
    assert got.items == expected
    assert res.wall_s >= 59 / 20  # the last frame is due 59 / 20 s after the first: never earlier
    # at 1x the same recording takes 59 s: a stop once 5 frames have arrived ends it with few published
    stop = threading.Event()
    early = _Collector(expected=1, stop=stop, stop_after=5)
    with open_session(bus) as sub_session, open_session(bus) as pub_session:
        sub = sub_session.declare_subscriber("cvvc/**", early)
        res = replay(pub_session, ReplayConfig(path=str(path), speed=1.0, bus=bus, wait_subscriber_s=10.0), stop)
        sub.undeclare()
    assert stop.is_set() and 5 <= res.messages < 60, res.messages
    assert early.items == expected[: len(early.items)]  # a prefix, in order


def test_fast_replay_in_log_time_order_within_bounds(router_endpoint: str, tmp_path: Path) -> None:
    frames = [head_frame(i) for i in range(200)]
    pv = examples()[m.PvFrame]
    file_order: list[tuple[str, msgspec.Struct]] = []
    for i, f in enumerate(frames):
        file_order.append((EXAMPLE_KEYS[m.HeadFrame], f))
        # PV frames are written one step late, so file order differs from log-time order
        if i > 0:
            file_order.append((EXAMPLE_KEYS[m.PvFrame],
                               msgspec.structs.replace(pv, t_ns=frames[i - 1].t_ns, seq=i)))
    path = write_recording(tmp_path / "day.mcap", file_order, flush_every=33)
    bus = BusConfig(mode="peer", connect=(router_endpoint,))
    got = _Collector(expected=200)
    start_ns, end_ns = frames[50].t_ns, frames[150].t_ns
    with open_session(bus) as sub_session, open_session(bus) as pub_session:
        sub = sub_session.declare_subscriber("cvvc/**", got)
        res = replay(pub_session, ReplayConfig(path=str(path), speed=None, start_ns=start_ns, end_ns=end_ns,
                                               bus=bus))
        assert got.done.wait(10.0), len(got.items)  # everything is put before replay returns; bounded wait
        sub.undeclare()
    assert res.messages == 200  # 100 head + 100 PV frames in [start, end)
    assert res.first_log_time_ns == start_ns and res.last_log_time_ns == frames[149].t_ns
    t_of = {EXAMPLE_KEYS[m.HeadFrame]: m.HeadFrame, EXAMPLE_KEYS[m.PvFrame]: m.PvFrame}
    log_times = [msgspec.json.decode(b, type=t_of[k]).t_ns for k, b in got.items]
    assert len(log_times) == 200 and log_times == sorted(log_times)
    assert min(log_times) == start_ns and max(log_times) < end_ns


def test_no_subscriber_is_an_error(router_endpoint: str, tmp_path: Path) -> None:
    path = write_recording(tmp_path / "day.mcap", [(EXAMPLE_KEYS[m.HeadFrame], head_frame(0))])
    bus = BusConfig(mode="peer", connect=(router_endpoint,))
    with open_session(bus) as session, pytest.raises(ReplayError, match="no subscriber"):
        replay(session, ReplayConfig(path=str(path), bus=bus, wait_subscriber_s=0.3))


def test_bad_inputs(router_endpoint: str, tmp_path: Path) -> None:
    path = write_recording(tmp_path / "day.mcap", [(EXAMPLE_KEYS[m.Decision], examples()[m.Decision])])
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:-40])
    bus = BusConfig(mode="peer", connect=(router_endpoint,))
    with open_session(bus) as session:
        with pytest.raises(ReplayError, match="no topic matching"):
            replay(session, ReplayConfig(path=str(path), bus=bus))
        with pytest.raises(UnreadableError, match="recover"):
            replay(session, ReplayConfig(path=str(cut), bus=bus))
        with pytest.raises(ReplayError, match="speed must be > 0"):
            replay(session, ReplayConfig(path=str(path), bus=bus, speed=0.0))
        with pytest.raises(ReplayError, match="after --end"):
            replay(session, ReplayConfig(path=str(path), bus=bus, keys=("cvvc/**",), start_ns=10, end_ns=5))


def test_cli_replay_without_subscriber(router_endpoint: str, tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    path = write_recording(tmp_path / "day.mcap", [(EXAMPLE_KEYS[m.HeadFrame], head_frame(0))])
    assert cvvc_main(["replay", str(path), "--fast", "--wait-s", "0.2", "--connect", router_endpoint,
                      "--insecure"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("cvvc replay: error: no subscriber") and err.count("\n") == 1


@pytest.mark.parametrize("text, expected", [
    ("2023-01-01T05:00:00+00:00", T0_NS),
    ("2023-01-01T00:00:00-05:00", T0_NS),
    ("2023-01-01T05:00:00", T0_NS),  # no zone: UTC
    ("2023-01-01T05:00:00.000001Z", T0_NS + 1000),
    (str(T0_NS), T0_NS),
])
def test_parse_time_ns(text: str, expected: int) -> None:
    assert parse_time_ns(text) == expected


def test_parse_time_ns_rejects_other_text() -> None:
    with pytest.raises(ReplayError, match="ISO 8601"):
        parse_time_ns("yesterday")


def _old_truth_recording(path: Path, packs: list[m.TruthPack]) -> Path:
    """A truth channel as the recorder of an earlier version wrote it: MessagePack, the TruthPack JSON Schema."""
    from mcap.writer import Writer

    from schemas.jsonschema import schema_bytes, schema_name

    with path.open("wb") as f:
        w = Writer(f)
        w.start()
        cid = w.register_channel(EXAMPLE_KEYS[m.TruthPack], "msgpack",
                                 w.register_schema(schema_name(m.TruthPack), "jsonschema", schema_bytes(m.TruthPack)))
        for p in packs:
            w.add_message(cid, log_time=p.t_ns, data=msgspec.msgpack.encode(p), publish_time=p.t_ns)
        w.finish()
    return path


def test_the_truth_of_any_recording_is_replayed_on_todays_wire(router_endpoint: str, tmp_path: Path) -> None:
    """Today's Protobuf truth goes out as recorded; an earlier version's MessagePack truth goes out as Protobuf,
    so a subscriber of today decodes both."""
    from schemas.bus import codec_for

    packs = [examples(t_ns=T0_NS + i * 60_000_000_000, seq=i + 1)[m.TruthPack] for i in range(4)]
    new = write_recording(tmp_path / "new.mcap", [(EXAMPLE_KEYS[m.TruthPack], p) for p in packs])
    old = _old_truth_recording(tmp_path / "old.mcap", packs)
    bus = BusConfig(mode="peer", connect=(router_endpoint,))
    for path in (new, old):
        got = _Collector(expected=len(packs))
        with open_session(bus) as sub_session, open_session(bus) as pub_session:
            sub = sub_session.declare_subscriber("cvvc/**", got)
            res = replay(pub_session, ReplayConfig(path=str(path), keys=("cvvc/*/sim/truth",), speed=None, bus=bus))
            assert got.done.wait(10.0), got.items
            sub.undeclare()
        assert res.messages == len(packs)
        assert [codec_for(m.TruthPack).decode(raw) for _, raw in got.items] == packs, path.name


def test_the_model_a_recording_names_is_found_from_any_directory(tmp_path: Path, monkeypatch) -> None:
    """Recordings of earlier versions named ``runs/x/model.json`` relative to where the run started: the file of that
    name beside the recording is used; an absolute path that exists is kept; nothing named stays nothing."""
    from recordings.offline import recorded_model

    run = tmp_path / "runs" / "x"
    run.mkdir(parents=True)
    (run / "model.json").write_text("{}")
    rec = run / "session.mcap"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert recorded_model(rec, "runs/x/model.json") == str(run / "model.json")
    assert recorded_model(Path("..") / "runs" / "x" / "session.mcap", "runs/x/model.json") == str(run / "model.json")
    assert recorded_model(rec, str(run / "model.json")) == str(run / "model.json")
    assert recorded_model(rec, "") == ""
    assert recorded_model(rec, "nowhere/other.json") == "nowhere/other.json"  # not there: named as recorded
