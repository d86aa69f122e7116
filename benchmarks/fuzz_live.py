"""``make fuzz``: thousands of hostile payloads at a live agent, bridge and recorder, and what each counted.

``python -m benchmarks.fuzz_live [N] [--seed S] [--out DIR]`` trains an IEEE 13 model (``cvvc train``), opens a
router on ``tcp/127.0.0.1`` in this process, starts ``cvvc record``, ``cvvc agent`` and a real-time ``cvvc bridge``
as processes, and, once decisions with commands come, publishes ``N`` (default 20,000) bad messages from a
plain-zenoh client on every topic of the feeder (what a broken device or an intruder without credentials would
use). It prints what was sent (by target and class) and what each process counted: the agent's and the
bridge's rejections by reason (their status messages), the recorder's messages per channel and its quarantine
channel, and whether every process survived and the agent still decides. Every process is stopped by its pid.

The generator (``Fuzzer``, ``TOPICS``) and the bus watcher are also what
``tests/reliability/test_live_fuzz.py`` uses: payloads meant to fail decoding are checked to fail with the
shared codec before they are sent; the schema-valid ones are built from real frames and commands seen so far
so that a later check must refuse each (replay, expiry, device range, unknown device, wrong feeder,
implausible values).
"""

from __future__ import annotations

import argparse
import json
import random
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypedDict

import msgspec
import zenoh

from benchmarks.bench_soak import run_folder, stop_process
from schemas import messages as m
from schemas.bus import MAX_PAYLOAD_BYTES, BadMessage, codec_for, has_subscribers
from schemas.errors import CvvcError
from schemas.examples import examples
from schemas.keys import message_type_for_key

__all__ = ["TOPICS", "FuzzError", "FuzzReport", "Fuzzer", "Watcher", "fuzz_live", "plain_session"]

REPO = Path(__file__).resolve().parents[1]
FEEDER = "ieee13"
FEEDER_MAP = REPO / "feeders" / "ieee13.toml"


class FuzzError(CvvcError):
    """The fuzz run could not start, or a process died; the message names it and its log."""


SEED = 20261121
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

    def __init__(self, seed: int, seen: Watcher) -> None:  # noqa: D107
        self.rng = random.Random(seed)
        self.seen = seen
        self.examples = {t: msgspec.to_builtins(x) for t, x in examples().items()}
        self.classes: Counter[str] = Counter()
        self.oversize_left = 12

    # ------------------------------------------------------------------ payloads that must not decode
    def undecodable(self, key: str) -> bytes:
        """A payload for ``key`` that must be refused at decode (a mutated valid message); FuzzError if none."""
        msg_type = message_type_for_key(key)
        if msg_type is None:
            raise FuzzError(f"{key} carries no message type")
        for _ in range(20):
            cls, raw = self._mutation(msg_type)
            try:
                codec_for(msg_type).decode(raw)
            except BadMessage:
                self.classes[cls] += 1
                return raw
        raise FuzzError(f"no undecodable mutation of {msg_type.__name__} found")

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
                bad: msgspec.Struct
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
        base = _CommandHeader(t_ns=1, seq=seq, source=f"fuzz{r.randrange(100)}", cmd_id=f"fuzz:{seq}",
                              in_reply_to=0, valid_until_t_ns=FAR_FUTURE_NS)
        expired = _CommandHeader(**(base | {"valid_until_t_ns": 1}))
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
                        m.PvCommand(**expired, plant_id=device, q_kvar=1.0))
                case "expired":
                    return msgspec.json.encode(m.PvCommand(**expired, plant_id=device,
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
                return msgspec.json.encode(m.RegCommand(**expired, regulator_id=device,
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
                return msgspec.json.encode(m.RegCommand(**expired, regulator_id=device,
                                                        action=action))

    def payload(self, key: str, i: int) -> bytes:
        """The ``i``-th bad message, for ``key``: schema-valid but refused by a later check (30 %) or undecodable."""
        target = TOPICS[key]
        payload = None
        if self.rng.random() < 0.3:  # schema-valid, refused by a later check
            payload = self.agent_semantic(key) if target == "agent" else (
                self.bridge_semantic(key) if target == "bridge" and "/extra" not in key
                and "otherfeeder" not in key else None)
        if payload is None and key == f"{F}/meas/head/extra" and self.rng.random() < 0.5:
            # a real head frame, newest seq, on a key one level too deep: refused by the key check
            self.classes["bad_key"] += 1
            head = self.seen.messages(m.HeadFrame, lambda f: f.source == "head" and f.seq < FAR_FUTURE_NS)[-1]
            payload = msgspec.json.encode(msgspec.structs.replace(head, seq=FAR_FUTURE_NS + i))
        if payload is None and target == "bridge" and (key.endswith("/extra") or "otherfeeder" in key):
            # a valid command on a key the bridge cannot answer on, or for a feeder without a bridge
            self.classes["bad_key"] += 1
            payload = msgspec.json.encode(m.PvCommand(t_ns=1, seq=i + 1, source="fuzz", cmd_id=f"k{i}",
                                                      in_reply_to=0, valid_until_t_ns=FAR_FUTURE_NS,
                                                      plant_id="pv675", q_kvar=1.0))
        return self.undecodable(key) if payload is None else payload

    def _replayed_command(self, msg_type: type[m.PvCommand] | type[m.RegCommand], device: str) -> bytes | None:
        decisions = self.seen.messages(m.Decision, lambda d: bool(d.commands))
        older = [c for d in decisions[:-1] for c in d.commands
                 if isinstance(c, msg_type) and _command_device(c) == device]
        return msgspec.json.encode(self.rng.choice(older)) if older else None


class _CommandHeader(TypedDict):
    """The fields every command has besides its device and value."""

    t_ns: int
    seq: int
    source: str
    cmd_id: str
    in_reply_to: int
    valid_until_t_ns: int


def _command_device(cmd: m.PvCommand | m.RegCommand) -> str:
    return cmd.plant_id if isinstance(cmd, m.PvCommand) else cmd.regulator_id


_FRAME_TYPE = {"head": m.HeadFrame, "pv": m.PvFrame, "vr": m.RegFrame}


def _device_of(frame: Any) -> str:
    return getattr(frame, "plant_id", None) or getattr(frame, "regulator_id", None) or "head"



class Watcher:
    """A plain-zenoh peer that decodes every sample of the feeder (and its liveliness) as it arrives."""

    def __init__(self, endpoint: str, feeder: str = FEEDER) -> None:
        from schemas.bus import BadMessage, codec_for
        from schemas.keys import message_type_for_key

        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        self.session = zenoh.open(conf)
        self._cond = threading.Condition()
        self.seen: list[tuple[str, Any, float]] = []
        self.alive: dict[str, bool] = {}
        self.undecodable = 0
        self.skip: tuple[str, ...] = ()  # key substrings not to keep (floods that tests send themselves)

        def on_sample(s: zenoh.Sample) -> None:
            key = str(s.key_expr)
            mtype = message_type_for_key(key)
            if mtype is None or any(part in key for part in self.skip):
                return
            try:
                msg = codec_for(mtype).decode(s.payload.to_bytes())
            except BadMessage:  # the fuzzers' own garbage, seen here too
                with self._cond:
                    self.undecodable += 1
                return
            with self._cond:
                self.seen.append((key, msg, time.monotonic()))
                self._cond.notify_all()

        def on_alive(s: zenoh.Sample) -> None:
            with self._cond:
                self.alive[str(s.key_expr)] = s.kind == zenoh.SampleKind.PUT
                self._cond.notify_all()

        self._sub = self.session.declare_subscriber(f"cvvc/{feeder}/**", on_sample)
        self._live = self.session.liveliness().declare_subscriber(f"cvvc/{feeder}/alive/**", on_alive,
                                                                  history=True)

    def messages(self, msg_type: type, pred: Callable[[Any], bool] = lambda x: True) -> list[Any]:
        """The messages of ``msg_type`` seen so far for which ``pred`` holds, in arrival order."""
        with self._cond:
            return [x for _, x, _ in self.seen if isinstance(x, msg_type) and pred(x)]

    def wait(self, pred: Callable[[], Any], timeout_s: float, what: str) -> Any:
        """Wait until ``pred()`` is truthy (re-checked on every sample); its value, or AssertionError."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                value = pred()
                if value:
                    return value
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
                self._cond.wait(min(remaining, 0.1))

    def first(self, msg_type: type, pred: Callable[[Any], bool], timeout_s: float, what: str) -> Any:
        """The first message of ``msg_type`` (seen so far or to come) for which ``pred`` holds."""
        def find() -> Any:
            for _, x, _ in self.seen:
                if isinstance(x, msg_type) and pred(x):
                    return x
            return None
        return self.wait(find, timeout_s, what)

    def is_alive(self, key: str) -> bool:
        """Whether the liveliness token ``key`` is alive now."""
        with self._cond:
            return self.alive.get(key, False)

    def close(self) -> None:
        """Undeclare the subscribers and close the session."""
        self._sub.undeclare()
        self._live.undeclare()
        self.session.close()


def plain_session(endpoint: str, mode: str = "peer") -> zenoh.Session:
    """A plain-zenoh session (what an attacker or a broken device would use); a client routes everything
    through the router (one link: no route change while it sends).
    """
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if mode != "client":
        conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    return zenoh.open(conf)



class FuzzReport(msgspec.Struct, frozen=True, kw_only=True):
    """What one live fuzz run sent and what each process counted.

    ``sent`` by target (``agent``, ``bridge``, ``none``: only the recorder reads it); ``classes`` by kind of
    payload; ``agent_rejected`` / ``bridge_rejected`` the growth of each process's rejection counts during the
    run, by reason; ``recorded`` messages per channel of the recording (``quarantined`` of them on the quarantine
    channel); ``alive`` whether every process was still running at the end; ``decided_after`` whether the agent
    decided (with commands) after the flood.
    """

    n: int
    seed: int
    topics: int
    wall_s: float
    sent: dict[str, int]
    classes: dict[str, int]
    agent_rejected: dict[str, int]
    bridge_rejected: dict[str, int]
    recorded: dict[str, int]
    quarantined: int
    recording_complete: bool
    alive: dict[str, bool]
    decided_after: bool


def _spawn(name: str, args: list[str], log_dir: Path) -> subprocess.Popen[bytes]:
    with open(log_dir / f"{name}.log", "wb") as log:
        return subprocess.Popen([sys.executable, "-m", "cvvc", *args], cwd=REPO, stdout=log,
                                stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)


def _delta(now: dict[str, int], before: dict[str, int]) -> dict[str, int]:
    return {k: v - before.get(k, 0) for k, v in sorted(now.items()) if v - before.get(k, 0)}


def fuzz_live(n: int = 20_000, seed: int = SEED, out_dir: Path | None = None) -> FuzzReport:
    """Throw ``n`` bad messages at live processes on IEEE 13 (module docstring); the counts of the run."""
    from recordings.info import recording_info
    from recordings.recorder import QUARANTINE_TOPIC, Quarantined
    from schemas.bus import BusConfig, free_port, open_session

    out, tmp = run_folder(out_dir, "cvvc-fuzz-")
    model, mcap = out / "ieee13-model.json", out / "fuzz.mcap"
    trained = subprocess.run([sys.executable, "-m", "cvvc", "train", "--feeder", str(FEEDER_MAP), "--out",
                              str(model), "--json", "--workers", "1", "--cache", str(out / "cache")], cwd=REPO,
                             capture_output=True, text=True, timeout=600)
    if trained.returncode != 0:
        raise FuzzError(f"cvvc train failed ({trained.returncode}):\n{trained.stderr[-2000:]}")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    bus = ["--connect", endpoint, "--insecure"]  # the payloads come from a plain client: decoding, not authentication
    procs: dict[str, subprocess.Popen[bytes]] = {}
    t0 = time.monotonic()
    try:
        with open_session(BusConfig(mode="router", listen=(endpoint,))):
            watcher = Watcher(endpoint)
            try:
                procs["recorder"] = _spawn("recorder", ["record", "--out", str(mcap), "--keys", f"cvvc/{FEEDER}/**",
                                                        "--flush-period-s", "0.5", *bus], out)
                procs["agent"] = _spawn("agent", ["agent", "--model", str(model), "--feeder-id", FEEDER,
                                                  "--stale-after-s", "5", *bus], out)
                watcher.wait(lambda: watcher.is_alive(AGENT_KEY), 60, "the agent's liveliness token")
                procs["bridge"] = _spawn("bridge", [
                    "bridge", "--feeder", str(FEEDER_MAP), "--cache-dir", str(out / "cache" / "profiles"),
                    "--start", "2023-07-01T12:00", "--truth-every", "0", "--realtime", "--speed", "300",
                    "--steps", "100000", *bus], out)
                watcher.wait(lambda: len(watcher.messages(m.Decision, lambda d: bool(d.commands))) >= 3, 120,
                             "three decisions with commands")
                a0 = watcher.first(m.AgentStatus, lambda s: s.state == "ok", 20, "an 'ok' agent status")
                b0 = watcher.messages(m.BridgeStatus)[-1]
                watcher.skip = ("/ghost", "/extra")
                fuzz = Fuzzer(seed, watcher)
                topics = list(TOPICS)
                sent: Counter[str] = Counter()
                with plain_session(endpoint, mode="client") as session:
                    pubs = {k: session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)
                            for k in topics}
                    watcher.wait(lambda: all(has_subscribers(p) for p in pubs.values()), 20,
                                 "every topic's subscribers")
                    for i in range(n):
                        key = topics[i % len(topics)]
                        pubs[key].put(fuzz.payload(key, i))
                        sent[TOPICS[key]] += 1
                    last_t_ns = watcher.messages(m.HeadFrame, lambda f: f.source == "head"
                                                 and f.seq < FAR_FUTURE_NS)[-1].t_ns

                    def settled(msgs: list, base: Any, k: int) -> Any:
                        total = sum(msgs[-1].rejected.values()) - sum(base.rejected.values()) if msgs else -1
                        return msgs[-1] if total >= k else None

                    try:
                        watcher.wait(lambda: settled(watcher.messages(m.AgentStatus), a0, sent["agent"]), 60, "")
                        watcher.wait(lambda: settled(watcher.messages(m.BridgeStatus), b0, sent["bridge"]), 60, "")
                    except AssertionError:
                        pass  # report what was counted, whatever it is
                    try:
                        watcher.wait(lambda: watcher.messages(m.Decision, lambda d: d.step_t_ns > last_t_ns
                                                              and bool(d.commands)), 30, "a decision after")
                        decided_after = True
                    except AssertionError:
                        decided_after = False
                    time.sleep(1.5)  # one more status of each (published every second) with the last counts
                    a1, b1 = watcher.messages(m.AgentStatus)[-1], watcher.messages(m.BridgeStatus)[-1]
                alive = {name: p.poll() is None for name, p in procs.items()}
            finally:
                watcher.close()
                for name in ("bridge", "agent", "recorder"):
                    if name in procs:
                        stop_process(procs[name])
    finally:
        for p in procs.values():
            stop_process(p)
    from mcap.reader import make_reader

    recorded: Counter[str] = Counter()
    quarantined = 0
    with open(mcap, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=False):
            if channel.topic == QUARANTINE_TOPIC:
                quarantined += 1
                recorded["quarantine:" + msgspec.json.decode(message.data, type=Quarantined).key] += 1
            else:
                recorded[channel.topic] += 1
    complete = recording_info(mcap).complete
    if tmp is not None:
        tmp.cleanup()
    return FuzzReport(n=n, seed=seed, topics=len(TOPICS), wall_s=round(time.monotonic() - t0, 1), sent=dict(sent),
                      classes=dict(sorted(fuzz.classes.items())), agent_rejected=_delta(a1.rejected, a0.rejected),
                      bridge_rejected=_delta(b1.rejected, b0.rejected), recorded=dict(sorted(recorded.items())),
                      quarantined=quarantined, recording_complete=complete, alive=alive, decided_after=decided_after)


def render(r: FuzzReport) -> str:
    """The report as text: what was sent and what each process counted."""
    def line(d: dict[str, int]) -> str:
        return ", ".join(f"{k} {v:,}" for k, v in sorted(d.items(), key=lambda kv: -kv[1]))

    real = {k: v for k, v in r.recorded.items() if not k.startswith("quarantine:")}
    return "\n".join([
        f"fuzz: {r.n:,} hostile payloads on {r.topics} topics (seed {r.seed}) in {r.wall_s:.0f} s",
        f"sent to: {line(r.sent)}",
        f"classes: {line(r.classes)}",
        f"agent counted {sum(r.agent_rejected.values()):,} refused (sent it {r.sent.get('agent', 0):,}): "
        f"{line(r.agent_rejected)}",
        f"bridge counted {sum(r.bridge_rejected.values()):,} refused (sent it {r.sent.get('bridge', 0):,}): "
        f"{line(r.bridge_rejected)}",
        f"recorder: {sum(real.values()):,} messages on {len(real)} channels, {r.quarantined:,} quarantined; "
        f"file complete: {r.recording_complete}",
        f"alive at the end: {', '.join(f'{k} {v}' for k, v in r.alive.items())}; "
        f"the agent decided after the flood: {r.decided_after}",
    ])


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.fuzz_live [N] [--seed S] [--out DIR] [--json]``."""
    p = argparse.ArgumentParser(prog="python -m benchmarks.fuzz_live", description=__doc__.splitlines()[0])
    p.add_argument("n", nargs="?", type=int, default=20_000, help="hostile payloads to send (default 20000)")
    p.add_argument("--seed", type=int, default=SEED, help=f"generator seed (default {SEED})")
    p.add_argument("--out", default=None, help="keep the logs, model and recording here (default: a temporary folder)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    args = p.parse_args(argv)
    try:
        report = fuzz_live(args.n, args.seed, Path(args.out) if args.out else None)
    except CvvcError as e:
        print(f"fuzz: error: {e}", file=sys.stderr)
        return 2
    print(msgspec.json.format(msgspec.json.encode(report)).decode() if args.json else render(report))
    return 0 if all(report.alive.values()) and report.decided_after else 1


if __name__ == "__main__":
    raise SystemExit(main())
