import numpy as np

from training.critical import extreme_nodes, node_phase, select_critical, upstream_regulators


def test_upstream_regulator_from_tap_sensitivities():
    # nodes: 0 = reg0 secondary, 1 behind reg0, 2 = reg1 secondary (behind reg0), 3 behind both, 4 neither
    step = 0.00625
    d = np.array(
        [
            [step, 0.0],
            [0.98 * step, 0.0],
            [0.97 * step, step],
            [0.95 * step, 0.99 * step],
            [0.0001, 0.0002],
        ]
    )
    assert upstream_regulators(d, np.array([0, 2])).tolist() == [0, 0, 1, 1, -1]


def test_no_regulators_means_no_upstream():
    assert upstream_regulators(np.zeros((3, 0)), np.zeros(0, int)).tolist() == [-1, -1, -1]


def test_extremes_and_required_nodes():
    v = np.array([[1.0, 1.02, 0.97, 1.01], [1.0, 1.01, 0.99, 0.98]])
    ex = extreme_nodes(v, eligible=np.array([True, True, True, True]))
    assert ex.tolist() == [1, 2, 3]
    ex2 = extreme_nodes(v, eligible=np.array([True, False, True, True]))
    assert ex2.tolist() == [0, 2, 3]  # node 1 excluded: flow 0's max becomes node 3 / flow 1's max node 0
    cs = select_critical({"head": np.array([0]), "pv": np.array([3])}, ex)
    assert cs.nodes.tolist() == [0, 1, 2, 3]
    assert cs.kinds[0] == ("head",)
    assert cs.kinds[3] == ("pv", "extreme")


def test_node_phase():
    assert node_phase("150r.3") == 3
    assert node_phase("sourcebus") == 0
