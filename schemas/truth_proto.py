"""The truth (``sim/truth``) as Protobuf: the bus's and the recordings' encoding of ``TruthPack``, which Foxglove
decodes from the schema the recording carries (``cvvc.Truth``, a ``FileDescriptorSet``).

The message, proto3 (field numbers are the contract: never renumber, only add)::

    message Truth {
      int64 t_ns = 1; uint64 seq = 2; string source = 3; string feeder_id = 4;
      repeated float v_pu = 5;          // every node's voltage [pu of its nominal L-N], float32, packed
      double v_min_pu = 6; double v_max_pu = 7;
      repeated string node_names = 8;   // the first frame only (none: not repeated)
      repeated sint32 taps = 9;         // regulator taps, device-map order
      repeated double pv_q_kvar = 10;   // each plant's Q [kvar], + injects
      repeated uint32 cap_states = 11;  // each bank's closed steps
    }

In Python the message stays a ``schemas.messages.TruthPack`` (its float32 voltages as byte planes):
:func:`encode_truth_proto` writes one, :func:`decode_truth_proto` reads one back and checks it as the typed
decoders of the other messages do (a bad payload is a ``msgspec.DecodeError``, a value out of bounds its
``ValidationError``), so the bus codec, the recorder and the readers treat it like any other wire.
"""

from __future__ import annotations

from functools import cache
from typing import Any

import msgspec
import numpy as np

from schemas import messages as m

__all__ = ["TRUTH_PROTO_NAME", "TruthProtoDecoder", "TruthProtoEncoder", "decode_truth_proto", "encode_truth_proto",
           "truth_descriptor_set", "truth_feeder_id"]

TRUTH_PROTO_NAME = "cvvc.Truth"
"""The Protobuf message's full name: the MCAP schema name of a ``sim/truth`` channel (schema encoding ``protobuf``)."""

_FIELDS: tuple[tuple[str, str, bool], ...] = (  # (name, type, repeated), numbered from 1 in this order
    ("t_ns", "int64", False), ("seq", "uint64", False), ("source", "string", False), ("feeder_id", "string", False),
    ("v_pu", "float", True), ("v_min_pu", "double", False), ("v_max_pu", "double", False),
    ("node_names", "string", True), ("taps", "sint32", True), ("pv_q_kvar", "double", True),
    ("cap_states", "uint32", True))


def _file_descriptor():
    from google.protobuf import descriptor_pb2

    f = descriptor_pb2.FieldDescriptorProto
    fd = descriptor_pb2.FileDescriptorProto(name="cvvc/truth.proto", package="cvvc", syntax="proto3")
    msg = fd.message_type.add(name="Truth")
    for number, (name, typ, repeated) in enumerate(_FIELDS, start=1):
        msg.field.add(name=name, number=number, type=getattr(f, f"TYPE_{typ.upper()}"), json_name=_camel(name),
                      label=f.LABEL_REPEATED if repeated else f.LABEL_OPTIONAL)
    return fd


def _camel(name: str) -> str:
    head, *rest = name.split("_")
    return head + "".join(p.capitalize() for p in rest)


@cache
def _truth_class() -> Any:
    from google.protobuf import descriptor_pool, message_factory

    pool = descriptor_pool.DescriptorPool()
    pool.Add(_file_descriptor())
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(TRUTH_PROTO_NAME))


@cache
def truth_descriptor_set() -> bytes:
    """The serialized ``google.protobuf.FileDescriptorSet`` of ``cvvc.Truth``: the MCAP schema data of the channel."""
    from google.protobuf import descriptor_pb2

    return descriptor_pb2.FileDescriptorSet(file=[_file_descriptor()]).SerializeToString()


def encode_truth_proto(msg: m.TruthPack) -> bytes:
    """The Protobuf bytes of a truth frame (the voltages as the float32 values ``msg`` holds)."""
    v = m.unpack_v_pu(msg.v_pu_f32, msg.n_nodes)
    return _truth_class()(
        t_ns=msg.t_ns, seq=msg.seq, source=msg.source, feeder_id=msg.feeder_id, v_pu=v.tolist(),
        v_min_pu=msg.v_min_pu, v_max_pu=msg.v_max_pu, node_names=msg.node_names or (), taps=msg.taps,
        pv_q_kvar=msg.pv_q_kvar, cap_states=msg.cap_states).SerializeToString()


def decode_truth_proto(raw: bytes) -> m.TruthPack:
    """A ``TruthPack`` from its Protobuf bytes, checked like every typed decode.

    Raises
    ------
    msgspec.ValidationError
        A field out of its bounds (a voltage outside 0..3 pu or NaN, a tap beyond ±16, node names that do not
        match the voltages, ...).
    msgspec.DecodeError
        Bytes that are not a ``cvvc.Truth`` message.
    """
    p = _parse(raw)
    v = np.asarray(p.v_pu, dtype="<f4")
    fields = {"t_ns": p.t_ns, "seq": p.seq, "source": p.source, "feeder_id": p.feeder_id, "n_nodes": int(v.size),
              "v_pu_f32": m.pack_v_pu(v), "v_min_pu": p.v_min_pu, "v_max_pu": p.v_max_pu,
              "node_names": list(p.node_names) or None, "taps": list(p.taps), "pv_q_kvar": list(p.pv_q_kvar),
              "cap_states": list(p.cap_states)}
    try:
        return msgspec.convert(fields, m.TruthPack)
    except ValueError as e:  # __post_init__'s own check, as msgspec reports it on a decode
        raise msgspec.ValidationError(str(e)) from None


def truth_feeder_id(raw: bytes) -> str | None:
    """The ``feeder_id`` of a truth frame's Protobuf bytes, the rest left unchecked and unconverted (a recording's
    check of which feeder each message is of); None when it has none.

    Raises
    ------
    msgspec.DecodeError
        Bytes that are not a ``cvvc.Truth`` message.
    """
    return _parse(raw).feeder_id or None


def _parse(raw: bytes) -> Any:
    """The ``cvvc.Truth`` message of ``raw``; ``msgspec.DecodeError`` when it is not one."""
    from google.protobuf.message import DecodeError

    p = _truth_class()()
    try:
        p.ParseFromString(raw)
    except (DecodeError, ValueError, TypeError) as e:
        raise msgspec.DecodeError(f"not a {TRUTH_PROTO_NAME} Protobuf message: {e}") from None
    return p


class TruthProtoEncoder:
    """``encode(msg) -> bytes``, the shape of msgspec's encoders, for the ``protobuf`` wire."""

    def encode(self, msg: m.TruthPack) -> bytes:
        """:func:`encode_truth_proto`."""
        return encode_truth_proto(msg)


class TruthProtoDecoder:
    """``decode(raw) -> TruthPack``, the shape of msgspec's typed decoders, for the ``protobuf`` wire."""

    def decode(self, raw: bytes) -> m.TruthPack:
        """:func:`decode_truth_proto`."""
        return decode_truth_proto(raw)
