"""``cvvc recordings export-json``: a copy of a recording with the truth as JSON.

Recordings of this version hold the truth (``sim/truth``) as Protobuf with its schema, which Foxglove decodes as it
is. Recordings of earlier versions hold it as MessagePack (``TruthPack``, the voltages as float32 byte planes),
which Foxglove does not decode (it reads JSON, Protobuf, FlatBuffers, ROS 1 and ROS 2 messages): the copy re-encodes
the truth, either encoding, into its JSON form (``schemas.truth.to_truth_frame``: ``TruthFrame``, message
encoding ``json``, its JSON Schema), so ``/sim/truth.v_pu[3]`` plots there from an older recording too, and tools
that read JSON only (``jq``) read every channel; every other channel, message (times, sequence) and metadata record
is copied as it is. The copy is larger (the truth as JSON text is about three times the compact form after zstd):
it is for viewing, the original stays the record.
"""

from __future__ import annotations

import os
from pathlib import Path

import msgspec
from mcap.reader import make_reader
from mcap.records import Channel, Schema
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

from recordings.errors import RecordingError
from recordings.info import MCAP_READ_ERRORS
from schemas import messages as m
from schemas.jsonschema import schema_bytes, schema_name
from schemas.truth import TruthDecodeError, to_truth_frame, truth_pack
from schemas.truth_proto import TRUTH_PROTO_NAME

__all__ = ["ExportResult", "export_json"]


class ExportResult(msgspec.Struct, frozen=True, kw_only=True):
    """What ``export_json`` wrote: messages copied, messages re-encoded as JSON, and any left out (undecodable)."""

    out_path: str
    messages: int
    reencoded: int
    skipped: int
    skipped_topics: dict[str, int] = {}


_COMPACT_TRUTH = ("protobuf", "msgpack")  # the truth's encodings, today's and an earlier version's


class _Copier:
    """Channels and schemas of the output, registered once per input channel."""

    def __init__(self, writer: Writer) -> None:
        self._w = writer
        self._schemas: dict[tuple[str, str, bytes], int] = {}
        self._channels: dict[int, tuple[int, bool]] = {}  # input channel id -> (output id, re-encode truth)

    def channel(self, schema: Schema | None, channel: Channel) -> tuple[int, bool]:
        got = self._channels.get(channel.id)
        if got is not None:
            return got
        truth = channel.message_encoding in _COMPACT_TRUTH and schema is not None and schema.name in (
            schema_name(m.TruthPack), TRUTH_PROTO_NAME)
        if truth:
            name, encoding, data, message_encoding = (schema_name(m.TruthFrame), "jsonschema",
                                                      schema_bytes(m.TruthFrame), "json")
        elif schema is not None:
            name, encoding, data, message_encoding = (schema.name, schema.encoding, bytes(schema.data),
                                                      channel.message_encoding)
        else:
            name = encoding = message_encoding = ""
            data = b""
        sid = 0
        if name:
            sid = self._schemas.get((name, encoding, data), 0)
            if not sid:
                sid = self._schemas[(name, encoding, data)] = self._w.register_schema(name, encoding, data)
        metadata = dict(channel.metadata) | ({"cvvc_message_type": "TruthFrame"} if truth else {})
        cid = self._w.register_channel(channel.topic, message_encoding or channel.message_encoding, sid, metadata)
        self._channels[channel.id] = (cid, truth)
        return cid, truth


def export_json(in_path: str | Path, out_path: str | Path) -> ExportResult:
    """Write ``out_path``: ``in_path`` with its truth channels (Protobuf, or an earlier version's MessagePack)
    re-encoded as JSON ``TruthFrame``.

    A truth message that does not decode is left out and counted (``skipped``); the file is written to
    ``OUT.exporting`` and renamed at the end, so ``out_path`` is never half written.

    Raises
    ------
    RecordingError
        ``in_path`` cannot be read as MCAP (run ``cvvc recordings recover`` first), or ``out_path`` is the input.
    """
    src, out = Path(in_path), Path(out_path)
    if src.resolve() == out.resolve():
        raise RecordingError(f"{out}: the export must go to another file than its input")
    tmp = out.with_name(out.name + ".exporting")
    encode = msgspec.json.Encoder().encode
    messages = reencoded = skipped = 0
    skipped_topics: dict[str, int] = {}
    try:
        with open(src, "rb") as f, open(tmp, "wb") as g:
            reader = make_reader(f)
            writer = Writer(g, compression=CompressionType.ZSTD)
            writer.start(profile="", library=f"cvvc-edge {_version()} (export-json); {LIBRARY_IDENTIFIER}")
            copier = _Copier(writer)
            for schema, channel, msg in reader.iter_messages(log_time_order=False):
                cid, truth = copier.channel(schema, channel)
                data = msg.data
                if truth:
                    try:
                        data = encode(to_truth_frame(truth_pack(msg.data, channel.message_encoding)))
                    except TruthDecodeError:
                        skipped += 1
                        skipped_topics[channel.topic] = skipped_topics.get(channel.topic, 0) + 1
                        continue
                    reencoded += 1
                writer.add_message(cid, log_time=msg.log_time, data=data, publish_time=msg.publish_time,
                                   sequence=msg.sequence)
                messages += 1
            for record in reader.iter_metadata():
                writer.add_metadata(record.name, dict(record.metadata))
            writer.finish()
    except MCAP_READ_ERRORS as e:
        tmp.unlink(missing_ok=True)
        raise RecordingError(f"{src}: not a readable MCAP recording ({e}); try `cvvc recordings recover` "
                             "first") from e
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise RecordingError(f"cannot export {src} to {out}: {e}") from e
    os.replace(tmp, out)
    return ExportResult(out_path=str(out), messages=messages, reencoded=reencoded, skipped=skipped,
                        skipped_topics=skipped_topics)


def _version() -> str:
    from schemas.version import __version__

    return __version__
