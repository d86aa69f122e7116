"""The embedded rural feeder: line constants, statistics, determinism, peak-load voltages, ``cvvc feeder``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cvvc.cli import main
from schemas.devicemap import load_device_map
from simulator_bridge.bus.cli import default_feeder_dir, ensure_default_feeder
from simulator_bridge.opendss.engine import FeederEngine
from simulator_bridge.rural.generator import (
    CONDUCTORS,
    GeneratorError,
    generate_rural_feeder,
    phase_capacitance_uf_per_mile,
    phase_impedance_ohm_per_mile,
)

# Paper section IV: "The rural circuit has 1003 buses (1284 single-phase nodes)".
PAPER_BUSES, PAPER_NODES = 1003, 1284
SEEDS = (1, 2, 7)

# Kersting, Distribution System Modeling and Analysis, example 4.1 / 5.1: 336,400 26/7 ACSR phases,
# 4/0 6/1 ACSR neutral on the ID-500 crossarm (phases at 28 ft: x = 0, 2.5, 7 ft; neutral at x = 4, 24 ft).
KERSTING_XY_FT = np.array([[0.0, 28.0], [2.5, 28.0], [7.0, 28.0], [4.0, 24.0]])
KERSTING_Z_ABC = np.array(
    [
        [0.4576 + 1.0780j, 0.1560 + 0.5017j, 0.1535 + 0.3849j],
        [0.1560 + 0.5017j, 0.4666 + 1.0482j, 0.1580 + 0.4236j],
        [0.1535 + 0.3849j, 0.1580 + 0.4236j, 0.4615 + 1.0651j],
    ]
)  # [ohm/mile]
KERSTING_Y_ABC_US = np.array(
    [[5.6711, -1.8362, -0.7033], [-1.8362, 5.9774, -1.169], [-0.7033, -1.169, 5.391]]
)  # shunt admittance (imaginary part) [uS/mile]


def test_line_impedance_matches_kersting_example_4_1():
    conds = [CONDUCTORS["336_acsr"]] * 3 + [CONDUCTORS["4/0_acsr"]]
    z = phase_impedance_ohm_per_mile(
        KERSTING_XY_FT, np.array([c.r_ohm_per_mile for c in conds]), np.array([c.gmr_ft for c in conds]), 3
    )
    np.testing.assert_allclose(z, KERSTING_Z_ABC, atol=2e-4)


def test_line_capacitance_matches_kersting_example_5_1():
    conds = [CONDUCTORS["336_acsr"]] * 3 + [CONDUCTORS["4/0_acsr"]]
    c_uf = phase_capacitance_uf_per_mile(KERSTING_XY_FT, np.array([c.diameter_in for c in conds]), 3)
    # the worked example rounds its image distances and potential coefficients: agreement within 1 %
    np.testing.assert_allclose(376.9911 * c_uf, KERSTING_Y_ABC_US, rtol=1e-2)


def _local_control(engine: FeederEngine, max_rounds: int = 40) -> int:
    """Regulators on local control, one tap per regulator per round, until every one is inside its band.

    Returns the number of rounds with a tap change. A test helper standing in for the QSTS controller.
    """
    sp, half_band = engine.reg_default_setpoint_v120, engine.reg_default_band_v120 / 2.0
    for rounds in range(max_rounds):
        engine.solve()
        v = engine.readings().reg_v120_compared
        move = np.where(v < sp - half_band, 1, np.where(v > sp + half_band, -1, 0))
        taps = np.clip(engine.taps() + move, -engine.reg_tap_max, engine.reg_tap_max)
        if np.array_equal(taps, engine.taps()):
            return rounds
        engine.set_taps(taps)
    raise AssertionError(f"regulators did not settle in {max_rounds} rounds")


@pytest.fixture(scope="module", params=SEEDS)
def rural(request, tmp_path_factory):
    seed = request.param
    path = generate_rural_feeder(seed, tmp_path_factory.mktemp(f"rural{seed}"))
    engine = FeederEngine(load_device_map(path))
    yield seed, path, engine
    engine.close()


def test_statistics_match_the_papers_rural_circuit(rural):
    _, _, engine = rural
    buses = {n.split(".")[0] for n in engine.node_names}
    assert abs(len(buses) - PAPER_BUSES) <= 0.05 * PAPER_BUSES
    assert abs(len(engine.node_names) - PAPER_NODES) <= 0.05 * PAPER_NODES
    assert 200 <= len(engine.load_names) <= 700  # a few hundred loads
    peak_kw = engine.load_kw_nominal.sum()
    assert 3000.0 <= peak_kw <= 6000.0  # a few MW
    assert engine.load_kw_nominal.max() <= 300.0  # no single load dominates
    # three PV plants, three-phase, together ~100 % of peak load, inverters rated above Pmpp
    assert len(engine.pv_ids) == 3
    assert all(len(nodes) == 3 for nodes in engine.pv_node_index)
    assert engine.pv_pmpp_kw.sum() / peak_kw == pytest.approx(1.0, abs=0.01)
    assert np.all(engine.pv_kva >= engine.pv_pmpp_kw)


def test_two_three_phase_and_two_single_phase_regulators(rural):
    _, path, engine = rural
    assert engine.regulator_ids == ("reg1a", "reg1b", "reg1c", "reg2a", "reg2b", "reg2c", "reg3", "reg4")
    names = engine.node_names
    primary = [names[i] for i in engine.reg_primary_node]
    secondary = [names[i] for i in engine.reg_secondary_node]
    for bank in (slice(0, 3), slice(3, 6)):  # one bus pair, phases 1, 2, 3
        assert len({n.split(".")[0] for n in primary[bank]}) == 1
        assert len({n.split(".")[0] for n in secondary[bank]}) == 1
        assert [n.split(".")[1] for n in secondary[bank]] == ["1", "2", "3"]
    for node in secondary[6:]:  # single-phase units on single-phase buses
        bus = node.split(".")[0]
        assert [n for n in names if n.split(".")[0] == bus] == [node]
    # +/-10 % in 32 steps, 2 V band around 123 V on the 120 V base
    assert np.all(engine.reg_tap_max == 16)
    np.testing.assert_allclose(engine.reg_default_setpoint_v120, 123.0)
    np.testing.assert_allclose(engine.reg_default_band_v120, 2.0)
    text = (path.parent / "regulators.dss").read_text()
    assert text.count("maxtap=1.1 mintap=0.9 numtaps=32") == 8


def test_peak_load_voltages_inside_limits_with_local_regulator_control(rural):
    _, _, engine = rural
    engine.set_loads_kw(engine.load_kw_nominal)
    engine.set_pv(np.zeros(3), np.zeros(3))
    engine.set_taps(np.zeros(8, dtype=int))
    engine.solve()
    v_neutral_taps = engine.node_voltages_pu()
    _local_control(engine)
    v = engine.node_voltages_pu()
    v120 = engine.readings().reg_v120_compared
    assert np.all(np.abs(v120 - engine.reg_default_setpoint_v120) <= engine.reg_default_band_v120 / 2.0)
    assert 0.95 < v.min() and v.max() < 1.05, (v.min(), v.max())
    assert v.min() > v_neutral_taps.min() + 0.01  # the regulators are where the voltage drop needs them


def test_same_seed_same_bytes_and_different_seeds_differ(tmp_path):
    a = generate_rural_feeder(3, tmp_path / "a").parent
    b = generate_rural_feeder(3, tmp_path / "b").parent
    c = generate_rural_feeder(4, tmp_path / "c").parent
    files = sorted(p.name for p in a.iterdir())
    assert files == sorted(p.name for p in b.iterdir())
    assert {"master.dss", "devicemap.toml", "lines.dss", "loads.dss", "regulators.dss"} <= set(files)
    for name in files:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    for name in ("lines.dss", "loads.dss", "devicemap.toml"):
        assert (a / name).read_bytes() != (c / name).read_bytes(), name


@pytest.mark.parametrize("seed", [-1, 1.5, True])
def test_bad_seed_is_rejected(seed, tmp_path):
    with pytest.raises(GeneratorError, match="seed"):
        generate_rural_feeder(seed, tmp_path)


def test_cli_generate_and_info_json(tmp_path, capsys):
    assert main(["feeder", "generate", "--seed", "2", "--out", str(tmp_path / "f")]) == 0
    printed = Path(capsys.readouterr().out.strip())
    assert printed == tmp_path / "f" / "devicemap.toml" and printed.is_file()
    assert main(["feeder", "info", str(tmp_path / "f"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["name"] == "rural-s2"
    assert abs(info["buses"] - PAPER_BUSES) <= 0.05 * PAPER_BUSES
    assert abs(info["nodes"] - PAPER_NODES) <= 0.05 * PAPER_NODES
    assert [r["phase"] for r in info["regulators"]][:6] == [1, 2, 3, 1, 2, 3]
    assert len(info["pv"]) == 3 and info["pv_share_of_peak"] == pytest.approx(1.0, abs=0.01)
    assert info["peak_load_kw"] == pytest.approx(sum(p["pmpp_kw"] for p in info["pv"]), rel=0.01)


def test_cli_info_on_a_missing_feeder_is_one_line_error(tmp_path, capsys):
    assert main(["feeder", "info", str(tmp_path / "nothing")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("cvvc feeder info: error:") and "devicemap.toml" in err and "\n" not in err


def test_ensure_default_feeder_generates_once(tmp_path):
    path = ensure_default_feeder(tmp_path, seed=1)
    assert path.parent == default_feeder_dir(tmp_path, 1) and path.is_file()
    mtime = path.stat().st_mtime_ns
    assert ensure_default_feeder(tmp_path, seed=1) == path
    assert path.stat().st_mtime_ns == mtime
    assert load_device_map(path).feeder.name == "rural-s1"
    assert [p.name for p in path.parent.parent.iterdir()] == [path.parent.name]  # no temporary folder left
