"""The bridge tests' bus client: a plain ``zenoh`` + ``msgspec`` peer that sees one feeder's samples and can play
the agent by hand (liveliness token, commands, decisions).

It decodes what the bridge publishes (``meas/``, ``ack/``, ``sim/`` keys; the oracle's replies excepted) with the
message structs of ``schemas.messages`` and keeps every sample it has seen, with its arrival time, in ``seen``.
"""

from __future__ import annotations

import json
import queue
import time
from collections.abc import Callable
from typing import Any

import msgspec
import zenoh

from schemas import keys
from schemas import messages as m
from schemas.wire import typed_decoder

__all__ = ["BusClient"]

_BRIDGE_KINDS = frozenset({"meas", "ack", "sim"})


class BusClient:
    """A plain-zenoh peer on ``endpoint`` that sees every ``cvvc/<feeder>/**`` sample (and those of ``also``)."""

    def __init__(self, endpoint: str, feeder: str, *, also: tuple[str, ...] = ()) -> None:
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        self.feeder = feeder
        self.session = zenoh.open(conf)
        self.q: queue.Queue[tuple[str, bytes, float]] = queue.Queue()
        self.seen: list[tuple[str, Any, float]] = []  # (key, message, arrival time.monotonic())

        def put(s: Any) -> None:
            self.q.put((str(s.key_expr), s.payload.to_bytes(), time.monotonic()))

        self.subs = [self.session.declare_subscriber(k, put) for k in (f"cvvc/{feeder}/**", *also)]
        self.token: Any = None
        self.seq = 0

    def close(self) -> None:
        if self.token is not None:
            self.token.undeclare()
        for s in self.subs:
            s.undeclare()
        self.session.close()

    def be_agent(self) -> None:
        self.token = self.session.liveliness().declare_token(f"cvvc/{self.feeder}/alive/agent/test")

    def next(self, pred: Callable[[str, Any], bool], timeout_s: float = 20.0) -> Any:
        """The first sample seen so far, or the next one to arrive, for which ``pred(key, msg)`` holds."""
        for key, msg, _ in self.seen:
            if pred(key, msg):
                return msg
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise AssertionError("no matching sample within the deadline")
            try:
                key, raw, t = self.q.get(timeout=remaining)
            except queue.Empty:
                continue
            parts = key.split("/")
            mtype = keys.message_type_for_key(key)
            if mtype is None or parts[2] not in _BRIDGE_KINDS or mtype is m.OracleReply:
                continue
            msg = typed_decoder(mtype).decode(raw)  # the truth is Protobuf, the rest JSON
            self.seen.append((key, msg, t))
            if pred(key, msg):
                return msg

    def head(self, t_ns: int | None = None, timeout_s: float = 20.0) -> m.HeadFrame:
        return self.next(lambda k, x: isinstance(x, m.HeadFrame) and (t_ns is None or x.t_ns == t_ns), timeout_s)

    def cap(self, cap_id: str, t_ns: int) -> m.CapFrame:
        return self.next(lambda k, x: isinstance(x, m.CapFrame) and x.capacitor_id == cap_id and x.t_ns == t_ns)

    def ack(self, cmd_id: str, status: str | None = None) -> m.Ack:
        return self.next(lambda k, x: isinstance(x, m.Ack) and x.cmd_id == cmd_id
                         and (status is None or x.status == status))

    def put(self, key: str, payload: bytes | msgspec.Struct) -> None:
        data = payload if isinstance(payload, bytes) else msgspec.json.encode(payload)
        self.session.put(key, data, congestion_control=zenoh.CongestionControl.BLOCK)

    def _next_seq(self, seq: int | None) -> int:
        self.seq += 1
        return self.seq if seq is None else seq

    def pv_cmd(self, plant: str, q_kvar: float, now_t_ns: int, *, valid_s: float = 3600, seq: int | None = None,
               key_plant: str | None = None, feeder: str | None = None, plant_id: str | None = None) -> m.PvCommand:
        c = m.PvCommand(t_ns=now_t_ns, seq=self._next_seq(seq), source="test-agent",
                        cmd_id=f"c{self.seq}-{plant}", in_reply_to=0,
                        valid_until_t_ns=now_t_ns + int(valid_s * 1e9), plant_id=plant_id or plant, q_kvar=q_kvar)
        self.put(f"cvvc/{feeder or self.feeder}/cmd/pv/{key_plant or plant}", c)  # any key: bad ones are tested
        return c

    def reg_cmd(self, reg: str, action: m.TapAction | m.SetpointAction, now_t_ns: int, *,
                valid_s: float = 3600) -> m.RegCommand:
        c = m.RegCommand(t_ns=now_t_ns, seq=self._next_seq(None), source="test-agent", cmd_id=f"c{self.seq}-{reg}",
                         in_reply_to=0, valid_until_t_ns=now_t_ns + int(valid_s * 1e9), regulator_id=reg,
                         action=action)
        self.put(f"cvvc/{self.feeder}/cmd/vr/{reg}", c)
        return c

    def cap_cmd(self, cap_id: str, steps: int | None, now_t_ns: int, *, valid_s: float = 3600,
                seq: int | None = None, key_cap: str | None = None) -> m.CapCommand:
        c = m.CapCommand(t_ns=now_t_ns, seq=self._next_seq(seq), source="test-agent",
                         cmd_id=f"c{self.seq}-{cap_id}", in_reply_to=0,
                         valid_until_t_ns=now_t_ns + int(valid_s * 1e9), capacitor_id=cap_id, closed_steps=steps)
        self.put(keys.cmd(self.feeder, "cap", key_cap or cap_id), c)
        return c

    def decide(self, t_ns: int, commands: list[Any] | None = None) -> None:
        self.put(keys.agent_decision(self.feeder), m.Decision(
            t_ns=t_ns, seq=self._next_seq(None), source="test-agent", feeder_id=self.feeder, step_t_ns=t_ns,
            in_reply_to=0, status="optimal" if commands else "hold", commands=commands or []))
