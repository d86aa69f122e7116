"""The typed encoder and decoder of a message type on its wire (``schemas.messages.wire_of``): JSON for every
message but the truth, Protobuf for the truth (``schemas.truth_proto``), MessagePack for a truth of an earlier
version's recordings. One place, so the bus codec, the bridge's publishers, the recorder and the readers agree.
"""

from __future__ import annotations

from typing import Any

import msgspec

from schemas.messages import Wire, wire_of

__all__ = ["typed_decoder", "typed_encoder"]


def typed_decoder(msg_type: type, wire: Wire | None = None) -> Any:
    """An object whose ``decode(raw)`` gives a ``msg_type`` checked against its bounds (``msgspec.DecodeError``,
    ``ValidationError`` when not), for ``wire`` (default: the type's own).
    """
    wire = wire or wire_of(msg_type)
    if wire == "protobuf":
        from schemas.truth_proto import TruthProtoDecoder

        return TruthProtoDecoder()
    return msgspec.msgpack.Decoder(msg_type) if wire == "msgpack" else msgspec.json.Decoder(msg_type)


def typed_encoder(msg_type: type) -> Any:
    """An object whose ``encode(msg)`` gives the bytes of a ``msg_type`` on its own wire."""
    wire = wire_of(msg_type)
    if wire == "protobuf":
        from schemas.truth_proto import TruthProtoEncoder

        return TruthProtoEncoder()
    return msgspec.msgpack.Encoder() if wire == "msgpack" else msgspec.json.Encoder()
