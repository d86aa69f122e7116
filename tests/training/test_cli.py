"""``cvvc train`` and ``cvvc report accuracy`` through the real command line (IEEE 13, real OpenDSS)."""

import json

import pytest

from tests.training.conftest import REPO
from tests.training.test_train import _map


@pytest.mark.slow  # trains IEEE 13
def test_train_json_then_accuracy(tmp_path, monkeypatch, capsys):
    from cvvc.cli import main

    work, cache = tmp_path / "work", tmp_path / "cache"
    work.mkdir()
    monkeypatch.chdir(work)  # nothing may be written here: the profiles go to --cache
    feeder = REPO / "feeders" / "ieee13.toml"
    out = tmp_path / "m13.json"
    argv = ["train", "--feeder", str(feeder), "--out", str(out), "--blocks", "2", "2", "--cache", str(cache)]
    assert main([*argv, "--json"]) == 0
    assert list(work.iterdir()) == [] and list((cache / "profiles").glob("profiles-ieee13-*.npz"))
    summary = json.loads(capsys.readouterr().out)
    for key in ("scenarios", "power_flows", "critical_nodes", "critical_share", "seconds", "voltage_rmse_pu"):
        assert key in summary
    assert summary["scenarios"] >= 4 and summary["power_flows"] > summary["scenarios"]
    assert out.is_file()
    argv = ["report", "accuracy", "--model", str(out), "--feeder", str(feeder), "--month", "4", "--max-minutes", "30",
            "--cache", str(cache)]
    assert main([*argv, "--json"]) == 0
    assert list(work.iterdir()) == []
    report = json.loads(capsys.readouterr().out)
    assert report["minutes"] == 30 and len(report["errors"]) == 2
    assert all(e["max_abs_pu"] < 0.01 for e in report["errors"])
    assert main(argv) == 0  # the text form: the bounds' line says whether they held within 2x of their promise
    (line,) = [x for x in capsys.readouterr().out.splitlines() if x.startswith("calibrated bounds")]
    ((label, alpha),) = report["bound_alpha"].items()
    held = report["bound_miss_rate"][label] <= 2 * alpha
    assert ("held, within 2x" in line) == held and ("NOT held" in line) == (not held)


def test_train_error_is_one_line_with_status_2(tmp_path, capsys):
    from cvvc.cli import main

    path = _map(tmp_path, pv=False, regulator=True)
    assert main(["train", "--feeder", str(path), "--out", str(tmp_path / "m.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("cvvc train: error:") and "no PV plant" in err and "\n" not in err
