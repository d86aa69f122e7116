"""Property-based fuzzing of every decoder: ``schemas.bus.codec_for(T).decode`` for each message type.

The property: whatever bytes arrive, ``decode`` either returns a valid message of its type (finite, and
re-encoding it gives an equal message) or raises ``BadMessage`` with one of the documented kinds; never
anything else (no ``RecursionError``, ``MemoryError``, ``UnicodeDecodeError``, ``ValueError``...). Inputs:
arbitrary bytes, byte-level mutations of valid messages, random JSON values, field-level mutations (wrong
types, deleted and unknown fields, out-of-range and non-finite numbers, NaN/Infinity literals), oversize
payloads and deep nesting. Hypothesis runs derandomized (a fixed seed per test) so CI is deterministic.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from typing import Any

import msgspec
import pytest
from hypothesis import HealthCheck, given, reject, settings
from hypothesis import strategies as st

from schemas.bus import MAX_ORACLE_REPLY_BYTES, MAX_PAYLOAD_BYTES, BadMessage, codec_for
from schemas.examples import examples
from schemas.messages import MESSAGE_TYPES, OracleReply, TruthPack, pack_v_pu, unpack_v_pu, wire_of

KINDS = {"oversize", "malformed", "unknown_field", "missing_field", "wrong_type", "out_of_range", "non_finite",
         "invalid"}
FUZZ = settings(max_examples=60, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
TYPES = pytest.mark.parametrize("msg_type", MESSAGE_TYPES, ids=lambda t: t.__name__)
EXAMPLES = examples()
#: Outcomes over the whole module, checked by the last test (every rejection kind must have been exercised).
OUTCOMES: Counter[str] = Counter()


def _check(msg_type: type, data: bytes) -> str:
    """Decode ``data``; the outcome is ``ok`` or the BadMessage kind. Anything else fails the test."""
    codec = codec_for(msg_type)
    try:
        msg = codec.decode(data)
    except BadMessage as e:
        assert e.kind in KINDS, e
        OUTCOMES[e.kind] += 1
        return e.kind
    assert isinstance(msg, msg_type)
    assert codec.decode(codec.encode(msg)) == msg  # valid means: finite, in range, and round-trips
    OUTCOMES["ok"] += 1
    return "ok"


def _valid(msg_type: type) -> bytes:
    return codec_for(msg_type).encode(EXAMPLES[msg_type])


def _builtins(msg_type: type) -> dict[str, Any]:
    if _PROTOBUF(msg_type):  # the truth: the fields of its Protobuf message (cvvc.Truth)
        ex = EXAMPLES[msg_type]
        return {"t_ns": ex.t_ns, "seq": ex.seq, "source": ex.source, "feeder_id": ex.feeder_id,
                "v_pu": unpack_v_pu(ex.v_pu_f32, ex.n_nodes).tolist(), "v_min_pu": ex.v_min_pu,
                "v_max_pu": ex.v_max_pu, "node_names": list(ex.node_names or []), "taps": list(ex.taps),
                "pv_q_kvar": list(ex.pv_q_kvar), "cap_states": list(ex.cap_states)}
    return msgspec.to_builtins(EXAMPLES[msg_type])


def _PROTOBUF(msg_type: type) -> bool:  # noqa: N802  (reads as a constant test)
    return wire_of(msg_type) == "protobuf"


def _wire(msg_type: type, tree: Any) -> bytes:
    """``tree`` in ``msg_type``'s wire: JSON text, or Protobuf (the truth); a value the Protobuf field cannot hold
    (a string for a number, an integer beyond 64 bits...) is not a case for it: the example is skipped."""
    if not _PROTOBUF(msg_type):
        return json.dumps(tree).encode()
    from schemas.truth_proto import _truth_class

    try:
        return _truth_class()(**tree).SerializeToString()
    except (TypeError, ValueError, OverflowError):
        reject()
        raise


json_values = st.recursive(
    st.none() | st.booleans() | st.integers(min_value=-(2**70), max_value=2**70)
    | st.floats(allow_nan=False, allow_infinity=False) | st.text(max_size=40),
    lambda children: st.lists(children, max_size=5) | st.dictionaries(st.text(max_size=12), children, max_size=5),
    max_leaves=25,
)


def _paths(value: Any, prefix: tuple = ()) -> list[tuple]:
    """Every path (tuple of keys / indices) to a value inside a JSON-like tree, the root excluded."""
    out: list[tuple] = []
    if isinstance(value, dict):
        for k, v in value.items():
            out.append(prefix + (k,))
            out += _paths(v, prefix + (k,))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            out.append(prefix + (i,))
            out += _paths(v, prefix + (i,))
    return out


def _set(tree: Any, path: tuple, value: Any) -> None:
    for p in path[:-1]:
        tree = tree[p]
    tree[path[-1]] = value


def _delete(tree: Any, path: tuple) -> None:
    for p in path[:-1]:
        tree = tree[p]
    del tree[path[-1]]


# ------------------------------------------------------------------------------------------ properties
@TYPES
def test_valid_examples_decode(msg_type: type) -> None:
    assert _check(msg_type, _valid(msg_type)) == "ok"
    assert codec_for(msg_type).decode(_valid(msg_type)) == EXAMPLES[msg_type]


@TYPES
@FUZZ
@given(data=st.binary(max_size=4096))
def test_arbitrary_bytes(msg_type: type, data: bytes) -> None:
    _check(msg_type, data)


@TYPES
@FUZZ
@given(ops=st.lists(st.tuples(st.sampled_from(["flip", "delete", "insert", "truncate", "duplicate"]),
                              st.integers(min_value=0, max_value=10**6), st.integers(min_value=0, max_value=255)),
                    min_size=1, max_size=8))
def test_mutated_valid_json(msg_type: type, ops: list[tuple[str, int, int]]) -> None:
    data = bytearray(_valid(msg_type))
    for op, pos, byte in ops:
        i = pos % max(len(data), 1)
        match op:
            case "flip":
                if data:
                    data[i] ^= 1 << (byte % 8)
            case "delete":
                del data[i:i + 1 + byte % 8]
            case "insert":
                data[i:i] = bytes([byte])
            case "truncate":
                del data[i:]
            case "duplicate":
                data[i:i] = data[i:i + 1 + byte % 32]
    _check(msg_type, bytes(data))


@TYPES
@FUZZ
@given(value=json_values)
def test_random_json_values(msg_type: type, value: Any) -> None:
    assert _check(msg_type, json.dumps(value).encode()) != "ok" or isinstance(value, dict)


@TYPES
@FUZZ
@given(data=st.data())
def test_field_mutations(msg_type: type, data: st.DataObject) -> None:
    """One field of a valid message replaced by a random value, deleted, or joined by an unknown field."""
    tree = _builtins(msg_type)
    paths = _paths(tree)
    action = data.draw(st.sampled_from(["replace", "delete", "unknown"]))
    if action == "unknown" and _PROTOBUF(msg_type):
        return  # Protobuf readers skip unknown field numbers by design; a name of no field cannot be encoded
    if action == "unknown":
        tree[data.draw(st.text(min_size=1, max_size=12).filter(lambda k: k not in tree))] = data.draw(json_values)
        assert _check(msg_type, _wire(msg_type, tree)) == "unknown_field"
        return
    path = data.draw(st.sampled_from(paths))
    if action == "delete":
        _delete(tree, path)
    else:
        _set(tree, path, data.draw(json_values))
    _check(msg_type, _wire(msg_type, tree))


BAD_NUMBERS = ["NaN", "nan", "Infinity", "-Infinity", "inf", "1e999", "-1e999", "1e309", "9" * 400,
               "-9223372036854775809", "18446744073709551616", "1e-400", "0x10", "+1", "01", ".5", "1.", "-"]


@TYPES
@FUZZ
@given(data=st.data())
def test_bad_number_literals(msg_type: type, data: st.DataObject) -> None:
    """Every number of a valid message, in turn, replaced by a non-finite, huge or invalid literal."""
    tree = _builtins(msg_type)
    numeric = [p for p in _paths(tree) if _get(tree, p).__class__ in (int, float)]
    if not numeric:
        return
    path = data.draw(st.sampled_from(numeric))
    if _PROTOBUF(msg_type):  # no literals in Protobuf: the non-finite and absurd numbers themselves
        _set(tree, path, data.draw(st.sampled_from([math.nan, math.inf, -math.inf, 1e308, -(2**63), 2**64 - 1])))
        kind = _check(msg_type, _wire(msg_type, tree))
        assert kind != "ok" or path in (("seq",), ("t_ns",)) or abs(_get(tree, path)) < 1e300, path
        return
    literal = data.draw(st.sampled_from(BAD_NUMBERS))
    marker = "__FUZZ_NUMBER__"
    _set(tree, path, marker)
    raw = json.dumps(tree).replace(f'"{marker}"', literal).encode()
    kind = _check(msg_type, raw)
    if literal in ("NaN", "nan", "Infinity", "-Infinity", "inf", "1e999", "-1e999", "1e309", "9" * 400):
        assert kind != "ok", literal  # never a non-finite or absurd number inside a message


def _get(tree: Any, path: tuple) -> Any:
    for p in path:
        tree = tree[p]
    return tree


@TYPES
@FUZZ
@given(value=st.floats(allow_nan=False) | st.integers(min_value=-(2**80), max_value=2**80))
def test_out_of_range_numbers(msg_type: type, value: float) -> None:
    """Any number in the first numeric field: accepted only within its bounds, and then finite."""
    tree = _builtins(msg_type)
    numeric = [p for p in _paths(tree) if isinstance(_get(tree, p), int | float) and not isinstance(_get(tree, p),
                                                                                                   bool)]
    for path in numeric[:3]:
        _set(tree, path, value)
    if _PROTOBUF(msg_type):
        raw = _wire(msg_type, tree)
    else:
        raw = (json.dumps(tree).encode() if math.isfinite(value)
               else json.dumps(tree).replace("Infinity", "1e999").encode())
    if _check(msg_type, raw) == "ok":
        assert math.isfinite(value) and abs(value) < 2**63


@TYPES
@pytest.mark.parametrize("depth", [100, 10_000, 200_000])
def test_deep_nesting(msg_type: type, depth: int) -> None:
    """Nested arrays and objects as a whole payload and inside a field: rejected, no RecursionError."""
    if _PROTOBUF(msg_type):  # Protobuf: groups (field 1, start 0x0b / end 0x0c) nested, and JSON's nesting
        assert _check(msg_type, b"\x0b" * depth + b"\x0c" * depth) != "ok"
        assert _check(msg_type, b"\x0b" * depth) != "ok"  # unterminated
        assert _check(msg_type, b"[" * depth + b"]" * depth) != "ok"
        return
    assert _check(msg_type, b"[" * depth + b"]" * depth) != "ok"
    assert _check(msg_type, b'{"a":' * depth + b"1" + b"}" * depth) != "ok"
    tree = _builtins(msg_type)
    first = next(iter(tree))
    raw = json.dumps(tree).replace(f'"{first}": ', f'"{first}": ' + "[" * depth, 1) + "]" * depth
    assert _check(msg_type, raw.encode()) != "ok"
    assert _check(msg_type, b"[" * depth) != "ok"  # unterminated


def test_oversize_truth_is_refused_before_parsing() -> None:
    """Protobuf cannot be padded: the largest truth frame within the limit decodes, four bytes more do not."""
    limit = codec_for(TruthPack).max_bytes

    def raw(n: int) -> bytes:
        return codec_for(TruthPack).encode(msgspec.structs.replace(EXAMPLES[TruthPack], n_nodes=n, node_names=None,
                                                                   v_pu_f32=pack_v_pu([1.0] * n)))

    n = (limit - len(raw(0))) // 4
    while len(raw(n)) > limit:
        n -= 1
    assert len(raw(n)) <= limit < len(raw(n + 1))
    assert _check(TruthPack, raw(n)) == "ok" and _check(TruthPack, raw(n + 1)) == "oversize"


@TYPES
def test_oversize_is_refused_before_parsing(msg_type: type) -> None:
    valid, limit = _valid(msg_type), codec_for(msg_type).max_bytes  # 1 MiB; the oracle's reply has its own
    assert limit == (MAX_ORACLE_REPLY_BYTES if msg_type is OracleReply else MAX_PAYLOAD_BYTES)
    if _PROTOBUF(msg_type):  # JSON padding: TruthPack's own test above
        return
    padded = valid[:-1] + b" " * (limit - len(valid) + 1) + b"}"
    assert len(padded) > limit and _check(msg_type, padded) == "oversize"
    assert _check(msg_type, valid[:-1] + b" " * (limit - len(valid)) + b"}") == "ok"  # at the limit


@TYPES
def test_valid_examples_still_decode_after_the_fuzzing(msg_type: type) -> None:
    assert codec_for(msg_type).decode(_valid(msg_type)) == EXAMPLES[msg_type]


def test_every_rejection_kind_was_exercised() -> None:
    """Every kind the decoder reports is produced (by the fuzzers above when the module runs, and by a fixed
    corpus here so the test stands alone).
    """
    hv = msgspec.json.encode(EXAMPLES[MESSAGE_TYPES[2]])
    corpus = [b"\xff", hv[:-1] + b',"zz":1}', b'{"t_ns":1}', b"[]", hv.replace(b'"tap":3', b'"tap":99'),
              b" " * (MAX_PAYLOAD_BYTES + 1)]
    for raw in corpus:
        _check(MESSAGE_TYPES[2], raw)
    hit = {k for k in OUTCOMES if k != "ok"}
    assert {"oversize", "malformed", "unknown_field", "missing_field", "wrong_type", "out_of_range"} <= hit, OUTCOMES
    print(f"\nfuzz outcomes: {dict(sorted(OUTCOMES.items()))} total {sum(OUTCOMES.values())}")
