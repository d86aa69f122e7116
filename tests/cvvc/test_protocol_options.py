"""``cvvc run`` refuses, before anything starts, the options the field-protocol closed loops do not take."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
REALISM = [(dict(drop_prob=0.1), "--drop-prob"), (dict(noise_scada_pct=1.0), "--noise-scada-pct"),
           (dict(clock_skew_s=2.0), "--clock-skew-s"), (dict(realtime=True, meas_delay_s=5.0), "--meas-delay-s")]


@pytest.mark.parametrize(("protocol", "option", "named"), [
    *[(dict(pv_protocol="sunspec"), option, named) for option, named in REALISM],
    *[(dict(field_protocol="dnp3"), option, named) for option, named in REALISM],
    (dict(field_protocol="dnp3"), dict(case="A"), "case A"),  # its agent commands taps: no DNP3 point for them
    (dict(field_protocol="dnp3"), dict(case="B"), "case B")])
def test_options_a_protocol_does_not_take_are_refused_before_anything_starts(tmp_path, protocol, option, named):
    from cvvc.launch import LaunchError, RunConfig, run

    config = RunConfig(feeder=str(REPO / "feeders" / "ieee13.toml"), out=str(tmp_path / "o"),
                       cache=str(tmp_path / "c"), **protocol, **option)
    with pytest.raises(LaunchError, match=named):
        run(config)
    assert not (tmp_path / "o").exists() and not (tmp_path / "c").exists()  # refused before anything was made


def test_an_unknown_field_protocol_is_refused():
    from cvvc.errors import CommandError
    from cvvc.field_protocol import check_field_protocol

    with pytest.raises(CommandError, match="choose bus or dnp3"):
        check_field_protocol("modbus", case="D", noise_scada_pct=0.0, drop_prob=0.0, meas_delay_s=0.0,
                             clock_skew_s=0.0)


def test_the_adapter_of_a_plant_the_map_gives_q_at_night_is_told_so_and_no_other():
    import msgspec

    from cvvc.pv_protocol import adapter_args
    from schemas.devicemap import load_device_map

    dm = load_device_map(REPO / "feeders" / "ieee13.toml")
    dm = msgspec.structs.replace(dm, pv=[msgspec.structs.replace(p, q_at_night=p.id == "pv675") for p in dm.pv])
    told = {p.id: "--q-at-night" in adapter_args(dm, "ieee13", p.id, "tcp/127.0.0.1:9", volt_var=False, connect=[])
            for p in dm.pv}
    assert told == {"pv675": True, "pv680": False, "pv633": False}
