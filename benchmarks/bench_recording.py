"""Recording throughput: messages per second through Zenoh into MCAP, as a ratio to the bare MCAP writer.

Both sides write the same encoded messages (the examples of every published message type, each with its
own ``t_ns`` and ``seq``) into a zstd-chunked MCAP file on disk:

(a) bare: ``mcap.writer.Writer.add_message`` in a loop (with the same ``t_ns`` parse), channels registered
    beforehand, then ``finish``; best of three runs, so the ratio is conservative on a busy machine;
(b) Zenoh: a publisher *process* puts them (congestion control BLOCK) to this process's router-mode
    session, where the ``Recorder`` (callback enqueues, writer thread parses ``t_ns``, writes, flushes
    every second) records them; timed from the first sample's receive time to the file being finished.

Run: ``python -m benchmarks.bench_recording [N]``.
"""

from __future__ import annotations

import multiprocessing
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import msgspec

from benchmarks.results import OfflineRerun, RecordingBench, to_json

__all__ = ["bench_recording"]


def _messages(n: int) -> list[tuple[str, bytes]]:
    from schemas import keys
    from schemas import messages as m
    from schemas.bus import codec_for
    from schemas.examples import T0_NS, examples

    key_of: dict[Any, str] = {
        m.HeadFrame: keys.meas_head("rural"), m.PvFrame: keys.meas_pv("rural", "pv1"),
        m.RegFrame: keys.meas_vr("rural", "vr1a"), m.PvCommand: keys.cmd("rural", "pv", "pv1"),
        m.RegCommand: keys.cmd("rural", "vr", "vr1a"), m.Ack: keys.ack("rural", "pv", "pv1"),
        m.Decision: keys.agent_decision("rural"), m.AgentStatus: keys.agent_status("rural"),
        m.TruthPack: keys.sim_truth("rural"), m.MetricsFrame: keys.sim_metrics("rural"),
        m.BridgeStatus: keys.sim_status("rural"),
    }
    types = list(key_of)
    out: list[tuple[str, bytes]] = []
    step = 0
    while len(out) < n:
        batch = examples(t_ns=T0_NS + step * 60_000_000_000, seq=step + 1)
        for t in types:
            if len(out) < n:
                out.append((key_of[t], codec_for(t).encode(batch[t])))
        step += 1
    return out


def _bare_writer(msgs: list[tuple[str, bytes]], path: Path) -> float:
    """Messages per second of the bare MCAP writer (including ``finish``)."""
    from mcap.writer import CompressionType, Writer

    class _T(msgspec.Struct):
        t_ns: int = 0

    from schemas.keys import message_type_for_key
    from schemas.messages import TruthPack, wire_of
    from schemas.wire import typed_decoder

    json_dec = msgspec.json.Decoder(_T)
    decoders = {key: typed_decoder(TruthPack) if wire_of(message_type_for_key(key) or _T) == "protobuf" else json_dec
                for key in dict(msgs)}  # the truth is Protobuf: its t_ns from its whole decode, as the recorder has it
    with open(path, "wb") as f:
        t0 = time.perf_counter()
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start()
        channels = {key: w.register_channel(key, "json", 0) for key in dict(msgs)}
        now = time.time_ns()
        for key, raw in msgs:
            w.add_message(channels[key], log_time=decoders[key].decode(raw).t_ns, data=raw, publish_time=now)
        w.finish()
        return len(msgs) / (time.perf_counter() - t0)


def _publisher_process(endpoint: str, n: int, go: Any) -> None:
    """Child process: connect, wait for the recorder's subscription, then put everything as fast as possible."""
    import zenoh

    from schemas.bus import BusConfig, has_subscribers, open_session, wait_for

    msgs = _messages(n)
    with open_session(BusConfig(mode="peer", connect=(endpoint,))) as session:
        pubs = {key: session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
                for key in dict(msgs)}
        wait_for(lambda: all(has_subscribers(p) for p in pubs.values()), 20.0)
        go.set()
        for key, raw in msgs:
            pubs[key].put(raw)
        time.sleep(0.5)  # let the transport drain before the session closes (closing drops queued data)


class _ZenohRun(msgspec.Struct, frozen=True, kw_only=True):
    """One run through Zenoh into MCAP: its rate [messages/s], counts and file size [bytes]."""

    msg_per_s: float
    recorded: int
    complete: bool
    dropped: int
    file_bytes: int


def _through_zenoh(n: int, path: Path) -> _ZenohRun:
    from mcap.reader import make_reader

    from recordings.recorder import Recorder, RecorderConfig
    from schemas.bus import BusConfig, free_port, open_session, wait_for

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    bus = BusConfig(mode="router", listen=(endpoint,))
    ctx = multiprocessing.get_context("spawn")
    go = ctx.Event()
    with open_session(bus) as session:
        with Recorder(session, RecorderConfig(out_path=str(path), bus=bus)) as recorder:
            proc = ctx.Process(target=_publisher_process, args=(endpoint, n, go), daemon=True)
            proc.start()
            try:
                if not wait_for(lambda: go.is_set() or not proc.is_alive(), 60.0) or not go.is_set():
                    raise RuntimeError("the publisher process never matched the recorder")
                complete = wait_for(lambda: recorder.stats().messages >= n, 120.0, poll_s=0.001)
                recorder.close()  # finish the file: part of the timed work, as for the bare writer
                t_end_wall = time.time_ns()
            finally:
                proc.join(30.0)
                if proc.is_alive():
                    proc.kill()
        stats = recorder.stats()
    with open(path, "rb") as f:
        first_recv = min(msg.publish_time for _, _, msg in make_reader(f).iter_messages(log_time_order=False))
    seconds = (t_end_wall - first_recv) / 1e9
    return _ZenohRun(msg_per_s=stats.messages / seconds, recorded=stats.messages, complete=complete,
                     dropped=stats.dropped_queue_full, file_bytes=path.stat().st_size)


def bench_recording(n: int = 20_000) -> RecordingBench:
    """Recording throughput [messages/s] bare vs through Zenoh, their ratio, and offline replay speed.

    ``offline_rerun``: the offline re-run of one synthetic day (``_offline_speed``), None while
    ``agent.runtime.decide_offline`` does not exist.
    """
    msgs = _messages(n)
    with tempfile.TemporaryDirectory(prefix="cvvc-bench-rec-") as tmp:
        bare = max(_bare_writer(msgs, Path(tmp) / "bare.mcap") for _ in range(3))  # best of 3: conservative ratio
        zen = _through_zenoh(n, Path(tmp) / "zenoh.mcap")
    return RecordingBench(
        messages=n,
        bare_writer_msg_per_s=round(bare),
        zenoh_to_mcap_msg_per_s=round(zen.msg_per_s),
        ratio=round(zen.msg_per_s / bare, 3),
        recorded=zen.recorded,
        all_recorded=zen.complete,
        dropped=zen.dropped,
        bytes_per_message=round(zen.file_bytes / max(1, zen.recorded), 1),
        mean_payload_bytes=round(sum(len(r) for _, r in msgs) / len(msgs), 1),
        offline_rerun=_offline_speed(),
    )


def _offline_speed(steps: int = 1440) -> OfflineRerun | None:
    """Offline re-run speed [simulated minutes per wall second] on one recorded synthetic day.

    The agent's synthetic feeder model (8 regulators, 3 PV plants): 1-minute frames of every device, the
    decisions ``decide_offline`` makes on them recorded beside them, then ``run_offline`` timed (reading
    the MCAP file, decoding, deciding, diffing). None while ``agent.runtime.decide_offline`` is missing.
    """
    try:
        from agent.runtime import AgentSettings, decide_offline
        from benchmarks.synthetic import synthetic_model
    except ImportError:
        return None
    import math

    from recordings.offline import run_offline
    from recordings.recorder import McapSink
    from regression.model import write_model
    from schemas import keys
    from schemas import messages as m
    from schemas.bus import Received, codec_for
    from schemas.examples import T0_NS, examples

    model = synthetic_model(seed=3)
    settings = AgentSettings(feeder_id="rural")
    ex: dict[Any, Any] = dict(examples())
    frames: list[tuple[str, Any]] = []
    for i in range(steps):
        t_ns, seq = T0_NS + i * 60_000_000_000, i + 1
        head_kw = 600.0 + 400.0 * math.sin(math.pi * i / steps)
        phases = [msgspec.structs.replace(p, p_kw=head_kw) for p in ex[m.HeadFrame].phases]
        frames.append((keys.meas_head("rural"), msgspec.structs.replace(
            ex[m.HeadFrame], t_ns=t_ns, seq=seq, phases=phases, p_kw=3 * head_kw,
            q_kvar=sum(p.q_kvar for p in phases))))
        for pv in model.pv:
            frames.append((keys.meas_pv("rural", pv.id), msgspec.structs.replace(
                ex[m.PvFrame], t_ns=t_ns, seq=seq, source=pv.id, plant_id=pv.id, s_rated_kva=pv.kva,
                q_available_kvar=0.4 * pv.kva, p_kw=0.6 * pv.kva, q_kvar=0.0,
                phases=[msgspec.structs.replace(p, p_kw=0.2 * pv.kva, q_kvar=0.0) for p in ex[m.PvFrame].phases])))
        for reg in model.regulators:
            frames.append((keys.meas_vr("rural", reg.id), msgspec.structs.replace(
                ex[m.RegFrame], t_ns=t_ns, seq=seq, source=reg.id, regulator_id=reg.id, tap=0)))
    decisions = list(decide_offline(model, settings, [Received(k, f, 0, b"") for k, f in frames]))
    with tempfile.TemporaryDirectory(prefix="cvvc-bench-offline-") as tmp:
        model_path = Path(tmp) / "model.json"
        write_model(model, model_path)
        rec = Path(tmp) / "day.mcap"
        with open(rec, "wb") as f:
            sink = McapSink(f, metadata={"model_path": str(model_path),
                                         "agent_settings": msgspec.json.encode(settings).decode()})
            by_step = {d.step_t_ns: d for d in decisions}
            for key, frame in frames:
                sink.write(codec_for(type(frame)).encode(frame), key, frame.t_ns)
                d = by_step.pop(frame.t_ns, None) if key.endswith(model.regulators[-1].id) else None
                if d is not None:
                    sink.write(codec_for(m.Decision).encode(d), keys.agent_decision("rural"), frame.t_ns)
            for d in by_step.values():
                sink.write(codec_for(m.Decision).encode(d), keys.agent_decision("rural"), d.step_t_ns)
            sink.finish()
        res = run_offline(rec)
    return OfflineRerun(sim_minutes_per_wall_s=round(res.sim_minutes_per_wall_s, 1), frames=res.frames,
                        decisions=res.diff.recorded, identical=res.diff.identical, wall_s=round(res.wall_s, 3))


if __name__ == "__main__":
    print(to_json(bench_recording(int(sys.argv[1]) if len(sys.argv) > 1 else 20_000)))
    sys.stdout.flush()
    os._exit(0)
