"""Joining the parts of a restarted recorder (``recordings.join``): every message kept, each gap recorded."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from mcap.reader import make_reader
from recutil import EXAMPLE_KEYS, encode, head_frame, write_recording

from recordings.errors import RecordingError
from recordings.info import recording_info
from recordings.join import GAP_TOPIC, join_parts
from recordings.recorder import McapSink
from schemas import messages as m

HEAD = EXAMPLE_KEYS[m.HeadFrame]


def _cut(path: Path, keep_bytes: int) -> Path:
    """The file as a recorder killed hard leaves it: without its summary and footer."""
    path.write_bytes(path.read_bytes()[:keep_bytes])
    return path


def _first_part(path: Path) -> Path:
    """Ten head frames, then, received last, a forged one stamped 2100-01-01 (quarantined: an extra field)."""
    with open(path, "wb") as f:
        sink = McapSink(f, metadata={"model_path": "m.json"})
        for i in range(10):
            frame = head_frame(i)
            sink.write(encode(frame), HEAD, frame.t_ns + 1_000_000)
            if i in (4, 9):
                sink.flush()
        sink.write(b'{"t_ns": 4102444800000000000, "seq": 1, "x": 1}', HEAD, head_frame(10).t_ns)
        sink.finish()
    return path


def _heads(path: Path) -> list[int]:
    with path.open("rb") as f:
        return [json.loads(msg.data)["seq"] for _, ch, msg in make_reader(f).iter_messages(log_time_order=False)
                if ch.topic == HEAD]


def test_parts_are_joined_with_the_gap_between_them(tmp_path: Path) -> None:
    first = _first_part(tmp_path / "a.mcap")
    _cut(first, recording_info(first).size_bytes - 200)  # the summary is gone, the flushed chunks stay
    second = write_recording(tmp_path / "b.mcap", [(HEAD, head_frame(i)) for i in range(20, 30)])
    out = tmp_path / "joined.mcap"

    result = join_parts([first, second], ["the recorder (pid 1) killed by signal 9"], out)

    info = recording_info(out)
    assert info.complete and info.metadata["cvvc.recording"]["model_path"] == "m.json"
    heads = _heads(out)
    assert heads[-10:] == list(range(21, 31)) and set(heads[:-10]) <= set(range(1, 11)) and heads[:-10]
    assert result.gaps == info.gaps
    [gap] = result.gaps
    assert gap.restart == 1 and "signal 9" in gap.reason
    # the gap is bounded by real messages: the forged time, received last, is copied (quarantined) but ignored
    assert gap.from_t_ns == head_frame(heads[-11] - 1).t_ns and gap.to_t_ns == head_frame(20).t_ns
    assert gap.from_wall_ns < gap.to_wall_ns
    assert [c.messages for c in info.channels if c.topic == GAP_TOPIC] == [1]
    quarantined = sum(c.messages for c in info.channels if c.topic == "cvvc.quarantine")
    assert quarantined == 1  # the forged sample survived the cut: it is what the gap must not be bounded by
    assert result.messages == info.messages == len(heads) + quarantined + 1
    assert not list(tmp_path.glob("*.recovered"))  # the rebuilt copy of the cut part is removed


def test_a_part_whose_recorder_died_before_its_header_is_an_empty_part(tmp_path: Path) -> None:
    first = write_recording(tmp_path / "a.mcap", [(HEAD, head_frame(i)) for i in range(3)])
    dead = tmp_path / "b.mcap"
    dead.write_bytes(b"\x89MCAP0\r\n")
    third = write_recording(tmp_path / "c.mcap", [(HEAD, head_frame(i)) for i in range(5, 8)])

    result = join_parts([first, dead, third], ["died", "died again"], tmp_path / "out.mcap")

    assert _heads(tmp_path / "out.mcap") == [1, 2, 3, 6, 7, 8]
    assert [(g.restart, g.from_t_ns, g.to_t_ns) for g in result.gaps] == [
        (1, head_frame(2).t_ns, -1), (2, -1, head_frame(5).t_ns)]


def test_one_reason_per_gap_is_required(tmp_path: Path) -> None:
    part = write_recording(tmp_path / "a.mcap", [(HEAD, head_frame(0))])
    with pytest.raises(RecordingError, match="2 parts need 1 reasons, got 0"):
        join_parts([part, part], [], tmp_path / "out.mcap")


def test_a_late_message_after_the_restart_does_not_shrink_the_gap(tmp_path: Path) -> None:
    """The new recorder's first message may carry an older time (a status lagging behind the frames): the gap
    runs from the latest time recorded before to the earliest *later* one after, so nothing recorded is inside.
    """
    first = write_recording(tmp_path / "a.mcap", [(HEAD, head_frame(i)) for i in range(5)])
    second = write_recording(tmp_path / "b.mcap", [(HEAD, head_frame(2)), (HEAD, head_frame(9))])
    [gap] = join_parts([first, second], ["died"], tmp_path / "out.mcap").gaps
    assert (gap.from_t_ns, gap.to_t_ns) == (head_frame(4).t_ns, head_frame(9).t_ns)
    assert gap.to_wall_ns == head_frame(2).t_ns + 1_000_000  # received first after the restart
