"""``cvvc record``, ``cvvc recordings info|recover|export-json`` and ``cvvc replay``.

Nothing heavy is imported at module level: each handler imports what it needs.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from datetime import UTC, datetime
from typing import Any

__all__ = ["register"]

Handler = Callable[[argparse.Namespace], int]


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``record``, ``recording`` and ``replay`` verbs to the ``cvvc`` command line's ``sub``."""
    from schemas.bus_args import add_bus_arguments

    r = sub.add_parser("record", help="record every bus message to an MCAP file",
                       description="Subscribe to KEYS and write every sample, bytes unchanged, to an MCAP file "
                                   "(zstd chunks, flushed every --flush-period-s). Stops on SIGINT/SIGTERM or "
                                   "after --duration-s; the file is always finished.")
    r.add_argument("--out", required=True, metavar="FILE.mcap", help="the MCAP file to write (overwritten)")
    r.add_argument("--keys", action="append", default=None, metavar="KEYEXPR",
                   help="Zenoh key expression to record (repeatable; default cvvc/**)")
    r.add_argument("--feeder-fingerprint", default="", metavar="X", help="stored in the file's metadata")
    r.add_argument("--model", default="", metavar="PATH", help="the agent's model file, stored in the metadata")
    r.add_argument("--agent-settings", default="", metavar="JSON",
                   help="the agent's settings as JSON, stored in the metadata for `cvvc replay --offline`")
    r.add_argument("--duration-s", type=float, default=None, metavar="S", help="stop after S seconds")
    r.add_argument("--flush-period-s", type=float, default=1.0, metavar="S",
                   help="close and write the open chunk every S seconds (the most a crash can lose)")
    add_bus_arguments(r)
    r.set_defaults(func=_record)

    p = sub.add_parser("recordings", help="inspect and repair MCAP recordings")
    psub = p.add_subparsers(dest="recordings_verb", metavar="SUBVERB")
    i = psub.add_parser("info", help="topics, counts, time span, schemas and metadata of a recording")
    i.add_argument("file", metavar="FILE")
    i.add_argument("--json", action="store_true", help="print JSON")
    i.set_defaults(func=_info)
    c = psub.add_parser("recover", help="rewrite a file cut short by a crash as a valid indexed MCAP")
    c.add_argument("input", metavar="IN")
    c.add_argument("output", metavar="OUT")
    c.add_argument("--json", action="store_true", help="print JSON")
    c.set_defaults(func=_recover)
    e = psub.add_parser("export-json", help="copy a recording with the truth re-encoded as JSON (older recordings "
                                            "in Foxglove, JSON-only tools)",
                        description="Write OUT: IN with the truth (sim/truth: Protobuf, or the MessagePack of "
                                    "recordings of earlier versions, which Foxglove does not decode) re-encoded as "
                                    "JSON TruthFrame with its JSON Schema; everything else is copied as it is. "
                                    "Recordings of this version open in Foxglove as they are.")
    e.add_argument("input", metavar="IN")
    e.add_argument("output", metavar="OUT")
    e.add_argument("--json", action="store_true", help="print JSON")
    e.set_defaults(func=_export_json)

    y = sub.add_parser("replay", help="republish recorded frames onto the bus, or re-run the agent offline",
                       description="Republish recorded measurement frames with their original spacing scaled by "
                                   "--speed (or --fast), or with --offline re-run the agent's decision code on "
                                   "them and diff its decisions against the recorded ones.")
    y.add_argument("file", metavar="FILE")
    pace = y.add_mutually_exclusive_group()
    pace.add_argument("--speed", type=float, default=1.0, metavar="X", help="time scale (default 1: real time)")
    pace.add_argument("--fast", action="store_true", help="as fast as possible")
    y.add_argument("--keys", action="append", default=None, metavar="KEYEXPR",
                   help="key expressions to replay (repeatable; default cvvc/*/meas/**)")
    y.add_argument("--start", default=None, metavar="ISO|NS", help="first log time (ISO 8601, UTC if no zone)")
    y.add_argument("--end", default=None, metavar="ISO|NS", help="end log time, exclusive")
    y.add_argument("--wait-s", type=float, default=10.0, metavar="S",
                   help="wait at most S seconds for a subscriber before publishing (0: do not wait)")
    y.add_argument("--offline", action="store_true", help="re-run the agent on the frames, no bus")
    y.add_argument("--model", default=None, metavar="MODEL",
                   help="model file for --offline (default: the one named in the recording's metadata)")
    y.add_argument("--agent-settings", default=None, metavar="JSON",
                   help="agent settings for --offline (default: the ones recorded in the metadata)")
    y.add_argument("--json", action="store_true", help="print JSON")
    add_bus_arguments(y)
    y.set_defaults(func=_replay)


def _json(obj: Any) -> str:
    import msgspec

    return msgspec.json.format(msgspec.json.encode(obj), indent=2).decode()


def _iso(t_ns: int | None) -> str:
    if t_ns is None:
        return "-"
    return datetime.fromtimestamp(t_ns / 1e9, tz=UTC).isoformat(timespec="milliseconds")


# ------------------------------------------------------------------------------------------ record
def _record(args: argparse.Namespace) -> int:
    from recordings.recorder import RecorderConfig, main
    from schemas.bus import bus_config_from_args

    config = RecorderConfig(out_path=args.out, keys=tuple(args.keys or ("cvvc/**",)),
                            bus=bus_config_from_args(args, role="recorder"), flush_period_s=args.flush_period_s,
                            feeder_fingerprint=args.feeder_fingerprint, model_path=args.model,
                            agent_settings_json=args.agent_settings, duration_s=args.duration_s)
    stats = main(config)
    print(f"recorded {stats.messages} messages on {stats.channels} channels into {args.out} "
          f"(dropped {stats.dropped_queue_full}, t_ns fallbacks {stats.log_time_fallbacks})", file=sys.stderr)
    return 0


# ---------------------------------------------------------------------------------------- info etc.
def _info(args: argparse.Namespace) -> int:
    from recordings.info import recording_info

    info = recording_info(args.file)
    if args.json:
        print(_json(info))
    else:
        state = "complete" if info.complete else "INCOMPLETE"
        print(f"{info.path}: {info.size_bytes} bytes, {state} (read from the {info.source}), {info.library}")
        print(f"  {info.messages} messages in {info.chunks} chunks, {_iso(info.start_ns)} .. {_iso(info.end_ns)} "
              f"({info.duration_s:.1f} s)")
        if info.devices:
            print("  devices: " + "; ".join(f"{len(ids)} {kind} ({', '.join(ids)})"
                                          for kind, ids in info.devices.items()))
        for ch in info.channels:
            schema = f"{ch.schema_name} ({ch.schema_encoding})" if ch.schema_name else "no schema"
            print(f"  {ch.messages:>9}  {ch.topic}  [{ch.message_encoding}; {schema}]")
        for name, meta in info.metadata.items():
            print(f"  metadata {name}:")
            for k, v in meta.items():
                print(f"    {k} = {v}")
        for gap in info.gaps:
            print(f"  gap: recorder restart {gap.restart}: nothing recorded from {_iso(gap.from_t_ns)} to "
                  f"{_iso(gap.to_t_ns)} (message time; received {_wall_span_s(gap.from_wall_ns, gap.to_wall_ns):.1f} "
                  f"s apart): {gap.reason}")
        for problem in info.problems:
            print(f"  problem: {problem}")
    return 0 if info.complete else 1


def _wall_span_s(a: int, b: int) -> float:
    return (b - a) / 1e9 if a >= 0 and b >= 0 else float("nan")


def _recover(args: argparse.Namespace) -> int:
    from recordings.info import recover

    res = recover(args.input, args.output)
    if args.json:
        print(_json(res))
        return 0
    print(f"{res.out_path}: recovered {res.messages} messages from {res.chunks_recovered} chunks "
          f"({_iso(res.start_ns)} .. {_iso(res.end_ns)})")
    for topic, n in res.messages_by_topic.items():
        print(f"  {n:>9}  {topic}")
    if res.input_was_complete and not res.corrupt_chunks:
        print("  the input was already complete: nothing lost")
    else:
        print(f"  lost: {res.lost_tail_bytes} bytes after byte {res.readable_bytes} of {res.size_bytes}; "
              f"{len(res.corrupt_chunks)} corrupt chunks; {res.orphan_messages} messages without channel")
    for problem in res.problems:
        print(f"  problem: {problem}")
    return 0


def _export_json(args: argparse.Namespace) -> int:
    from recordings.export import export_json

    res = export_json(args.input, args.output)
    if args.json:
        print(_json(res))
    else:
        print(f"{res.out_path}: {res.messages} messages, {res.reencoded} truth frames re-encoded as JSON"
              + (f", {res.skipped} undecodable left out ({res.skipped_topics})" if res.skipped else ""))
    return 0 if res.skipped == 0 else 1


# ------------------------------------------------------------------------------------------ replay
def _replay(args: argparse.Namespace) -> int:
    if args.offline:
        return _offline(args)
    from recordings.replay import MEASUREMENT_KEYS, ReplayConfig, main, parse_time_ns
    from schemas.bus import bus_config_from_args

    config = ReplayConfig(path=args.file, keys=tuple(args.keys or MEASUREMENT_KEYS),
                          speed=None if args.fast else args.speed,
                          start_ns=parse_time_ns(args.start) if args.start else None,
                          end_ns=parse_time_ns(args.end) if args.end else None,
                          bus=bus_config_from_args(args, role="devices"),  # replays device frames
                          wait_subscriber_s=args.wait_s)
    res = main(config)
    if args.json:
        print(_json(res))
    else:
        print(f"published {res.messages} messages on {len(res.by_topic)} topics in {res.wall_s:.2f} s "
              f"({_iso(res.first_log_time_ns)} .. {_iso(res.last_log_time_ns)}; "
              f"at most {res.max_late_s * 1e3:.1f} ms late)")
    return 0


def _offline(args: argparse.Namespace) -> int:
    from recordings.offline import run_offline

    res = run_offline(args.file, model_path=args.model, settings_json=args.agent_settings)
    if args.json:
        print(_json(res))
    else:
        d = res.diff
        print(f"{res.path} with {res.model_path}: {res.frames} frames ({res.frames_rejected} rejected), "
              f"{res.simulated_s / 60:.0f} simulated min in {res.wall_s:.2f} s "
              f"({res.sim_minutes_per_wall_s:.0f} min/s)")
        print(f"  decisions: {d.recorded} recorded, {d.rerun} re-run; identical {d.identical}, changed {d.changed} "
              f"({d.changed_identity_only} only in counters, {d.status_changed} in status), missing {d.missing}, "
              f"extra {d.extra}")
        for q, c in d.largest_change.items():
            print(f"  largest change {q}: {c.recorded} -> {c.rerun} at {_iso(c.step_t_ns)}")
        for q, n in d.appeared_or_vanished.items():
            print(f"  {q}: present on one side only in {n} decisions")
    return 0 if res.diff.all_identical else 1
