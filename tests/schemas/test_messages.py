"""Round trip of every message type, and a table of bad payloads per type."""

from __future__ import annotations

import json
import math
from typing import Annotated, ClassVar

import msgspec
import msgspec.inspect
import pytest

from schemas import messages as m
from schemas.bus import BadMessage, NonFiniteError, codec_for
from schemas.examples import examples
from schemas.jsonschema import export_schemas, json_schema
from schemas.messages import MESSAGE_TYPES

EXAMPLES = examples()


@pytest.mark.parametrize("msg_type", MESSAGE_TYPES, ids=lambda t: t.__name__)
def test_round_trip(msg_type):
    msg = EXAMPLES[msg_type]
    codec = codec_for(msg_type)
    assert codec.decode(codec.encode(msg)) == msg


@pytest.mark.parametrize("msg_type", MESSAGE_TYPES, ids=lambda t: t.__name__)
def test_structs_are_frozen_kw_only_strict(msg_type):
    cfg = msg_type.__struct_config__
    assert cfg.frozen and cfg.forbid_unknown_fields
    values = msgspec.structs.astuple(EXAMPLES[msg_type])
    with pytest.raises(TypeError):
        msg_type(*values)  # kw_only: positional construction is refused
    with pytest.raises(AttributeError):
        EXAMPLES[msg_type].t_ns = 0  # frozen


def _mutations(msg_type) -> list[tuple[str, bytes, str]]:
    """(label, payload, expected kind) for one type, derived from its valid example."""
    good = json.loads(msgspec.json.encode(EXAMPLES[msg_type]))
    cases = [
        ("not json", b"{not json", "malformed"),
        ("empty", b"", "malformed"),
        ("array", b"[1,2,3]", "wrong_type"),
        ("unknown field", json.dumps({**good, "surprise": 1}).encode(), "unknown_field"),
        ("missing t_ns", json.dumps({k: v for k, v in good.items() if k != "t_ns"}).encode(), "missing_field"),
        ("t_ns as string", json.dumps({**good, "t_ns": "soon"}).encode(), "wrong_type"),
        ("negative t_ns", json.dumps({**good, "t_ns": -1}).encode(), "out_of_range"),
        ("oversize", b"{" + b" " * (codec_for(msg_type).max_bytes + 1) + b"}", "oversize"),
    ]
    floats = [k for k, v in good.items() if isinstance(v, float)]
    if floats:
        cases.append(("infinite float", json.dumps({**good, floats[0]: 1}).encode()
                      .replace(b'"' + floats[0].encode() + b'": 1', b'"' + floats[0].encode() + b'": 1e999'),
                      "out_of_range"))
        cases.append(("NaN literal", json.dumps({**good, floats[0]: math.nan}).encode(), "malformed"))
    if "source" in good:
        cases.append(("bad source id", json.dumps({**good, "source": "a/b*"}).encode(), "out_of_range"))
    return cases


# JSON payloads; the one Protobuf type (TruthPack) has its own table in test_truth.py
BAD = [(t, label, payload, kind) for t in MESSAGE_TYPES if m.wire_of(t) == "json"
       for (label, payload, kind) in _mutations(t)]


@pytest.mark.parametrize(("msg_type", "label", "payload", "kind"), BAD,
                         ids=[f"{t.__name__}-{label}" for t, label, _, _ in BAD])
def test_bad_payload_is_rejected_with_kind(msg_type, label, payload, kind):
    with pytest.raises(BadMessage) as e:
        codec_for(msg_type).decode(payload)
    assert e.value.kind == kind, str(e.value)


@pytest.mark.parametrize(
    ("field", "value"),
    [("p_kw", 2e6), ("q_kvar", -2e6)],
)
def test_out_of_range_power_rejected(field, value):
    good = json.loads(msgspec.json.encode(EXAMPLES[m.HeadFrame]))
    with pytest.raises(BadMessage, match="out_of_range"):
        codec_for(m.HeadFrame).decode(json.dumps({**good, field: value}).encode())


def test_sender_refuses_non_finite():
    bad = msgspec.structs.replace(EXAMPLES[m.PvCommand], q_kvar=math.nan)
    with pytest.raises(NonFiniteError, match="q_kvar"):
        codec_for(m.PvCommand).encode(bad)
    nested = msgspec.structs.replace(
        EXAMPLES[m.Decision], dv_dq_pu_per_kvar=[[1e-5, math.inf]])
    with pytest.raises(NonFiniteError, match=r"dv_dq_pu_per_kvar\[0\]\[1\]"):
        codec_for(m.Decision).encode(nested)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_found_in_every_shape_of_list(bad):
    """The one-pass sum of number lists (``_finite_numbers``) never hides a NaN or an infinity; the walk then
    names it. Including where the sum alone would cancel (inf and -inf) or overflow (finite values)."""
    from schemas.bus import check_finite

    big = [[1e-5] * 14 for _ in range(1283)]
    big[700][9] = bad
    with pytest.raises(NonFiniteError, match=r"x\[700\]\[9\]"):
        check_finite(big, "x")
    with pytest.raises(NonFiniteError, match=r"x\[2\]"):
        check_finite([1.0, 2, bad], "x")
    with pytest.raises(NonFiniteError, match=r"x\[1\]"):
        check_finite([1.0, math.inf, -math.inf], "x")  # the two would cancel to NaN: still found
    with pytest.raises(NonFiniteError, match=r"x\[1\]\[0\]"):
        check_finite([[1.0], [bad], "label"], "x")  # mixed: walked
    check_finite([1e308, 1e308], "x")  # the sum overflows; every value is finite
    check_finite([[1e308], [1e308]], "x")
    check_finite([10**400, 1.0, True], "x")  # a huge int: no float sum, walked
    check_finite([[], [1.0, 2]], "x")
    check_finite(["a", "b"], "x")


def test_tagged_unions_dispatch():
    d = codec_for(m.Decision).decode(codec_for(m.Decision).encode(EXAMPLES[m.Decision]))
    kinds = []
    for c in d.commands:
        match c:
            case m.PvCommand(q_kvar=q):
                kinds.append(("pv", q))
            case m.RegCommand(action=m.TapAction(tap=t)):
                kinds.append(("tap", t))
    assert kinds == [("pv", -120.0), ("tap", 4)]


def test_exported_schemas_are_top_level_objects(tmp_path):
    paths = export_schemas(tmp_path)
    assert len(paths) == len(MESSAGE_TYPES)
    for p in paths:
        schema = json.loads(p.read_text())
        assert schema["type"] == "object"
        assert "$ref" not in schema
        assert schema["additionalProperties"] is False


def test_schema_validates_example_with_jsonschema_semantics():
    """Every required property of the schema is present in the encoded example."""
    for t in MESSAGE_TYPES:
        schema = json_schema(t)
        doc = json.loads(msgspec.json.encode(EXAMPLES[t]))
        assert set(schema.get("required", [])) <= set(doc), t


# ------------------------------------------------------------------------------------ capacitor banks
def _cap_command(**change) -> bytes:
    good = json.loads(msgspec.json.encode(EXAMPLES[m.CapCommand]))
    return json.dumps({**good, **change}).encode()


def test_cap_command_release_is_null_and_required():
    codec = codec_for(m.CapCommand)
    assert codec.decode(_cap_command(closed_steps=None)).closed_steps is None
    good = json.loads(_cap_command())
    del good["closed_steps"]
    with pytest.raises(BadMessage) as e:
        codec.decode(json.dumps(good).encode())
    assert e.value.kind == "missing_field"  # a command must say switch or release; nothing is implied


@pytest.mark.parametrize("steps", [-1, 65, 1.5, "1"])
def test_cap_command_bad_steps_rejected(steps):
    with pytest.raises(BadMessage):
        codec_for(m.CapCommand).decode(_cap_command(closed_steps=steps))


def test_cap_command_in_a_decision():
    ex = EXAMPLES[m.CapCommand]
    d = msgspec.structs.replace(EXAMPLES[m.Decision], commands=[ex])
    codec = codec_for(m.Decision)
    assert codec.decode(codec.encode(d)).commands == [ex]


def test_recordings_before_capacitors_still_decode():
    """Append-only: TruthFrame, MetricsFrame and Decision payloads without the capacitor fields decode."""
    for t, defaults in ((m.TruthFrame, {"cap_states": []}),
                        (m.MetricsFrame, {"cap_switches": 0, "cap_cost": 0.0, "cap_switches_per_bank": {}})):
        old = {k: v for k, v in json.loads(msgspec.json.encode(EXAMPLES[t])).items() if k not in defaults}
        msg = codec_for(t).decode(json.dumps(old).encode())
        assert {f: getattr(msg, f) for f in defaults} == defaults


def test_cap_frame_schema_is_an_object():
    s = json_schema(m.CapFrame)
    assert s["type"] == "object"
    assert "closed_steps" in s["required"] and "control_value" in s["properties"]


class _Loose(msgspec.Struct, frozen=True):
    """A MessagePack type with unbounded floats: inf decodes there (JSON refuses 1e999 even unbounded), so the
    codec's walk must run after the decode."""

    WIRE: ClassVar[str] = "msgpack"
    t_ns: int
    x: float
    y: list[Annotated[float, msgspec.Meta(ge=0.0)]] = []  # bounded below only: still open above


@pytest.mark.parametrize("payload", [{"t_ns": 1, "x": math.inf}, {"t_ns": 1, "x": 1.0, "y": [math.inf]},
                                     {"t_ns": 1, "x": math.nan}])
def test_the_decode_walk_runs_for_a_type_with_an_unbounded_float(payload):
    with pytest.raises(BadMessage) as e:
        codec_for(_Loose).decode(msgspec.msgpack.encode(payload))
    assert e.value.kind == "non_finite"
    assert codec_for(_Loose).decode(msgspec.msgpack.encode({"t_ns": 1, "x": 2.0})) == _Loose(t_ns=1, x=2.0)


@pytest.mark.parametrize("msg_type", MESSAGE_TYPES, ids=lambda t: t.__name__)
def test_every_message_float_is_bounded_so_decode_alone_refuses_non_finite(msg_type):
    """The codec skips its NaN/inf walk after decoding these types: every float in them has both bounds."""
    from schemas.bus import _has_unbounded_float

    assert not _has_unbounded_float(msgspec.inspect.type_info(msg_type), set())


def _unbounded(t: msgspec.inspect.Type, path: str, seen: set[type]) -> list[str]:
    """Paths in ``t`` of a list, dict, string or byte string without a maximal length."""
    mi = msgspec.inspect
    if isinstance(t, mi.StructType):
        if t.cls in seen:
            return []
        seen.add(t.cls)
        return [x for f in t.fields for x in _unbounded(f.type, f"{path}.{f.name}", seen)]
    if isinstance(t, mi.StrType | mi.BytesType):
        return [] if t.max_length is not None else [path]
    if isinstance(t, mi.ListType | mi.VarTupleType | mi.SetType | mi.FrozenSetType):
        own = [] if t.max_length is not None else [path]
        return own + _unbounded(t.item_type, f"{path}[]", seen)
    if isinstance(t, mi.DictType):
        own = [] if t.max_length is not None else [path]
        return own + _unbounded(t.key_type, f"{path}{{key}}", seen) + _unbounded(t.value_type, f"{path}{{}}", seen)
    if isinstance(t, mi.UnionType):
        return [x for u in t.types for x in _unbounded(u, path, seen)]
    return []


@pytest.mark.parametrize("msg_type", MESSAGE_TYPES, ids=lambda t: t.__name__)
def test_every_list_dict_and_string_of_every_message_has_a_bound(msg_type):
    assert _unbounded(msgspec.inspect.type_info(msg_type), msg_type.__name__, set()) == []


@pytest.mark.parametrize(("msg_type", "field", "value"), [
    (m.HeadFrame, "quality", ["noisy"] * 100_000),  # 0.9 MB of flags: under the payload limit, not under the bound
    (m.StepEnd, "pv", ["pv1"] * 5_000),
    (m.AgentStatus, "rejected", {f"kind{i}": 1 for i in range(5_000)}),
    (m.HeadFrame, "source", "x" * 65),
])
def test_an_oversized_list_or_string_fails_cleanly_as_out_of_range(msg_type, field, value):
    raw = msgspec.json.encode(msgspec.structs.replace(EXAMPLES[msg_type], **{field: value}))
    assert len(raw) < codec_for(msg_type).max_bytes
    with pytest.raises(BadMessage) as e:
        codec_for(msg_type).decode(raw)
    assert e.value.kind == "out_of_range", e.value
