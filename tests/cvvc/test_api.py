"""cvvc.api: the public API's readers on real MCAP files and real summaries, and docs/api.md's example run as
written (a real closed loop on IEEE 13)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import msgspec
import numpy as np
import pytest
from mcap.writer import CompressionType, Writer

import cvvc.api as api
from cvvc.evaluation import EvaluateConfig, Evaluation, RunFailure, RunResult, RunSpec
from cvvc.run_summary import RunSummary
from schemas import messages as m
from schemas.examples import example
from schemas.jsonschema import schema_bytes, schema_name
from schemas.truth_proto import TRUTH_PROTO_NAME, encode_truth_proto, truth_descriptor_set

REPO = Path(__file__).resolve().parents[2]
LIVE = REPO / "tests" / "data" / "live_session.mcap"
T0 = 1_688_990_400_000_000_000  # 2023-07-10T12:00 UTC: 07:00 local standard time (UTC-5)


def _truth(t_ns: int, v: list[float], *, names: bool) -> m.TruthPack:
    return m.TruthPack(t_ns=t_ns, seq=t_ns // 60_000_000_000 % 1000, source="bridge", feeder_id="f", n_nodes=3,
                       v_pu_f32=m.pack_v_pu(np.array(v)), v_min_pu=min(v), v_max_pu=max(v),
                       node_names=["a.1", "a.2", "b.3"] if names else None, taps=[2, -1], pv_q_kvar=[10.5],
                       cap_states=[1])


def _write(path: Path, channels: list[tuple[str, str, str, str, bytes, list[tuple[int, bytes]]]]) -> None:
    """An MCAP file: (topic, message encoding, schema name, schema encoding, schema data, [(log time, data)])."""
    with path.open("wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start()
        for topic, enc, sname, senc, sdata, messages in channels:
            cid = w.register_channel(topic, enc, w.register_schema(sname, senc, sdata))
            for log_time, data in messages:
                w.add_message(cid, log_time=log_time, data=data, publish_time=log_time)
        w.finish()


def test_every_public_name_is_in_the_manual():
    text = api.__doc__ or ""
    for name in ("train", "run", "evaluate", "read_recording", "read_summary", "read_evaluation"):
        assert f"``{name}(" in text, name
        assert getattr(api, name).__doc__, name
    assert set(api.__all__) <= set(dir(api))


def test_a_recording_is_one_dataframe_per_channel_in_simulated_time():
    frames = api.read_recording(LIVE)
    assert len(frames) == 25 and "cvvc/rural/agent/decision" in frames  # every channel, none left out
    head = frames["cvvc/rural/meas/head"]
    assert len(head) == 30 and head.attrs["undecodable"] == 0
    assert list(head.columns[:4]) == ["t_ns", "log_time_ns", "seq", "source"]
    assert head["t_ns"].is_monotonic_increasing and head["t_ns"].diff().dropna().eq(60 * 10**9).all()
    assert str(head.index[0]) == "2023-01-01 00:00:00-05:00"  # the profiles' midnight, local standard time
    assert "p_kw" in head.columns and head["p_kw"].notna().all()
    decisions = frames["cvvc/rural/agent/decision"]
    assert len(decisions) == 6 and set(decisions["status"]) <= {"optimal", "soft", "hold"}
    assert "timings.total_s" in decisions.columns  # nested structs flattened
    assert isinstance(decisions["estimates"].iloc[0], list)
    only = api.read_recording(LIVE, keys=("cvvc/*/meas/pv/*",))
    assert sorted(only) == [f"cvvc/rural/meas/pv/pv{i}" for i in range(3)]


@pytest.mark.parametrize("encoding", ["protobuf", "msgpack", "json"])
def test_the_truth_is_read_in_every_encoding_it_was_recorded_in(tmp_path, encoding):
    packs = [_truth(T0, [1.01, 0.99, 1.03], names=True), _truth(T0 + 60 * 10**9, [1.02, 0.98, 1.04], names=False)]
    if encoding == "protobuf":
        schema = (TRUTH_PROTO_NAME, "protobuf", truth_descriptor_set())
        data = [encode_truth_proto(p) for p in packs]
    elif encoding == "msgpack":
        schema = (schema_name(m.TruthPack), "jsonschema", schema_bytes(m.TruthPack))
        data = [msgspec.msgpack.encode(p) for p in packs]
    else:
        from schemas.truth import to_truth_frame

        schema = (schema_name(m.TruthFrame), "jsonschema", schema_bytes(m.TruthFrame))
        data = [msgspec.json.encode(to_truth_frame(p)) for p in packs]
    path = tmp_path / "truth.mcap"
    _write(path, [("cvvc/f/sim/truth", encoding, *schema, [(p.t_ns, d) for p, d in zip(packs, data, strict=True)])])
    truth = api.read_recording(path)["cvvc/f/sim/truth"]
    assert [c for c in truth.columns if c.startswith("v_pu.")] == ["v_pu.a.1", "v_pu.a.2", "v_pu.b.3"]
    np.testing.assert_allclose(truth[["v_pu.a.1", "v_pu.a.2", "v_pu.b.3"]].to_numpy(),
                               [[1.01, 0.99, 1.03], [1.02, 0.98, 1.04]], atol=1e-6)  # float32 on the wire
    assert truth["taps.0"].tolist() == [2, 2] and truth["taps.1"].tolist() == [-1, -1]
    assert truth["pv_q_kvar.0"].tolist() == [10.5, 10.5] and truth["cap_states.0"].tolist() == [1, 1]
    assert [f"{t:%H:%M}" for t in truth.index] == ["07:00", "07:01"]


def test_a_message_that_does_not_decode_is_counted_and_left_out(tmp_path):
    good = msgspec.json.encode(example(m.Decision))
    bad_bounds = good.replace(b'"status":"optimal"', b'"status":"maybe"')
    assert bad_bounds != good
    path = tmp_path / "bad.mcap"
    schema = (schema_name(m.Decision), "jsonschema", schema_bytes(m.Decision))
    _write(path, [("cvvc/f/agent/decision", "json", *schema,
                   [(1, good), (2, b"{not json"), (3, bad_bounds)]),
                  ("cvvc.quarantine", "json", "q", "jsonschema", b"{}", [(4, b"{}")])])
    frames = api.read_recording(path)
    assert list(frames) == ["cvvc/f/agent/decision"]  # the quarantine is no cvvc message channel
    decisions = frames["cvvc/f/agent/decision"]
    assert len(decisions) == 1 and decisions.attrs["undecodable"] == 2


def test_files_that_are_not_what_they_should_be_give_a_clear_error(tmp_path):
    (tmp_path / "x.mcap").write_bytes(b"not an mcap file at all")
    with pytest.raises(api.FramesError, match="not an MCAP file"):
        api.read_recording(tmp_path / "x.mcap")
    with pytest.raises(api.FramesError, match="invalid key expression"):
        api.read_recording(LIVE, keys=("cvvc//x",))
    with pytest.raises(api.FramesError, match="no such file"):
        api.read_summary(tmp_path)
    (tmp_path / "summary.json").write_text('{"feeder": 3}')
    with pytest.raises(api.FramesError, match="not a cvvc run summary"):
        api.read_summary(tmp_path)
    (tmp_path / "results.json").write_text("[]")
    with pytest.raises(api.FramesError, match="not a cvvc evaluate result"):
        api.read_evaluation(tmp_path)


def _metrics(**changes: object) -> m.MetricsFrame:
    return msgspec.structs.replace(example(m.MetricsFrame), **changes)  # type: ignore[type-var]


def test_a_run_summary_puts_the_case_beside_the_baseline(tmp_path):
    summary = RunSummary(feeder="f.toml", feeder_id="f", case="D", start="2023-07-10T11:00", days=0.01, steps=15,
                         wall_s=1.0, metrics=_metrics(nvv=0, ntc=2), baseline=_metrics(nvv=7, ntc=0, q_cost=0.0),
                         lockstep_misses=0, decisions=3, out_dir=str(tmp_path), recording=None, model=None)
    (tmp_path / "summary.json").write_bytes(msgspec.json.encode(summary))
    df = api.read_summary(tmp_path)
    assert list(df.columns) == ["case D", "no control"]
    assert df.loc["nvv"].tolist() == [0, 7] and df.loc["ntc"].tolist() == [2, 0]
    assert df.loc["q_cost", "no control"] == 0.0 and df.loc["taps_changes.vr1a", "case D"] == 2
    assert "seq" not in df.index and "t_ns" not in df.index  # the header is no metric
    assert df.attrs["summary"].decisions == 3
    no_baseline = msgspec.structs.replace(summary, baseline=None)
    (tmp_path / "summary.json").write_bytes(msgspec.json.encode(no_baseline))
    assert list(api.read_summary(tmp_path / "summary.json").columns) == ["case D"]


def test_an_evaluation_is_one_row_per_run(tmp_path):
    def spec(case: str, season: str) -> RunSpec:
        return RunSpec(case=case, season=season, bandwidth_v120=2.0, start="2023-01-01", days=1.0)  # type: ignore[arg-type]

    runs = tuple(RunResult(spec=spec(c, "winter"), metrics=_metrics(nvv=n), wall_s=10.0, steps=1440, decisions=288,
                           lockstep_misses=0, out_dir=f"o/{c}", recording=None) for c, n in (("A", 1), ("D", 4)))
    ev = Evaluation(config=EvaluateConfig(), feeder_id="f", feeder="f.toml", model="m.json", control_period_s=300,
                    runs=runs, wall_s=20.0,
                    failures=(RunFailure(spec=spec("B", "summer"), error="the bridge exited with 1", out_dir="o/B"),))
    (tmp_path / "results.json").write_bytes(msgspec.json.encode(ev))
    df = api.read_evaluation(tmp_path)
    assert df.index.tolist() == ["winter-A", "winter-D-bw2", "summer-B"]
    assert df.loc["winter-D-bw2", "nvv"] == 4 and df.loc["winter-A", "decisions"] == 288
    assert df.loc["summer-B", "error"] == "the bridge exited with 1" and np.isnan(df.loc["summer-B", "nvv"])
    assert df.attrs["feeder_id"] == "f"


@pytest.mark.bus
@pytest.mark.process
@pytest.mark.slow
def test_the_example_of_docs_api_runs_as_written(tmp_path, sharing_profiles):
    """docs/api.md's python block, in a fresh interpreter and cache (the session's year profiles in it): trains
    IEEE 13, runs 15 minutes, reads both."""
    text = (REPO / "docs" / "api.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert len(blocks) == 1
    (tmp_path / "feeders").symlink_to(REPO / "feeders")  # the example runs from a repository's root
    sharing_profiles(tmp_path / "cache" / "cvvc-edge")  # the default cache root under XDG_CACHE_HOME
    env = dict(os.environ, PYTHONPATH=str(REPO), XDG_CACHE_HOME=str(tmp_path / "cache"))
    proc = subprocess.run([sys.executable, "-c", blocks[0]], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=540, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = proc.stdout
    assert "model: ieee13-" in out
    assert re.search(r"^(\d+) decisions, 0 held", out, flags=re.M), out
    assert re.search(r"^nvv\s+\d+\s+\d+$", out, flags=re.M), out  # the case's column and the baseline's
    assert re.search(r"^15 truth frames from 11:00 to 11:14; highest node voltage 1\.\d{4} pu at v_pu\.", out,
                     flags=re.M), out
    assert re.search(r"^(optimal|soft)\s+\d+$", out, flags=re.M), out
    assert re.search(r"^taps\.2\s+\d+$", out, flags=re.M), out
    assert (tmp_path / "runs" / "api-example" / "session.mcap").is_file()
    assert list((tmp_path / "cache" / "cvvc-edge" / "models").glob("ieee13-*.json"))
