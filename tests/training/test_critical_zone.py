"""Critical nodes are taken in the feeder zone, and only where a controlled device can move the voltage."""

from __future__ import annotations

import numpy as np
import pytest

from tests.training.conftest import REPO
from training.critical import MOVABLE_PU, movable_nodes


@pytest.mark.parametrize(
    ("dv_dtap", "dv_dq", "kva", "expected"),
    [
        # a regulator secondary: one tap moves it 0.00625 pu
        ([[0.00625]], [[1e-6]], [1000.0], [True]),
        # a stiff source bus: neither a tap nor the whole Q range of the plant moves it 0.001 pu
        ([[0.0]], [[5e-7]], [1000.0], [False]),
        # no regulator, but the plant's Q range moves it 2e-6 pu/kvar x 1000 kvar = 0.002 pu
        (np.zeros((1, 0)), [[2e-6]], [1000.0], [True]),
        # a plant whose Q could not be perturbed (NaN column) moves nothing
        (np.zeros((1, 0)), [[np.nan]], [1000.0], [False]),
        # exactly at the threshold counts
        ([[MOVABLE_PU]], np.zeros((1, 0)), [], [True]),
    ],
)
def test_movable_nodes(dv_dtap, dv_dq, kva, expected):
    got = movable_nodes(np.asarray(dv_dtap, float), np.asarray(dv_dq, float), np.asarray(kva, float))
    assert got.tolist() == expected


@pytest.mark.slow  # trains EPRI K1
def test_ltc_primary_and_other_feeders_are_never_critical_on_epri_k1(tmp_path):
    """epri-k1: the 69 kV primary of LTC t2 (trans_equiv) and the second feeder K22 lie upstream of the meter."""
    from schemas.devicemap import load_device_map
    from schemas.settings import TrainingOptions
    from simulator_bridge.opendss.engine import FeederEngine
    from training.train import train

    path = REPO / "feeders" / "epri-k1.toml"
    result = train(path, TrainingOptions(blocks=(2, 2)), workers=1, cache_dir=tmp_path, progress=False)
    names = [c.name for c in result.model.critical_nodes]
    engine = FeederEngine(load_device_map(path))
    try:
        primary = engine.node_names[int(engine.reg_primary_node[0])]
        zone = {n for n, inside in zip(engine.node_names, engine.node_in_feeder, strict=True) if inside}
    finally:
        engine.close()
    assert primary.startswith("trans_equiv.") and primary not in names
    assert not any(n.startswith(("trans_equiv.", "k22.")) for n in names)
    assert set(names) <= zone
    assert not any(n.endswith(".4") for n in names)  # neutral nodes are no voltages to constrain
    kinds = {c.name: c.kinds for c in result.model.critical_nodes}
    assert "reg_secondary" in kinds["k_lsb.1"] and "head" in kinds["k_lsb.1"]
    assert sum("pv" in k for k in kinds.values()) == 9  # three three-phase plants
