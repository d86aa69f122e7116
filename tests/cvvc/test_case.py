"""Case files (``cvvc.case``) on the settings tree (``schemas.settings``): ``cvvc init`` writes every default,
``cvvc run case.toml`` reads it, flags override it, unknown keys are refused, ``--print-case`` prints the result,
and the same run from flags or from the equivalent file is the same run."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import msgspec
import pytest

from cvvc.case import RUN_FLAGS, CaseFileError, apply_flags, case_toml, load_case, write_case
from cvvc.cli import build_parser, main
from cvvc.launch import RunConfig, bridge_args, case_agent_settings
from schemas.settings import SECTIONS, AgentOptions, AgentSettings, RunCase

REPO = Path(__file__).resolve().parents[2]
IEEE13 = REPO / "feeders" / "ieee13.toml"


def _run_args(*argv: str) -> argparse.Namespace:
    return build_parser().parse_args(["run", *argv])


def test_init_writes_every_setting_and_decodes_to_the_defaults(tmp_path, capsys):
    path = tmp_path / "case.toml"
    assert main(["init", str(path)]) == 0
    assert load_case(path) == RunCase()
    text = path.read_text()
    for section in SECTIONS:  # every key of every section is written, with a comment line above it
        assert f"\n[{section}]" in text
        for name in msgspec.structs.fields(getattr(RunCase(), section)):
            line = next(x for x in text.splitlines() if x.lstrip("# ").startswith(f"{name.name} = "))
            above = text.splitlines()[text.splitlines().index(line) - 1]
            assert above.startswith("# ") and len(above) > 10, name.name
    assert main(["init", str(path)]) == 2  # an existing file is not overwritten
    assert "exists" in capsys.readouterr().err
    assert main(["init", str(path), "--force"]) == 0


def test_a_resolved_case_round_trips_through_its_toml(tmp_path):
    case = RunCase(case="C", cache=str(tmp_path / "c"),
                   agent=AgentOptions(pv_margin_window_s=0.0, setpoint_hold=True, bandwidth_v120=3.0),
                   window=msgspec.structs.replace(RunCase().window, days=0.25, start="2023-07-10T11:00"))
    path = tmp_path / "resolved.toml"
    path.write_text(case_toml(case))
    assert load_case(path) == case
    assert "[default: false]" in case_toml(case)  # a value off its default says the default


def test_flags_override_the_file_and_the_rest_comes_from_the_file(tmp_path):
    path = tmp_path / "case.toml"
    path.write_text('case = "C"\n[window]\ndays = 0.5\nyear_seed = 5\n[agent]\npv_margin_window_s = 600.0\n'
                    '[bridge]\nnoise_scada_pct = 1.0\n[feeder]\nmap = "maps/feeder.toml"\n')
    case = apply_flags(load_case(path), _run_args(str(path), "--days", "0.25", "--setpoint-hold", "--insecure"))
    assert case.case == "C" and case.window.year_seed == 5  # the file's
    assert case.window.days == 0.25 and case.agent.setpoint_hold and not case.security.secure  # the flags'
    assert case.agent.pv_margin_window_s == 600.0 and case.bridge.noise_scada_pct == 1.0
    assert case.feeder.map == str(tmp_path / "maps" / "feeder.toml")  # relative to the file's folder
    assert apply_flags(load_case(path), _run_args(str(path))) == load_case(path)  # no flag: the file as it is


def test_every_run_flag_reaches_a_setting_of_the_tree():
    parser_dests = {a.dest for a in build_parser()._subparsers._group_actions[0].choices["run"]._actions}
    launcher_only = {"help", "case_file", "print_case", "json", "quiet"}  # display, not settings
    assert parser_dests - launcher_only == set(RUN_FLAGS)
    for dest, (section, key, _) in RUN_FLAGS.items():
        holder = RunCase() if section is None else getattr(RunCase(), section)
        assert key in holder.__struct_fields__, dest


@pytest.mark.parametrize(("text", "named"), [
    ("[agent]\npv_margin_windw_s = 0.0\n", "unknown key 'agent.pv_margin_windw_s'"),
    ("colour = 1\n", "unknown key 'colour'"),
    ("[windows]\ndays = 1\n", "unknown key 'windows'"),
    ("[window]\ndays = -1.0\n", "key 'window.days'"),
    ('case = "E"\n', "key 'case'"),
])
def test_a_bad_case_file_is_refused_in_one_line_naming_the_key(tmp_path, capsys, text, named):
    path = tmp_path / "case.toml"
    path.write_text(text)
    with pytest.raises(CaseFileError, match=named.replace(".", r"\.")):
        load_case(path)
    assert main(["run", str(path), "--print-case"]) == 2
    err = capsys.readouterr().err
    assert named in err and len(err.strip().splitlines()) == 1 and str(path) in err


def test_print_case_prints_the_resolved_case_and_runs_nothing(tmp_path, capsys, monkeypatch):
    path = tmp_path / "case.toml"
    path.write_text('[window]\ndays = 0.5\n[output]\nout = "here"\n')
    assert main(["run", str(path), "--print-case", "--case", "B", "--noise-pmu-pct", "0.1"]) == 0
    printed = capsys.readouterr().out
    resolved = msgspec.toml.decode(printed.encode(), type=RunCase)
    assert resolved.case == "B" and resolved.window.days == 0.5 and resolved.bridge.noise_pmu_pct == 0.1
    assert resolved.output.out == str(tmp_path / "here")
    assert not (tmp_path / "here").exists()  # nothing ran
    monkeypatch.chdir(tmp_path)  # a flag's path is printed absolute: the printed case runs the same run elsewhere
    assert main(["run", "--print-case", "--feeder", "maps/f.toml"]) == 0
    assert msgspec.toml.decode(capsys.readouterr().out.encode(), type=RunCase).feeder.map == str(
        tmp_path / "maps" / "f.toml")
    assert main(["run", "--print-case"]) == 0  # no file: the defaults
    assert msgspec.toml.decode(capsys.readouterr().out.encode(), type=RunCase) == RunCase()


def test_a_flag_that_breaks_a_constraint_is_refused_naming_the_key(capsys):
    assert main(["run", "--print-case", "--drop-prob", "1.5"]) == 2
    assert "key 'bridge.drop_prob'" in capsys.readouterr().err


def test_run_config_is_the_case_flattened_and_back():
    assert RunConfig().settings() == RunCase()  # RunConfig's defaults are the tree's
    case = RunCase(case="A", feeder=msgspec.structs.replace(RunCase().feeder, map="x.toml", train_seed=3),
                   agent=AgentOptions(control_banks=True), bridge=msgspec.structs.replace(RunCase().bridge,
                                                                                          drop_prob=0.05))
    config = RunConfig.of_case(case, progress=False, case_file="c.toml")
    assert config.feeder == "x.toml" and config.train_seed == 3 and config.drop_prob == 0.05
    assert config.settings() == case and not config.progress and config.case_file == "c.toml"


def test_the_shipped_agent_settings_of_each_case_are_as_before():
    """Case D with the defaults is ``AgentSettings``' defaults; A and B keep the default band and hold."""
    assert case_agent_settings("D", "f") == AgentSettings(feeder_id="f")
    a = case_agent_settings("A", "f", AgentOptions(control_banks=True, bandwidth_v120=3.0, setpoint_hold=True))
    assert a == AgentSettings(feeder_id="f", mode="taps", correction=False, full_visibility=True)
    c = case_agent_settings("C", "f", AgentOptions(bandwidth_v120=3.0, setpoint_hold=True))
    assert c == AgentSettings(feeder_id="f", correction=False, bandwidth_v120=3.0, setpoint_hold=True)


def test_the_same_run_from_flags_and_from_the_equivalent_case_file(tmp_path):
    """Same RunConfig, so the same agent settings and the same bridge command line: the same decisions."""
    flags = ["--feeder", str(IEEE13), "--case", "C", "--days", "0.25", "--start", "2023-07-10T11:00",
             "--bandwidth-v", "3", "--pv-margin-window-s", "0", "--setpoint-hold", "--noise-scada-pct", "1",
             "--drop-prob", "0.05", "--drop-burst-min", "10", "--year-seed", "4", "--no-baseline", "--insecure"]
    path = tmp_path / "case.toml"
    path.write_text(f'case = "C"\n[feeder]\nmap = {json.dumps(str(IEEE13))}\n'
                    '[window]\ndays = 0.25\nstart = "2023-07-10T11:00"\nyear_seed = 4\n'
                    '[agent]\nbandwidth_v120 = 3.0\npv_margin_window_s = 0.0\nsetpoint_hold = true\n'
                    '[bridge]\nnoise_scada_pct = 1.0\ndrop_prob = 0.05\ndrop_burst_min = 10.0\n'
                    '[output]\nbaseline = false\n[security]\nsecure = false\n')
    from_flags = RunConfig.of_case(apply_flags(RunCase(), _run_args(*flags)))
    from_file = RunConfig.of_case(apply_flags(load_case(path), _run_args(str(path))))
    assert from_flags == from_file
    settings = case_agent_settings(from_file.case, "ieee13", from_file.agent)
    assert settings == case_agent_settings(from_flags.case, "ieee13", from_flags.agent)
    assert settings is not None and settings.bandwidth_v120 == 3.0 and settings.setpoint_hold
    args = [bridge_args(c, IEEE13, "ieee13", c.start, 360, settings, tmp_path / "s.json", []) for c in
            (from_flags, from_file)]
    assert args[0] == args[1] and "--noise-scada-pct" in args[0] and "--drop-burst-min" in args[0]


def test_a_campaign_variants_agent_section_and_its_old_keys_are_one_setting(tmp_path):
    from cvvc.campaign import load_campaign, variant_agent
    from cvvc.evaluate import EvaluateError

    path = tmp_path / "campaign.toml"
    path.write_text('feeders = ["rural"]\ncases = ["D"]\nseasons = ["winter"]\n'
                    '[variants.old]\npv_margin_window_s = 0.0\nsetpoint_hold = true\n'
                    '[variants.new.agent]\npv_margin_window_s = 0.0\nsetpoint_hold = true\n'
                    '[variants.band.agent]\nbandwidth_v120 = 2.0\nreading_window_s = 0.0\n'
                    '[variants.both]\nsetpoint_hold = false\n[variants.both.agent]\nsetpoint_hold = true\n')
    campaign = load_campaign(path)
    assert variant_agent(campaign.variants["old"]) == variant_agent(campaign.variants["new"]) == \
        AgentOptions(pv_margin_window_s=0.0, setpoint_hold=True)
    assert variant_agent(campaign.variants["band"]).reading_window_s == 0.0
    with pytest.raises(EvaluateError, match="setpoint_hold"):
        variant_agent(campaign.variants["both"], "both")
    path.write_text('feeders = ["rural"]\ncases = ["D"]\nseasons = ["winter"]\n[variants.x.agent]\nfoo = 1\n')
    with pytest.raises(EvaluateError, match="foo"):
        load_campaign(path)


def test_an_evaluation_without_bands_runs_its_agents_band():
    """One source for the band: ``bandwidths_v120`` left out is the agent's, written out in the configuration."""
    from cvvc.evaluation import EvaluateConfig

    assert EvaluateConfig().bandwidths_v120 == (AgentOptions().bandwidth_v120,)
    assert EvaluateConfig(agent=AgentOptions(bandwidth_v120=3.0)).bandwidths_v120 == (3.0,)
    assert EvaluateConfig(agent=AgentOptions(bandwidth_v120=3.0), bandwidths_v120=(2.0, 4.0)).bandwidths_v120 == \
        (2.0, 4.0)
    back = msgspec.json.decode(msgspec.json.encode(EvaluateConfig()), type=EvaluateConfig)
    assert back == EvaluateConfig()


@pytest.mark.bus
@pytest.mark.process
def test_cvvc_run_of_a_case_file_runs_it_and_records_the_case(tmp_path, ieee13_model):
    """Ten daylight minutes of case D on IEEE 13 from a case file whose paths are relative to it, one flag on top;
    the summary records the file and the resolved case, the report names the file."""
    folder = tmp_path / "cases"
    folder.mkdir()
    path = folder / "case.toml"
    write_case(path)
    text = path.read_text()
    text = text.replace('# map = "..."', f"map = {json.dumps(str(IEEE13))}", 1)
    text = text.replace('# model = "..."', f"model = {json.dumps(str(ieee13_model))}", 1)
    text = text.replace('# out = "..."', 'out = "out"', 1).replace('# cache = "..."', 'cache = "cache"', 1)
    text = text.replace('start = "2023-01-16"', 'start = "2023-07-10T11:00"', 1)
    text = text.replace("baseline = true", "baseline = false", 1)
    path.write_text(text)
    elsewhere = tmp_path / "cwd"
    elsewhere.mkdir()
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-m", "cvvc", "run", str(path), "--days", str(10 / 1440), "--json"],
                          cwd=elsewhere, env=env, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout)
    assert summary["out_dir"] == str(folder / "out") and summary["steps"] == 10 and summary["decisions"] == 2
    assert summary["case_file"] == str(path)
    recorded = msgspec.convert(summary["settings"], RunCase)
    assert recorded == msgspec.structs.replace(load_case(path), window=msgspec.structs.replace(
        load_case(path).window, days=10 / 1440))
    assert f"case file: `{path}`" in (folder / "out" / "report.md").read_text()
    assert (folder / "cache" / "security").is_dir()  # the cache the file names, relative to it


def test_a_fleet_files_agent_section_is_a_case_files(tmp_path):
    from cvvc.fleet import load_fleet_file
    from cvvc.launch import LaunchError

    path = tmp_path / "fleet.toml"
    path.write_text('case = "D"\n[agent]\npv_margin_window_s = 0.0\n[[feeder]]\nrural_seed = 1\n')
    assert load_fleet_file(path).agent == AgentOptions(pv_margin_window_s=0.0)
    path.write_text('[[feeder]]\nrural_seed = 1\n')  # a fleet file without it: the defaults
    assert load_fleet_file(path).agent is None
    path.write_text('[agent]\npv_margin = 0.0\n[[feeder]]\nrural_seed = 1\n')
    with pytest.raises(LaunchError, match="pv_margin"):
        load_fleet_file(path)
