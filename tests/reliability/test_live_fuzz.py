"""Live fuzzing: the real agent, bridge and recorder processes under 12,000 bad messages over loopback.

A plain-zenoh session (what a broken device or an intruder without credentials would use) publishes
malformed, truncated, mutated, wrongly typed, out-of-range, non-finite, oversize, deeply nested,
out-of-order and replayed messages on every topic of the feeder: measurements, acks and commands of every
device, decisions, statuses and simulation topics. Payloads meant to fail decoding are checked to fail with
the shared codec before they are sent; the schema-valid ones are built so that every one of them must be
refused by a later check (replay, expiry, device range, unknown device, wrong feeder, implausible values).
The generator is seeded; the schema-valid messages are built from the real frames and commands seen so far.

Afterwards: no process crashed; the agent's ``AgentStatus.rejected`` and the bridge's ``BridgeStatus.rejected``
totals grew by exactly what was sent to each of them (more only by ``queue_full`` drops, which count too);
the recorder wrote every message to a valid file; a valid command is acked and the agent's next decision
with commands arrives.
"""

from __future__ import annotations

import json
import random
from collections import Counter
from pathlib import Path
from typing import Any

import msgspec
import zenoh
from mcap.reader import make_reader
from relutil import FEEDER, Procs, Watcher, plain_session

from recordings.recorder import QUARANTINE_TOPIC, Quarantined
from schemas import messages as m
from schemas.bus import MAX_PAYLOAD_BYTES, BadMessage, codec_for
from schemas.examples import examples
from schemas.keys import message_type_for_key

SEED = 20261121
N_MESSAGES = 12_000
AGENT_KEY = f"cvvc/{FEEDER}/alive/agent/agent"
PVS = ("pv675", "pv680", "pv633")
REGS = ("reg1", "reg2", "reg3")
FAR_FUTURE_NS = 2**62
F = f"cvvc/{FEEDER}"
# topic -> who counts what arrives there ("agent", "bridge", or "none": only the recorder sees it)
TOPICS: dict[str, str] = {
    f"{F}/meas/head": "agent",
    **{f"{F}/meas/pv/{p}": "agent" for p in PVS},
    **{f"{F}/meas/vr/{r}": "agent" for r in REGS},
    f"{F}/meas/pv/ghost": "agent",
    f"{F}/meas/head/extra": "agent",
    **{f"{F}/ack/pv/{p}": "agent" for p in PVS},
    **{f"{F}/ack/vr/{r}": "agent" for r in REGS},
    **{f"{F}/cmd/pv/{p}": "bridge" for p in PVS},
    **{f"{F}/cmd/vr/{r}": "bridge" for r in REGS},
    f"{F}/cmd/pv/ghost": "bridge",
    f"{F}/cmd/pv/pv675/extra": "bridge",
    "cvvc/otherfeeder/cmd/pv/pv675": "bridge",
    f"{F}/agent/decision": "bridge",
    f"{F}/agent/status": "none",
    f"{F}/sim/truth": "none",
    f"{F}/sim/metrics": "none",
    f"{F}/sim/status": "none",
}
BAD_LITERALS = ["NaN", "Infinity", "-Infinity", "1e999", "-1e999", "nan", "9" * 30, "-1", "1e400"]


class Fuzzer:
    """Seeded generator of bad messages; keeps per-topic and per-class counts for the report."""

    def __init__(self, seed: int, seen: Watcher) -> None:
        self.rng = random.Random(seed)
        self.seen = seen
        self.examples = {t: msgspec.to_builtins(x) for t, x in examples().items()}
        self.classes: Counter[str] = Counter()
        self.oversize_left = 12

    # ------------------------------------------------------------------ payloads that must not decode
    def undecodable(self, key: str) -> bytes:
        msg_type = message_type_for_key(key)
        assert msg_type is not None
        for _ in range(20):
            cls, raw = self._mutation(msg_type)
            try:
                codec_for(msg_type).decode(raw)
            except BadMessage:
                self.classes[cls] += 1
                return raw
        raise AssertionError(f"no undecodable mutation of {msg_type.__name__} found")

    def _mutation(self, msg_type: type) -> tuple[str, bytes]:
        r = self.rng
        tree = json.loads(json.dumps(self.examples[msg_type]))
        valid = json.dumps(tree).encode()
        choice = r.choice(["garbage", "truncated", "flipped", "wrong_type", "missing", "unknown", "out_of_range",
                           "non_finite", "deep", "bad_utf8", "oversize"])
        match choice:
            case "garbage":
                return choice, r.randbytes(r.randint(0, 300))
            case "truncated":
                return choice, valid[: r.randint(0, len(valid) - 1)]
            case "flipped":
                data = bytearray(valid)
                for _ in range(r.randint(1, 4)):
                    data[r.randrange(len(data))] = r.randrange(256)
                return choice, bytes(data)
            case "wrong_type":
                field = r.choice(list(tree))
                tree[field] = r.choice([{"x": 1}, [1, 2], "text", True, None, 1.5, -3])
                return choice, json.dumps(tree).encode()
            case "missing":
                del tree[r.choice(list(tree))]
                return choice, json.dumps(tree).encode()
            case "unknown":
                tree[f"extra_{r.randrange(1000)}"] = r.random()
                return choice, json.dumps(tree).encode()
            case "out_of_range" | "non_finite":
                numeric = [k for k, v in tree.items() if isinstance(v, int | float) and not isinstance(v, bool)]
                if not numeric:
                    return choice, b"[]"
                field = r.choice(numeric)
                literal = (r.choice(["-5", "1e300", str(2**64), "-1e20"]) if choice == "out_of_range"
                           else r.choice(BAD_LITERALS))
                tree[field] = "__X__"
                return choice, json.dumps(tree).replace('"__X__"', literal).encode()
            case "deep":
                depth = r.choice([50, 5000, 50_000])
                field = r.choice(list(tree))
                text = json.dumps(tree).replace(f'"{field}": ', f'"{field}": ' + "[" * depth, 1)
                return choice, (text[:-1] + "]" * depth + "}").encode()
            case "bad_utf8":
                field = r.choice(list(tree))
                return choice, json.dumps(tree).replace(f'"{field}"', f'"{field}\\u0000', 1).encode() \
                    if r.random() < 0.5 else valid.replace(b'"', b'"\xf4\x90', 1)
            case _:
                if self.oversize_left <= 0:
                    return "garbage", r.randbytes(50)
                self.oversize_left -= 1
                return choice, valid[:-1] + b" " * (MAX_PAYLOAD_BYTES + 1 - len(valid)) + b"}"

    # ------------------------------------------------------------- schema-valid, refused by a later check
    def agent_semantic(self, key: str) -> bytes | None:
        """A schema-valid frame the agent's aligner must refuse, or None for topics without one."""
        r = self.rng
        parts = key.split("/")
        if parts[2] != "meas":
            return None
        if parts[-1] == "ghost":
            self.classes["unknown_device"] += 1
            frame = msgspec.structs.replace(examples()[m.PvFrame], plant_id="ghost", source="ghost",
                                            seq=r.randrange(1, 2**40))
            return msgspec.json.encode(frame)
        real = [x for x in self.seen.messages(_FRAME_TYPE[parts[3]]) if _device_of(x) == parts[-1]]
        if len(real) < 3:
            return None
        old = r.choice(real[:-2])  # a frame at least two steps old: never the newest one
        choice = r.choice(["replayed", "out_of_order", "wrong_feeder", "implausible"])
        if choice == "wrong_feeder" and not isinstance(old, m.HeadFrame):
            choice = "implausible"
        self.classes[choice] += 1
        match choice:
            case "replayed":
                return msgspec.json.encode(old)
            case "out_of_order":
                return msgspec.json.encode(msgspec.structs.replace(old, seq=max(0, old.seq - r.randint(1, 5)),
                                                                   t_ns=old.t_ns + 1))
            case "wrong_feeder":
                return msgspec.json.encode(msgspec.structs.replace(old, feeder_id="otherfeeder",
                                                                   seq=FAR_FUTURE_NS + r.randrange(2**20)))
            case _:
                fresh = dict(seq=FAR_FUTURE_NS + r.randrange(2**20), t_ns=FAR_FUTURE_NS)
                if isinstance(old, m.PvFrame):
                    bad = msgspec.structs.replace(old, p_kw=2.0 * old.s_rated_kva + 10.0, **fresh)
                elif isinstance(old, m.RegFrame):
                    bad = msgspec.structs.replace(old, v_compared_120=199.0, **fresh)
                else:
                    bad = msgspec.structs.replace(old, p_kw=old.p_kw + 5000.0, **fresh)
                return msgspec.json.encode(bad)

    def bridge_semantic(self, key: str) -> bytes | None:
        """A schema-valid command or decision the bridge must refuse, or None."""
        r = self.rng
        parts = key.split("/")
        seq = r.randrange(1, 2**40)
        base = dict(t_ns=1, seq=seq, source=f"fuzz{r.randrange(100)}", cmd_id=f"fuzz:{seq}", in_reply_to=0,
                    valid_until_t_ns=FAR_FUTURE_NS)
        if parts[2] == "agent":
            self.classes["decision_wrong_feeder"] += 1
            return msgspec.json.encode(msgspec.structs.replace(examples()[m.Decision], feeder_id="otherfeeder",
                                                               seq=seq))
        kind, device = parts[3], parts[4]
        if kind == "pv":
            choice = r.choice(["replayed", "expired", "wrong_device"]) if device in PVS else "unknown_device"
            self.classes[choice] += 1
            match choice:
                case "replayed":
                    return self._replayed_command(m.PvCommand, device) or msgspec.json.encode(
                        m.PvCommand(**{**base, "valid_until_t_ns": 1}, plant_id=device, q_kvar=1.0))
                case "expired":
                    return msgspec.json.encode(m.PvCommand(**{**base, "valid_until_t_ns": 1}, plant_id=device,
                                                           q_kvar=1.0))
                case "wrong_device":
                    other = next(p for p in PVS if p != device)
                    return msgspec.json.encode(m.PvCommand(**base, plant_id=other, q_kvar=1.0))
                case _:
                    return msgspec.json.encode(m.PvCommand(**base, plant_id="pv675", q_kvar=1.0))
        choice = r.choice(["replayed", "out_of_range", "wrong_device", "expired"])
        self.classes[choice] += 1
        action: m.TapAction | m.SetpointAction = m.SetpointAction(setpoint_v120=120.0, band_v120=2.0)
        match choice:
            case "replayed":
                old = self._replayed_command(m.RegCommand, device)
                if old is not None:
                    return old
                return msgspec.json.encode(m.RegCommand(**{**base, "valid_until_t_ns": 1}, regulator_id=device,
                                                        action=action))
            case "out_of_range":
                action = r.choice([m.SetpointAction(setpoint_v120=135.0, band_v120=2.0),
                                   m.SetpointAction(setpoint_v120=120.0, band_v120=10.0),
                                   m.SetpointAction(setpoint_v120=105.0, band_v120=0.5)])
                return msgspec.json.encode(m.RegCommand(**base, regulator_id=device, action=action))
            case "wrong_device":
                return msgspec.json.encode(m.RegCommand(**base, regulator_id=next(x for x in REGS if x != device),
                                                        action=action))
            case _:
                return msgspec.json.encode(m.RegCommand(**{**base, "valid_until_t_ns": 1}, regulator_id=device,
                                                        action=action))

    def _replayed_command(self, msg_type: type, device: str) -> bytes | None:
        decisions = self.seen.messages(m.Decision, lambda d: bool(d.commands))
        older = [c for d in decisions[:-1] for c in d.commands
                 if isinstance(c, msg_type) and (getattr(c, "plant_id", None) or c.regulator_id) == device]
        return msgspec.json.encode(self.rng.choice(older)) if older else None


_FRAME_TYPE = {"head": m.HeadFrame, "pv": m.PvFrame, "vr": m.RegFrame}


def _device_of(frame: Any) -> str:
    return getattr(frame, "plant_id", None) or getattr(frame, "regulator_id", None) or "head"


def _total(rejected: dict[str, int]) -> int:
    return sum(rejected.values())


def test_live_agent_bridge_and_recorder_survive_12000_bad_messages(procs: Procs, watcher: Watcher,
                                                                   router_endpoint: str, tmp_path: Path) -> None:
    from recordings.info import recording_info

    mcap = tmp_path / "fuzz.mcap"
    recorder = procs.recorder(mcap, "--flush-period-s", "0.5")
    agent = procs.agent(stale_after_s=5.0)
    watcher.wait(lambda: watcher.is_alive(AGENT_KEY), 30, "the agent's liveliness token")
    bridge = procs.bridge("--realtime", "--speed", "300", "--steps", "100000")
    watcher.wait(lambda: len(watcher.messages(m.Decision, lambda d: bool(d.commands))) >= 3, 30,
                 "three decisions with commands")
    a0 = watcher.first(m.AgentStatus, lambda s: s.state == "ok", 10, "an 'ok' agent status")
    b0 = watcher.messages(m.BridgeStatus)[-1]
    watcher.skip = ("/ghost", "/extra")

    fuzz = Fuzzer(SEED, watcher)
    topics = list(TOPICS)
    sent: Counter[str] = Counter()  # per target
    per_topic: Counter[str] = Counter()
    # a client: everything through the router, on one link; open until the end (closing drops what is in flight)
    with plain_session(router_endpoint, mode="client") as session:
        pubs = {k: session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK) for k in topics}
        watcher.wait(lambda: all(p.matching_status.matching for p in pubs.values()), 10, "every topic's subscribers")
        for i in range(N_MESSAGES):
            key = topics[i % len(topics)]
            target = TOPICS[key]
            payload = None
            if fuzz.rng.random() < 0.3:  # schema-valid, refused by a later check
                payload = fuzz.agent_semantic(key) if target == "agent" else (
                    fuzz.bridge_semantic(key) if target == "bridge" and "/extra" not in key
                    and "otherfeeder" not in key else None)
            if payload is None and key == f"{F}/meas/head/extra" and fuzz.rng.random() < 0.5:
                # a real head frame, newest seq, on a key one level too deep: refused by the key check
                fuzz.classes["bad_key"] += 1
                head = watcher.messages(m.HeadFrame, lambda f: f.source == "head" and f.seq < FAR_FUTURE_NS)[-1]
                payload = msgspec.json.encode(msgspec.structs.replace(head, seq=FAR_FUTURE_NS + i))
            if payload is None and target == "bridge" and (key.endswith("/extra") or "otherfeeder" in key):
                # a valid command on a key the bridge cannot answer on, or for a feeder without a bridge
                fuzz.classes["bad_key"] += 1
                payload = msgspec.json.encode(m.PvCommand(t_ns=1, seq=i + 1, source="fuzz", cmd_id=f"k{i}",
                                                          in_reply_to=0, valid_until_t_ns=FAR_FUTURE_NS,
                                                          plant_id="pv675", q_kvar=1.0))
            if payload is None:
                payload = fuzz.undecodable(key)
            pubs[key].put(payload)
            sent[target] += 1
            per_topic[key] += 1
        real_heads = watcher.messages(m.HeadFrame, lambda f: f.source == "head" and f.seq < FAR_FUTURE_NS)
        last_fuzz_t_ns = real_heads[-1].t_ns

        # every bad message was counted and rejected (queue_full drops count as rejections too)
        def grown(msgs: list, base: Any, n: int) -> Any:
            return msgs[-1] if msgs and _total(msgs[-1].rejected) - _total(base.rejected) >= n else None

        try:
            a1 = watcher.wait(lambda: grown(watcher.messages(m.AgentStatus), a0, sent["agent"]), 60,
                              "the agent's reject counts")
        finally:
            last = watcher.messages(m.AgentStatus)[-1]
            print(f"\nagent: sent {sent['agent']}, counted {_total(last.rejected) - _total(a0.rejected)}; "
                  f"classes {dict(sorted(fuzz.classes.items()))}; now {last.rejected}; before {a0.rejected}")
        b1 = watcher.wait(lambda: grown(watcher.messages(m.BridgeStatus), b0, sent["bridge"]), 60,
                          "the bridge's reject counts")
        a_extra = _total(a1.rejected) - _total(a0.rejected) - sent["agent"]
        b_extra = _total(b1.rejected) - _total(b0.rejected) - sent["bridge"]
        print(f"\nsent {dict(sent)} in {len(per_topic)} topics; classes {dict(sorted(fuzz.classes.items()))}"
              f"\nagent rejected {dict(sorted(a1.rejected.items()))}"
              f"\nbridge rejected {dict(sorted(b1.rejected.items()))}")
        assert sum(sent.values()) == N_MESSAGES and sent["agent"] > 4000 and sent["bridge"] > 3000
        # the fuzz frames are never 'stale' (their seq is refused first): stale ones are real frames that came
        # after their step was closed (a starved bridge, a late window that ran out), also counted
        stale = a1.rejected.get("stale", 0) - a0.rejected.get("stale", 0)
        assert stale <= a_extra <= stale + a1.rejected.get("queue_full", 0) - a0.rejected.get("queue_full", 0)
        assert 0 <= b_extra <= b1.rejected.get("decode_queue_full", 0) - b0.rejected.get("decode_queue_full", 0)
        assert a1.rejected.get("internal", 0) == 0 and b1.rejected.get("decode_internal", 0) == 0

        # nothing crashed, and the next good command and frames are handled normally
        assert agent.alive() and bridge.alive() and recorder.alive()
        now_t_ns = last_fuzz_t_ns  # a command may be in force at most 12 periods past the device's time
        probe = m.PvCommand(t_ns=1, seq=1, source="probe", cmd_id="probe:1", in_reply_to=0,
                            valid_until_t_ns=now_t_ns + 3_600_000_000_000, plant_id="pv680", q_kvar=-50.0)
        pubs[f"{F}/cmd/pv/pv680"].put(msgspec.json.encode(probe))
        ack = watcher.first(m.Ack, lambda a: a.cmd_id == "probe:1", 10, "the probe's ack")
        assert ack.status in ("accepted", "clipped"), ack
        after = watcher.wait(lambda: watcher.messages(m.Decision, lambda d: d.step_t_ns > last_fuzz_t_ns
                                                      and bool(d.commands)), 15, "the agent's next decision")
        assert after[0].status in ("optimal", "soft")
        # refusing most frames during the flood, the agent said 'degraded'; once it is over, 'ok' again
        last = watcher.messages(m.AgentStatus)[-1].seq
        watcher.first(m.AgentStatus, lambda s: s.seq > last and s.state == "ok", 20, "an 'ok' status after the flood")

    # the recorder kept every message of the feeder, bytes unchanged, in a valid file
    assert recorder.stop() == 0, recorder.log()
    info = recording_info(mcap)
    assert info.complete, info.problems
    # ... on its key's channel if it decodes as that key's type, else on the quarantine channel (issue 17 (e))
    recorded: Counter[str] = Counter()
    with open(mcap, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=False):
            if channel.topic == QUARANTINE_TOPIC:
                recorded[msgspec.json.decode(message.data, type=Quarantined).key] += 1
            else:
                msg_type = message_type_for_key(channel.topic)
                assert msg_type is not None, channel.topic
                codec_for(msg_type).decode(message.data)  # only what decodes sits on a real channel
                recorded[channel.topic] += 1
    for key, n in per_topic.items():
        if key.startswith(F + "/") and "/extra" not in key:
            assert recorded.get(key, 0) >= n, (key, recorded.get(key), n)
