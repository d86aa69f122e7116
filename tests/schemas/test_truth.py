"""The compact truth frame (``TruthPack``): packing, Protobuf on the bus and in recordings (with the schema
Foxglove reads), the checks on decode, the readers of every encoding it was recorded in."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from schemas import messages as m
from schemas.bus import BadMessage, codec_for
from schemas.examples import examples
from schemas.truth import TruthDecodeError, decode_truth, to_truth_frame, truth_arrays

RNG = np.random.default_rng(7)
V = np.concatenate([[0.0, 3.0, 1.0, 0.5], RNG.uniform(0.9, 1.1, 1279)])  # the bounds, and a feeder's spread


def _pack(v: np.ndarray = V, **kw: object) -> m.TruthPack:
    fields: dict = dict(t_ns=1_673_845_200_000_000_000, seq=1, source="bridge", feeder_id="rural", n_nodes=len(v),
                        v_pu_f32=m.pack_v_pu(v), v_min_pu=float(v.min()), v_max_pu=float(v.max()),
                        node_names=[f"n{i}.1" for i in range(len(v))], taps=[3, -2], pv_q_kvar=[12.5, -40.0],
                        cap_states=[1])
    fields.update(kw)
    return m.TruthPack(**fields)


def test_voltages_come_back_within_float32_rounding_and_bounds_exactly():
    back = m.unpack_v_pu(m.pack_v_pu(V), len(V))
    assert back.dtype == np.float64 and back.shape == V.shape
    np.testing.assert_array_equal(back, V.astype(np.float32).astype(np.float64))  # exactly float32's value
    assert np.abs(back - V).max() <= 6e-8  # half a float32 ulp below 2 pu: 2**-24
    assert back[:4].tolist() == [0.0, 3.0, 1.0, 0.5]  # representable values are kept exactly


def test_layout_is_byte_planes_of_little_endian_float32():
    raw = m.pack_v_pu(np.array([1.0, 2.0]))  # 1.0 = 00 00 80 3f, 2.0 = 00 00 00 40 (little endian)
    assert raw == bytes([0, 0, 0, 0, 0x80, 0, 0x3F, 0x40])


def test_a_frame_is_protobuf_a_quarter_of_its_json_form_and_round_trips_on_the_bus_codec():
    pack = _pack()
    codec = codec_for(m.TruthPack)
    assert codec.wire == "protobuf"
    raw = codec.encode(pack)
    assert codec.decode(raw) == pack
    later = _pack(node_names=None)  # the names go on the first frame only
    assert len(codec.encode(later)) < 0.3 * len(msgspec.json.encode(to_truth_frame(later)))
    assert 4 * len(V) < len(codec.encode(later)) < 4 * len(V) + 200  # float32 voltages, packed
    arrays = decode_truth(raw, "protobuf")
    np.testing.assert_array_equal(arrays.v_pu, m.unpack_v_pu(pack.v_pu_f32, pack.n_nodes))
    assert arrays.taps.tolist() == [3, -2] and arrays.cap_states.tolist() == [1]
    assert arrays.pv_q_kvar.tolist() == [12.5, -40.0] and arrays.node_names == tuple(pack.node_names or ())


def test_the_protobuf_bytes_are_what_the_schema_in_the_recording_describes():
    """A reader that knows nothing but the FileDescriptorSet (as Foxglove) decodes the frame into named fields."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    from schemas.truth_proto import TRUTH_PROTO_NAME, truth_descriptor_set

    pool = descriptor_pool.DescriptorPool()
    for f in descriptor_pb2.FileDescriptorSet.FromString(truth_descriptor_set()).file:
        pool.Add(f)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(TRUTH_PROTO_NAME))
    pack = _pack()
    msg = cls.FromString(codec_for(m.TruthPack).encode(pack))
    assert (msg.t_ns, msg.seq, msg.source, msg.feeder_id) == (pack.t_ns, pack.seq, "bridge", "rural")
    np.testing.assert_array_equal(np.asarray(msg.v_pu, dtype=np.float64), m.unpack_v_pu(pack.v_pu_f32, pack.n_nodes))
    assert list(msg.taps) == [3, -2] and list(msg.pv_q_kvar) == [12.5, -40.0] and list(msg.cap_states) == [1]
    assert list(msg.node_names) == pack.node_names and (msg.v_min_pu, msg.v_max_pu) == (pack.v_min_pu, pack.v_max_pu)


def test_recordings_of_the_messagepack_form_still_read_as_arrays():
    pack = _pack()
    arrays = decode_truth(msgspec.msgpack.encode(pack), "msgpack")
    np.testing.assert_array_equal(arrays.v_pu, m.unpack_v_pu(pack.v_pu_f32, pack.n_nodes))
    assert arrays.taps.tolist() == [3, -2] and arrays.node_names == tuple(pack.node_names or ())


def test_recordings_made_before_the_compact_form_still_read_as_arrays():
    old = examples()[m.TruthFrame]
    arrays = decode_truth(msgspec.json.encode(old), "json")
    assert arrays.v_pu.tolist() == old.v_pu and arrays.taps.tolist() == old.taps
    assert (arrays.t_ns, arrays.seq, arrays.v_min_pu) == (old.t_ns, old.seq, old.v_min_pu)


def test_the_json_form_holds_the_same_numbers():
    pack = _pack()
    frame = to_truth_frame(pack)
    assert frame.v_pu == m.unpack_v_pu(pack.v_pu_f32, pack.n_nodes).tolist()
    assert (frame.t_ns, frame.seq, frame.node_names, frame.taps, frame.cap_states) == (
        pack.t_ns, pack.seq, pack.node_names, pack.taps, pack.cap_states)
    assert msgspec.json.decode(msgspec.json.encode(frame), type=m.TruthFrame) == frame  # valid TruthFrame JSON


def _raw(**change: object) -> bytes:
    good = msgspec.to_builtins(_pack(), enc_hook=None)
    good["v_pu_f32"] = _pack().v_pu_f32  # to_builtins base64-encodes bytes: keep them raw for msgpack
    return msgspec.msgpack.encode({**good, **change})


@pytest.mark.parametrize(("label", "payload"), [
    ("not msgpack", b"\xc1\xc1"),
    ("empty", b""),
    ("json text", msgspec.json.encode(examples()[m.TruthFrame])),  # "{" is a msgpack integer
    ("a byte short", _raw(v_pu_f32=m.pack_v_pu(V)[:-1])),
    ("one node more than the bytes", _raw(n_nodes=len(V) + 1)),
    ("NaN voltage", _raw(v_pu_f32=m.pack_v_pu(np.r_[V[:-1], math.nan]))),
    ("voltage above 3 pu", _raw(v_pu_f32=m.pack_v_pu(np.r_[V[:-1], 3.5]))),
    ("negative voltage", _raw(v_pu_f32=m.pack_v_pu(np.r_[V[:-1], -0.1]))),
    ("names for other nodes", _raw(node_names=["a.1"])),
    ("unknown layout", _raw(layout="f16")),
    ("unknown field", _raw(surprise=1)),
    ("voltages as a list", _raw(v_pu_f32=[1.0, 1.0])),
    ("negative t_ns", _raw(t_ns=-1)),
    ("tap out of range", _raw(taps=[40])),
])
def test_a_bad_messagepack_truth_of_an_old_recording_is_a_clear_error(label, payload):
    with pytest.raises(TruthDecodeError, match=r"not a truth frame \(msgpack\)"):
        decode_truth(payload, "msgpack")


def _proto(**change: object) -> bytes:
    from schemas.truth_proto import _truth_class

    fields: dict = dict(t_ns=1_673_845_200_000_000_000, seq=1, source="bridge", feeder_id="rural", v_pu=V.tolist(),
                        v_min_pu=0.0, v_max_pu=3.0, taps=[3, -2], pv_q_kvar=[12.5, -40.0], cap_states=[1])
    return _truth_class()(**{**fields, **change}).SerializeToString()


@pytest.mark.parametrize(("label", "payload", "kind"), [
    ("not protobuf", b"\xff\xff", "malformed"),
    ("json text", msgspec.json.encode(examples()[m.TruthFrame]), "malformed"),
    ("empty: no source", b"", "out_of_range"),
    ("NaN voltage", _proto(v_pu=[*V[:-1].tolist(), math.nan]), "invalid"),
    ("voltage above 3 pu", _proto(v_pu=[*V[:-1].tolist(), 3.5]), "invalid"),
    ("negative voltage", _proto(v_pu=[*V[:-1].tolist(), -0.1]), "invalid"),
    ("names for other nodes", _proto(node_names=["a.1"]), "invalid"),
    ("negative t_ns", _proto(t_ns=-1), "out_of_range"),
    ("seq beyond int64", _proto(seq=2**64 - 1), "out_of_range"),
    ("tap out of range", _proto(taps=[40]), "out_of_range"),
    ("infinite Q", _proto(pv_q_kvar=[math.inf, 0.0]), "out_of_range"),
    ("a feeder id with a space", _proto(feeder_id="a b"), "out_of_range"),
])
def test_bad_payload_is_rejected_with_kind(label, payload, kind):
    with pytest.raises(BadMessage) as e:
        codec_for(m.TruthPack).decode(payload)
    assert e.value.kind == kind, str(e.value)
    with pytest.raises(TruthDecodeError):
        decode_truth(payload, "protobuf")


def test_an_unknown_encoding_is_named():
    with pytest.raises(TruthDecodeError, match="not 'cbor'"):
        decode_truth(b"", "cbor")


def test_the_arrays_do_not_share_the_message():
    pack = _pack()
    a = truth_arrays(pack)
    a.v_pu[0] = 2.0
    assert truth_arrays(pack).v_pu[0] == 0.0


def test_a_frames_feeder_id_reads_alone():
    """The feeder id of a frame's Protobuf bytes, as the whole decode gives it; None without one; not Protobuf: the
    decoders' error."""
    from schemas.truth_proto import truth_feeder_id

    raw = _proto()
    assert truth_feeder_id(raw) == codec_for(m.TruthPack).decode(raw).feeder_id == "rural"
    assert truth_feeder_id(b"") is None
    with pytest.raises(msgspec.DecodeError):
        truth_feeder_id(b"\xff\xff")
