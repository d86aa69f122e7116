"""What a test client saw on the bus: head frame times, acks and command ids, by its subscriptions (thread-safe)."""

from __future__ import annotations

import json
import threading

import zenoh

from schemas import messages as m
from schemas.bus import codec_for


class Seen:
    """Callbacks for ``declare_subscriber``: head frames' ``t_ns``, acks by ``cmd_id``, commands' ``cmd_id``."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.head_t_ns: list[int] = []
        self.acks: dict[str, m.Ack] = {}
        self.cmd_ids: list[str] = []

    def on_head(self, s: zenoh.Sample) -> None:
        """A head frame: keep its time."""
        with self.lock:
            self.head_t_ns.append(json.loads(s.payload.to_bytes())["t_ns"])

    def on_ack(self, s: zenoh.Sample) -> None:
        """An ack: keep it by its command id."""
        ack = codec_for(m.Ack).decode(s.payload.to_bytes())
        with self.lock:
            self.acks[ack.cmd_id] = ack

    def on_cmd(self, s: zenoh.Sample) -> None:
        """A command: keep its id."""
        with self.lock:
            self.cmd_ids.append(json.loads(s.payload.to_bytes())["cmd_id"])
