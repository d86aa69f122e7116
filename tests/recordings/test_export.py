"""``cvvc recordings export-json``: the compact truth (today's Protobuf, an earlier version's MessagePack)
re-encoded as JSON, everything else copied as it is."""

from __future__ import annotations

import json
from pathlib import Path

import msgspec
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from recutil import EXAMPLE_KEYS, encode, head_frame, write_recording

from cvvc.cli import main as cvvc_main
from recordings.errors import RecordingError
from recordings.export import export_json
from schemas import messages as m
from schemas.examples import T0_NS
from schemas.jsonschema import schema_bytes, schema_name

TRUTH = EXAMPLE_KEYS[m.TruthPack]
HEAD = EXAMPLE_KEYS[m.HeadFrame]


def _truth(i: int) -> m.TruthPack:
    v = 1.0 + 0.01 * np.sin(np.arange(200) + i)
    return m.TruthPack(t_ns=T0_NS + i * 60_000_000_000, seq=i + 1, source="bridge", feeder_id="rural", n_nodes=200,
                       v_pu_f32=m.pack_v_pu(v), v_min_pu=float(v.min()), v_max_pu=float(v.max()),
                       node_names=[f"b{k}.1" for k in range(200)] if i == 0 else None, taps=[i % 3],
                       pv_q_kvar=[-10.0 * i], cap_states=[i % 2])


def _read(path: Path) -> dict[str, list[tuple[str, str, str, int, bytes]]]:
    out: dict[str, list[tuple[str, str, str, int, bytes]]] = {}
    with path.open("rb") as f:
        for schema, channel, msg in make_reader(f).iter_messages(log_time_order=True):
            out.setdefault(channel.topic, []).append(
                (channel.message_encoding, schema.name if schema else "", schema.encoding if schema else "",
                 msg.log_time, bytes(msg.data)))
    return out


def test_the_truth_becomes_json_truth_frames_and_the_rest_is_unchanged(tmp_path: Path) -> None:
    truth, heads = [_truth(i) for i in range(5)], [head_frame(i) for i in range(5)]
    src = write_recording(tmp_path / "in.mcap", [x for i in range(5) for x in ((HEAD, heads[i]), (TRUTH, truth[i]))])
    res = export_json(src, tmp_path / "out.mcap")
    assert (res.messages, res.reencoded, res.skipped) == (10, 5, 0)
    before, after = _read(src), _read(tmp_path / "out.mcap")
    assert {e[:3] for e in before[TRUTH]} == {("protobuf", "cvvc.Truth", "protobuf")}
    assert after[HEAD] == before[HEAD] == [("json", schema_name(m.HeadFrame), "jsonschema", h.t_ns, encode(h))
                                           for h in heads]
    for (enc, name, schema_enc, log_time, data), pack in zip(after[TRUTH], truth, strict=True):
        assert (enc, name, schema_enc, log_time) == ("json", schema_name(m.TruthFrame), "jsonschema", pack.t_ns)
        frame = msgspec.json.decode(data, type=m.TruthFrame)  # valid against the TruthFrame type, bounds included
        assert frame.v_pu == m.unpack_v_pu(pack.v_pu_f32, 200).tolist()
        assert (frame.node_names, frame.taps, frame.pv_q_kvar) == (pack.node_names, pack.taps, pack.pv_q_kvar)
    with (tmp_path / "out.mcap").open("rb") as f:
        schemas = {s.name: s.data for s in make_reader(f).get_summary().schemas.values()}
    assert schemas[schema_name(m.TruthFrame)] == schema_bytes(m.TruthFrame)
    assert json.loads(schemas[schema_name(m.TruthFrame)])["type"] == "object"  # what Foxglove needs
    with (tmp_path / "out.mcap").open("rb") as f:
        assert {r.name for r in make_reader(f).iter_metadata()} == {"cvvc.recording"}


def _messagepack_recording(path: Path, data: list[bytes]) -> Path:
    """A truth channel as the recorder of an earlier version wrote it (MessagePack, the TruthPack JSON Schema)."""
    with path.open("wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema(schema_name(m.TruthPack), "jsonschema", schema_bytes(m.TruthPack))
        cid = w.register_channel(TRUTH, "msgpack", sid)
        for i, raw in enumerate(data):
            w.add_message(cid, log_time=T0_NS + i, data=raw, publish_time=T0_NS + i)
        w.finish()
    return path


def test_an_earlier_versions_messagepack_truth_becomes_json_too(tmp_path: Path) -> None:
    truth = [_truth(i) for i in range(3)]
    src = _messagepack_recording(tmp_path / "old.mcap", [msgspec.msgpack.encode(t) for t in truth])
    res = export_json(src, tmp_path / "out.mcap")
    assert (res.messages, res.reencoded, res.skipped) == (3, 3, 0)
    for (enc, name, _, _, data), pack in zip(_read(tmp_path / "out.mcap")[TRUTH], truth, strict=True):
        assert (enc, name) == ("json", schema_name(m.TruthFrame))
        assert msgspec.json.decode(data, type=m.TruthFrame).v_pu == m.unpack_v_pu(pack.v_pu_f32, 200).tolist()


def test_an_undecodable_truth_message_is_left_out_and_counted(tmp_path: Path) -> None:
    # written by hand: the recorder would have quarantined it
    src = _messagepack_recording(tmp_path / "bad.mcap", [msgspec.msgpack.encode(_truth(0)), b"\xc1"])
    res = export_json(src, tmp_path / "out.mcap")
    assert (res.messages, res.reencoded, res.skipped, res.skipped_topics) == (1, 1, 1, {TRUTH: 1})
    assert cvvc_main(["recordings", "export-json", str(src), str(tmp_path / "cli.mcap")]) == 1  # said, not hidden


def test_the_command_line_and_its_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = write_recording(tmp_path / "in.mcap", [(TRUTH, _truth(0))])
    assert cvvc_main(["recordings", "export-json", "--json", str(src), str(tmp_path / "out.mcap")]) == 0
    assert json.loads(capsys.readouterr().out)["reencoded"] == 1
    with pytest.raises(RecordingError, match="another file"):
        export_json(src, src)
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(RecordingError, match="recover"):
        export_json(junk, tmp_path / "x.mcap")
    assert not (tmp_path / "x.mcap").exists() and not (tmp_path / "x.mcap.exporting").exists()
