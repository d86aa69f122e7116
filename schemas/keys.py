"""Zenoh key expressions of the cvvc bus, and which message type each key carries.

Layout, for a feeder id ``F`` and a device id ``D``::

    cvvc/F/meas/head            HeadFrame        feeder-head meter
    cvvc/F/meas/pv/D            PvFrame          PV plant inverter
    cvvc/F/meas/vr/D            RegFrame         regulator controller
    cvvc/F/meas/cap/D           CapFrame         capacitor bank (its switch and local control)
    cvvc/F/meas/ami/D           MeterFrame       AMI meter at a customer node (explicit option, every interval)
    cvvc/F/meas/step            StepEnd          end of a scan: which devices sent a frame for that time
    cvvc/F/cmd/pv/D             PvCommand        agent -> inverter
    cvvc/F/cmd/vr/D             RegCommand       agent -> regulator controller
    cvvc/F/cmd/cap/D            CapCommand       agent -> capacitor bank
    cvvc/F/ack/pv/D, ack/vr/D, ack/cap/D   Ack   device -> agent
    cvvc/F/link/pv/D, link/vr/D, link/cap/D   LinkStatus   a field-protocol adapter's link to its device
                                             (SunSpec, DNP3)
    cvvc/F/agent/decision       Decision
    cvvc/F/agent/status         AgentStatus
    cvvc/F/sim/truth            TruthPack        simulation only (MessagePack: schemas.truth)
    cvvc/F/sim/metrics          MetricsFrame     simulation only
    cvvc/F/sim/status           BridgeStatus     simulation only
    cvvc/F/sim/oracle           OracleRequest -> OracleReply (queryable, case A)
    cvvc/F/alive/<role>/<id>    liveliness tokens (role: agent, head, pv, vr, cap, bridge, recorder)
"""

from __future__ import annotations

import re
from typing import Literal

import msgspec

from schemas import messages as m
from schemas.errors import CvvcError

__all__ = [
    "KeyExprError",
    "Role",
    "ack",
    "agent_decision",
    "agent_status",
    "alive",
    "alive_all",
    "cmd",
    "feeder_all",
    "link",
    "meas_ami",
    "meas_cap",
    "meas_head",
    "meas_pv",
    "meas_step",
    "meas_vr",
    "message_type_for_key",
    "parse_device_key",
    "sim_metrics",
    "sim_oracle",
    "sim_status",
    "sim_truth",
]

ROOT = "cvvc"
_ID = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")
DeviceKind = Literal["pv", "vr", "cap"]
Role = Literal["agent", "head", "pv", "vr", "cap", "bridge", "recorder"]


class KeyExprError(CvvcError):
    """An id that cannot be part of a key expression (empty, too long, or with '/', '*', '$', ...)."""


def _id(value: str) -> str:
    if not _ID.match(value):
        raise KeyExprError(f"{value!r} is not a valid id: use 1-64 of A-Z a-z 0-9 _ . -")
    return value


def feeder_all(feeder: str) -> str:
    """Every key of one feeder (a subscription pattern)."""
    return f"{ROOT}/{_id(feeder)}/**"


def meas_head(feeder: str) -> str:
    """The head meter's ``HeadFrame`` (bridge -> agent)."""
    return f"{ROOT}/{_id(feeder)}/meas/head"


def meas_pv(feeder: str, plant: str = "*") -> str:
    """A PV plant's ``PvFrame`` (bridge -> agent); ``*`` for every plant."""
    return f"{ROOT}/{_id(feeder)}/meas/pv/{plant if plant == '*' else _id(plant)}"


def meas_vr(feeder: str, regulator: str = "*") -> str:
    """A regulator controller's ``RegFrame`` (bridge -> agent); ``*`` for every regulator."""
    return f"{ROOT}/{_id(feeder)}/meas/vr/{regulator if regulator == '*' else _id(regulator)}"


def meas_ami(feeder: str, meter: str = "*") -> str:
    """An AMI meter's ``MeterFrame`` (bridge -> agent); ``*`` for every meter."""
    return f"{ROOT}/{_id(feeder)}/meas/ami/{meter if meter == '*' else _id(meter)}"


def meas_cap(feeder: str, capacitor: str = "*") -> str:
    """A capacitor bank's ``CapFrame`` (bridge -> agent); ``*`` for every bank."""
    return f"{ROOT}/{_id(feeder)}/meas/cap/{capacitor if capacitor == '*' else _id(capacitor)}"


def meas_step(feeder: str) -> str:
    """The bridge's ``StepEnd`` marker: every frame of a step was put (bridge -> agent, lockstep)."""
    return f"{ROOT}/{_id(feeder)}/meas/step"


def cmd(feeder: str, kind: DeviceKind, device: str = "*") -> str:
    """Commands to a device of ``kind`` (``PvCommand``, ``RegCommand``, ``CapCommand``; agent -> bridge)."""
    return f"{ROOT}/{_id(feeder)}/cmd/{kind}/{device if device == '*' else _id(device)}"


def ack(feeder: str, kind: DeviceKind, device: str = "*") -> str:
    """A device's ``Ack`` of each command it got (bridge -> agent)."""
    return f"{ROOT}/{_id(feeder)}/ack/{kind}/{device if device == '*' else _id(device)}"


def link(feeder: str, kind: DeviceKind, device: str = "*") -> str:
    """A field-protocol adapter's ``LinkStatus`` of its device (adapter -> agent, recorder, operators)."""
    return f"{ROOT}/{_id(feeder)}/link/{kind}/{device if device == '*' else _id(device)}"


def agent_decision(feeder: str) -> str:
    """The agent's ``Decision`` of each control step (agent -> bridge, recorder)."""
    return f"{ROOT}/{_id(feeder)}/agent/decision"


def agent_status(feeder: str) -> str:
    """The agent's ``AgentStatus``, about once a second."""
    return f"{ROOT}/{_id(feeder)}/agent/status"


def sim_truth(feeder: str) -> str:
    """The simulator's ``TruthPack``: every node's true voltage (simulation only; never used by the agent)."""
    return f"{ROOT}/{_id(feeder)}/sim/truth"


def sim_metrics(feeder: str) -> str:
    """The simulator's running and final ``MetricsFrame``."""
    return f"{ROOT}/{_id(feeder)}/sim/metrics"


def sim_status(feeder: str) -> str:
    """The bridge's ``BridgeStatus``."""
    return f"{ROOT}/{_id(feeder)}/sim/status"


def sim_oracle(feeder: str) -> str:
    """The case-A oracle's queryable (``OracleRequest`` -> ``OracleReply``; simulation only)."""
    return f"{ROOT}/{_id(feeder)}/sim/oracle"


def alive(feeder: str, role: Role, ident: str) -> str:
    """A liveliness token of one participant (``role``: a process, or a field device of a kind) on one feeder."""
    return f"{ROOT}/{_id(feeder)}/alive/{role}/{_id(ident)}"


def alive_all(feeder: str) -> str:
    """Every liveliness token of one feeder (a subscription pattern)."""
    return f"{ROOT}/{_id(feeder)}/alive/**"


def parse_device_key(key: str) -> tuple[str, str, str, str] | None:
    """Split ``cvvc/F/<group>/<kind>/<id>`` into (feeder, group, kind, id); None if not of that shape."""
    parts = key.split("/")
    if len(parts) == 5 and parts[0] == ROOT:
        return parts[1], parts[2], parts[3], parts[4]
    return None


_BY_SUFFIX: dict[tuple[str, ...], type[msgspec.Struct]] = {
    ("meas", "head"): m.HeadFrame,
    ("meas", "pv"): m.PvFrame,
    ("meas", "vr"): m.RegFrame,
    ("meas", "cap"): m.CapFrame,
    ("meas", "ami"): m.MeterFrame,
    ("meas", "step"): m.StepEnd,
    ("cmd", "pv"): m.PvCommand,
    ("cmd", "vr"): m.RegCommand,
    ("cmd", "cap"): m.CapCommand,
    ("ack", "pv"): m.Ack,
    ("ack", "vr"): m.Ack,
    ("ack", "cap"): m.Ack,
    ("link", "pv"): m.LinkStatus,
    ("link", "vr"): m.LinkStatus,
    ("link", "cap"): m.LinkStatus,
    ("agent", "decision"): m.Decision,
    ("agent", "status"): m.AgentStatus,
    ("sim", "truth"): m.TruthPack,
    ("sim", "metrics"): m.MetricsFrame,
    ("sim", "status"): m.BridgeStatus,
    ("sim", "oracle"): m.OracleReply,
}


def message_type_for_key(key: str) -> type[msgspec.Struct] | None:
    """The message type a concrete key carries, or None for keys outside the cvvc layout."""
    parts = key.split("/")
    if len(parts) < 4 or parts[0] != ROOT:
        return None
    return _BY_SUFFIX.get((parts[2], parts[3]))
