import numpy as np
import pytest

from training.errors import TrainingError
from training.scenarios import YearSummary, center_ohm, select_scenarios


def _year():
    # minutes 0-5: low load block; 6-8: high load block; PV axis has one bin
    load = np.array([10, 11, 12, 13, 14, 15, 100, 101, 102], float)
    pv = np.array([0, 0, 0, 0, 0, 0, 5, 6, 7], float)
    d_load = np.array([3, 1, 4, 1.5, 9, 2.6, 5, 7, 6], float)
    d_pv = np.array([0, 0, 0, 0, 0, 0, 0.2, 0.1, 0.3], float)
    return YearSummary(load_kw=load, pv_kw=pv, d_load_ohm=d_load, d_pv_ohm=d_pv)


def test_center_is_power_weighted_distance_and_zero_without_power():
    p = np.array([[1.0, 3.0], [0.0, 0.0]])
    d = np.array([2.0, 10.0])
    np.testing.assert_allclose(center_ohm(p, d), [(2 + 30) / 4, 0.0])


def test_guided_selection_picks_the_expected_minutes():
    s = select_scenarios(_year(), blocks=(2, 1), selection="guided")
    # block 0: D_L max=min4, median=min5 (2.6), min=min1; D_PV ties (all 0) -> next free minutes in order
    # block 1: 3 minutes, D_L max/median/min = 7/8/6; the D_PV picks repeat them and are dropped
    assert s.steps.tolist() == [4, 5, 1, 3, 2, 0, 7, 8, 6]
    assert s.kind[:3] == ("dl_max", "dl_median", "dl_min")
    assert s.kind[3:6] == ("dpv_max", "dpv_median", "dpv_min")
    assert s.block.tolist() == [0] * 6 + [1] * 3
    assert s.non_empty_blocks == 2


def test_dpv_picks_when_pv_varies():
    y = _year()
    # make block 1 have 7 minutes so every pick is distinct
    load = np.concatenate([y.load_kw[:6], np.full(7, 100.0)])
    d_load = np.concatenate([y.d_load_ohm[:6], [1, 2, 3, 4, 5, 6, 7]])
    d_pv = np.concatenate([np.zeros(6), [0.5, 0.9, 0.1, 0.7, 0.3, 0.2, 0.6]])
    s = select_scenarios(
        YearSummary(load_kw=load, pv_kw=np.ones(13), d_load_ohm=d_load, d_pv_ohm=d_pv),
        blocks=(2, 1),
        selection="guided",
    )
    blk1 = s.steps[s.block == 1].tolist()
    # D_L: max minute 12, median minute 9, min minute 6; D_PV: max 7, median (0.5 = minute 6 is taken;
    # the next position nearest the middle, lower first, is 0.3 = minute 10), min 8
    assert blk1 == [12, 9, 6, 7, 10, 8]


def test_empty_blocks_are_skipped():
    s = select_scenarios(_year(), blocks=(3, 1), selection="guided")
    assert s.non_empty_blocks == 2
    assert s.minutes_per_block.ravel().tolist() == [6, 0, 3]


def test_random_selection_is_seeded_and_stays_in_blocks():
    a = select_scenarios(_year(), blocks=(2, 1), selection="random", seed=3, per_block=2)
    b = select_scenarios(_year(), blocks=(2, 1), selection="random", seed=3, per_block=2)
    assert a.steps.tolist() == b.steps.tolist()
    assert len(a.steps) == 4
    assert set(a.steps[:2]) <= set(range(6)) and set(a.steps[2:]) <= {6, 7, 8}
    assert len(set(a.steps.tolist())) == 4


def test_bad_blocks_raise():
    with pytest.raises(TrainingError, match="blocks"):
        select_scenarios(_year(), blocks=(0, 3), selection="guided")


def test_calendar_cover_fills_every_month_and_hour_and_skips_the_scenarios():
    from calendar import monthrange

    from training.scenarios import calendar_cover

    n = 365 * 1440
    picked = np.arange(0, n, 7)  # every 7th minute is a scenario already
    steps = calendar_cover(n, 2023, per_cell=2, seed=3, exclude=picked)
    assert steps.size == 12 * 24 * 2 and np.all(np.diff(steps) > 0)
    assert not np.isin(steps, picked).any()
    month_start = np.cumsum([0] + [monthrange(2023, m)[1] for m in range(1, 13)]) * 1440
    month = np.searchsorted(month_start, steps, side="right")
    hour = steps % 1440 // 60
    cells = np.bincount((month - 1) * 24 + hour, minlength=288)
    assert cells.tolist() == [2] * 288
    np.testing.assert_array_equal(steps, calendar_cover(n, 2023, per_cell=2, seed=3, exclude=picked))
    assert not np.array_equal(steps, calendar_cover(n, 2023, per_cell=2, seed=4, exclude=picked))
    assert calendar_cover(n, 2023, per_cell=0, seed=3, exclude=picked).size == 0
    with pytest.raises(TrainingError, match="per cell"):
        calendar_cover(n, 2023, per_cell=-1, seed=3, exclude=picked)
