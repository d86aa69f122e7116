"""``cvvc feeder scaffold`` and the feeder zone on IEEE 13/123 and the four EPRI feeders (real OpenDSS).

Each draft must load with ``load_device_map``, pass ``check_device_map`` and compile in ``FeederEngine``; the zone
peak must leave out the other feeders' loads; the three suggested plants must be three-phase primaries of the
head's voltage class inside the zone, sized together to 100 % of the zone's peak.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from schemas.devicemap import load_device_map
from simulator_bridge.opendss.engine import FeederEngine
from simulator_bridge.survey.circuit_survey import survey_circuit
from simulator_bridge.survey.mapcheck import check_device_map
from simulator_bridge.survey.scaffold import PV_KVA_PER_KW, scaffold_device_map
from simulator_bridge.survey.zone import feeder_zone
from tests.conftest import REPO, SHARED_FEEDERS

# folder, master, the head element the feeder's EnergyMeter meters (or the first line out), the load(s) of
# other feeders upstream of / beside the meter (from the model's own files), the RegControl a map must name
FEEDERS = [
    ("ieee13", "IEEE13Nodeckt.dss", "Line.650632", (), ("reg1", "reg2", "reg3")),
    ("ieee123", "IEEE123Master.dss", "Line.sw1", (), ("creg1a", "creg2a")),
    ("epri-k1", "Master_NoPV.dss", "Line.k21_feeder", ("k_22_aggregate",), ("t2",)),
    ("epri-m1", "Master_NoPV.dss", "Line.temp2", ("aggregated",), ("m1_xfmr_regulator",)),
    ("epri-ckt5", "Master_ckt5.dss", "Line.mdv201_connector", (), ()),
    ("epri-ckt24", "master_ckt24.dss", "Line.fdr_05410", ("other_feeders",), ("subxfmr_regulator",)),
]


@pytest.mark.parametrize(("folder", "master", "head", "others", "regs"), FEEDERS, ids=[f[0] for f in FEEDERS])
def test_scaffold_drafts_a_map_that_loads_fits_and_compiles(tmp_path, folder, master, head, others, regs):
    master_path = SHARED_FEEDERS / folder / master
    out = tmp_path / "maps" / f"{folder}.toml"
    r = scaffold_device_map(master_path, out)
    dm = load_device_map(out)
    survey = survey_circuit(master_path)
    assert check_device_map(dm, survey) == []
    assert dm.feeder.name == folder and dm.feeder.head_element == head == r.head_element
    assert dm.master_path == master_path.resolve()
    assert {x.regcontrol for x in dm.regulator} == {x.name for x in survey.regcontrols} >= set(regs)
    assert {c.capacitor for c in dm.capacitor} == {c.name for c in survey.capacitors}
    for c in dm.capacitor:
        assert c.capcontrol == next(s.capcontrol for s in survey.capacitors if s.name == c.capacitor)
    # the zone's peak leaves out the other feeders' loads, and only them
    loads = {ld.name: ld.kw for ld in survey.loads}
    assert set(others) <= set(loads) and not set(others) & set(r.zone.load_names)
    assert len(r.zone.load_names) == len(loads) - len(others)
    assert r.zone.peak_load_kw == pytest.approx(sum(loads.values()) - sum(loads[o] for o in others), rel=1e-9)
    # three three-phase primary plants in the zone, in the head bus's voltage class, 100 % of the zone peak
    kv = {b.name: b for b in survey.buses}
    head_kv_ll = kv[r.zone.head_bus].kv_ln * math.sqrt(3)
    plants = [p for p in dm.pv if p.create]
    assert len(plants) == 3 and len({p.bus for p in plants}) == 3
    for p in plants:
        assert p.phases == 3 and kv[p.bus].phases == (1, 2, 3) and p.bus in r.zone.buses
        assert p.kv_ll == pytest.approx(kv[p.bus].kv_ln * math.sqrt(3), rel=1e-3)
        assert abs(p.kv_ll - head_kv_ll) <= 0.1 * head_kv_ll and p.kv_ll >= 1.0
        assert p.kva == pytest.approx(PV_KVA_PER_KW * p.pmpp_kw, abs=0.05)
    assert sum(p.pmpp_kw for p in plants) == pytest.approx(r.zone.peak_load_kw, abs=1.0)
    fractions = [s.fraction for s in r.pv_sites]
    assert fractions == sorted(fractions) and fractions[0] < 0.5 < fractions[-1] and fractions[-1] > 0.85
    # every line of the draft that sets a value is explained by a comment above it or beside it
    assert out.read_text().count("#") >= 3 + len(dm.regulator) + len(dm.capacitor) + 3
    # and it compiles in the simulator (epri-m1's LTC with its remote sensing too)
    engine = FeederEngine(load_device_map(out))
    try:
        assert engine.zone_peak_load_kw == pytest.approx(r.zone.peak_load_kw, rel=1e-9)
        outside = [n for n, inside in zip(engine.load_names, engine.load_in_feeder, strict=True) if not inside]
        assert sorted(outside) == sorted(others)
        zone_buses = {n.split(".")[0] for n, inside in zip(engine.node_names, engine.node_in_feeder, strict=True)
                      if inside}
        assert zone_buses == set(r.zone.buses)
    finally:
        engine.close()


@pytest.mark.parametrize("name", ["epri-k1", "epri-m1", "epri-ckt5", "epri-ckt24"])
def test_committed_epri_maps_fit_their_circuits(name):
    """The reviewed maps in feeders/ still fit the shared models, with their head and 100 % PV of the zone."""
    dm = load_device_map(REPO / "feeders" / f"{name}.toml")
    survey = survey_circuit(dm.master_path)
    assert check_device_map(dm, survey) == []
    zone = feeder_zone(survey, dm.feeder.head_element)
    assert sum(p.pmpp_kw for p in dm.pv) == pytest.approx(zone.peak_load_kw, abs=1.0)
    assert zone.outside_load_kw > 0 or name == "epri-ckt5"


def test_scaffold_refuses_to_overwrite_and_names_the_cause(tmp_path, capsys):
    from cvvc.cli import main

    out = tmp_path / "k1.toml"
    master = str(SHARED_FEEDERS / "epri-k1" / "Master_NoPV.dss")
    assert main(["feeder", "scaffold", master, "--out", str(out)]) == 0
    assert "zone peak 4769.8 kW" in capsys.readouterr().out  # the meter's side only: K22's 7685 kW left out
    before = out.read_bytes()
    assert main(["feeder", "scaffold", master, "--out", str(out)]) == 2
    assert "exists; pass --force" in capsys.readouterr().err and out.read_bytes() == before
    assert main(["feeder", "scaffold", str(tmp_path / "missing.dss"), "--out", str(tmp_path / "x.toml")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("cvvc feeder scaffold: error:") and "\n" not in err


def test_zone_of_a_circuit_without_meter_starts_at_the_first_line_out():
    survey = survey_circuit(SHARED_FEEDERS / "ieee123" / "IEEE123Master.dss")
    assert survey.meters == ()
    zone = feeder_zone(survey, "Line.sw1")
    assert zone.head_bus == "150r" and "150" not in zone.buses and len(zone.buses) == len(survey.buses) - 1
    assert np.isclose(zone.peak_load_kw, 3490.0)
