"""What a recording holds (``cvvc recordings info``) and how to save a file cut short (``... recover``).

``recording_info`` reads the summary section of a finished file (fast); a file without a usable summary
(the recorder was killed, the disk filled up, the tail is corrupt) is scanned linearly instead, and the
result says where reading stopped and why.

``recover`` scans a file record by record from the start and rewrites every complete record into a new,
finished and indexed MCAP file: message bytes, ``log_time``, ``publish_time`` and ``sequence`` unchanged;
schemas, channels, metadata and attachments copied (channel and schema ids may be renumbered). What is lost:
the bytes after the last complete record (a chunk that was being written when the process died) and any
chunk whose compressed data or CRC is corrupt (skipped whole; its time range is reported). Messages whose
channel record was lost with a corrupt chunk cannot be decoded and are counted as ``orphan_messages``.
"""

from __future__ import annotations

import io
import os
import struct
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Literal

import msgspec
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType, Writer

from recordings.errors import NotMcapError, RecordingError, UnreadableError

__all__ = [
    "MCAP_MAGIC",
    "MCAP_READ_ERRORS",
    "ChannelInfo",
    "CorruptChunk",
    "GAPS_METADATA_NAME",
    "RecorderGap",
    "RecordingInfo",
    "RecoverResult",
    "check_mcap_file",
    "devices_of",
    "gaps_of",
    "recording_info",
    "recover",
]

MCAP_MAGIC = b"\x89MCAP0\r\n"
_RECORDS: dict[int, type[McapRecord]] = {
    0x01: Header, 0x02: Footer, 0x03: Schema, 0x04: Channel, 0x05: Message, 0x06: Chunk, 0x07: MessageIndex,
    0x08: ChunkIndex, 0x09: Attachment, 0x0A: AttachmentIndex, 0x0B: Statistics, 0x0C: Metadata,
    0x0D: MetadataIndex, 0x0E: SummaryOffset, 0x0F: DataEnd,
}
# What the mcap library raises on bad bytes: its own errors, short reads, bad UTF-8, bad zstd data, CRCs.
MCAP_READ_ERRORS = (McapError, struct.error, ValueError, EOFError, IndexError, zstandard.ZstdError)


# ----------------------------------------------------------------------------------------- results
GAPS_METADATA_NAME = "cvvc.recorder_gaps"
"""The metadata record that lists a joined recording's gaps (``recordings.join``)."""


class RecorderGap(msgspec.Struct, frozen=True, kw_only=True):
    """What a recording misses between two parts: its recorder ended and a new one was started.

    ``from_t_ns`` / ``to_t_ns`` [ns]: the latest message time (``log_time``) recorded before the gap and the earliest
    later one recorded after it: no recorded message lies strictly between. ``from_wall_ns`` / ``to_wall_ns``
    [ns]: receive wall time of the last message before and of the first after (-1: the part held none).
    ``lost_tail_bytes``: bytes of the ended recorder's file after its last complete record.
    """

    restart: int  # 1 for the first restart
    reason: str  # how the recorder ended, as its supervisor saw it
    from_t_ns: int
    to_t_ns: int
    from_wall_ns: int
    to_wall_ns: int
    lost_tail_bytes: int = 0


def gaps_of(metadata: dict[str, dict[str, str]]) -> list[RecorderGap]:
    """The recorder gaps a recording's metadata lists (none for a recording of one recorder)."""
    raw = metadata.get(GAPS_METADATA_NAME, {}).get("gaps")
    if not raw:
        return []
    try:
        return msgspec.json.decode(raw, type=list[RecorderGap])
    except msgspec.DecodeError as e:
        raise RecordingError(f"the metadata {GAPS_METADATA_NAME} is not a list of gaps: {e}") from e


class ChannelInfo(msgspec.Struct, frozen=True, kw_only=True):
    """One channel. The per-channel time span [ns] is known only after a linear scan (None otherwise)."""

    topic: str
    message_encoding: str
    schema_name: str  # "" when the channel has no schema
    schema_encoding: str
    messages: int
    first_log_time_ns: int | None = None
    last_log_time_ns: int | None = None


class CorruptChunk(msgspec.Struct, frozen=True, kw_only=True):
    """A chunk whose data could not be read; its messages are lost."""

    offset: int
    length_bytes: int
    message_start_time_ns: int
    message_end_time_ns: int
    reason: str


class RecordingInfo(msgspec.Struct, frozen=True, kw_only=True):
    """What ``cvvc recordings info`` reports.

    ``source``: ``summary`` (a finished file's index) or ``scan`` (read linearly; ``complete`` is False when
    the scan stopped before the footer, and ``problems`` says where and why).
    """

    path: str
    size_bytes: int
    source: Literal["summary", "scan"]
    complete: bool
    library: str
    profile: str
    messages: int
    start_ns: int | None
    end_ns: int | None
    duration_s: float
    channels: list[ChannelInfo]
    metadata: dict[str, dict[str, str]]
    chunks: int
    readable_bytes: int
    problems: list[str] = []
    corrupt_chunks: list[CorruptChunk] = []
    devices: dict[str, list[str]] = {}  # field devices by kind ("pv", "vr", "cap"), from the meas/<kind>/<id> channels
    gaps: list[RecorderGap] = []  # spans missed because the recorder ended and was restarted (recordings.join)


def devices_of(channels: list[ChannelInfo]) -> dict[str, list[str]]:
    """The field devices a recording has channels of, by kind: ``cvvc/<F>/meas/<kind>/<id>`` topics."""
    out: dict[str, set[str]] = {}
    for ch in channels:
        parts = ch.topic.split("/")
        if len(parts) == 5 and parts[0] == "cvvc" and parts[2] == "meas":
            out.setdefault(parts[3], set()).add(parts[4])
    return {kind: sorted(ids) for kind, ids in sorted(out.items())}


class RecoverResult(msgspec.Struct, frozen=True, kw_only=True):
    """What ``cvvc recordings recover`` saved and lost."""

    in_path: str
    out_path: str
    size_bytes: int
    readable_bytes: int  # end of the last complete record
    lost_tail_bytes: int  # bytes after it: a record being written when the file was cut
    input_was_complete: bool  # the input already ended with a footer
    messages: int
    messages_by_topic: dict[str, int]
    chunks_recovered: int
    corrupt_chunks: list[CorruptChunk]
    orphan_messages: int  # messages on a channel whose Channel record was lost
    metadata_records: int
    start_ns: int | None
    end_ns: int | None
    problems: list[str]


# ------------------------------------------------------------------------------------- linear scan
@dataclass
class _ScanState:
    """Where a linear scan stopped: ``end`` is the offset after the last complete record."""

    size: int
    end: int = len(MCAP_MAGIC)
    footer: bool = False
    good_chunks: int = 0
    stop_reason: str | None = None
    problems: list[str] = field(default_factory=list)


def check_mcap_file(path: str | Path) -> int:
    """The size of ``path`` in bytes, or ``NotMcapError`` if it is missing, empty or not MCAP."""
    p = Path(path)
    try:
        size = p.stat().st_size
        with open(p, "rb") as f:
            magic = f.read(len(MCAP_MAGIC))
    except FileNotFoundError as e:
        raise NotMcapError(f"{path}: no such file") from e
    except IsADirectoryError as e:
        raise NotMcapError(f"{path} is a directory, not an MCAP file") from e
    except OSError as e:
        raise NotMcapError(f"{path}: cannot read: {e}") from e
    if size == 0:
        raise NotMcapError(f"{path} is empty (0 bytes): the recorder never wrote to it")
    if magic != MCAP_MAGIC:
        if MCAP_MAGIC.startswith(magic):
            raise NotMcapError(f"{path} holds only {size} bytes of the MCAP magic: nothing was recorded")
        raise NotMcapError(f"{path} is not an MCAP file (it does not start with the MCAP magic bytes)")
    return size


def _scan(f: IO[bytes], state: _ScanState) -> Iterator[tuple[int, McapRecord]]:
    """Yield ``(offset, record)`` for every complete, parseable top-level record; stop at the first that is
    cut short or corrupt (``state`` says where and why). Chunks are yielded whole, not broken up.
    """
    f.seek(len(MCAP_MAGIC))
    pos = len(MCAP_MAGIC)
    while True:
        head = f.read(9)
        if not head:
            state.stop_reason = f"the file ends at byte {pos} without a footer (the writer never finished)"
            return
        if len(head) < 9:
            state.stop_reason = f"the file ends inside a record header at byte {pos}"
            return
        opcode, length = struct.unpack("<BQ", head)
        cls = _RECORDS.get(opcode)
        if cls is None:
            state.stop_reason = f"unknown record opcode 0x{opcode:02x} at byte {pos}: the file is corrupt from here"
            return
        if pos + 9 + length > state.size:
            state.stop_reason = (f"a {cls.__name__} record at byte {pos} needs {length} bytes but the file ends "
                                 f"after {state.size - pos - 9}: it was cut short")
            return
        body = f.read(length)
        try:
            stream = ReadDataStream(io.BytesIO(body))
            record = cls.read(stream, length) if cls is Message else cls.read(stream)  # type: ignore[attr-defined]
        except MCAP_READ_ERRORS as e:
            state.stop_reason = f"a {cls.__name__} record at byte {pos} is corrupt ({_why(e)}): unreadable from here"
            return
        pos += 9 + length
        state.end = pos
        yield pos - 9 - length, record
        if isinstance(record, Footer):
            state.footer = True
            if f.read(len(MCAP_MAGIC)) == MCAP_MAGIC:
                state.end += len(MCAP_MAGIC)
            return


def _why(e: BaseException) -> str:
    return str(e) or type(e).__name__


def _chunk_records(offset: int, chunk: Chunk) -> tuple[list[McapRecord], CorruptChunk | None]:
    try:
        return breakup_chunk(chunk, validate_crc=True), None
    except MCAP_READ_ERRORS as e:
        return [], CorruptChunk(offset=offset, length_bytes=len(chunk.data),
                                message_start_time_ns=chunk.message_start_time,
                                message_end_time_ns=chunk.message_end_time, reason=_why(e))


def _flat_records(f: IO[bytes], state: _ScanState, corrupt: list[CorruptChunk]
                  ) -> Iterator[tuple[McapRecord, bool]]:
    """Every record in file order with chunks broken up; ``(record, from_chunk)``. Summary records skipped."""
    in_summary = False
    for offset, record in _scan(f, state):
        if isinstance(record, DataEnd):
            in_summary = True
        if in_summary:
            continue
        if isinstance(record, Chunk):
            records, bad = _chunk_records(offset, record)
            if bad is not None:
                corrupt.append(bad)
            else:
                state.good_chunks += 1
            for r in records:
                yield r, True
        else:
            yield record, False


# -------------------------------------------------------------------------------------------- info
def recording_info(path: str | Path) -> RecordingInfo:
    """Describe ``path``: from its summary if it has a readable one, else from a linear scan.

    Raises ``NotMcapError`` for a missing, empty or non-MCAP file; never for a truncated or corrupt one
    (the result's ``problems`` say what could not be read).
    """
    size = check_mcap_file(path)
    problems: list[str] = []
    try:
        return _info_from_summary(path, size)
    except _SummaryUnavailable as e:
        problems.append(str(e))
    except MCAP_READ_ERRORS as e:
        problems.append(f"the summary section is unreadable ({_why(e)}); scanned the file linearly instead")
    return _info_from_scan(path, size, problems)


class _SummaryUnavailable(Exception):
    """The file has no summary (or no statistics in it): a linear scan is needed."""


def _info_from_summary(path: str | Path, size: int) -> RecordingInfo:
    with open(path, "rb") as f:
        if size < 2 * len(MCAP_MAGIC) + 29 or _tail_magic(f) != MCAP_MAGIC:
            raise _SummaryUnavailable("the file does not end with the MCAP magic (not finished): scanned linearly")
        f.seek(0)
        reader = make_reader(f)
        header = reader.get_header()
        summary = reader.get_summary()
        if summary is None or summary.statistics is None:
            raise _SummaryUnavailable("the file has no summary statistics: scanned linearly")
        stats = summary.statistics
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    channels = []
    for cid, ch in sorted(summary.channels.items()):
        schema = summary.schemas.get(ch.schema_id)
        channels.append(ChannelInfo(topic=ch.topic, message_encoding=ch.message_encoding,
                                    schema_name=schema.name if schema else "",
                                    schema_encoding=schema.encoding if schema else "",
                                    messages=stats.channel_message_counts.get(cid, 0)))
    start = stats.message_start_time if stats.message_count else None
    end = stats.message_end_time if stats.message_count else None
    return RecordingInfo(path=str(path), size_bytes=size, source="summary", complete=True, library=header.library,
                         profile=header.profile, messages=stats.message_count, start_ns=start, end_ns=end,
                         duration_s=_span_s(start, end), channels=channels, metadata=metadata,
                         chunks=stats.chunk_count, readable_bytes=size, devices=devices_of(channels),
                         gaps=_gaps(metadata))


def _tail_magic(f: IO[bytes]) -> bytes:
    f.seek(-len(MCAP_MAGIC), os.SEEK_END)
    return f.read(len(MCAP_MAGIC))


def _span_s(start: int | None, end: int | None) -> float:
    return 0.0 if start is None or end is None else (end - start) / 1e9


def _info_from_scan(path: str | Path, size: int, problems: list[str]) -> RecordingInfo:
    state = _ScanState(size=size)
    corrupt: list[CorruptChunk] = []
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    counts: Counter[int] = Counter()
    first: dict[int, int] = {}
    last: dict[int, int] = {}
    metadata: dict[str, dict[str, str]] = {}
    header: Header | None = None
    chunks = 0
    orphans = 0
    with open(path, "rb") as f:
        for offset, record in _scan(f, state):
            if isinstance(record, Chunk):
                chunks += 1
                records, bad = _chunk_records(offset, record)
                if bad is not None:
                    corrupt.append(bad)
            else:
                records = [record]
            for r in records:
                match r:
                    case Header():
                        header = r
                    case Schema():
                        schemas[r.id] = r
                    case Channel():
                        channels[r.id] = r
                    case Message():
                        if r.channel_id not in channels:
                            orphans += 1
                            continue
                        counts[r.channel_id] += 1
                        first[r.channel_id] = min(first.get(r.channel_id, r.log_time), r.log_time)
                        last[r.channel_id] = max(last.get(r.channel_id, r.log_time), r.log_time)
                    case Metadata():
                        metadata[r.name] = dict(r.metadata)
    if state.stop_reason is not None:
        problems.append(f"{state.stop_reason}; {size - state.end} bytes after byte {state.end} are unreadable: "
                        f"run `cvvc recordings recover {path} OUT.mcap` to save the rest")
    problems += [f"corrupt chunk at byte {c.offset} ({c.reason}): its messages are lost" for c in corrupt]
    if orphans:
        problems.append(f"{orphans} messages refer to channels whose definition was lost")
    infos = []
    for cid, ch in sorted(channels.items()):
        schema = schemas.get(ch.schema_id)
        infos.append(ChannelInfo(topic=ch.topic, message_encoding=ch.message_encoding,
                                 schema_name=schema.name if schema else "",
                                 schema_encoding=schema.encoding if schema else "", messages=counts[cid],
                                 first_log_time_ns=first.get(cid), last_log_time_ns=last.get(cid)))
    start = min(first.values()) if first else None
    end = max(last.values()) if last else None
    return RecordingInfo(path=str(path), size_bytes=size, source="scan", complete=state.footer and not corrupt,
                         library=header.library if header else "", profile=header.profile if header else "",
                         messages=sum(counts.values()), start_ns=start, end_ns=end, duration_s=_span_s(start, end),
                         channels=infos, metadata=metadata, chunks=chunks, readable_bytes=state.end,
                         problems=problems, corrupt_chunks=corrupt, devices=devices_of(infos), gaps=_gaps(metadata))


def _gaps(metadata: dict[str, dict[str, str]]) -> list[RecorderGap]:
    """The recorder gaps of the metadata, or none with a problem noted when that metadata is unreadable."""
    try:
        return gaps_of(metadata)
    except RecordingError:
        return []


# ----------------------------------------------------------------------------------------- recover
def recover(in_path: str | Path, out_path: str | Path) -> RecoverResult:
    """Rewrite every complete record of ``in_path`` into a finished, indexed MCAP file at ``out_path``.

    Raises ``NotMcapError`` for a non-MCAP input, ``UnreadableError`` when not even the header record is
    complete, ``RecordingError`` when ``out_path`` is the input or cannot be written.
    """
    size = check_mcap_file(in_path)
    if Path(out_path).resolve() == Path(in_path).resolve():
        raise RecordingError("recover writes a new file: give an OUT path different from IN")
    state = _ScanState(size=size)
    corrupt: list[CorruptChunk] = []
    by_topic: Counter[str] = Counter()
    problems: list[str] = []
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, tuple[int, str]] = {}
    orphans = 0
    n_metadata = 0
    start: int | None = None
    end: int | None = None
    try:
        out = open(out_path, "wb")  # noqa: SIM115  # closed below
    except OSError as e:
        raise RecordingError(f"cannot write {out_path}: {e}") from e
    with out, open(in_path, "rb") as f:
        records = _flat_records(f, state, corrupt)
        first = next(records, None)
        if first is None or not isinstance(first[0], Header):
            out.close()
            os.unlink(out_path)
            raise UnreadableError(f"{in_path}: {state.stop_reason or 'the first record is not a Header'}; "
                                  "nothing can be recovered")
        header = first[0]
        writer = Writer(out, compression=CompressionType.ZSTD)
        writer.start(profile=header.profile, library=header.library)
        for record, _ in records:
            match record:
                case Schema():
                    if record.id not in schema_ids:
                        schema_ids[record.id] = writer.register_schema(record.name, record.encoding, record.data)
                case Channel():
                    if record.id not in channel_ids:
                        sid = schema_ids.get(record.schema_id, 0)
                        if record.schema_id and not sid:
                            problems.append(f"channel {record.topic}: its schema was lost; kept without schema")
                        cid = writer.register_channel(record.topic, record.message_encoding, sid,
                                                      dict(record.metadata))
                        channel_ids[record.id] = (cid, record.topic)
                case Message():
                    target = channel_ids.get(record.channel_id)
                    if target is None:
                        orphans += 1
                        continue
                    writer.add_message(target[0], log_time=record.log_time, data=record.data,
                                       publish_time=record.publish_time, sequence=record.sequence)
                    by_topic[target[1]] += 1
                    start = record.log_time if start is None else min(start, record.log_time)
                    end = record.log_time if end is None else max(end, record.log_time)
                case Metadata():
                    writer.add_metadata(record.name, dict(record.metadata))
                    n_metadata += 1
                case Attachment():
                    writer.add_attachment(record.create_time, record.log_time, record.name, record.media_type,
                                          record.data)
        writer.finish()
    if state.stop_reason is not None:
        problems.append(state.stop_reason)
    if orphans:
        problems.append(f"{orphans} messages dropped: their channel definition was in a lost chunk")
    problems += [f"corrupt chunk at byte {c.offset} skipped ({c.reason})" for c in corrupt]
    check = recording_info(out_path)
    if check.messages != sum(by_topic.values()) or not check.complete:
        raise RecordingError(f"{out_path}: the rewritten file reads back {check.messages} messages, expected "
                             f"{sum(by_topic.values())}; please report this")
    return RecoverResult(in_path=str(in_path), out_path=str(out_path), size_bytes=size, readable_bytes=state.end,
                         lost_tail_bytes=size - state.end, input_was_complete=state.footer,
                         messages=sum(by_topic.values()), messages_by_topic=dict(sorted(by_topic.items())),
                         chunks_recovered=state.good_chunks, corrupt_chunks=corrupt, orphan_messages=orphans,
                         metadata_records=n_metadata, start_ns=start, end_ns=end, problems=problems)
