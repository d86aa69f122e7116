"""Replay: republish recorded messages onto Zenoh with their original spacing, scaled by a speed factor.

Messages are read in ``log_time`` order (the messages' own ``t_ns``; ties keep file order) and each is
published, bytes unchanged (but the MessagePack truth of an earlier version's recording, sent as today's Protobuf),
on its recorded key at ``wall0 + (log_time - log_time0) / speed``. With
``speed=None`` they go out as fast as possible. Publishers use congestion control BLOCK so a fast replay
loses nothing. Before the first message, replay waits (bounded) until every selected key has a matching
subscriber; if none has one by then it stops with an error, if some have it goes ahead.

By default only measurement frames are replayed (``cvvc/*/meas/**``), so a live agent can run against a
past day and publish its own decisions.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import msgspec
import zenoh

from recordings.errors import ReplayError, UnreadableError
from recordings.info import MCAP_READ_ERRORS, check_mcap_file
from schemas import messages as m
from schemas.bus import BusConfig, has_subscribers, open_session, zenoh_encoding
from schemas.keys import message_type_for_key
from schemas.messages import wire_of

__all__ = [
    "MEASUREMENT_KEYS",
    "RecordedMessage",
    "RecordedMessages",
    "ReplayConfig",
    "ReplayResult",
    "main",
    "parse_time_ns",
    "replay",
    "select_topics",
]

log = logging.getLogger(__name__)

MEASUREMENT_KEYS: tuple[str, ...] = ("cvvc/*/meas/**",)


class ReplayConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """What to replay and how fast. ``speed`` None: as fast as possible. Times [ns], ``[start, end)``."""

    path: str
    keys: tuple[str, ...] = MEASUREMENT_KEYS
    speed: float | None = 1.0
    start_ns: int | None = None
    end_ns: int | None = None
    bus: BusConfig = BusConfig()
    wait_subscriber_s: float = 10.0


class ReplayResult(msgspec.Struct, frozen=True, kw_only=True):
    """What was published: counts per topic, the recorded span [ns], wall time [s], and the worst lateness
    of a message behind its schedule [s] (0 when as fast as possible).
    """

    messages: int
    by_topic: dict[str, int]
    first_log_time_ns: int | None
    last_log_time_ns: int | None
    wall_s: float
    max_late_s: float
    unmatched_topics: list[str]


class RecordedMessage(msgspec.Struct, frozen=True, kw_only=True):
    """One recorded message: its topic (the Zenoh key), times [ns] and the payload bytes as recorded."""

    topic: str
    log_time_ns: int
    publish_time_ns: int
    data: bytes


def _truth_on_todays_wire(raw: bytes) -> bytes:
    """A MessagePack truth (recordings of earlier versions) as Protobuf, the wire its key has today; bytes that do
    not decode go out as recorded (a subscriber refuses and counts them).
    """
    from schemas.truth import TruthDecodeError, truth_pack
    from schemas.truth_proto import encode_truth_proto

    try:
        return encode_truth_proto(truth_pack(raw, "msgpack"))
    except TruthDecodeError:
        return raw


def parse_time_ns(text: str) -> int:
    """``text`` as integer ns since the epoch, or an ISO 8601 time (no zone: UTC) converted to ns."""
    t = text.strip()
    if t.isdigit():
        return int(t)
    try:
        dt = datetime.fromisoformat(t)
    except ValueError as e:
        raise ReplayError(f"{text!r} is neither integer ns since the epoch nor an ISO 8601 time "
                          "such as 2023-07-01T12:00:00+00:00") from e
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=UTC)
    delta = dt - datetime(1970, 1, 1, tzinfo=UTC)
    return (delta.days * 86_400 + delta.seconds) * 1_000_000_000 + delta.microseconds * 1_000


def select_topics(topics: list[str], key_exprs: tuple[str, ...]) -> list[str]:
    """The topics included by at least one of the Zenoh key expressions."""
    try:
        exprs = [zenoh.KeyExpr(k) for k in key_exprs]
    except Exception as e:  # zenoh raises a plain Exception subclass for a malformed key expression
        raise ReplayError(f"invalid key expression in {list(key_exprs)}: {e}") from e
    out = []
    for topic in topics:
        try:
            ke = zenoh.KeyExpr(topic)
        except Exception:  # a topic that is not a Zenoh key cannot be republished
            continue
        if any(e.includes(ke) for e in exprs):
            out.append(topic)
    return out


class RecordedMessages:
    """The selected topics of a finished recording and their messages in ``log_time`` order.

    Use as ``with RecordedMessages(path, keys) as rec: for msg in rec: ...`` (the file is closed on leaving).
    Only ``start_ns <= log_time < end_ns`` when given. Needs a finished (indexed) file: ``UnreadableError``
    says to ``recover`` one that was cut short.
    """

    def __init__(self, path: str | Path, key_exprs: tuple[str, ...], *, start_ns: int | None = None,
                 end_ns: int | None = None) -> None:
        from mcap.reader import make_reader

        check_mcap_file(path)
        if start_ns is not None and end_ns is not None and start_ns > end_ns:
            raise ReplayError(f"--start ({start_ns}) is after --end ({end_ns})")
        self.path = str(path)
        self._start_ns = start_ns
        self._end_ns = end_ns
        self._file = open(path, "rb")  # noqa: SIM115  # closed by close()
        try:
            self._reader = make_reader(self._file)
            summary = self._reader.get_summary()
            if summary is None or not summary.chunk_indexes:
                raise UnreadableError(f"{path} has no index; run `cvvc recordings recover {path} OUT.mcap` first")
            self.topics = select_topics(sorted({c.topic for c in summary.channels.values()}), key_exprs)
        except MCAP_READ_ERRORS as e:
            self._file.close()
            raise UnreadableError(f"{path} cannot be read by index ({e}); run `cvvc recordings recover {path} "
                                  "OUT.mcap` and use OUT.mcap") from e
        except BaseException:
            self._file.close()
            raise

    def __enter__(self) -> RecordedMessages:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the MCAP file."""
        self._file.close()

    def __iter__(self) -> Iterator[RecordedMessage]:
        if not self.topics:
            return
        try:
            for _, channel, message in self._reader.iter_messages(topics=self.topics, starting_at=self._start_ns,
                                                                  ending_before=self._end_ns, log_time_order=True):
                data = bytes(message.data)
                if channel.message_encoding == "msgpack":  # the truth of an earlier version: today's wire
                    data = _truth_on_todays_wire(data)
                yield RecordedMessage(topic=channel.topic, log_time_ns=message.log_time,
                                      publish_time_ns=message.publish_time, data=data)
        except MCAP_READ_ERRORS as e:
            raise UnreadableError(f"{self.path}: a chunk cannot be read ({e}); run `cvvc recordings recover` "
                                  "to skip corrupt chunks") from e


def replay(session: zenoh.Session, config: ReplayConfig, stop: threading.Event | None = None) -> ReplayResult:
    """Publish the selected recorded messages on ``session``; returns what was published."""
    if config.speed is not None and not config.speed > 0:
        raise ReplayError(f"speed must be > 0 (or as fast as possible), got {config.speed}")
    stop = stop or threading.Event()
    with RecordedMessages(config.path, config.keys, start_ns=config.start_ns, end_ns=config.end_ns) as rec:
        if not rec.topics:
            raise ReplayError(f"{config.path} has no topic matching {list(config.keys)}; see `cvvc recordings info`")
        return _replay_topics(session, config, rec, stop)


def _replay_topics(session: zenoh.Session, config: ReplayConfig, rec: RecordedMessages,
                   stop: threading.Event) -> ReplayResult:
    topics = rec.topics
    pubs = {t: session.declare_publisher(t, encoding=zenoh_encoding(wire_of(message_type_for_key(t) or m.Message)),
                                         congestion_control=zenoh.CongestionControl.BLOCK) for t in topics}
    try:
        unmatched = _wait_matched(pubs, config.wait_subscriber_s)
        if config.wait_subscriber_s > 0 and len(unmatched) == len(topics):
            raise ReplayError(f"no subscriber for {list(config.keys)} after {config.wait_subscriber_s} s; start "
                              "the receiving program first, or pass --wait-s 0 to publish anyway")
        if unmatched and config.wait_subscriber_s > 0:
            log.warning("no subscriber for %d of %d topics (e.g. %s); replaying anyway", len(unmatched),
                        len(topics), unmatched[0])
        return _publish(pubs, iter(rec), config.speed, stop, unmatched)
    finally:
        for p in pubs.values():
            p.undeclare()


def _wait_matched(pubs: dict[str, zenoh.Publisher], timeout_s: float) -> list[str]:
    deadline = time.monotonic() + timeout_s
    while True:
        unmatched = [t for t, p in pubs.items() if not has_subscribers(p)]
        if not unmatched or time.monotonic() >= deadline:
            return unmatched
        time.sleep(0.01)


def _publish(pubs: dict[str, zenoh.Publisher], messages: Iterator[RecordedMessage], speed: float | None,
             stop: threading.Event, unmatched: list[str]) -> ReplayResult:
    counts: Counter[str] = Counter()
    first: int | None = None
    last: int | None = None
    max_late_ns = 0
    wall0 = time.perf_counter_ns()
    for msg in messages:
        if stop.is_set():
            break
        if first is None:
            first = msg.log_time_ns
        last = msg.log_time_ns
        if speed is not None:
            due = wall0 + int((msg.log_time_ns - first) / speed)
            ahead_ns = due - time.perf_counter_ns()
            if ahead_ns > 0 and stop.wait(ahead_ns / 1e9):  # pacing, interruptible by stop
                break
            max_late_ns = max(max_late_ns, time.perf_counter_ns() - due)
        pubs[msg.topic].put(msg.data)
        counts[msg.topic] += 1
    wall_s = (time.perf_counter_ns() - wall0) / 1e9
    return ReplayResult(messages=sum(counts.values()), by_topic=dict(sorted(counts.items())),
                        first_log_time_ns=first, last_log_time_ns=last, wall_s=wall_s, max_late_s=max_late_ns / 1e9,
                        unmatched_topics=unmatched)


def main(config: ReplayConfig, stop: threading.Event | None = None) -> ReplayResult:
    """Open a session from ``config.bus`` and replay."""
    with open_session(config.bus) as session:
        return replay(session, config, stop)
