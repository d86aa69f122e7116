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

from collections import Counter
from pathlib import Path
from typing import Any

import msgspec
import zenoh
from mcap.reader import make_reader
from relutil import Procs, Watcher, plain_session

from benchmarks.fuzz_live import AGENT_KEY, FAR_FUTURE_NS, SEED, TOPICS, F, Fuzzer
from recordings.recorder import QUARANTINE_TOPIC, Quarantined
from schemas import messages as m
from schemas.bus import codec_for
from schemas.keys import message_type_for_key

N_MESSAGES = 12_000


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
            payload = fuzz.payload(key, i)
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
        # the bridge acks the fuzz commands it refuses, and the agent refuses those acks too (``foreign_ack``: not
        # answers to its own commands): counted beyond what the fuzz sent the agent, at most that many
        foreign = a1.rejected.get("foreign_ack", 0) - a0.rejected.get("foreign_ack", 0)
        assert stale <= a_extra <= (stale + foreign + a1.rejected.get("queue_full", 0)
                                    - a0.rejected.get("queue_full", 0))
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
    # ... on its key's channel if it decodes as that key's type, else on the quarantine channel
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
