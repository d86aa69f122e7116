"""Helpers for the recordings tests: the key of every example message; recordings written without a bus."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import msgspec

from schemas import keys
from schemas import messages as m
from schemas.bus import codec_for
from schemas.examples import T0_NS

FEEDER = "rural"
# Where each example message travels. OracleRequest is a query payload (never published): it is recorded
# here on a key outside the cvvc layout, which also exercises the schemaless-channel path.
EXAMPLE_KEYS: dict[type, str] = {
    m.HeadFrame: keys.meas_head(FEEDER),
    m.PvFrame: keys.meas_pv(FEEDER, "pv1"),
    m.RegFrame: keys.meas_vr(FEEDER, "vr1a"),
    m.PvCommand: keys.cmd(FEEDER, "pv", "pv1"),
    m.RegCommand: keys.cmd(FEEDER, "vr", "vr1a"),
    m.Ack: keys.ack(FEEDER, "pv", "pv1"),
    m.Decision: keys.agent_decision(FEEDER),
    m.AgentStatus: keys.agent_status(FEEDER),
    m.TruthPack: keys.sim_truth(FEEDER),
    m.TruthFrame: "test/truth_frame",  # the JSON form of the truth (export-json): not a bus message any more
    m.MetricsFrame: keys.sim_metrics(FEEDER),
    m.BridgeStatus: keys.sim_status(FEEDER),
    m.OracleRequest: "test/oracle_request",
    m.OracleReply: keys.sim_oracle(FEEDER),
    m.CapFrame: keys.meas_cap(FEEDER, "cap1"),
    m.MeterFrame: keys.meas_ami(FEEDER, "ami1"),
    m.CapCommand: keys.cmd(FEEDER, "cap", "cap1"),
    m.StepEnd: keys.meas_step(FEEDER),
    m.LinkStatus: keys.link(FEEDER, "pv", "pv1"),
}


def encode(msg: msgspec.Struct) -> bytes:
    return codec_for(type(msg)).encode(msg)


def write_recording(path: Path, items: Iterable[tuple[str, msgspec.Struct | bytes]], *,
                    flush_every: int | None = None, metadata: dict[str, str] | None = None) -> Path:
    """Write ``(key, message)`` items through the recorder's file layout (no bus); receive time = t_ns + 1 ms."""
    from recordings.recorder import McapSink

    with open(path, "wb") as f:
        sink = McapSink(f, metadata=metadata if metadata is not None else {"model_path": ""})
        for i, (key, msg) in enumerate(items):
            raw = msg if isinstance(msg, bytes) else encode(msg)
            t_ns = getattr(msg, "t_ns", T0_NS)
            sink.write(raw, key, t_ns + 1_000_000)
            if flush_every and (i + 1) % flush_every == 0:
                sink.flush()
        sink.finish()
    return path


def head_frame(i: int, *, step_s: float = 60.0, p_kw: float = 2430.0) -> m.HeadFrame:
    from schemas.examples import example

    base = example(m.HeadFrame)
    return msgspec.structs.replace(base, t_ns=T0_NS + int(i * step_s * 1e9), seq=i + 1, p_kw=p_kw)
