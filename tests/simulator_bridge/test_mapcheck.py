"""``cvvc feeder info`` checks a device map against its circuit: one line per problem, saying how to mend it.

Real OpenDSS (IEEE 13); the head-bus load rule of the zone on a small hand-made survey.
"""

from __future__ import annotations

import json

import pytest

from simulator_bridge.survey.survey import CircuitSurvey, SurveyBus, SurveyEdge, SurveyLoad
from simulator_bridge.survey.zone import feeder_zone
from tests.conftest import REPO, SHARED_FEEDERS

IEEE13 = (REPO / "feeders" / "ieee13.toml").read_text().replace(
    'master = "../../shared/feeders/ieee13/IEEE13Nodeckt.dss"',
    f'master = "{(SHARED_FEEDERS / "ieee13" / "IEEE13Nodeckt.dss").as_posix()}"')

CAPS = '\n[[capacitor]]\nid = "cap1"\ncapacitor = "cap1"\n'
METER = '\n[[meter]]\nid = "ami1"\nnode = "675.1"\n'

# (what is changed in the IEEE 13 map, the one line expected)
BROKEN = [
    (("source_bus = \"650\"", "source_bus = \"nowhere\""),
     r"feeder.source_bus 'nowhere' is not a bus of IEEE13Nodeckt.dss; set source_bus = 'sourcebus'"),
    (("head_element = \"Line.650632\"", "head_element = \"Line.nosuch\""),
     r"feeder.head_element 'Line.nosuch' is not an element of IEEE13Nodeckt.dss; set head_element = 'Line.650632'"),
    (("regcontrol = \"reg2\"", "regcontrol = \"reg9\""),
     r"regulator 'reg2': RegControl 'reg9' not found in IEEE13Nodeckt.dss; known: reg1, reg2, reg3"),
    (("bus = \"675\"", "bus = \"675x\""), r"pv 'pv675': bus '675x' not found in IEEE13Nodeckt.dss"),
    (("bus = \"675\"", "bus = \"611\""),
     r"pv 'pv675': phases = 3 but bus '611' has phase(s) [3]; pick a three-phase bus or set phases = 1"),
    (("bus = \"675\"", "bus = \"650\""),
     r"pv 'pv675': bus '650' is outside the feeder zone (not downstream of Line.650632); pick a bus downstream"),
    (("id = \"pv680\"\nbus = \"680\"\nkv_ll = 4.16", "id = \"pv680\"\nbus = \"680\"\nkv_ll = 12.47"),
     r"pv 'pv680': kv_ll = 12.47 but bus '680' has a base of 4.16 kV line to line; set kv_ll = 4.16"),
    ((CAPS, CAPS.replace('capacitor = "cap1"', 'capacitor = "cap7"')),
     r"capacitor 'cap1': Capacitor 'cap7' not found in IEEE13Nodeckt.dss; known: cap1, cap2"),
    ((CAPS, CAPS + 'capcontrol = "cc1"\n'),
     r"capacitor 'cap1': CapControl 'cc1' does not control Capacitor 'cap1' in IEEE13Nodeckt.dss; remove capcontrol"),
    ((METER, METER.replace('"675.1"', '"675x.1"')),
     r"meter 'ami1': node '675x.1' is not a node of IEEE13Nodeckt.dss (bus '675x' not found); name it bus.phase"),
    ((METER, METER.replace('"675.1"', '"611.1"')),
     r"meter 'ami1': node '611.1' is not a node of IEEE13Nodeckt.dss (bus '611' has phase(s) [3], not '1')"),
    ((METER, METER.replace('"675.1"', '"650.1"')),
     r"meter 'ami1': node '650.1' is outside the feeder zone (not downstream of Line.650632)"),
]


@pytest.fixture
def info(tmp_path, capsys):
    from cvvc.cli import main

    def run(text: str, *extra: str) -> tuple[int, str, str]:
        path = tmp_path / "map.toml"
        path.write_text(text)
        code = main(["feeder", "info", str(path), *extra])
        out = capsys.readouterr()
        return code, out.out, out.err

    return run


def test_a_good_map_is_described_with_its_zone(info):
    code, out, err = info(IEEE13 + CAPS + METER, "--json")  # an AMI meter at a node of the zone is fine
    assert code == 0, err
    d = json.loads(out)
    assert d["peak_load_kw"] == 3466.0 and d["loads"] == 15 and d["outside_loads"] == 0
    assert d["zone_nodes"] < d["nodes"]  # sourcebus and 650 are upstream of the head meter
    assert d["capacitors"] == [{"id": "cap1", "capacitor": "cap1", "bus": "675", "kvar": 600.0, "capcontrol": None}]


@pytest.mark.parametrize(("change", "line"), BROKEN, ids=[b[1].split(":")[0] + str(i) for i, b in enumerate(BROKEN)])
def test_each_problem_is_one_line_that_says_how_to_mend_it(info, change, line):
    base = IEEE13 + CAPS + METER
    assert change[0] in base
    code, out, err = info(base.replace(change[0], change[1], 1))
    assert code == 2 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("cvvc feeder info: error: ") and line in lines[0]


def test_every_problem_is_reported_at_once(info):
    text = IEEE13.replace('regcontrol = "reg2"', 'regcontrol = "reg9"').replace('bus = "675"', 'bus = "611"')
    code, _, err = info(text)
    assert code == 2 and len(err.strip().splitlines()) == 2


def test_a_map_that_does_not_decode_is_one_line(info):
    code, _, err = info(IEEE13.replace("kva = 1200.0", "kva = 10.0"))
    assert code == 2 and len(err.strip().splitlines()) == 1 and "kva 10.0 < pmpp_kw 1080.0" in err


def _bus(name: str) -> SurveyBus:
    return SurveyBus(name, 7.2, (1, 2, 3))


def test_loads_on_the_meter_bus_or_upstream_are_outside_the_zone():
    """src -> sub (transformer); sub carries an aggregate load beside the meter; Line.head sub -> a -> b."""
    survey = CircuitSurvey(
        master="x.dss", circuit="x", source_bus="src", source_kv_ll=69.0, source_pu=0.97,
        buses=tuple(_bus(b) for b in ("src", "sub", "a", "b", "other")),
        edges=(SurveyEdge("transformer.sub", "transformer", "src", "sub", 3, 0j),
               SurveyEdge("line.head", "line", "sub", "a", 3, 0.1 + 0.2j),
               SurveyEdge("line.ab", "line", "a", "b", 3, 0.3 + 0.4j),
               SurveyEdge("line.other", "line", "sub", "other", 3, 0.1 + 0.1j)),
        elements=frozenset(), regcontrols=(), capacitors=(), pvsystems=(),
        loads=(SurveyLoad("agg", "sub", 5000.0), SurveyLoad("la", "a", 100.0), SurveyLoad("lb", "b", 200.0),
               SurveyLoad("lo", "other", 300.0), SurveyLoad("ls", "src", 50.0)),
        meters=(), node_count=15)
    zone = feeder_zone(survey, "Line.head")
    assert zone.head_bus == "sub" and zone.buses == {"sub", "a", "b"}
    assert zone.load_names == ("la", "lb") and zone.peak_load_kw == 300.0 and zone.outside_load_kw == 5350.0
