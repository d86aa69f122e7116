"""The recorder: every sample on the bus, bytes unchanged, into an MCAP file.

File layout (docs/recordings.md):

- one channel per concrete Zenoh key (the topic is the key, e.g. ``cvvc/rural/meas/pv/pv1``), message
  encoding ``json``, with the JSON Schema of the key's message type (schema encoding ``jsonschema``, name
  ``cvvc.<Type>``, top-level ``"type": "object"`` so Foxglove can plot it); the truth (``sim/truth``,
  ``TruthPack``) is ``protobuf``, with its Protobuf schema (name ``cvvc.Truth``, encoding ``protobuf``, data a
  ``FileDescriptorSet``: ``schemas.truth_proto``), which Foxglove decodes too; ``schemas.truth`` reads it as
  arrays. Only payloads that decode into
  their key's message type (msgspec's typed decode: types, bounds, unknown fields) reach these channels;
- everything else goes to the **quarantine** channel ``cvvc.quarantine`` (schema ``cvvc.Quarantined``): the
  key, the reason and the payload (base64), so nothing is lost and nothing junk sits on a real channel: a key
  outside the cvvc layout, a payload that does not decode, or a new key past ``max_channels`` (a flood of
  made-up device ids cannot open unbounded channels);
- each message: ``log_time`` = the message's own ``t_ns`` (measurement time); a payload with no time of its own
  (``t_ns`` 0, as an agent's status before its first frame, or no valid ``t_ns``; counted) is logged at the latest
  time seen, and those before any at the first, so the file's span is the session's; ``publish_time`` = receive
  wall time [ns], ``sequence`` = the message's ``seq`` modulo 2**32 (MCAP sequences are 32-bit);
- a metadata record ``cvvc.recording`` at the start (project version, feeder fingerprint, model path, bus
  config, keys) and ``cvvc.recorder_stats`` at the end (written only when the file is finished cleanly);
- zstd chunks, closed and flushed to the OS every ``flush_period_s``: a recorder killed hard loses at
  most the last period, and ``cvvc recordings recover`` rebuilds the index of what was flushed.

Threads: the Zenoh callback only appends ``(bytes, key, receive wall ns)`` to a bounded deque (drops are
counted, never blocking Zenoh); one writer thread owns the ``mcap`` writer (it is not thread safe).
"""

from __future__ import annotations

import base64
import collections
import json
import logging
import signal
import threading
import time
from pathlib import Path
from types import FrameType, TracebackType
from typing import IO, Any

import msgspec
import zenoh
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

from recordings.errors import RecordingError
from schemas.bus import MAX_PAYLOAD_BYTES, BusConfig, open_session
from schemas.jsonschema import schema_bytes, schema_name
from schemas.keys import message_type_for_key
from schemas.messages import TruthPack, Wire, wire_of
from schemas.truth_proto import TRUTH_PROTO_NAME, truth_descriptor_set
from schemas.wire import typed_decoder

__all__ = ["METADATA_NAME", "QUARANTINE_TOPIC", "STATS_METADATA_NAME", "McapSink", "Quarantined", "Recorder",
           "RecorderConfig", "RecorderStats", "main"]

log = logging.getLogger(__name__)

METADATA_NAME = "cvvc.recording"
STATS_METADATA_NAME = "cvvc.recorder_stats"
QUARANTINE_TOPIC = "cvvc.quarantine"
"""The MCAP topic of refused samples (not a Zenoh key: it cannot collide with one)."""
MAX_CHANNELS = 512
"""Default bound on the real channels of one recording (the largest feeder here has under 40 devices)."""
_U32 = 0xFFFFFFFF
_U64_MAX = 2**64 - 1
_MAX_TIMELESS = 10_000  # messages held until the first timed one; past that, logged at their receive time


class RecorderConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """What to record and where.

    ``flush_period_s`` [s]: how often the open chunk is closed and written to the OS (the most a hard
    kill can lose). ``queue_size``: samples waiting for the writer before new ones are dropped (counted).
    ``duration_s`` [s]: stop after this long (``main`` only); None records until stopped.
    """

    out_path: str
    keys: tuple[str, ...] = ("cvvc/**",)
    bus: BusConfig = BusConfig()
    flush_period_s: float = 1.0
    queue_size: int = 200_000
    chunk_size_bytes: int = 1 << 20
    max_channels: int = MAX_CHANNELS
    feeder_fingerprint: str = ""
    model_path: str = ""
    agent_settings_json: str = ""  # the agent's settings, for the offline re-run (empty: unknown)
    duration_s: float | None = None


class RecorderStats(msgspec.Struct, frozen=True, kw_only=True):
    """Counts of one recording: written messages, drops, and ``t_ns`` fallbacks."""

    messages: int
    payload_bytes: int
    channels: int
    dropped_queue_full: int
    log_time_fallbacks: int  # payloads without a time of their own (t_ns 0 or invalid): logged at the session's
    callback_errors: int
    flushes: int
    quarantined: int = 0  # samples written to the quarantine channel instead of their key's channel


class Quarantined(msgspec.Struct, frozen=True, kw_only=True):
    """One refused sample on the quarantine channel: where it came, why it was refused, its bytes (base64)."""

    key: str
    reason: str
    payload_b64: str


class _Header(msgspec.Struct):
    """The two header fields the recorder reads; everything else in the payload is skipped unparsed."""

    t_ns: int = -1
    seq: int = 0


class McapSink:
    """The file layout of a recording, on an open binary file: one channel per key, schemas, times.

    Not thread safe (neither is the ``mcap`` writer): one thread owns it. ``Recorder`` feeds it from its
    writer thread; tests and benchmarks may use it directly to write recordings without a bus.
    """

    def __init__(self, file: IO[bytes], *, metadata: dict[str, str] | None = None,
                 chunk_size_bytes: int = 1 << 20, max_channels: int = MAX_CHANNELS) -> None:
        self._writer = Writer(file, chunk_size=chunk_size_bytes, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library=f"cvvc-edge {_version()}; {LIBRARY_IDENTIFIER}")
        if metadata is not None:
            self._writer.add_metadata(METADATA_NAME, metadata)
        self._channels: dict[str, int] = {}
        self._schemas: dict[type, int] = {}
        self._header_decoders: dict[str, Any] = {  # t_ns and seq only (the truth's: its whole decode)
            "json": msgspec.json.Decoder(_Header), "msgpack": msgspec.msgpack.Decoder(_Header),
            "protobuf": typed_decoder(TruthPack)}
        self._add = self._writer.add_message
        self._max_channels = max_channels
        self._decoders: dict[type, Any] = {}
        # key -> (channel id, decoder, message type), for the keys that have a channel
        self._routes: dict[str, tuple[int, Any, type]] = {}
        self._quarantine_channel = 0
        self.quarantined = 0
        self.messages = 0
        self.payload_bytes = 0
        self.log_time_fallbacks = 0
        self.flushes = 0
        self._clock_ns = 0  # the latest valid log time: the session's clock as far as the file knows it
        self._timeless: list[tuple[int, bytes, int, int]] = []  # (channel, raw, recv_ns, seq) before any clock

    @property
    def channels(self) -> int:
        """Channels (keys) written so far."""
        return len(self._channels)

    def write(self, raw: bytes, key: str, recv_ns: int) -> None:
        """Add one sample: ``log_time`` from its ``t_ns`` (else ``recv_ns``), ``publish_time`` = ``recv_ns``.

        A sample that does not decode into its key's message type goes to the quarantine channel instead. The one
        typed decode that checks it also gives its ``t_ns`` and ``seq``; a key's channel and decoder are looked up
        once (bounded by ``max_channels``: only keys that have a channel are kept).
        """
        route = self._routes.get(key)
        if route is None:
            msg_type = message_type_for_key(key)
            if msg_type is None:
                return self._quarantine(raw, key, recv_ns, "not a key of the cvvc layout")
            if len(self._channels) >= self._max_channels:
                return self._quarantine(raw, key, recv_ns, f"channel limit: already {self._max_channels} channels")
            decoder = self._decoder(msg_type)
        else:
            channel_id, decoder, msg_type = route
        if len(raw) > MAX_PAYLOAD_BYTES:
            return self._quarantine(raw, key, recv_ns,
                                    f"not a {msg_type.__name__}: oversize: {len(raw)} bytes > {MAX_PAYLOAD_BYTES}")
        try:  # msgspec's typed decode: types, Meta bounds, unknown or missing fields
            msg = decoder.decode(raw)
        except (msgspec.DecodeError, UnicodeDecodeError, RecursionError) as e:  # ValidationError is a DecodeError
            return self._quarantine(raw, key, recv_ns, f"not a {msg_type.__name__}: {str(e) or type(e).__name__}")
        if route is None:
            channel_id = self._register_channel(key, msg_type)
            self._routes[key] = (channel_id, decoder, msg_type)
        self._add_timed(channel_id, raw, recv_ns, msg.t_ns, msg.seq)

    def _decoder(self, msg_type: type) -> Any:
        """The typed decoder of ``msg_type`` on its wire (built once).

        msgspec's typed decode alone, without the bus codec's walk for non-finite numbers: bounded fields refuse
        inf already, and the walk tripled the cost per message on the writer thread (measured: 18 vs 5 us for a
        head frame; the recording bench fell from 0.64 to 0.21 of the bare writer).
        """
        decoder = self._decoders.get(msg_type)
        if decoder is None:
            decoder = self._decoders[msg_type] = typed_decoder(msg_type)
        return decoder

    def _quarantine(self, raw: bytes, key: str, recv_ns: int, reason: str) -> None:
        if not self._quarantine_channel:
            schema_id = self._writer.register_schema("cvvc.Quarantined", "jsonschema",
                                                     msgspec.json.encode(msgspec.json.schema(Quarantined)))
            self._quarantine_channel = self._writer.register_channel(
                QUARANTINE_TOPIC, "json", schema_id, {"cvvc_message_type": "Quarantined"})
        record = Quarantined(key=key[:1000], reason=reason[:500], payload_b64=base64.b64encode(raw).decode())
        self._write(self._quarantine_channel, msgspec.json.encode(record), recv_ns, header_of=raw,
                    wire=wire_of(message_type_for_key(key) or Quarantined))
        self.quarantined += 1

    def _write(self, channel_id: int, raw: bytes, recv_ns: int, *, header_of: bytes | None = None,
               wire: Wire = "json") -> None:
        try:
            header = self._header_decoders[wire].decode(raw if header_of is None else header_of)
            log_time, seq = header.t_ns, header.seq
        except (msgspec.DecodeError, UnicodeDecodeError, RecursionError):  # not a JSON object, t_ns/seq not
            # integers, bad UTF-8, or nested too deeply: msgspec raises the last two as they are
            log_time, seq = -1, 0
        self._add_timed(channel_id, raw, recv_ns, log_time, seq)

    def _add_timed(self, channel_id: int, raw: bytes, recv_ns: int, log_time: int, seq: int) -> None:
        """Write ``raw`` at ``log_time`` (its own ``t_ns``; not positive: the session's latest instant)."""
        self.messages += 1
        self.payload_bytes += len(raw)
        if 0 < log_time <= _U64_MAX:
            self._clock_ns = max(self._clock_ns, log_time)
            self._add(channel_id, log_time, raw, recv_ns, seq & _U32)  # positional: (channel, log, data, pub, seq)
            for held in self._timeless:  # what came before the session's first instant is logged at it
                self._add(held[0], log_time, held[1], held[2], held[3])
            self._timeless.clear()
            return
        # No time of its own (t_ns 0: an agent's status before its first frame; or no valid t_ns at all): logged
        # at the session's latest instant, so a lockstep recording of 2023 does not span to the epoch or to today.
        self.log_time_fallbacks += 1
        if self._clock_ns:
            self._add(channel_id, self._clock_ns, raw, recv_ns, seq & _U32)
        elif len(self._timeless) < _MAX_TIMELESS:
            self._timeless.append((channel_id, raw, recv_ns, seq & _U32))
        else:
            self._add(channel_id, recv_ns, raw, recv_ns, seq & _U32)

    def flush(self) -> None:
        """Close the open chunk and hand everything to the OS (survives the process being killed)."""
        self._writer.flush()
        self.flushes += 1

    def finish(self, stats: dict[str, str] | None = None) -> None:
        """Write the ``cvvc.recorder_stats`` metadata (if given), the summary and the index."""
        for channel_id, raw, recv_ns, seq in self._timeless:  # no message ever had a time: receive time
            self._add(channel_id, recv_ns, raw, recv_ns, seq)
        self._timeless.clear()
        if stats is not None:
            self._writer.add_metadata(STATS_METADATA_NAME, stats)
        self._writer.finish()

    def _register_channel(self, key: str, msg_type: type) -> int:
        schema_id = self._schemas.get(msg_type, 0)
        if not schema_id:
            if wire_of(msg_type) == "protobuf":  # the truth: its Protobuf schema, which Foxglove decodes
                schema_id = self._writer.register_schema(TRUTH_PROTO_NAME, "protobuf", truth_descriptor_set())
            else:
                schema_id = self._writer.register_schema(schema_name(msg_type), "jsonschema", schema_bytes(msg_type))
            self._schemas[msg_type] = schema_id
        channel_id = self._writer.register_channel(key, wire_of(msg_type), schema_id,
                                                   {"cvvc_message_type": msg_type.__name__})
        self._channels[key] = channel_id
        return channel_id


class Recorder:
    """Records ``config.keys`` from ``session`` into ``config.out_path`` while used as a context manager.

    The file is always finished (summary and index written) on leaving the ``with`` block, whatever the
    reason: normal exit, exception, ``KeyboardInterrupt``. The caller owns ``session``.
    """

    def __init__(self, session: zenoh.Session, config: RecorderConfig) -> None:
        if config.flush_period_s <= 0:
            raise RecordingError(f"flush_period_s must be > 0, got {config.flush_period_s}")
        self.config = config
        self._session = session
        self._queue: collections.deque[tuple[bytes, str, int]] = collections.deque()
        self._maxsize = config.queue_size
        self._drop_lock = threading.Lock()
        self._dropped = 0
        self._callback_errors = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="mcap-writer", daemon=True)
        self._subs: list[Any] = []
        self._file: IO[bytes] | None = None
        self._sink: McapSink | None = None
        self._writer_error: BaseException | None = None
        self._closed = False

    # ------------------------------------------------------------------------------------ lifecycle
    def __enter__(self) -> Recorder:
        self.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def start(self) -> None:
        """Open the file, subscribe, write the header and metadata, start the writer.

        The subscribers come before the header reaches the disk, so a file that is not empty says the recorder is
        subscribed (what starters wait on); samples arriving meanwhile wait in the queue for the writer.
        """
        try:
            self._file = open(Path(self.config.out_path), "wb")  # noqa: SIM115  # closed in close()
            self._sink = McapSink(self._file, metadata=_recording_metadata(self.config),
                                  chunk_size_bytes=self.config.chunk_size_bytes,
                                  max_channels=self.config.max_channels)
            for key in self.config.keys:
                self._subs.append(self._session.declare_subscriber(key, self._on_sample))
            self._sink.flush()
            self._thread.start()
        except OSError as e:
            self.close()
            raise RecordingError(f"cannot write {self.config.out_path}: {e}; check the directory exists "
                                 "and is writable") from e
        except BaseException:
            self.close()
            raise

    def close(self) -> RecorderStats:
        """Unsubscribe, write everything queued, finish the file. Safe to call more than once."""
        if self._closed:
            return self.stats()
        self._closed = True
        for sub in self._subs:
            try:
                sub.undeclare()
            except Exception as e:  # zenoh raises plain Exception subclasses; keep finishing the file
                log.warning("could not undeclare a recorder subscriber: %s", e)
        self._subs.clear()
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        try:
            if self._sink is not None:
                if self._writer_error is None:
                    self._drain(self._sink)  # anything the thread did not get to
                stats = {k: str(v) for k, v in msgspec.structs.asdict(self.stats()).items()}
                self._sink.finish(stats | {"stopped_wall_ns": str(time.time_ns())})
        except OSError as e:
            self._writer_error = self._writer_error or e
        finally:
            if self._file is not None:
                self._file.close()
        if self._writer_error is not None:
            raise RecordingError(f"writing {self.config.out_path} failed: {self._writer_error}; the file was "
                                 "finished with what was written before") from self._writer_error
        return self.stats()

    def stats(self) -> RecorderStats:
        """The counters so far (messages, payload bytes, channels, drops, fallbacks, errors, flushes, quarantine)."""
        sink = self._sink
        return RecorderStats(messages=sink.messages if sink else 0, payload_bytes=sink.payload_bytes if sink else 0,
                             channels=sink.channels if sink else 0, dropped_queue_full=self._dropped,
                             log_time_fallbacks=sink.log_time_fallbacks if sink else 0,
                             callback_errors=self._callback_errors, flushes=sink.flushes if sink else 0,
                             quarantined=sink.quarantined if sink else 0)

    @property
    def pending(self) -> int:
        """Samples received but not yet handed to the MCAP writer."""
        return len(self._queue)

    # ------------------------------------------------------------------------------- zenoh callback
    def _on_sample(self, sample: zenoh.Sample) -> None:
        """Runs on a Zenoh thread: enqueue only (or count a drop). Never raises."""
        try:
            if len(self._queue) >= self._maxsize:
                with self._drop_lock:
                    self._dropped += 1
                return
            self._queue.append((sample.payload.to_bytes(), str(sample.key_expr), time.time_ns()))
        except Exception:  # nothing may escape into Zenoh's thread
            with self._drop_lock:
                self._callback_errors += 1

    # -------------------------------------------------------------------------------- writer thread
    def _run(self) -> None:
        sink = self._sink
        if sink is None:
            return
        period = self.config.flush_period_s
        next_flush = time.monotonic() + period
        try:
            while True:
                stopping = self._stop.is_set()  # read before draining: nothing is enqueued after stop
                wrote = self._drain(sink)
                now = time.monotonic()
                if now >= next_flush:
                    sink.flush()
                    next_flush = now + period
                if stopping:
                    return
                if not wrote:
                    self._stop.wait(min(0.005, max(0.0, next_flush - now)))
        except Exception as e:  # disk full, ...: reported by close(), which finishes the file
            log.error("MCAP writer failed: %s", e)
            self._writer_error = e

    def _drain(self, sink: McapSink) -> int:
        n = 0
        pop = self._queue.popleft
        write = sink.write
        while True:
            try:
                raw, key, recv_ns = pop()
            except IndexError:
                return n
            write(raw, key, recv_ns)
            n += 1


def _version() -> str:
    from schemas.version import __version__

    return __version__


def _recording_metadata(config: RecorderConfig) -> dict[str, str]:
    return {
        "project_version": _version(),
        "feeder_fingerprint": config.feeder_fingerprint,
        # absolute: the recording names its model wherever it is read from (replay also looks beside the file)
        "model_path": str(Path(config.model_path).resolve()) if config.model_path else "",
        "agent_settings": config.agent_settings_json,
        "bus_config": msgspec.json.encode(config.bus).decode(),
        "keys": json.dumps(list(config.keys)),
        "flush_period_s": repr(config.flush_period_s),
        "started_wall_ns": str(time.time_ns()),
        "log_time": "message t_ns (receive wall time when absent)",
        "publish_time": "receive wall time",
    }


def main(config: RecorderConfig, stop: threading.Event | None = None) -> RecorderStats:
    """Record until ``stop`` is set, ``config.duration_s`` has passed, or SIGINT/SIGTERM; return the counts.

    Signal handlers are installed only when called from the main thread (and restored afterwards).
    """
    stop = stop or threading.Event()
    previous: dict[signal.Signals, Any] = {}
    if threading.current_thread() is threading.main_thread():
        def on_signal(signum: int, frame: FrameType | None) -> None:
            stop.set()

        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, on_signal)
    try:
        with open_session(config.bus) as session, Recorder(session, config) as recorder:
            deadline = None if config.duration_s is None else time.monotonic() + config.duration_s
            while not stop.is_set():
                timeout = 0.5 if deadline is None else min(0.5, deadline - time.monotonic())
                if timeout <= 0:
                    break
                stop.wait(timeout)
        return recorder.stats()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
