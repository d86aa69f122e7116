"""One recording from the parts of a restarted recorder, with what it missed recorded as a gap.

``cvvc run`` keeps the recorder off the control path: when the recorder
process dies, the run goes on, a new recorder writes a new part, and at the end the parts are joined here into
one finished MCAP file:

- every message of every part, bytes, ``log_time``, ``publish_time`` and ``sequence`` unchanged (a part whose
  recorder died unfinished is first rebuilt with :func:`recordings.info.recover`; its unflushed tail is lost);
- channels and schemas merged by topic and by (name, encoding, data);
- between two parts, one :class:`RecorderGap` on the channel ``cvvc.recorder_gap`` (not a Zenoh key): in message
  time (``log_time``) the latest time recorded before and the earliest later one recorded after, so nothing
  recorded lies strictly between them; in receive wall time (``publish_time``) the last message received before
  and the first after; and how the recorder ended; the same list in the metadata ``cvvc.recorder_gaps``, which
  ``cvvc recordings info`` prints;
- the metadata ``cvvc.recording`` of the first part and ``cvvc.recorder_stats`` of the last one.

Message times come from the senders; the interval is bounded by receive times too, which are the recorder's own.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import msgspec
from mcap.reader import make_reader
from mcap.records import Channel, Schema
from mcap.writer import CompressionType, Writer

from recordings.errors import RecordingError, UnreadableError
from recordings.info import GAPS_METADATA_NAME, MCAP_READ_ERRORS, RecorderGap, gaps_of, recording_info, recover

__all__ = ["GAPS_METADATA_NAME", "GAP_TOPIC", "JoinResult", "RecorderGap", "gaps_of", "join_parts"]

GAP_TOPIC = "cvvc.recorder_gap"
"""The MCAP topic of recorder gaps (not a Zenoh key: it cannot collide with one)."""
_KEEP_METADATA = ("cvvc.recording",)  # from the first part; ``cvvc.recorder_stats`` from the last


class JoinResult(msgspec.Struct, frozen=True, kw_only=True):
    """The joined file, its message count and its gaps."""

    out_path: str
    messages: int
    gaps: list[RecorderGap]


@dataclass
class _Span:
    """When one part's real messages were received (wall [ns]) and what times they carry (message time [ns])."""

    first_wall_ns: int = -1
    last_wall_ns: int = -1
    last_t_ns: int = -1  # the latest message time of the part
    first_t_ns_after: int = -1  # its earliest message time later than the previous part's latest

    def add(self, t_ns: int, wall_ns: int, after_t_ns: int) -> None:
        self.first_wall_ns = wall_ns if self.first_wall_ns < 0 else min(self.first_wall_ns, wall_ns)
        self.last_wall_ns = max(self.last_wall_ns, wall_ns)
        self.last_t_ns = max(self.last_t_ns, t_ns)
        if t_ns > after_t_ns and (self.first_t_ns_after < 0 or t_ns < self.first_t_ns_after):
            self.first_t_ns_after = t_ns


class _Part(msgspec.Struct, kw_only=True):
    path: Path
    lost_tail_bytes: int
    temporary: bool


def _finished(path: Path) -> _Part | None:
    """``path`` itself when it is a finished MCAP file, else a recovered copy beside it; None when the recorder
    left nothing readable (no file, an empty one, not even a complete header).
    """
    if not path.is_file() or path.stat().st_size == 0:
        return None
    try:
        if recording_info(path).complete:
            return _Part(path=path, lost_tail_bytes=0, temporary=False)
        out = path.with_name(path.name + ".recovered")
        res = recover(path, out)
        return _Part(path=out, lost_tail_bytes=res.lost_tail_bytes, temporary=True)
    except UnreadableError:
        return None  # the recorder died before its header reached the disk: an empty part
    except (RecordingError, *MCAP_READ_ERRORS, OSError) as e:
        raise RecordingError(f"cannot read the recording part {path}: {e}") from e


class _Joiner:
    """Copies parts into one writer, merging schemas and channels, noting each part's first and last message."""

    def __init__(self, writer: Writer) -> None:
        self._w = writer
        self._schemas: dict[tuple[str, str, bytes], int] = {}
        self._channels: dict[str, int] = {}
        self.messages = 0

    def copy(self, path: Path, after_t_ns: int) -> tuple[_Span, dict[str, dict[str, str]]]:
        """Copy ``path``'s messages; returns the span of its real messages (``after_t_ns``: the previous part's
        latest message time) and its metadata. Quarantined samples are copied but bound no gap: their times are
        their senders' word.
        """
        from recordings.recorder import QUARANTINE_TOPIC

        span = _Span()
        with open(path, "rb") as f:
            reader = make_reader(f)
            for schema, channel, msg in reader.iter_messages(log_time_order=False):
                cid = self._channel(schema, channel)
                self._w.add_message(cid, log_time=msg.log_time, data=msg.data, publish_time=msg.publish_time,
                                    sequence=msg.sequence)
                self.messages += 1
                if channel.topic not in (QUARANTINE_TOPIC, GAP_TOPIC):
                    span.add(msg.log_time, msg.publish_time, after_t_ns)
            metadata = {md.name: dict(md.metadata) for md in reader.iter_metadata()}
        return span, metadata

    def _channel(self, schema: Schema | None, channel: Channel) -> int:
        cid = self._channels.get(channel.topic)
        if cid is not None:
            return cid
        sid = 0
        if schema is not None:
            key = (schema.name, schema.encoding, bytes(schema.data))
            sid = self._schemas.get(key, 0)
            if not sid:
                sid = self._schemas[key] = self._w.register_schema(schema.name, schema.encoding, schema.data)
        cid = self._channels[channel.topic] = self._w.register_channel(channel.topic, channel.message_encoding, sid,
                                                                      dict(channel.metadata))
        return cid


def join_parts(parts: Sequence[str | Path], reasons: Sequence[str], out_path: str | Path) -> JoinResult:
    """Join the recording ``parts`` (in order) into ``out_path``; ``reasons[i]`` says how part ``i``'s recorder
    ended (one per gap: ``len(parts) - 1``). Parts are left in place; recovered copies are removed.
    """
    if len(reasons) != len(parts) - 1 or not parts:
        raise RecordingError(f"{len(parts)} parts need {max(len(parts) - 1, 0)} reasons, got {len(reasons)}")
    finished = [_finished(Path(p)) for p in parts]
    try:
        return _write(finished, reasons, Path(out_path))
    finally:
        for part in finished:
            if part is not None and part.temporary:
                part.path.unlink(missing_ok=True)


def _write(parts: list[_Part | None], reasons: Sequence[str], out: Path) -> JoinResult:
    from recordings.recorder import STATS_METADATA_NAME

    tmp = out.with_name(out.name + ".joining")
    gaps: list[RecorderGap] = []
    with open(tmp, "wb") as f:
        writer = Writer(f, compression=CompressionType.ZSTD)
        writer.start(profile="", library=_library())
        joiner = _Joiner(writer)
        spans: list[_Span] = []
        kept: dict[str, dict[str, str]] = {}
        for i, part in enumerate(parts):
            after_t_ns = spans[-1].last_t_ns if spans else -1
            span, metadata = (_Span(), {}) if part is None else joiner.copy(part.path, after_t_ns)
            spans.append(span)
            for name in _KEEP_METADATA:
                if name in metadata and name not in kept:
                    kept[name] = metadata[name]
            if STATS_METADATA_NAME in metadata:
                kept[STATS_METADATA_NAME] = metadata[STATS_METADATA_NAME]
            if i:
                gaps.append(_gap(i, reasons[i - 1], spans[i - 1], span, parts[i - 1]))
        _write_gaps(writer, gaps)
        for name, record in kept.items():
            writer.add_metadata(name, record)
        writer.add_metadata(GAPS_METADATA_NAME, {"restarts": str(len(gaps)),
                                                 "gaps": msgspec.json.encode(gaps).decode()})
        writer.finish()
    os.replace(tmp, out)
    return JoinResult(out_path=str(out), messages=joiner.messages + len(gaps), gaps=gaps)


def _gap(restart: int, reason: str, before: _Span, after: _Span, dead: _Part | None) -> RecorderGap:
    return RecorderGap(restart=restart, reason=reason[:500], from_t_ns=before.last_t_ns,
                       to_t_ns=after.first_t_ns_after, from_wall_ns=before.last_wall_ns,
                       to_wall_ns=after.first_wall_ns, lost_tail_bytes=dead.lost_tail_bytes if dead else 0)


def _write_gaps(writer: Writer, gaps: list[RecorderGap]) -> None:
    if not gaps:
        return
    schema = msgspec.json.encode(msgspec.json.schema(RecorderGap))
    sid = writer.register_schema("cvvc.RecorderGap", "jsonschema", schema)
    cid = writer.register_channel(GAP_TOPIC, "json", sid, {"cvvc_message_type": "RecorderGap"})
    for gap in gaps:
        t = max(gap.from_t_ns, 0)
        writer.add_message(cid, log_time=t, data=msgspec.json.encode(gap), publish_time=max(gap.from_wall_ns, 0),
                           sequence=gap.restart)


def _library() -> str:
    from mcap.writer import LIBRARY_IDENTIFIER

    from schemas.version import __version__

    return f"cvvc-edge {__version__} (joined parts); {LIBRARY_IDENTIFIER}"
