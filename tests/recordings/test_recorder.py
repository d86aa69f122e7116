"""The recorder on a real Zenoh bus into real MCAP files: every field intact, crashes lose only the last period."""

from __future__ import annotations

import base64
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import msgspec
import pytest
import zenoh
from mcap.reader import make_reader
from recutil import EXAMPLE_KEYS, encode, head_frame

from recordings.info import recording_info, recover
from recordings.recorder import (
    METADATA_NAME,
    QUARANTINE_TOPIC,
    STATS_METADATA_NAME,
    Quarantined,
    Recorder,
    RecorderConfig,
)
from schemas.bus import BusConfig, codec_for, open_session, wait_for
from schemas.examples import examples
from schemas.jsonschema import schema_bytes, schema_name
from schemas.messages import MESSAGE_TYPES, TruthPack, wire_of
from schemas.truth_proto import truth_descriptor_set

REPO = Path(__file__).resolve().parents[2]


def _publisher(session: zenoh.Session, key: str) -> zenoh.Publisher:
    return session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)


def test_round_trip_every_message_type(router_endpoint: str, tmp_path: Path) -> None:
    out = tmp_path / "all.mcap"
    bus = BusConfig(mode="peer", connect=(router_endpoint,))
    sent: dict[str, list[bytes]] = {}
    with open_session(bus) as rec_session, open_session(bus) as pub_session:
        config = RecorderConfig(out_path=str(out), bus=bus, keys=("cvvc/**", "test/**"),
                                feeder_fingerprint="fp-123", model_path="models/rural.json")
        wall0 = time.time_ns()
        with Recorder(rec_session, config) as recorder:
            pubs = {key: _publisher(pub_session, key) for key in EXAMPLE_KEYS.values()}
            assert wait_for(lambda: all(p.matching_status.matching for p in pubs.values()), 10.0)
            for i in range(3):
                for msg_type, msg in examples(t_ns=1_700_000_000_000_000_000 + i * 60_000_000_000, seq=10 + i).items():
                    key = EXAMPLE_KEYS[msg_type]
                    raw = encode(msg)
                    pubs[key].put(raw)
                    sent.setdefault(key, []).append(raw)
            pubs["test/oracle_request"].put(b'{"no_time": 1}')  # JSON without t_ns: the latest time, counted
            sent["test/oracle_request"].append(b'{"no_time": 1}')
            n = sum(len(v) for v in sent.values())
            assert wait_for(lambda: recorder.stats().messages == n, 10.0), recorder.stats()
        wall1 = time.time_ns()
    stats = recorder.stats()
    assert stats.dropped_queue_full == 0 and stats.callback_errors == 0
    assert stats.log_time_fallbacks == 1
    # the three OracleRequests, the JSON without t_ns and the three TruthFrames (the truth's JSON form, not a bus
    # message since TruthPack), on keys outside the cvvc layout
    assert stats.quarantined == 7

    with open(out, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        got: dict[str, list[bytes]] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            key, data = channel.topic, message.data
            if key == QUARANTINE_TOPIC:  # a key outside the cvvc layout: kept, with its bytes, apart
                q = msgspec.json.decode(data, type=Quarantined)
                key, data = q.key, base64.b64decode(q.payload_b64)
                assert q.reason == "not a key of the cvvc layout"
            got.setdefault(key, []).append(data)
            msg_type = next(t for t, k in EXAMPLE_KEYS.items() if k == key)
            assert wall0 <= message.publish_time <= wall1
            if data == b'{"no_time": 1}':  # no time of its own: logged at the session's latest instant
                assert message.log_time == 1_700_000_000_000_000_000 + 2 * 60_000_000_000
                continue
            decoded = codec_for(msg_type).decode(data)
            assert message.log_time == decoded.t_ns
            assert message.sequence == getattr(decoded, "seq", 0)
            assert channel.message_encoding == ("json" if channel.topic == QUARANTINE_TOPIC else wire_of(msg_type))
            if key in ("test/oracle_request", "test/truth_frame"):
                assert channel.topic == QUARANTINE_TOPIC and schema is not None and schema.name == "cvvc.Quarantined"
            elif msg_type is TruthPack:  # the truth: Protobuf with its FileDescriptorSet, which Foxglove decodes
                assert schema is not None and (schema.name, schema.encoding) == ("cvvc.Truth", "protobuf")
                assert schema.data == truth_descriptor_set()
            else:
                assert schema is not None
                assert schema.encoding == "jsonschema"
                assert schema.name == schema_name(msg_type)
                assert schema.data == schema_bytes(msg_type)
                assert json.loads(schema.data)["type"] == "object"
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert got == sent  # bytes unchanged, order per key kept
    # every field intact: decode what was recorded and compare with the originals
    for i in range(3):
        for msg_type, msg in examples(t_ns=1_700_000_000_000_000_000 + i * 60_000_000_000, seq=10 + i).items():
            assert codec_for(msg_type).decode(got[EXAMPLE_KEYS[msg_type]][i]) == msg
    assert set(EXAMPLE_KEYS) == set(MESSAGE_TYPES)
    meta = metadata[METADATA_NAME]
    assert meta["feeder_fingerprint"] == "fp-123"
    assert meta["model_path"] == str(Path("models/rural.json").resolve())  # absolute: readable from anywhere
    assert msgspec.json.decode(meta["bus_config"], type=BusConfig) == bus
    assert meta["project_version"]
    assert metadata[STATS_METADATA_NAME]["messages"] == str(n)


@pytest.mark.parametrize("exc_type", [RuntimeError, KeyboardInterrupt])
def test_file_is_finished_when_the_block_raises(router_endpoint: str, tmp_path: Path,
                                                exc_type: type[BaseException]) -> None:
    out = tmp_path / "raised.mcap"
    bus = BusConfig(mode="peer", connect=(router_endpoint,))
    with open_session(bus) as rec_session, open_session(bus) as pub_session:
        with pytest.raises(exc_type, match="boom"), Recorder(rec_session, RecorderConfig(out_path=str(out))) as rec:
            pub = _publisher(pub_session, "cvvc/rural/meas/head")
            assert wait_for(lambda: pub.matching_status.matching, 10.0)
            for i in range(20):
                pub.put(encode(head_frame(i)))
            assert wait_for(lambda: rec.stats().messages == 20, 10.0)
            raise exc_type("boom")
    info = recording_info(out)
    assert info.source == "summary" and info.complete and info.messages == 20


def _spawn_recorder(out: Path, endpoint: str, flush_period_s: float) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "cvvc", "record", "--out", str(out), "--connect", endpoint, "--insecure",
         "--flush-period-s", str(flush_period_s), "--feeder-fingerprint", "fp"],
        cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=os.environ | {"PYTHONPATH": str(REPO)})


def _flushed_messages(path: Path) -> int:
    """Messages readable now by a linear scan (what a crash would leave)."""
    if not path.exists() or path.stat().st_size < 8:
        return 0
    return recording_info(path).messages


@pytest.mark.parametrize("n_before, n_after", [(400, 300)])
@pytest.mark.process
def test_sigkill_loses_nothing_before_the_last_flush(router_endpoint: str, tmp_path: Path, n_before: int,
                                                      n_after: int) -> None:
    out = tmp_path / "killed.mcap"
    proc = _spawn_recorder(out, router_endpoint, flush_period_s=0.2)
    try:
        with open_session(BusConfig(mode="peer", connect=(router_endpoint,))) as session:
            pub = _publisher(session, "cvvc/rural/meas/head")
            assert wait_for(lambda: pub.matching_status.matching, 20.0), "recorder process never subscribed"
            for i in range(n_before):
                pub.put(encode(head_frame(i)))
            # the recorder has flushed all of them once a scan of the file sees them
            assert wait_for(lambda: _flushed_messages(out) == n_before, 10.0, poll_s=0.05)
            for i in range(n_before, n_before + n_after):
                pub.put(encode(head_frame(i)))
            proc.send_signal(signal.SIGKILL)
            proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=10)
    assert proc.returncode == -signal.SIGKILL
    info = recording_info(out)
    assert not info.complete  # killed: no summary
    res = recover(out, tmp_path / "recovered.mcap")
    assert not res.input_was_complete
    with open(tmp_path / "recovered.mcap", "rb") as f:
        got = list(make_reader(f).iter_messages(log_time_order=False))
    seqs = [codec_for(type(head_frame(0))).decode(m.data).seq for _, _, m in got]
    assert n_before <= len(seqs) <= n_before + n_after
    assert seqs == list(range(1, len(seqs) + 1))  # everything flushed, in order, nothing twice
    assert res.messages_by_topic == {"cvvc/rural/meas/head": len(seqs)}


@pytest.mark.process
def test_sigterm_finishes_the_file(router_endpoint: str, tmp_path: Path) -> None:
    out = tmp_path / "terminated.mcap"
    proc = _spawn_recorder(out, router_endpoint, flush_period_s=0.2)
    try:
        with open_session(BusConfig(mode="peer", connect=(router_endpoint,))) as session:
            pub = _publisher(session, "cvvc/rural/meas/head")
            assert wait_for(lambda: pub.matching_status.matching, 20.0)
            for i in range(50):
                pub.put(encode(head_frame(i)))
            assert wait_for(lambda: _flushed_messages(out) == 50, 10.0, poll_s=0.05)
            proc.send_signal(signal.SIGTERM)
            _, stderr = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=10)
    assert proc.returncode == 0, stderr.decode()
    assert b"recorded 50 messages" in stderr
    info = recording_info(out)
    assert info.source == "summary" and info.complete and info.messages == 50
    assert info.metadata[METADATA_NAME]["feeder_fingerprint"] == "fp"


def test_full_queue_drops_are_counted_not_blocking(router_endpoint: str, tmp_path: Path) -> None:
    out = tmp_path / "full.mcap"
    bus = BusConfig(mode="peer", connect=(router_endpoint,))
    with open_session(bus) as rec_session, open_session(bus) as pub_session:
        with Recorder(rec_session, RecorderConfig(out_path=str(out), queue_size=0)) as rec:
            pub = _publisher(pub_session, "cvvc/rural/meas/head")
            assert wait_for(lambda: pub.matching_status.matching, 10.0)
            for i in range(20):
                pub.put(encode(head_frame(i)))
            assert wait_for(lambda: rec.stats().dropped_queue_full == 20, 10.0), rec.stats()
    info = recording_info(out)
    assert info.complete and info.messages == 0
    assert info.metadata[STATS_METADATA_NAME]["dropped_queue_full"] == "20"


def test_unwritable_output_is_a_clear_error(router_endpoint: str, tmp_path: Path) -> None:
    from recordings.errors import RecordingError

    with open_session(BusConfig(mode="peer", connect=(router_endpoint,))) as session:
        with pytest.raises(RecordingError, match="cannot write .*check the directory exists"):
            Recorder(session, RecorderConfig(out_path=str(tmp_path / "no" / "such" / "dir.mcap"))).start()


def test_junk_goes_to_quarantine_and_channels_are_bounded(router_endpoint: str, tmp_path: Path) -> None:
    """Junk on a real key sat on the real channel; a flood of made-up keys opened 813 channels."""
    out = tmp_path / "junk.mcap"
    bus = BusConfig(mode="peer", connect=(router_endpoint,))
    good = encode(head_frame(1))
    negative_seq = msgspec.json.encode(msgspec.to_builtins(head_frame(1)) | {"seq": -1})
    junk = [b"not json", b'{"t_ns": 5, "seq": 1}', negative_seq]
    with open_session(bus) as rec_session, open_session(bus) as pub_session:
        config = RecorderConfig(out_path=str(out), bus=bus, max_channels=3)
        with Recorder(rec_session, config) as recorder:
            head = _publisher(pub_session, "cvvc/rural/meas/head")
            ghosts = [_publisher(pub_session, f"cvvc/rural/meas/head/g{i}") for i in range(5)]
            assert wait_for(lambda: head.matching_status.matching and all(g.matching_status.matching
                                                                          for g in ghosts), 10.0)
            head.put(good)
            for raw in junk:
                head.put(raw)
            for g in ghosts:  # valid head frames on made-up keys: two get channels, three hit the bound
                g.put(good)
            assert wait_for(lambda: recorder.stats().messages == 9, 10.0), recorder.stats()
    stats = recorder.stats()
    assert stats.quarantined == 3 + 3 and stats.channels == 3
    with open(out, "rb") as f:
        by_topic: dict[str, list[bytes]] = {}
        for _, channel, message in make_reader(f).iter_messages(log_time_order=False):
            by_topic.setdefault(channel.topic, []).append(message.data)
    assert by_topic["cvvc/rural/meas/head"] == [good]  # the real channel holds only the real frame
    quarantined = [msgspec.json.decode(d, type=Quarantined) for d in by_topic[QUARANTINE_TOPIC]]
    assert [base64.b64decode(q.payload_b64) for q in quarantined[:3]] == junk  # nothing lost
    assert [q.reason.split(":")[0] for q in quarantined] == ["not a HeadFrame"] * 3 + ["channel limit"] * 3


def test_the_time_span_is_the_sessions_not_the_epochs(router_endpoint: str, tmp_path: Path) -> None:
    """An agent's status before its first frame (t_ns 0) and a payload with no t_ns are
    logged at the session's instants, so the file spans the simulated session, not 1970 (or today) to 2023."""
    from schemas import messages as m
    from schemas.examples import T0_NS

    out = tmp_path / "span.mcap"
    bus = BusConfig(mode="peer", connect=(router_endpoint,))
    status_key, head_key = EXAMPLE_KEYS[m.AgentStatus], EXAMPLE_KEYS[m.HeadFrame]
    starting = msgspec.structs.replace(examples(t_ns=0, seq=1)[m.AgentStatus], state="starting", last_frame_t_ns=0)
    with open_session(bus) as rec_session, open_session(bus) as pub_session:
        with Recorder(rec_session, RecorderConfig(out_path=str(out), bus=bus)) as recorder:
            status, head = _publisher(pub_session, status_key), _publisher(pub_session, head_key)
            assert wait_for(lambda: status.matching_status.matching and head.matching_status.matching, 10.0)
            status.put(encode(starting))  # before any timed message: held, then logged at the first instant
            assert wait_for(lambda: recorder.stats().messages == 1, 10.0)
            head.put(encode(head_frame(0)))
            head.put(b'{"seq": 5}')  # no t_ns: quarantined, logged at the latest instant
            head.put(encode(head_frame(3)))
            assert wait_for(lambda: recorder.stats().messages == 4, 10.0), recorder.stats()
    assert recorder.stats().log_time_fallbacks == 2
    with open(out, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_start_time == T0_NS
        assert summary.statistics.message_end_time == T0_NS + 3 * 60_000_000_000
        times = [(ch.topic, msg.log_time) for _, ch, msg in reader.iter_messages()]
    assert (status_key, T0_NS) in times
    assert sorted(t for _, t in times) == [T0_NS, T0_NS, T0_NS, T0_NS + 3 * 60_000_000_000]
    assert recording_info(out).start_ns == T0_NS
