"""JSON Schemas of the message types, in the form Foxglove and MCAP channels want.

``msgspec.json.schema(T)`` returns ``{"$ref": "#/$defs/T", "$defs": {...}}``; Foxglove needs a top-level
``"type": "object"``, so the root definition is inlined and the other definitions kept beside it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import msgspec

from schemas.messages import MESSAGE_TYPES

__all__ = ["export_schemas", "json_schema", "schema_bytes", "schema_name"]


def schema_name(msg_type: type) -> str:
    """The schema name of ``msg_type`` in recordings: ``cvvc.<Type>``."""
    return f"cvvc.{msg_type.__name__}"


def json_schema(msg_type: type) -> dict[str, Any]:
    """The JSON Schema of ``msg_type`` with the root inlined (top-level ``"type": "object"``)."""
    raw = msgspec.json.schema(msg_type)
    defs = dict(raw.get("$defs", {}))
    ref = raw.get("$ref")
    if ref:
        root = dict(defs[ref.rsplit("/", 1)[-1]])
    else:
        root = {k: v for k, v in raw.items() if k != "$defs"}
    out: dict[str, Any] = {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": schema_name(msg_type)}
    out.update(root)
    if defs:
        out["$defs"] = defs
    return out


def schema_bytes(msg_type: type) -> bytes:
    """The JSON Schema of ``msg_type`` as canonical bytes (sorted keys), as MCAP schemas store it."""
    return json.dumps(json_schema(msg_type), sort_keys=True).encode()


def export_schemas(out_dir: str | Path) -> list[Path]:
    """Write one ``<Type>.schema.json`` per message type into ``out_dir``; returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for t in MESSAGE_TYPES:
        p = out / f"{t.__name__}.schema.json"
        p.write_text(json.dumps(json_schema(t), indent=2, sort_keys=True) + "\n")
        paths.append(p)
    return paths
