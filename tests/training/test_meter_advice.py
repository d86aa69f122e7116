"""Meter advice (training.meter_advice): the ranking rule, then IEEE 13 through real OpenDSS and the CLI."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from regression.model import read_model
from schemas.devicemap import load_device_map
from tests.training.conftest import REPO
from training.errors import TrainingError
from training.meter_advice import advise_meters, rank_sites, write_advised_map

IEEE13 = REPO / "feeders" / "ieee13.toml"


def test_sites_rank_by_the_squared_error_a_meter_removes_not_by_the_error_alone():
    rng = np.random.default_rng(0)
    err = rng.normal(0.0, [0.001, 0.004, 0.008, 0.006], (200, 4))
    metered = err.copy()
    metered[:, 0] *= 0.5  # a small error, halved: gains least
    metered[:, 1] *= 0.1
    metered[:, 2] *= 0.99  # the largest error, but a meter barely helps (it moves within the reading interval)
    metered[:, 3] *= 0.2  # gains most
    assert rank_sites(err, metered).tolist() == [3, 1, 2, 0]
    assert rank_sites(err, metered, exclude=[3]).tolist() == [1, 2, 0]
    same = rank_sites(np.ones((5, 3)), np.zeros((5, 3)))
    assert same.tolist() == [0, 1, 2]  # ties to the lower index
    noisy = metered.copy()
    noisy[:, 0] = err[:, 0] * 1.5  # the meter's noise outweighs the estimate's error there: not a site
    assert rank_sites(err, noisy).tolist() == [3, 1, 2]


@pytest.fixture(scope="module")
def advice(ieee13_model, profile_cache):
    return advise_meters(ieee13_model, IEEE13, k=2, months=[7], minutes=120, cache_dir=profile_cache,
                         progress=False)


def test_the_advised_sites_are_the_largest_measured_gains_and_lower_the_feeder_error(advice, ieee13_model):
    names = [c.name for c in read_model(ieee13_model).critical_nodes]
    assert advice.k == 2 and len(advice.sites) == 2 and advice.minutes == 120
    assert [s.rank for s in advice.sites] == [1, 2]
    assert all(s.node in names for s in advice.sites)
    assert advice.sites[0].gain >= advice.sites[1].gain > 0.0
    for s in advice.sites:
        # the squared error the meter removes there, as a share of every critical node's
        assert s.gain == pytest.approx((s.rmse_pu ** 2 - s.rmse_metered_pu ** 2) / (len(names) * advice.rmse_pu ** 2),
                                       rel=1e-9)
    assert advice.rmse_with_k_pu < advice.rmse_pu  # the gains are real: the feeder's error falls
    assert advice.miss_rate is not None and advice.miss_rate_with_k is not None


def test_the_advised_map_adds_the_meters_and_keeps_the_fingerprint(advice, tmp_path, ieee13_model):
    (tmp_path / "tree" / "feeders").mkdir(parents=True)
    (tmp_path / "shared").symlink_to(load_device_map(IEEE13).master_path.parents[2])
    src = tmp_path / "tree" / "feeders" / "ieee13.toml"
    src.write_text(IEEE13.read_text())
    out = write_advised_map(src, advice, src.with_name("ieee13-advised.toml"))
    dm = load_device_map(out)
    assert [(m.id, m.node, m.interval_s) for m in dm.meter] == [
        ("ami1", advice.sites[0].node, 900), ("ami2", advice.sites[1].node, 900)]
    assert dm.fingerprint() == read_model(ieee13_model).fingerprint  # the same model serves the advised map
    with pytest.raises(TrainingError, match="beside"):
        write_advised_map(src, advice, tmp_path / "elsewhere.toml")
    with pytest.raises(TrainingError, match="the map itself"):
        write_advised_map(src, advice, src)


def test_bad_requests_are_refused_before_simulating(ieee13_model, profile_cache):
    n = len(read_model(ieee13_model).critical_nodes)
    with pytest.raises(TrainingError, match=f"the model has {n} critical nodes"):
        advise_meters(ieee13_model, IEEE13, k=n + 1, cache_dir=profile_cache, progress=False)
    with pytest.raises(TrainingError, match="months"):
        advise_meters(ieee13_model, IEEE13, k=1, months=[13], cache_dir=profile_cache, progress=False)


def test_the_cli_prints_the_advice_as_json(ieee13_model, tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "cvvc", "feeder", "advise-meters", str(IEEE13), "--model", str(ieee13_model),
         "--k", "1", "--months", "4", "--minutes", "30", "--cache", str(tmp_path), "--json"],
        capture_output=True, text=True, timeout=300, cwd=REPO)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)
    assert out["k"] == 1 and len(out["sites"]) == 1 and out["months"] == [4]
    bad = subprocess.run([sys.executable, "-m", "cvvc", "feeder", "advise-meters", str(IEEE13), "--model",
                          str(ieee13_model), "--k", "1", "--months", "x"], capture_output=True, text=True, timeout=60,
                         cwd=REPO)
    assert bad.returncode == 2 and "months" in bad.stderr
