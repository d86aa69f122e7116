"""Trust nothing on the wire: attacks on a running agent through the real bus, in the default (secure) mode.

A router with the access policy on loopback, the agent (with the device map) and a lockstep bridge as processes with
their certificates; the attacker holds a ``devices`` certificate (a compromised field gateway: the policy lets it put
frames and acks, and read commands and the head frames). One clean window and one attacked window of the same half
hour of IEEE 13 daylight (30 one-minute steps, six control steps), each run once per module; the attacked window
carries every attack at once:

* forged AMI readings at 0.80 pu for every critical node of a map without meters, each claiming a day-long interval;
* head frames dated 2100 from made-up sources ``x1``, ``x2``;
* near-future head frames: for each control step, a head frame stamped 3 s after it (snapped onto it by the clock
  tolerance) with a ``seq`` a million above the real one;
* forged agent commands stamped ahead with the largest ``seq`` (to lock the agent out of a plant) and rogue bank
  commands (the policy lets only the ``agent`` certificate command: they reach no device);
* a forged ``Decision`` without commands for each control step (to release the lockstep step before the agent's
  commands are applied; only the ``agent`` certificate may put decisions);
* ``rejected`` acks, PV and capacitor, for commands the agent never sent.

A third window runs the same half hour with every plant behind a simulated SunSpec inverter and its adapter process
(``cvvc run --pv-protocol sunspec``): from the second control step on, a rogue Modbus master connects to every
inverter and writes full absorption at each control step.

Asserted: no rogue command or set point applied, every input refused and counted, at least 95 % of the due decisions
made, NVV within 100 node-minutes of the clean window.
"""

from __future__ import annotations

import datetime as dt
import queue
import threading
from pathlib import Path

import msgspec
import pytest
import zenoh
from relutil import FEEDER, Attack, secure_window

from adapters.errors import AdapterError, DeviceRefusedError
from adapters.sunspec import SunSpecLink
from agent.runtime import AgentSummary
from cvvc.integrity import run_integrity
from regression.model import read_model
from schemas import keys
from schemas import messages as m
from schemas.bus import codec_for, free_port, wait_for
from schemas.examples import example
from simulator_bridge.bus.bridge import BridgeSummary

pytestmark = [pytest.mark.bus, pytest.mark.process, pytest.mark.slow]  # a secure router, cvvc programs, two runs

NS = 10**9
STEPS = 30  # six control steps of 5 minutes
PERIOD_NS = 300 * NS
T_2100 = 4_102_444_800 * NS
T0 = int(dt.datetime(2023, 7, 1, 17, tzinfo=dt.UTC).timestamp()) * NS  # NOON, local standard time (UTC-5)
PLANT = "pv675"
BANK = "cap1"  # a bank of the circuit that the map does not declare


def _publisher(session: zenoh.Session, key: str) -> zenoh.Publisher:
    return session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)


class ForgedMeters(Attack):
    """A reading at 0.80 pu for every critical node, from meters a map without meters does not declare."""

    def __init__(self, nodes: list[str]) -> None:
        super().__init__()
        self.nodes = nodes

    def arm(self, forger: zenoh.Session) -> None:
        for i, node in enumerate(self.nodes):
            pub = _publisher(forger, keys.meas_ami(FEEDER, f"m{i}"))
            assert wait_for(lambda p=pub: bool(p.matching_status.matching), 10.0)
            pub.put(codec_for(m.MeterFrame).encode(m.MeterFrame(
                t_ns=T0, seq=10**9, source=f"m{i}", meter_id=f"m{i}", node=node, v_pu=0.80, interval_s=86_400)))
            self.count("meters")


class FarFutureHeads(Attack):
    """Two head frames dated 2100 from the made-up sources ``x1`` and ``x2`` (two 'devices' agreeing on a new time)."""

    def arm(self, forger: zenoh.Session) -> None:
        pub = _publisher(forger, keys.meas_head(FEEDER))
        assert wait_for(lambda: bool(pub.matching_status.matching), 10.0)
        for source in ("x1", "x2"):
            pub.put(codec_for(m.HeadFrame).encode(msgspec.structs.replace(
                example(m.HeadFrame), t_ns=T_2100, seq=10**12, source=source, feeder_id=FEEDER)))
            self.count("heads_2100")


class ForeignAcks(Attack):
    """'rejected' acks of a plant and of a bank for commands the agent never sent."""

    def arm(self, forger: zenoh.Session) -> None:
        for kind, device in (("pv", PLANT), ("cap", BANK)):
            pub = _publisher(forger, keys.ack(FEEDER, kind, device))
            assert wait_for(lambda p=pub: bool(p.matching_status.matching), 10.0)  # or the acks reach no one
            for i in range(5):
                pub.put(codec_for(m.Ack).encode(m.Ack(
                    t_ns=T0, seq=i + 1, source=device, cmd_id=f"agent:{T0}:{device}:{i}", device_id=device,
                    status="rejected", applied_value=None, reason="forged")))
                self.count(f"acks_{kind}")


class OnEachControlStep(Attack):
    """Watches the real head frames (the policy lets a devices certificate read them) and, once for every control
    step of the window ahead of the one just seen, puts: a head frame stamped 3 s after it with a seq a million above
    the real one, a command to a plant stamped a period ahead with the largest seq, a rogue bank command, and a
    decision without commands for that step (a few small puts, from the subscriber's callback)."""

    def __init__(self) -> None:
        super().__init__()
        self.heads: list[m.HeadFrame] = []
        self.done: set[int] = set()

    def arm(self, forger: zenoh.Session) -> None:
        self.pub_head = _publisher(forger, keys.meas_head(FEEDER))
        self.pub_cmd = _publisher(forger, keys.cmd(FEEDER, "pv", PLANT))
        self.pub_bank = _publisher(forger, keys.cmd(FEEDER, "cap", BANK))
        self.pub_decision = _publisher(forger, keys.agent_decision(FEEDER))
        codec = codec_for(m.HeadFrame)
        self.sub = forger.declare_subscriber(keys.meas_head(FEEDER), lambda s: self._on_head(codec, s))

    def _on_head(self, codec, sample: zenoh.Sample) -> None:
        head = codec.decode(sample.payload.to_bytes())
        if head.t_ns % (60 * NS) or head.t_ns >= T_2100:  # not a real step's frame (our own forgeries come back too)
            return
        nxt = (head.t_ns // PERIOD_NS + 1) * PERIOD_NS  # the next control step
        if nxt in self.done or nxt >= T0 + STEPS * 60 * NS:  # none after the window's last step: every forgery
            return  # then reaches the agent while it runs, however late the forger is
        self.done.add(nxt)
        self.pub_head.put(codec.encode(msgspec.structs.replace(head, t_ns=nxt + 3 * NS, seq=head.seq + 10**6)))
        self.count("near_future_heads")
        self.pub_cmd.put(codec_for(m.PvCommand).encode(m.PvCommand(
            t_ns=nxt + PERIOD_NS - NS, seq=2**63 - 1, source="agent", cmd_id=f"rogue-pv-{nxt}", in_reply_to=0,
            valid_until_t_ns=nxt + 10 * PERIOD_NS, plant_id=PLANT, q_kvar=-300.0)))
        self.count("commands_ahead")
        self.pub_bank.put(codec_for(m.CapCommand).encode(m.CapCommand(
            t_ns=nxt, seq=2**63 - 1, source="agent", cmd_id=f"rogue-cap-{nxt}", in_reply_to=0,
            valid_until_t_ns=nxt + 2 * PERIOD_NS, capacitor_id=BANK, closed_steps=0)))
        self.count("bank_commands")
        self.pub_decision.put(codec_for(m.Decision).encode(m.Decision(
            t_ns=nxt, seq=10**9, source="agent", feeder_id=FEEDER, step_t_ns=nxt, in_reply_to=head.seq + 1,
            status="hold", reason="forged")))
        self.count("decisions")


class RogueMaster(Attack):
    """A second Modbus master on the plants' network: from the second control step on, at each control step it writes
    full absorption (-800 kvar, an hour's revert time) into every inverter. The writes run on a thread of their own."""

    def __init__(self, endpoints: dict[str, str]) -> None:
        super().__init__()
        self.endpoints = endpoints
        self.links: dict[str, SunSpecLink] = {}
        self.steps: queue.Queue[int | None] = queue.Queue()
        self.thread = threading.Thread(target=self._write, name="rogue-master", daemon=True)
        self.seen: set[int] = set()

    def arm(self, forger: zenoh.Session) -> None:
        codec = codec_for(m.HeadFrame)
        self.sub = forger.declare_subscriber(keys.meas_head(FEEDER), lambda s: self._on_head(codec, s))
        self.thread.start()

    def _on_head(self, codec, sample: zenoh.Sample) -> None:
        t = codec.decode(sample.payload.to_bytes()).t_ns
        if t % PERIOD_NS == 0 and t >= T0 + PERIOD_NS and t not in self.seen:  # the adapters are connected by then
            self.seen.add(t)
            self.steps.put(t)

    def _write(self) -> None:
        while self.steps.get() is not None:
            for pid, ep in self.endpoints.items():
                host, port = ep.removeprefix("tcp/").rsplit(":", 1)
                try:
                    if pid not in self.links:
                        self.links[pid] = SunSpecLink(host, int(port), timeout_s=2.0)
                        self.links[pid].read()  # learns the scale factors, as any master would
                    self.links[pid].write_var_setpoint(-800.0, 3600)
                    self.count("applied")
                except DeviceRefusedError:
                    self.count("refused")
                except AdapterError as e:  # the test says what went wrong instead of a dead thread
                    self.count(f"failed: {e}"[:200])

    def close(self) -> None:
        if self.thread.is_alive():
            self.steps.put(None)
            self.thread.join(30.0)
        for link in self.links.values():
            link.close()
        self.links.clear()


@pytest.fixture(scope="module")
def clean(tmp_path_factory, model13: Path, rel_cache: Path, secure_certs: Path) -> dict:
    """The window without an attacker (run once per module)."""
    return secure_window(tmp_path_factory.mktemp("clean"), model13, rel_cache, secure_certs, steps=STEPS)


@pytest.fixture(scope="module")
def attacked(tmp_path_factory, model13: Path, rel_cache: Path, secure_certs: Path) -> dict:
    """The same window with every attack of the module at once (run once per module)."""
    nodes = [c.name for c in read_model(model13).critical_nodes]
    attacks = (ForgedMeters(nodes), FarFutureHeads(), ForeignAcks(), OnEachControlStep())
    out = secure_window(tmp_path_factory.mktemp("attacked"), model13, rel_cache, secure_certs, steps=STEPS,
                        attacks=attacks)
    out["critical_nodes"] = len(nodes)
    return out


def _applied(bridge: dict) -> int:
    return bridge["acks"].get("accepted", 0) + bridge["acks"].get("clipped", 0)


def test_the_clean_window_decides_every_control_step_and_refuses_nothing(clean):
    agent, bridge = clean["agent"], clean["bridge"]
    assert agent["decisions"] == bridge["control_steps"] == STEPS // 5 and bridge["lockstep_misses"] == 0
    assert _applied(bridge) == agent["commands"] > 0 and agent["rejected"] == {}


def test_no_rogue_command_or_decision_reaches_a_device_or_the_lockstep(attacked):
    """Commands stamped a period ahead with the largest seq (on old code, without the policy, they were applied and
    locked the agent out of the plant for a period), rogue bank commands and forged decisions: the devices apply the
    agent's commands only, and the bridge takes the agent's decisions only (a forged one would release the step)."""
    agent, bridge, sent = attacked["agent"], attacked["bridge"], attacked["sent"]["OnEachControlStep"]
    assert sent["commands_ahead"] == sent["bank_commands"] == sent["decisions"] >= STEPS // 5 - 1
    assert _applied(bridge) == agent["commands"] > 0  # every command applied is the agent's
    assert agent["acks"].get("rejected", 0) == 0  # and none of the agent's was refused (no lockout)
    assert not {"replay", "out_of_window", "unknown_device"} & set(bridge["rejected"])  # none even reached it
    assert bridge["decisions"] == agent["decisions"] and bridge["lockstep_misses"] == 0


def test_decisions_and_violations_hold_under_attack(attacked, clean):
    agent, bridge = attacked["agent"], attacked["bridge"]
    assert agent["decisions"] >= 0.95 * bridge["control_steps"] and bridge["control_steps"] == STEPS // 5
    assert bridge["metrics"]["nvv"] <= clean["bridge"]["metrics"]["nvv"] + 100
    integrity = run_integrity(msgspec.convert(agent, AgentSummary), msgspec.convert(bridge, BridgeSummary), {},
                              step_s=60, control_period_s=300)
    assert integrity.degraded == "" and integrity.foreign_decisions == 0


def test_forged_meter_readings_on_a_map_without_meters_change_nothing_and_are_counted(attacked):
    agent, sent = attacked["agent"], attacked["sent"]["ForgedMeters"]
    assert sent["meters"] == attacked["critical_nodes"] > 0
    assert agent["ami"].get("ami_readings", 0) == 0 and agent["ami"].get("ami_used", 0) == 0
    assert agent["ami"]["ami_unknown_meter"] == sent["meters"]
    assert agent["rejected"]["unknown_device"] >= sent["meters"]


def test_head_frames_of_made_up_sources_dated_2100_do_not_blind_the_agent(attacked):
    """Before the clock-jump rule counted devices of the map, two made-up sources agreeing moved the clock to 2100:
    every real frame was then stale and 2 of 6 steps were decided."""
    agent, bridge = attacked["agent"], attacked["bridge"]
    assert bridge["lockstep_misses"] == 0 and agent["decisions"] == STEPS // 5 == bridge["decisions"]
    assert agent["rejected"].get("stale", 0) == 0


def test_near_future_head_frames_with_a_high_seq_never_replace_the_real_ones(attacked):
    """A head frame 3 s after a control step is snapped onto it; with a seq a million above the device's it was taken
    as the step's head (the real one then refused as out of order); later a jump was held for the device's next frame,
    and a forgery arriving late was confirmed by the forger's next one. Now a frame breaking the sequence of a device
    that still reports is refused: each is refused ``seq_jump`` whenever it arrives, every real head frame taken."""
    agent, sent = attacked["agent"], attacked["sent"]["OnEachControlStep"]
    assert agent["rejected"]["seq_jump"] == sent["near_future_heads"] >= STEPS // 5 - 1
    assert agent["rejected"].get("out_of_order", 0) == 0 and agent["rejected"].get("duplicate", 0) == 0


def test_rejected_acks_for_commands_the_agent_never_sent_are_refused_and_counted(attacked):
    """Before acks were checked against the commands sent, a forged 'rejected' ack was taken (a bank's held it)."""
    agent, sent = attacked["agent"], attacked["sent"]["ForeignAcks"]
    assert agent["rejected"]["foreign_ack"] == sent["acks_pv"] + sent["acks_cap"] == 10
    assert agent["acks"].get("rejected", 0) == 0 and agent.get("commands_refused", {}) == {}
    assert agent["acks"].get("accepted", 0) + agent["acks"].get("clipped", 0) == agent["commands"] > 0


@pytest.fixture(scope="module")
def sunspec_attacked(tmp_path_factory, model13: Path, rel_cache: Path, secure_certs: Path) -> dict:
    """The window with every plant behind SunSpec and a rogue Modbus master at every inverter (run once per module)."""
    endpoints = {pid: f"tcp/127.0.0.1:{free_port()}" for pid in ("pv675", "pv680", "pv633")}
    rogue = RogueMaster(endpoints)
    return secure_window(tmp_path_factory.mktemp("sunspec"), model13, rel_cache, secure_certs, steps=STEPS,
                         attacks=(rogue,), sunspec=endpoints)


def test_a_rogue_modbus_master_is_refused_by_every_inverter_and_changes_nothing(sunspec_attacked, clean):
    """Before, the simulated inverter took any connection's write: the rogue -800 kvar held until the adapter's next
    scan undid it (a foreign write, counted). Now only the adapter's connection, the inverter's one master, writes."""
    agent, bridge, links = sunspec_attacked["agent"], sunspec_attacked["bridge"], sunspec_attacked["links"]
    sent = sunspec_attacked["sent"]["RogueMaster"]
    assert set(sent) == {"refused"} and sent["refused"] >= 3 * (STEPS // 5 - 2), sent  # none applied, none failed
    assert sum(bridge["sunspec_foreign_master_writes"].values()) == sent["refused"]
    assert set(bridge["sunspec_foreign_master_writes"]) == set(links)
    assert all(link["foreign_writes"] == 0 for link in links.values())  # no scan found a set point not its adapter's
    assert agent["acks"].get("accepted", 0) + agent["acks"].get("clipped", 0) == agent["commands"] > 0
    assert agent["decisions"] >= 0.95 * bridge["control_steps"] and bridge["lockstep_misses"] == 0
    assert bridge["metrics"]["nvv"] <= clean["bridge"]["metrics"]["nvv"] + 100
    integrity = run_integrity(msgspec.convert(agent, AgentSummary), msgspec.convert(bridge, BridgeSummary),
                              {pid: msgspec.convert(x, m.LinkStatus) for pid, x in links.items()}, step_s=60,
                              control_period_s=300)
    assert integrity.degraded == "" and sum(integrity.foreign_master_writes.values()) == sent["refused"]
