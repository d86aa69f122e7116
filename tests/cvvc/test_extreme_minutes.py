"""The extreme minutes of a run from hand-made truth steps: the node, the decision in force, what moved, episodes."""

import numpy as np

from cvvc.extreme_minutes import EPISODE_GAP_NS, LOOKBACK_STEPS, ExtremeMinutes

MINUTE_NS = 60_000_000_000


def _steps(n: int) -> ExtremeMinutes:
    """``n`` minutes of three nodes; at minute 10 bank b1 opens and node "c" falls to 0.95; at minute 12 regulator r0
    steps up two; at minute 100 node "a" rises to 1.06; at minute 103 node "c" dips to 0.96."""
    acc = ExtremeMinutes(regulator_ids=("r0", "r1"), capacitor_ids=("b0", "b1"))
    for k in range(n):
        v = np.array([1.0, 1.0, 1.0])
        taps = np.array([2 if k >= 12 else 0, 0])
        caps = np.array([1, 0 if k >= 10 else 1])
        if k == 10:
            v[2] = 0.95
        if k == 100:
            v[0] = 1.06
        if k == 103:
            v[2] = 0.96
        acc.add(k * MINUTE_NS, v, taps, caps, "soft form" if k >= 5 else "optimal", ("a", "b", "c") if k == 0 else None)
    return acc


def test_each_extreme_names_its_node_decision_and_the_moves_up_to_it():
    rows = _steps(200).result()
    low = [r for r in rows if r.side == "lowest"]
    high = [r for r in rows if r.side == "highest"]
    assert (low[0].t_ns, low[0].v_pu, low[0].node, low[0].decision) == (10 * MINUTE_NS, 0.95, "c", "soft form")
    assert low[0].moves == ((0, "b1 opened"),)
    assert (high[0].t_ns, high[0].v_pu, high[0].node) == (100 * MINUTE_NS, 1.06, "a")
    assert high[0].moves == ()  # the regulator's step was 88 minutes before: outside the look-back


def test_extremes_of_one_side_are_an_hour_apart_and_the_lookback_is_bounded():
    rows = _steps(200).result()
    low = [r for r in rows if r.side == "lowest"]
    # 0.96 at minute 103 is 93 minutes after the lowest: a second episode; the 1.0 minutes within the hour are not
    assert [r.v_pu for r in low[:2]] == [0.95, 0.96]
    assert all(abs(a.t_ns - b.t_ns) >= EPISODE_GAP_NS for a in low for b in low if a is not b)
    # a step 4 minutes before an extreme is listed, one 5 minutes before is not (LOOKBACK_STEPS = 5)
    for ago, listed in ((LOOKBACK_STEPS - 1, ((LOOKBACK_STEPS - 1, "r0 +1"),)), (LOOKBACK_STEPS, ())):
        acc = ExtremeMinutes(regulator_ids=("r0",))
        for k in range(12 + ago + 1):
            v = np.array([0.99 if k == 12 + ago else 1.0])
            acc.add(k * MINUTE_NS, v, np.array([1 if k >= 12 else 0]), np.zeros(0), "optimal")
        lowest = acc.result(rows_per_side=1)[0]
        assert (lowest.t_ns, lowest.moves) == ((12 + ago) * MINUTE_NS, listed)
    acc3 = ExtremeMinutes()  # no ids: devices named by position
    acc3.add(0, np.array([1.0]), np.array([0]), np.array([0]), "optimal")
    acc3.add(MINUTE_NS, np.array([0.9]), np.array([-1]), np.array([2]), "optimal")
    assert acc3.result()[0].moves == ((0, "regulator 0 -1, bank 0 closed 2 steps"),)
