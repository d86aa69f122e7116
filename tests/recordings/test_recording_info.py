"""info and recover on finished, truncated, corrupt, empty and foreign files: clear answers, no tracebacks."""

from __future__ import annotations

from pathlib import Path

import msgspec
import pytest
from mcap.reader import make_reader
from recutil import EXAMPLE_KEYS, head_frame, write_recording

from cvvc.cli import main as cvvc_main
from recordings.errors import NotMcapError, RecordingError, UnreadableError
from recordings.info import recording_info, recover
from schemas import messages as m
from schemas.examples import examples

N_CHUNKS = 8
PER_CHUNK = 25


def _items(n: int) -> list[tuple[str, msgspec.Struct]]:
    """Head frames and decisions alternating (two topics), in time order."""
    out: list[tuple[str, msgspec.Struct]] = []
    for i in range(n):
        if i % 2 == 0:
            out.append((EXAMPLE_KEYS[m.HeadFrame], head_frame(i)))
        else:
            d = examples(t_ns=head_frame(i).t_ns, seq=i)[m.Decision]
            out.append((EXAMPLE_KEYS[m.Decision], d))
    return out


@pytest.fixture
def recording(tmp_path: Path) -> Path:
    return write_recording(tmp_path / "rec.mcap", _items(N_CHUNKS * PER_CHUNK), flush_every=PER_CHUNK,
                           metadata={"model_path": "m.json", "feeder_fingerprint": "abc"})


def _messages(path: Path) -> list[tuple[str, int, bytes]]:
    with open(path, "rb") as f:
        return [(c.topic, msg.log_time, msg.data) for _, c, msg in make_reader(f).iter_messages(log_time_order=False)]


def _chunk_spans(path: Path) -> list[tuple[int, int]]:
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return [(c.chunk_start_offset, c.chunk_start_offset + c.chunk_length) for c in summary.chunk_indexes]


def test_info_of_a_finished_file(recording: Path) -> None:
    info = recording_info(recording)
    assert info.source == "summary" and info.complete and not info.problems
    assert info.messages == N_CHUNKS * PER_CHUNK and info.chunks == N_CHUNKS
    assert {c.topic: c.messages for c in info.channels} == {EXAMPLE_KEYS[m.HeadFrame]: 100,
                                                            EXAMPLE_KEYS[m.Decision]: 100}
    assert {c.schema_name for c in info.channels} == {"cvvc.HeadFrame", "cvvc.Decision"}
    assert info.start_ns == head_frame(0).t_ns and info.end_ns == head_frame(199).t_ns
    assert info.duration_s == pytest.approx(199 * 60.0)
    assert info.metadata["cvvc.recording"] == {"model_path": "m.json", "feeder_fingerprint": "abc"}


@pytest.mark.parametrize("cut_fraction", [0.1, 0.35, 0.5, 0.77, 0.999])
def test_truncated_file_info_and_recover(recording: Path, tmp_path: Path, cut_fraction: float) -> None:
    data = recording.read_bytes()
    cut = int(len(data) * cut_fraction)
    broken = tmp_path / "cut.mcap"
    broken.write_bytes(data[:cut])
    whole_chunks = sum(1 for _, end in _chunk_spans(recording) if end <= cut)

    info = recording_info(broken)
    assert not info.complete and info.source == "scan"
    assert any("recover" in p for p in info.problems)
    assert info.messages == whole_chunks * PER_CHUNK
    assert info.readable_bytes <= cut

    res = recover(broken, tmp_path / "fixed.mcap")
    assert res.messages == whole_chunks * PER_CHUNK
    assert res.lost_tail_bytes == cut - res.readable_bytes > 0
    assert not res.input_was_complete
    original = _messages(recording)
    assert _messages(tmp_path / "fixed.mcap") == original[: res.messages]  # a prefix, bytes and times intact
    fixed = recording_info(tmp_path / "fixed.mcap")
    assert fixed.complete and fixed.source == "summary"
    assert fixed.metadata["cvvc.recording"]["model_path"] == "m.json"


def test_recover_of_a_complete_file_keeps_everything(recording: Path, tmp_path: Path) -> None:
    res = recover(recording, tmp_path / "copy.mcap")
    assert res.input_was_complete and res.lost_tail_bytes == 0 and not res.problems
    assert _messages(tmp_path / "copy.mcap") == _messages(recording)


def test_corrupt_chunk_is_skipped_and_reported(recording: Path, tmp_path: Path) -> None:
    spans = _chunk_spans(recording)
    data = bytearray(recording.read_bytes())
    start, end = spans[2]
    for i in range(end - 12, end - 4):  # inside the third chunk's compressed data
        data[i] ^= 0xFF
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    res = recover(bad, tmp_path / "fixed.mcap")
    assert len(res.corrupt_chunks) == 1 and res.corrupt_chunks[0].offset == start
    assert res.messages == (N_CHUNKS - 1) * PER_CHUNK
    original = _messages(recording)
    assert _messages(tmp_path / "fixed.mcap") == original[: 2 * PER_CHUNK] + original[3 * PER_CHUNK:]


def test_corrupt_first_chunk_loses_channel_definitions(recording: Path, tmp_path: Path) -> None:
    start, end = _chunk_spans(recording)[0]
    data = bytearray(recording.read_bytes())
    for i in range(end - 12, end - 4):
        data[i] ^= 0xFF
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    res = recover(bad, tmp_path / "fixed.mcap")
    assert res.orphan_messages == (N_CHUNKS - 1) * PER_CHUNK and res.messages == 0
    assert any("channel definition" in p for p in res.problems)


def test_garbage_after_a_cut_stops_the_scan_there(recording: Path, tmp_path: Path) -> None:
    data = recording.read_bytes()
    _, end3 = _chunk_spans(recording)[3]
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(data[:end3] + b"\x42" * 100 + data[end3:])
    info = recording_info(junk)
    assert not info.complete
    assert any("unknown record opcode 0x42" in p for p in info.problems)
    res = recover(junk, tmp_path / "fixed.mcap")
    assert res.messages == 4 * PER_CHUNK


def test_header_only_file(tmp_path: Path, recording: Path) -> None:
    stub = tmp_path / "stub.mcap"
    stub.write_bytes(recording.read_bytes()[:12])
    info = recording_info(stub)
    assert info.messages == 0 and not info.complete and info.problems
    with pytest.raises(UnreadableError, match="nothing can be recovered"):
        recover(stub, tmp_path / "out.mcap")
    assert not (tmp_path / "out.mcap").exists()


@pytest.mark.parametrize("content, message", [
    (b"", "is empty"),
    (b"\x89MCA", "only 4 bytes"),
    (b"hello, this is a text file\n" * 10, "not an MCAP file"),
    (b"PK\x03\x04" + bytes(200), "not an MCAP file"),
])
def test_not_mcap_files(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "x.mcap"
    path.write_bytes(content)
    with pytest.raises(NotMcapError, match=message):
        recording_info(path)
    with pytest.raises(NotMcapError, match=message):
        recover(path, tmp_path / "out.mcap")


def test_missing_file_and_directory(tmp_path: Path) -> None:
    with pytest.raises(NotMcapError, match="no such file"):
        recording_info(tmp_path / "nope.mcap")
    with pytest.raises(NotMcapError, match="is a directory"):
        recording_info(tmp_path)


def test_recover_refuses_to_overwrite_its_input(recording: Path) -> None:
    with pytest.raises(RecordingError, match="different from IN"):
        recover(recording, recording)


# --------------------------------------------------------------------------------- command line
def test_cli_info_and_recover(recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cvvc_main(["recordings", "info", str(recording)]) == 0
    out = capsys.readouterr().out
    assert "200 messages in 8 chunks" in out and "cvvc.Decision (jsonschema)" in out
    assert cvvc_main(["recordings", "info", "--json", str(recording)]) == 0
    assert msgspec.json.decode(capsys.readouterr().out)["messages"] == 200

    cut = tmp_path / "cut.mcap"
    cut.write_bytes(recording.read_bytes()[: recording.stat().st_size // 2])
    assert cvvc_main(["recordings", "info", str(cut)]) == 1
    assert "problem:" in capsys.readouterr().out
    assert cvvc_main(["recordings", "recover", "--json", str(cut), str(tmp_path / "ok.mcap")]) == 0
    res = msgspec.json.decode(capsys.readouterr().out)
    assert res["messages"] > 0 and res["lost_tail_bytes"] > 0


@pytest.mark.parametrize("argv_tail", [
    ["info", "{text}"], ["info", "{empty}"], ["info", "{missing}"], ["recover", "{text}", "{out}"],
    ["recover", "{empty}", "{out}"], ["recover", "{stub}", "{out}"],
])
def test_cli_errors_are_one_line(tmp_path: Path, recording: Path, capsys: pytest.CaptureFixture[str],
                                 argv_tail: list[str]) -> None:
    paths = {"text": tmp_path / "t.mcap", "empty": tmp_path / "e.mcap", "missing": tmp_path / "m.mcap",
             "stub": tmp_path / "s.mcap", "out": tmp_path / "o.mcap"}
    paths["text"].write_text("not mcap\n")
    paths["empty"].write_bytes(b"")
    paths["stub"].write_bytes(recording.read_bytes()[:10])
    argv = ["recordings"] + [a.format(**{k: str(v) for k, v in paths.items()}) for a in argv_tail]
    assert cvvc_main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"cvvc recordings {argv_tail[0]}: error: ") and err.count("\n") == 1
