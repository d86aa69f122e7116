"""AMI meters (explicit option, ``[[meter]]``) end to end on IEEE 13: the bridge reads a critical node every 15
minutes onto the bus, the agent moves its estimate of that node by the reading, the recording replays bit for bit.
Real processes, real Zenoh on loopback, real OpenDSS, real MCAP."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from regression.model import read_model
from schemas import messages as m
from schemas.bus import codec_for
from schemas.devicemap import load_device_map

REPO = Path(__file__).resolve().parents[2]
_NS = 1_000_000_000


def _cvvc(*args: str, cwd: Path, timeout_s: float = 300.0) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", "cvvc", *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout_s, check=False)


@pytest.fixture(scope="module")
def ami_run(tmp_path_factory, ieee13_model, sharing_profiles):
    """One simulated hour of case D on IEEE 13 from 11:00, with a meter at the critical node of widest bounds."""
    model = read_model(ieee13_model)
    assert model.bounds is not None and model.bounds.ami_interval_s == 900  # calibration gives the AMI bounds
    widest = int(np.argmax(np.add(model.bounds.upper_pu, model.bounds.lower_pu)))
    node = model.critical_nodes[widest].name
    work = tmp_path_factory.mktemp("ami-run")
    # the map beside a link to ../shared, as feeders/ieee13.toml is: the same text but the meter, the same model
    (work / "tree" / "feeders").mkdir(parents=True)
    (work / "shared").symlink_to(load_device_map(REPO / "feeders" / "ieee13.toml").master_path.parents[2])
    ami_map = work / "tree" / "feeders" / "ieee13-ami.toml"
    ami_map.write_text((REPO / "feeders" / "ieee13.toml").read_text() + f'\n[[meter]]\nid = "ami1"\nnode = "{node}"\n')
    assert load_device_map(ami_map).fingerprint() == model.fingerprint  # meters leave the fingerprint alone
    out = work / "out"
    proc = _cvvc("run", "--feeder", str(ami_map), "--model", str(ieee13_model),
                 "--days", str(1 / 24), "--start", "2023-07-10T11:00", "--out", str(out),
                 "--cache", str(sharing_profiles(work / "cache")), "--json", cwd=work)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out, node, widest, model


def _recorded(path: Path) -> tuple[list[m.MeterFrame], list[m.Decision]]:
    meters, decisions = [], []
    with path.open("rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
            if "/meas/ami/" in channel.topic:
                meters.append(codec_for(m.MeterFrame).decode(message.data))
            elif channel.topic.endswith("/agent/decision"):
                decisions.append(codec_for(m.Decision).decode(message.data))
    return meters, decisions


def test_the_meter_reads_every_15_minutes_and_the_agent_takes_its_readings(ami_run):
    out, node, idx, model = ami_run
    meters, decisions = _recorded(out / "session.mcap")
    minutes = [(f.t_ns // _NS) % 3600 // 60 for f in meters]
    assert minutes == [0, 15, 30, 45]
    assert {f.node for f in meters} == {node} and {f.meter_id for f in meters} == {"ami1"}
    agent = json.loads((out / "agent-summary.json").read_text())
    assert agent["ami"]["ami_readings"] == 4 and agent["ami"]["ami_used"] >= 9
    assert not any(k for k in agent["rejected"] if k.startswith("ami"))
    by_t = {d.step_t_ns: d for d in decisions}
    assert len(by_t) == 12
    est = {t: d.estimates[idx] for t, d in by_t.items()}
    assert all(e.node == node for e in est.values())
    # a reading published before the step's device frames: the decision of its minute estimates the node exactly
    for f in meters:
        assert abs(est[f.t_ns].v_pu - f.v_pu) < 1e-8
        ami_low = min(model.bounds.lower_pu[idx], model.bounds.ami_lower_pu[idx])
        assert est[f.t_ns].bound_low_pu == pytest.approx(ami_low, abs=1e-6)
    # between readings, the reading's offset carried forward: not the reading itself
    between = [t for t in by_t if t not in {f.t_ns for f in meters}]
    assert between and all(abs(est[t].v_pu - meters[0].v_pu) > 1e-9 for t in between)


def test_the_sessions_decisions_replay_bit_for_bit_with_the_readings(ami_run, tmp_path):
    out, *_ = ami_run
    proc = _cvvc("replay", str(out / "session.mcap"), "--offline", "--json", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    diff = json.loads(proc.stdout)["diff"]
    assert diff["identical"] == diff["recorded"] == 12


def test_the_epri_ckt24_ami_map_is_epri_ckt24_plus_its_meters():
    """``feeders/epri-ckt24-ami.toml`` is a copy with meters: it must not drift from the map it copies."""
    from msgspec.structs import replace

    base = load_device_map(REPO / "feeders" / "epri-ckt24.toml")
    ami = load_device_map(REPO / "feeders" / "epri-ckt24-ami.toml")
    assert [x.node for x in ami.meter] == ["g2100gi2700_n292330_sec_1.3", "g2100nj7400_n300463_sec_1.1",
                                           "g2000vh9100_n283615_sec_2.3"]
    assert replace(ami, meter=[]) == base and ami.fingerprint() == base.fingerprint()
