"""A run's recording read back by topic, every message as a dict (what the closed-loop tests compare)."""

from __future__ import annotations

import json
from pathlib import Path

import msgspec
from mcap.reader import make_reader

from schemas.truth import to_truth_frame, truth_pack


def _as_dict(raw: bytes, encoding: str) -> dict:
    """A recorded message as a dict: JSON as it is, the truth (Protobuf ``cvvc.Truth``) in its JSON form."""
    if encoding == "protobuf":
        return msgspec.to_builtins(to_truth_frame(truth_pack(raw, encoding)))
    return json.loads(raw)


def messages_by_topic(path: str | Path) -> dict[str, list[dict]]:
    """Every message of the MCAP file at ``path``, in log time order, by topic."""
    by_topic: dict[str, list[dict]] = {}
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
            by_topic.setdefault(channel.topic, []).append(_as_dict(message.data, channel.message_encoding))
    return by_topic
