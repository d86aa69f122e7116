"""The bus layer: Zenoh sessions configured safely, typed publishers, and typed, counted inboxes.

- ``BusConfig`` + ``zenoh_config``: multicast scouting always off, explicit ``tcp/127.0.0.1`` endpoints by
  default; a JSON5 config file or ``--listen`` / ``--connect`` override. ``add_bus_arguments`` gives every
  program the same flags.
- ``TypedPublisher``: refuses non-finite numbers at the sender, encodes with msgspec, puts bytes.
- ``Inbox``: Zenoh callbacks only check size, decode with the typed decoder of the key's message type and
  enqueue into one bounded queue; a bad payload is rejected with a reason, counted per topic and kind, and
  logged once per kind. Nothing raises out of a callback, and the consumer thread does the real work.
"""

from __future__ import annotations

import argparse
import itertools
import logging
import math
import queue
import re
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Generic, Literal, TypeVar

import msgspec
import msgspec.inspect
import zenoh

from schemas.bus_args import add_bus_arguments
from schemas.errors import CvvcError
from schemas.keys import message_type_for_key
from schemas.logs import RateLimitedLog
from schemas.messages import OracleReply, Wire, wire_of
from schemas.wire import typed_decoder, typed_encoder

__all__ = [
    "BadMessage",
    "BusConfig",
    "BusError",
    "Codec",
    "Inbox",
    "LivelinessWatcher",
    "NonFiniteError",
    "Received",
    "RejectCounter",
    "TypedPublisher",
    "add_bus_arguments",
    "bus_config_from_args",
    "check_finite",
    "codec_for",
    "free_port",
    "has_subscribers",
    "open_session",
    "wait_for",
    "zenoh_config",
    "zenoh_encoding",
]

log = logging.getLogger(__name__)

T = TypeVar("T", bound=msgspec.Struct)
Mode = Literal["peer", "router", "client"]
MAX_PAYLOAD_BYTES = 1 << 20  # 1 MiB: the largest frame (8500-node truth) is ~200 kB
#: The case-A oracle's reply, a query reply from the bridge alone (in secure mode, the access policy's): every zone
#: node's voltage and sensitivities to every plant and regulator, 1.49 MB as JSON on epri-ckt24 (7,516 zone nodes,
#: 3 plants, 1 regulator; measured).
MAX_ORACLE_REPLY_BYTES = 64 << 20
_MAX_BYTES: dict[type, int] = {OracleReply: MAX_ORACLE_REPLY_BYTES}
_LOOPBACK = "127.0.0.1"


class BusError(CvvcError):
    """A bus that cannot be configured or opened."""


class NonFiniteError(CvvcError, ValueError):
    """A message with NaN or infinite numbers: refused at the sender (JSON would carry null)."""


# ------------------------------------------------------------------------------------ configuration
class BusConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """How a program joins the bus. Endpoints are Zenoh locators such as ``tcp/127.0.0.1:7447``."""

    mode: Mode = "peer"
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    config_file: str | None = None
    connect_timeout_ms: int = 5000
    exit_on_failure: bool = True
    tls_dir: str | None = None  # security state directory (``cvvc security init``): mTLS + access control
    role: str | None = None  # the certificate this program presents: agent, devices, recorder or router


def zenoh_config(bus: BusConfig) -> zenoh.Config:
    """Build a ``zenoh.Config``: the file (if any), then mode and endpoints, and always no multicast scouting.

    A peer or router with no listen endpoint listens on an ephemeral port of 127.0.0.1, never on every
    interface (Zenoh's default). Peers must listen: two peers that reach each other through a router
    only exchange data once gossip has connected them directly.

    With ``tls_dir`` (the security profile, ``schemas.security``): every ``tcp/`` endpoint becomes
    ``tls/``, the session presents the certificate of ``role`` and requires mTLS; the router also gets
    the access-control policy. A peer then joins as a *client*: it never listens and talks only to the
    router, so nothing bypasses the router's policy through a direct peer-to-peer link.
    """
    if bus.config_file:
        try:
            conf = zenoh.Config.from_file(bus.config_file)
        except Exception as e:  # zenoh raises ZError, a plain Exception subclass
            raise BusError(f"{bus.config_file}: cannot read Zenoh config: {e}") from e
    else:
        conf = zenoh.Config()
    secure = bus.tls_dir is not None
    mode = "client" if secure and bus.mode == "peer" else bus.mode
    listen = list(bus.listen)
    if not listen and mode != "client":
        listen = [f"tcp/{_LOOPBACK}:0"]
    connect = list(bus.connect)
    if secure:
        listen, connect = _to_tls(listen), _to_tls(connect)
    try:
        conf.insert_json5("mode", _j(mode))
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("scouting/gossip/enabled", "false" if mode == "client" or secure else "true")
        if listen or not bus.config_file:
            conf.insert_json5("listen/endpoints", _j(listen))
        if connect or not bus.config_file:
            conf.insert_json5("connect/endpoints", _j(connect))
        if bus.connect:
            conf.insert_json5("connect/timeout_ms", _j(bus.connect_timeout_ms))
            conf.insert_json5("connect/exit_on_failure", _j(bus.exit_on_failure))
    except Exception as e:
        raise BusError(f"invalid Zenoh setting: {e}") from e
    if secure:
        _insert_security(conf, bus, policy=mode == "router")
    return conf


def _to_tls(endpoints: list[str]) -> list[str]:
    return [f"tls/{e[len('tcp/'):]}" if e.startswith("tcp/") else e for e in endpoints]


def _insert_security(conf: zenoh.Config, bus: BusConfig, *, policy: bool) -> None:
    """The role's mTLS settings; with ``policy`` (a router) the access-control policy too, whatever the role."""
    from schemas.security import SecurityError, zenoh_security_settings

    if bus.role is None:
        raise BusError("a secure session needs a role (agent, devices, recorder or router)")
    try:
        settings = zenoh_security_settings(bus.tls_dir or "", bus.role, policy=policy)
    except SecurityError as e:
        raise BusError(str(e)) from e
    for key, value in settings.items():
        try:
            conf.insert_json5(key, _j(value))
        except Exception as e:  # zenoh raises ZError, a plain Exception subclass
            raise BusError(f"invalid Zenoh security setting {key}: {e}") from e


def _j(value: Any) -> str:
    return msgspec.json.encode(value).decode()


def open_session(bus: BusConfig) -> zenoh.Session:
    """Open a session; use it as ``with open_session(bus) as session:`` so it is always closed."""
    try:
        return zenoh.open(zenoh_config(bus))
    except BusError:
        raise
    except Exception as e:
        where = ", ".join(bus.listen + bus.connect) or "an ephemeral loopback port"
        raise BusError(f"cannot open a Zenoh session on {where}: {e}") from e


def bus_config_from_args(args: argparse.Namespace, *, default_mode: Mode = "peer",
                         role: str | None = None) -> BusConfig:
    """The ``BusConfig`` of the parsed flags; ``role`` is the certificate the program presents.

    Secure by default: without ``--secure-dir`` the certificates of ``<cache>/security`` (the program's ``--cache``
    when it has one), issued on first use from a local CA created in ``<cache>/ca``
    (``schemas.security.ensure_local_security``); ``--insecure`` joins without TLS and logs a warning.
    """
    from schemas.cache import ca_dir, security_dir
    from schemas.security import INSECURE_WARNING, ensure_local_security

    mode = args.zenoh_mode or default_mode
    tls_dir = getattr(args, "secure_dir", None)
    if getattr(args, "insecure", False):
        log.warning(INSECURE_WARNING)
    elif tls_dir is None:
        cache = getattr(args, "cache", None)
        tls_dir = str(security_dir(cache))
        ensure_local_security(tls_dir, ca_dir=ca_dir(cache))
    return BusConfig(
        mode=mode,
        listen=tuple(args.listen),
        connect=tuple(args.connect),
        config_file=args.zenoh_config,
        tls_dir=tls_dir,
        role=role,
    )


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free now (for tests and the launcher)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((_LOOPBACK, 0))
        return int(s.getsockname()[1])


# ---------------------------------------------------------------------------------------- encoding
def _finite_numbers(seq: list | tuple) -> bool:
    """True if ``seq`` is a list of numbers, or of lists of numbers, all finite: their sum is then finite (a NaN
    or an infinity never leaves a float sum). False otherwise, or when a finite sum overflows: walk it then.
    One C-level pass: the oracle's reply holds tens of thousands of sensitivities.
    """
    if not seq:
        return True
    try:
        items = itertools.chain.from_iterable(seq) if isinstance(seq[0], list | tuple) else seq
        return math.isfinite(sum(items, 0.0))
    except (TypeError, OverflowError):  # not all numbers (strings, structs, deeper lists), or a huge int
        return False


def check_finite(msg: Any, path: str = "") -> None:
    """Raise ``NonFiniteError`` naming the first NaN or infinite number anywhere in ``msg``."""
    if isinstance(msg, float):
        if not math.isfinite(msg):
            raise NonFiniteError(f"non-finite value {msg!r} at {path or 'message'}; refusing to publish")
    elif isinstance(msg, msgspec.Struct):
        for name in msg.__struct_fields__:
            check_finite(getattr(msg, name), f"{path}.{name}" if path else name)
    elif isinstance(msg, list | tuple):
        if _finite_numbers(msg):
            return
        for i, v in enumerate(msg):
            check_finite(v, f"{path}[{i}]")
    elif isinstance(msg, dict):
        for k, v in msg.items():
            check_finite(v, f"{path}[{k!r}]")


class BadMessage(CvvcError):
    """A payload that did not decode into its message type. ``kind`` is a short counter label."""

    def __init__(self, kind: str, detail: str) -> None:
        super().__init__(f"{kind}: {detail}")
        self.kind = kind
        self.detail = detail


_KINDS = (
    (re.compile(r"unknown field"), "unknown_field"),
    (re.compile(r"missing required field"), "missing_field"),
    (re.compile(r"Number out of range|Expected `[^`]*` (>=|<=|>|<) |length (>=|<=)|Expected `str` matching"),
     "out_of_range"),
    (re.compile(r"Expected `"), "wrong_type"),
)


class Codec(Generic[T]):
    """A typed encoder/decoder for one message type, built once and reused: JSON, or MessagePack for the types
    whose ``schemas.messages.wire_of`` says so (``TruthPack``).
    """

    def __init__(self, msg_type: type[T], *, max_bytes: int = MAX_PAYLOAD_BYTES) -> None:
        self.msg_type = msg_type
        self.max_bytes = max_bytes
        self.wire = wire_of(msg_type)
        # the walk for NaN/inf after a decode finds nothing when every float of the type is bounded (msgspec refuses
        # NaN and inf there at decode, in JSON and MessagePack): skipped then, as the recorder does
        self._walk_after_decode = _has_unbounded_float(msgspec.inspect.type_info(msg_type), set())
        self._decoder = typed_decoder(msg_type)
        self._encoder = typed_encoder(msg_type)

    def encode(self, msg: T) -> bytes:
        """The bytes of ``msg`` (its wire: JSON, or Protobuf for the truth), after checking that every number in it
        is finite (``NonFiniteError``).
        """
        check_finite(msg)
        return self._encoder.encode(msg)

    def decode(self, data: bytes) -> T:
        """Decode or raise ``BadMessage`` with kind oversize / malformed / unknown_field / missing_field /
        wrong_type / out_of_range / non_finite.
        """
        if len(data) > self.max_bytes:
            raise BadMessage("oversize", f"{len(data)} bytes > {self.max_bytes}")
        try:
            msg = self._decoder.decode(data)
        except msgspec.ValidationError as e:
            text = str(e)
            kind = next((k for rx, k in _KINDS if rx.search(text)), "invalid")
            raise BadMessage(kind, text) from None
        except msgspec.DecodeError as e:
            raise BadMessage("malformed", str(e)) from None
        except UnicodeDecodeError as e:  # invalid UTF-8 inside a JSON string: msgspec raises this one as is
            raise BadMessage("malformed", f"invalid UTF-8: {e}") from None
        except RecursionError:  # e.g. 10,000 nested objects where a tagged struct skips unknown fields
            raise BadMessage("malformed", "JSON nested too deeply") from None
        if self._walk_after_decode:
            try:
                check_finite(msg)
            except NonFiniteError as e:
                raise BadMessage("non_finite", str(e)) from None
        return msg


def _has_unbounded_float(t: msgspec.inspect.Type, seen: set[type]) -> bool:
    """Whether a value of type ``t`` may hold a float without both a lower and an upper bound (or any value)."""
    mi = msgspec.inspect
    if isinstance(t, mi.FloatType):
        return (t.ge is None and t.gt is None) or (t.le is None and t.lt is None)
    if isinstance(t, mi.StructType):
        if t.cls in seen:
            return False
        seen.add(t.cls)
        return any(_has_unbounded_float(f.type, seen) for f in t.fields)
    if isinstance(t, mi.ListType | mi.VarTupleType | mi.SetType | mi.FrozenSetType):
        return _has_unbounded_float(t.item_type, seen)
    if isinstance(t, mi.TupleType):
        return any(_has_unbounded_float(x, seen) for x in t.item_types)
    if isinstance(t, mi.DictType):
        return _has_unbounded_float(t.value_type, seen)
    if isinstance(t, mi.UnionType):
        return any(_has_unbounded_float(x, seen) for x in t.types)
    return isinstance(t, mi.AnyType | mi.CustomType | mi.DecimalType)


_CODECS: dict[type, Codec[Any]] = {}
_CODECS_LOCK = threading.Lock()


def codec_for(msg_type: type[T]) -> Codec[T]:
    """The shared codec of a message type (built on first use)."""
    with _CODECS_LOCK:
        codec = _CODECS.get(msg_type)
        if codec is None:
            codec = _CODECS[msg_type] = Codec(msg_type, max_bytes=_MAX_BYTES.get(msg_type, MAX_PAYLOAD_BYTES))
        return codec


# --------------------------------------------------------------------------------------- publishing
def zenoh_encoding(wire: Wire) -> zenoh.Encoding:
    """The Zenoh encoding of a payload of ``wire`` (``schemas.messages.wire_of``)."""
    if wire == "protobuf":
        return zenoh.Encoding("application/protobuf")
    return zenoh.Encoding("application/msgpack") if wire == "msgpack" else zenoh.Encoding.APPLICATION_JSON


class TypedPublisher(Generic[T]):
    """A Zenoh publisher of one message type on one key.

    Measurements use congestion control DROP (the newest frame matters); commands and decisions use
    BLOCK at a high priority (they must not be lost). ``express`` (default: ``reliable``) sends each message at
    once in a batch of its own; ``express=False`` on a reliable publisher lets Zenoh batch it with what follows on
    the same priority (an express message of that priority flushes them in one write): for messages that come in
    bursts, e.g. a decision's commands just before the decision, or the acks of a decision.
    """

    def __init__(self, session: zenoh.Session, key: str, msg_type: type[T], *, reliable: bool = False,
                 express: bool | None = None) -> None:
        self.key = key
        self.codec = codec_for(msg_type)
        self._pub = session.declare_publisher(
            key,
            encoding=zenoh_encoding(self.codec.wire),
            congestion_control=zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.REAL_TIME if reliable else zenoh.Priority.DATA,
            express=reliable if express is None else express,
        )

    def put(self, msg: T) -> bytes:
        """Publish ``msg``; raises ``NonFiniteError`` (nothing is sent) if it holds NaN or inf."""
        data = self.codec.encode(msg)
        self._pub.put(data)
        return data

    @property
    def matched(self) -> bool:
        """Whether a subscriber matches this publisher now."""
        return has_subscribers(self._pub)

    def wait_matched(self, timeout_s: float) -> bool:
        """Wait until a subscriber exists (a put right after a remote declaration is often lost)."""
        return wait_for(lambda: self.matched, timeout_s)

    def undeclare(self) -> None:
        """Withdraw the publisher."""
        self._pub.undeclare()


# ---------------------------------------------------------------------------------------- receiving
class RejectCounter:
    """Thread-safe counts of rejected messages per (topic, kind).

    Logs at most one line per kind per ``log_period_s`` whatever the topic (a flood on made-up keys wrote one line
    per key); :meth:`log_suppressed` counts the lines not written, by kind.
    """

    def __init__(self, name: str = "bus", *, log_period_s: float = 10.0) -> None:
        self._lock = threading.Lock()
        self._counts: Counter[tuple[str, str]] = Counter()
        self._rlog = RateLimitedLog(logging.getLogger(f"{__name__}.{name}"), period_s=log_period_s)

    def reject(self, topic: str, kind: str, detail: str) -> None:
        """Count one rejected message on ``topic``; logged at most once per kind per ``log_period_s``."""
        with self._lock:
            self._counts[(topic, kind)] += 1
            self._rlog.warning(kind, "rejected message on %s (%s): %s", topic[:200], kind, detail[:300])

    def log_suppressed(self) -> dict[str, int]:
        """Warning lines not written by the rate limit, by kind of rejection."""
        with self._lock:
            return dict(self._rlog.suppressed)

    def total(self, kind: str | None = None) -> int:
        """Rejections counted so far, of ``kind`` or of every kind."""
        with self._lock:
            return sum(n for (_, k), n in self._counts.items() if kind is None or k == kind)

    def by_kind(self) -> dict[str, int]:
        """Rejections counted so far, by kind."""
        with self._lock:
            out: Counter[str] = Counter()
            for (_, k), n in self._counts.items():
                out[k] += n
            return dict(out)

    def by_topic(self) -> dict[str, dict[str, int]]:
        """Rejections counted so far, by topic and kind."""
        with self._lock:
            out: dict[str, dict[str, int]] = {}
            for (t, k), n in self._counts.items():
                out.setdefault(t, {})[k] = n
            return out


@dataclass(frozen=True)
class Received:
    """One accepted message: its key, the decoded message, receive wall time [ns] and the raw bytes."""

    key: str
    msg: Any
    recv_wall_ns: int
    raw: bytes


class Inbox:
    """One bounded queue fed by any number of typed subscriptions.

    The Zenoh callback decodes (about a microsecond) and enqueues; when the queue is full the *oldest*
    item is dropped and counted as ``queue_full`` (the newest measurement matters more). A ``validate``
    hook may reject decoded messages with a reason (wrong feeder, unknown device, ...).
    """

    def __init__(self, *, maxsize: int = 4096, counter: RejectCounter | None = None) -> None:
        self.queue: queue.Queue[Received] = queue.Queue(maxsize=maxsize)
        self.rejects = counter or RejectCounter("inbox")
        self.accepted = 0
        self._subs: list[Any] = []
        self._lock = threading.Lock()

    def subscribe(
        self,
        session: zenoh.Session,
        key_expr: str,
        msg_type: type[msgspec.Struct] | None = None,
        *,
        validate: Callable[[str, Any], str | None] | None = None,
    ) -> None:
        """Subscribe ``key_expr``; decode as ``msg_type`` or, if None, the type the concrete key carries."""

        def on_sample(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            try:
                raw = sample.payload.to_bytes()
                mtype = msg_type or message_type_for_key(key)
                if mtype is None:
                    self.rejects.reject(key, "unknown_key", f"no message type for key {key!r}")
                    return
                msg = codec_for(mtype).decode(raw)
                if validate is not None:
                    why = validate(key, msg)
                    if why:
                        self.rejects.reject(key, "rejected", why)
                        return
                self.put(Received(key, msg, time.time_ns(), raw))
            except BadMessage as e:
                self.rejects.reject(key, e.kind, e.detail)
            except Exception as e:  # never let anything escape into Zenoh's thread
                self.rejects.reject(key, "internal", repr(e))

        self._subs.append(session.declare_subscriber(key_expr, on_sample))

    def put(self, item: Received) -> None:
        """Enqueue ``item`` without ever blocking (safe in a Zenoh callback): when full, the oldest is dropped."""
        with self._lock:
            while True:
                try:
                    self.queue.put_nowait(item)
                    self.accepted += 1
                    return
                except queue.Full:
                    try:
                        dropped = self.queue.get_nowait()
                        self.rejects.reject(dropped.key, "queue_full", "consumer too slow; oldest dropped")
                    except queue.Empty:
                        pass

    def get(self, timeout_s: float | None = None) -> Received | None:
        """The next message, or None after ``timeout_s``."""
        try:
            return self.queue.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def drain(self) -> Iterator[Received]:
        """Every message received and not yet taken, without waiting."""
        while True:
            try:
                yield self.queue.get_nowait()
            except queue.Empty:
                return

    def undeclare(self) -> None:
        """Withdraw every subscriber of this inbox."""
        for s in self._subs:
            s.undeclare()
        self._subs.clear()


class LivelinessWatcher:
    """Tracks which liveliness tokens under a key expression are alive (history included)."""

    def __init__(self, session: zenoh.Session, key_expr: str,
                 on_change: Callable[[str, bool], None] | None = None) -> None:
        self._alive: set[str] = set()
        self._lock = threading.Lock()
        self._on_change = on_change

        def cb(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            up = sample.kind == zenoh.SampleKind.PUT
            with self._lock:
                (self._alive.add if up else self._alive.discard)(key)
            if self._on_change is not None:
                try:
                    self._on_change(key, up)
                except Exception:
                    log.exception("liveliness callback failed for %s", key)

        self._sub = session.liveliness().declare_subscriber(key_expr, cb, history=True)

    def alive(self) -> set[str]:
        """The keys whose liveliness tokens are alive now."""
        with self._lock:
            return set(self._alive)

    def is_alive(self, key: str) -> bool:
        """Whether the token ``key`` is alive now."""
        with self._lock:
            return key in self._alive

    def undeclare(self) -> None:
        """Withdraw the liveliness subscriber."""
        self._sub.undeclare()


def has_subscribers(publisher: zenoh.Publisher) -> bool:
    """Whether a subscriber matches ``publisher`` now.

    zenoh's stub types ``Publisher.matching_status`` as ``bool``; it is a ``MatchingStatus`` whose ``matching``
    says it (hence the one ignore).
    """
    return bool(publisher.matching_status.matching)  # type: ignore[attr-defined]


def wait_for(predicate: Callable[[], bool], timeout_s: float, poll_s: float = 0.005) -> bool:
    """Poll ``predicate`` until true or the deadline passes; returns its last value. Bounded, never sleeps long."""
    deadline = time.monotonic() + timeout_s
    while True:
        if predicate():
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(poll_s)
