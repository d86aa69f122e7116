"""Faults on real processes (IEEE 13, real OpenDSS, real Zenoh on loopback): what the system does.

docs/reliability.md lists each fault, the behaviour and the test here that shows it.
"""

from __future__ import annotations

from relutil import FEEDER, Procs, Watcher

from schemas import messages as m

CONTROL_PERIOD_NS = 300 * 1_000_000_000  # IEEE 13 device map: 5-minute control period
AGENT_KEY = f"cvvc/{FEEDER}/alive/agent/agent"


def _decisions_with_commands(w: Watcher, after_t_ns: int = -1) -> list[m.Decision]:
    return w.messages(m.Decision, lambda d: d.commands and d.step_t_ns > after_t_ns)


def _last_head_t_ns(w: Watcher) -> int:
    heads = w.messages(m.HeadFrame)
    return heads[-1].t_ns if heads else -1


# ----------------------------------------------------------------------------------- agent killed
def test_agent_killed_devices_fall_back_and_a_restarted_agent_resumes(procs: Procs, watcher: Watcher) -> None:
    # real time at 300x: one 1-minute step every 0.2 s, a control step every second of wall time; commands
    # are valid for two control periods (10 simulated minutes, 2 s of wall time)
    agent = procs.agent()
    watcher.wait(lambda: watcher.is_alive(AGENT_KEY), 30, "the agent's liveliness token")
    bridge = procs.bridge("--realtime", "--speed", "300", "--steps", "100000")
    first = watcher.wait(lambda: _decisions_with_commands(watcher), 30, "a decision with commands")[0]
    sent = {c.cmd_id for c in first.commands}
    good = ("accepted", "clipped")
    good = ("accepted", "clipped")
    watcher.wait(lambda: sent <= {a.cmd_id for a in watcher.messages(m.Ack, lambda a: a.status in good)},
                 10, "acks of the first commands")

    agent.kill()
    killed_at_t_ns = _last_head_t_ns(watcher)
    # the bridge reports the agent's liveliness loss
    watcher.first(m.BridgeStatus, lambda s: not s.agent_alive and s.t_ns > killed_at_t_ns, 10,
                  "a BridgeStatus with agent_alive false")
    # the last commands expire and every device is back on its local default
    last_cmds = {c.cmd_id: c for d in watcher.messages(m.Decision) for c in d.commands}
    last_valid = max(c.valid_until_t_ns for c in last_cmds.values())
    commanded = {c.plant_id if isinstance(c, m.PvCommand) else c.regulator_id for c in last_cmds.values()}
    watcher.wait(lambda: {a.device_id for a in watcher.messages(m.Ack, lambda a: a.status == "expired")}
                 >= commanded, 15, "expired acks from every commanded device")
    after = last_valid + 1
    pv = watcher.first(m.PvFrame, lambda f: f.t_ns > after, 10, "a PV frame after the expiry")
    reg = watcher.first(m.RegFrame, lambda f: f.t_ns > after, 10, "a regulator frame after the expiry")
    assert pv.q_setpoint_kvar is None and pv.local_mode == "unity_pf"
    assert reg.mode == "local"

    # an agent restarted with the same model resumes control within one control interval
    procs.agent()
    watcher.wait(lambda: watcher.is_alive(AGENT_KEY), 30, "the restarted agent's token")
    up_t_ns = _last_head_t_ns(watcher)
    resumed = watcher.wait(lambda: _decisions_with_commands(watcher, up_t_ns), 15,
                           "a decision with commands from the restarted agent")[0]
    assert resumed.step_t_ns - up_t_ns <= CONTROL_PERIOD_NS
    ids = {c.cmd_id for c in resumed.commands}
    acks = watcher.wait(lambda: (lambda got: got if {a.cmd_id for a in got} >= ids else None)(
        watcher.messages(m.Ack, lambda a: a.cmd_id in ids)), 10, "acks of the restarted agent's commands")
    assert {a.status for a in acks} <= {"accepted", "clipped"}, [(a.device_id, a.status, a.reason) for a in acks]
    assert bridge.alive()
