"""Recordings, run summaries and evaluations as pandas DataFrames (the readers of ``cvvc.api``).

- :func:`recording_frames`: an MCAP recording, one DataFrame per channel (topic), one row per message, decoded with
  the project's own decoders: the truth (``sim/truth``) by its channel's message encoding (Protobuf, MessagePack or
  JSON: ``schemas.truth.decode_truth``), every other message with its type's typed decoder
  (``schemas.keys.message_type_for_key``, ``schemas.wire.typed_decoder``), so a message is checked against its
  bounds as the recorder and the agent check it.
- :func:`summary_frame`: a run's ``summary.json``, the case's final metrics beside the no-control baseline's.
- :func:`evaluation_frame`: a ``cvvc evaluate`` folder's ``results.json``, one row per run.

pandas is imported inside the functions: importing this module costs nothing.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgspec

from cvvc.errors import CommandError
from cvvc.report import NO_CONTROL, decode_evaluation, decode_summary
from cvvc.run_summary import RunSummary
from recordings.info import MCAP_READ_ERRORS, check_mcap_file
from recordings.replay import select_topics
from schemas import messages as m
from schemas.keys import message_type_for_key
from schemas.truth import TruthArrays, TruthDecodeError, decode_truth
from schemas.wire import typed_decoder
from simulator_bridge.rural.synthesis import UTC_OFFSET_H

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["LOCAL_TZ", "FramesError", "evaluation_frame", "recording_frames", "summary_frame"]

#: The profiles' local standard time, without daylight saving (docs/conventions.md; POSIX signs: Etc/GMT+5 is UTC-5).
LOCAL_TZ = f"Etc/GMT{-UTC_OFFSET_H:+d}"
_HEADER = ("seq", "source")  # the message header columns written after the time columns
_NOT_METRICS = {"t_ns", "seq", "source", "feeder_id", "start_t_ns", "final"}


class FramesError(CommandError):
    """A file that cannot be read into DataFrames; the message says which and why."""


def _time_index(df: pd.DataFrame) -> pd.DataFrame:
    """``df`` indexed by its ``t_ns`` (simulation time) as local standard time, ``t_ns`` kept as a column."""
    import pandas as pd

    df.index = pd.DatetimeIndex(pd.to_datetime(df["t_ns"], unit="ns", utc=True).dt.tz_convert(LOCAL_TZ), name="time")
    return df


def _truth_row(tr: TruthArrays, names: tuple[str, ...] | None) -> dict[str, Any]:
    row: dict[str, Any] = {"t_ns": tr.t_ns, "seq": tr.seq, "v_min_pu": tr.v_min_pu, "v_max_pu": tr.v_max_pu}
    if names is not None and len(names) == tr.v_pu.size:
        row.update(zip((f"v_pu.{n}" for n in names), tr.v_pu.tolist(), strict=True))
    else:  # frames before the first with node names (a recording that started late): by position
        row.update((f"v_pu.{i}", v) for i, v in enumerate(tr.v_pu.tolist()))
    for field, values in (("taps", tr.taps), ("pv_q_kvar", tr.pv_q_kvar), ("cap_states", tr.cap_states)):
        row.update((f"{field}.{i}", v) for i, v in enumerate(values.tolist()))  # device-map order
    return row


def recording_frames(path: str | Path, keys: tuple[str, ...] = ("**",)) -> dict[str, pd.DataFrame]:
    """Every channel of the recording at ``path`` whose topic a Zenoh key expression of ``keys`` includes, as
    ``{topic: DataFrame}``.

    Each DataFrame has one row per message that decoded, in log-time order, indexed by the message's simulation
    time ``t_ns`` as local standard time (``time``, UTC-5, the profiles' clock), with the columns ``t_ns``,
    ``log_time_ns`` (when the recorder received it, wall clock [ns since the UTC epoch]), the message's header and
    its fields, nested ones flattened with ``.`` (``timings.total_s``); lists stay lists (``Decision.estimates``).
    The truth (``cvvc/<F>/sim/truth``) has one column per node, ``v_pu.<node>``, named from the first frame that
    carries the node names, and ``taps.<i>``, ``pv_q_kvar.<i>``, ``cap_states.<i>`` per device in device-map order.

    A message that does not decode is left out and counted in the DataFrame's ``attrs["undecodable"]``; channels
    of no cvvc message type (the recorder's quarantine) are left out.

    Raises
    ------
    FramesError
        ``path`` is not a readable MCAP file (``cvvc recordings recover`` saves one cut short), or a key is invalid.
    """
    import pandas as pd
    from mcap.reader import make_reader

    from recordings.errors import RecordingError

    try:
        check_mcap_file(path)
        with open(path, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            if summary is None:
                raise FramesError(f"{path}: the recording has no summary (cut short?); run `cvvc recordings recover "
                                  f"{path} OUT.mcap` and read OUT.mcap")
            topics = [t for t in select_topics(sorted({c.topic for c in summary.channels.values()}), keys)
                      if message_type_for_key(t) is not None]
            rows: dict[str, list[dict[str, Any]]] = {t: [] for t in topics}
            bad: Counter[str] = Counter()
            decoders: dict[type, Any] = {}
            names: dict[str, tuple[str, ...]] = {}
            for _, channel, msg in reader.iter_messages(topics=topics, log_time_order=True):
                topic = channel.topic
                if topic.endswith("/sim/truth"):
                    try:
                        tr = decode_truth(msg.data, channel.message_encoding)
                    except TruthDecodeError:
                        bad[topic] += 1
                        continue
                    if tr.node_names:
                        names[topic] = tr.node_names
                    row = _truth_row(tr, names.get(topic))
                else:
                    msg_type = message_type_for_key(topic) or m.Message
                    decoder = decoders.get(msg_type) or decoders.setdefault(msg_type, typed_decoder(msg_type))
                    try:
                        row = msgspec.to_builtins(decoder.decode(msg.data))
                    except (msgspec.DecodeError, UnicodeDecodeError, RecursionError, ValueError):
                        bad[topic] += 1
                        continue
                row["log_time_ns"] = msg.log_time
                rows[topic].append(row)
    except RecordingError as e:  # not MCAP, or an invalid key expression (ReplayError)
        raise FramesError(str(e)) from e
    except MCAP_READ_ERRORS as e:
        raise FramesError(f"{path}: a chunk cannot be read ({e}); run `cvvc recordings recover` to skip corrupt "
                          "chunks") from e
    frames = {}
    for topic, topic_rows in rows.items():
        df = pd.json_normalize(topic_rows, sep=".") if topic_rows else pd.DataFrame(columns=["t_ns", "log_time_ns"])
        first = ["t_ns", "log_time_ns", *(c for c in _HEADER if c in df.columns)]
        df = _time_index(df[first + [c for c in df.columns if c not in first]])
        df.attrs["topic"] = topic
        df.attrs["undecodable"] = bad[topic]
        frames[topic] = df
    return frames


def summary_frame(run_dir: str | Path) -> pd.DataFrame:
    """A ``cvvc run`` folder's ``summary.json`` (or that file itself) as one DataFrame: one row per metric (paper
    IV.F: ``mvvm_pu``, ``nvv``, ``ntc``, costs, minutes outside the limits; per device: ``taps_changes.<reg>``,
    ``q_mvar_intervals.<pv>``, ``cap_switches_per_bank.<bank>``), one column for the run's case and one for the
    no-control baseline of the same days (``no control``; left out when the run simulated none).

    ``attrs["summary"]`` holds the decoded :class:`cvvc.run_summary.RunSummary` (decisions, holds, decision times,
    the resolved case, where the recording is).

    Raises
    ------
    FramesError
        No ``summary.json`` there, or one that is not a run summary this version reads.
    """
    import pandas as pd

    from cvvc.report import ReportError

    p = Path(run_dir)
    path = p / "summary.json" if p.is_dir() else p
    if not path.is_file():
        raise FramesError(f"{path}: no such file; pass a cvvc run output folder or its summary.json")
    try:
        summary = decode_summary(path, RunSummary)
    except ReportError as e:
        raise FramesError(str(e)) from e
    columns = {f"case {summary.case}": _metrics(summary.metrics)}
    if summary.baseline is not None:
        columns[NO_CONTROL] = _metrics(summary.baseline)
    names = list(dict.fromkeys(k for column in columns.values() for k in column))  # the case's order first
    df = pd.DataFrame([[column.get(k) for column in columns.values()] for k in names],
                      index=pd.Index(names, name="metric"), columns=list(columns), dtype=object)  # counts stay int
    df.attrs["summary"] = summary
    return df


def _metrics(frame: m.MetricsFrame) -> dict[str, float]:
    """The metrics of a frame as one flat mapping (per-device counts as ``field.device``)."""
    out: dict[str, float] = {}
    for name, value in msgspec.structs.asdict(frame).items():
        if name in _NOT_METRICS:
            continue
        if isinstance(value, dict):
            out.update((f"{name}.{k}", v) for k, v in value.items())
        else:
            out[name] = value
    return out


def evaluation_frame(eval_dir: str | Path) -> pd.DataFrame:
    """A ``cvvc evaluate`` folder's ``results.json`` (or that file itself) as one DataFrame, one row per run: the
    run's spec (``name``, ``case``, ``season``, ``bandwidth_v120``, ``variant``, ``start``, ``days``), its final
    metrics (the columns of :func:`summary_frame`'s rows), ``decisions``, ``soft``, ``holds``, ``lockstep_misses``,
    ``wall_s``, ``attempts``, ``out_dir``, and ``error`` (empty for a finished run; a failed run has its reason
    there and no metrics). Indexed by the run's ``name`` (its folder).

    Raises
    ------
    FramesError
        No ``results.json`` there, or one that is not an evaluation this version reads.
    """
    import pandas as pd

    from cvvc.report import ReportError

    p = Path(eval_dir)
    path = p / "results.json" if p.is_dir() else p
    if not path.is_file():
        raise FramesError(f"{path}: no such file; pass a cvvc evaluate output folder or its results.json")
    try:
        ev = decode_evaluation(path)
    except ReportError as e:
        raise FramesError(str(e)) from e
    rows: list[dict[str, Any]] = []
    for r in ev.runs:
        rows.append({"name": r.spec.name, **msgspec.structs.asdict(r.spec), **_metrics(r.metrics),
                     "decisions": r.decisions, "soft": r.soft, "holds": r.holds,
                     "lockstep_misses": r.lockstep_misses, "wall_s": r.wall_s, "attempts": r.attempts,
                     "out_dir": r.out_dir, "error": ""})
    for f in ev.failures:
        rows.append({"name": f.spec.name, **msgspec.structs.asdict(f.spec), "attempts": f.attempts,
                     "out_dir": f.out_dir, "error": f.error})
    df = pd.DataFrame(rows).set_index("name") if rows else pd.DataFrame(index=pd.Index([], name="name"))
    df.attrs["feeder_id"] = ev.feeder_id
    df.attrs["evaluation"] = ev
    return df
