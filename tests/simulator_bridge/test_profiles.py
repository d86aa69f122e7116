"""Statistics and contracts of the synthetic year of load and PV (simulator_bridge/simulation/profiles.py)."""

import datetime as dt

import numpy as np
import pytest

from schemas.errors import CvvcError
from simulator_bridge.simulation.profiles import (
    ARCHETYPES,
    ProfileError,
    YearProfiles,
    make_profiles,
    month_steps,
    season_month,
)

N_LOADS = 240
PMPP_KW = np.array([1800.0, 1200.0, 900.0])


def _feeder(seed=7):
    rng = np.random.default_rng(seed)
    return rng.uniform(3.0, 80.0, N_LOADS), rng.uniform(0.0, 25.0, N_LOADS)


@pytest.fixture(scope="module")
def feeder():
    return _feeder()


@pytest.fixture(scope="module")
def year1(feeder):
    nominal, distance = feeder
    return make_profiles(seed=1, load_kw_nominal=nominal, pv_pmpp_kw=PMPP_KW, load_distance_ohm=distance)


@pytest.fixture(scope="module")
def year2(feeder):
    nominal, distance = feeder
    return make_profiles(seed=2, load_kw_nominal=nominal, pv_pmpp_kw=PMPP_KW, load_distance_ohm=distance)


@pytest.fixture(scope="module")
def year1_loads(year1):
    """The whole year of loads of seed 1, assembled from weekly chunks (float32, ~500 MB would be dense
    for 600 loads; 240 loads here)."""
    out = np.empty((year1.n_steps, year1.n_loads), dtype=np.float32)
    for a in range(0, year1.n_steps, 7 * 1440):
        b = min(a + 7 * 1440, year1.n_steps)
        out[a:b] = year1.load_kw(a, b)
    return out


def test_calendar_and_time(year1):
    assert year1.n_steps == 525_600 and year1.step_s == 60
    assert (year1.n_loads, year1.n_pv) == (N_LOADS, 3)
    # Step 0 is midnight 1 Jan 2023 in UTC-5 = 05:00 UTC.
    t0 = int(dt.datetime(2023, 1, 1, 5, tzinfo=dt.UTC).timestamp()) * 10**9
    assert year1.t_ns(0) == t0 == year1.start_t_ns
    assert year1.t_ns(1) - year1.t_ns(0) == 60 * 10**9
    assert year1.t_ns(year1.n_steps) == int(dt.datetime(2024, 1, 1, 5, tzinfo=dt.UTC).timestamp()) * 10**9
    assert month_steps(year1, 1) == range(0, 31 * 1440)
    assert month_steps(year1, 2) == range(31 * 1440, 59 * 1440)
    assert month_steps(year1, 12).stop == year1.n_steps
    assert sum(len(month_steps(year1, m)) for m in range(1, 13)) == year1.n_steps
    assert [season_month(s) for s in ("winter", "spring", "summer", "fall")] == [1, 4, 7, 10]
    with pytest.raises(ProfileError, match="unknown season"):
        season_month("monsoon")
    with pytest.raises(ProfileError, match="1..12"):
        month_steps(year1, 13)
    with pytest.raises(ProfileError, match="outside"):
        year1.t_ns(year1.n_steps + 1)


def test_leap_year_has_366_days(feeder):
    p = make_profiles(seed=1, load_kw_nominal=feeder[0][:5], pv_pmpp_kw=PMPP_KW[:1], year=2024)
    assert p.n_steps == 366 * 1440
    assert len(month_steps(p, 2)) == 29 * 1440


def test_feeder_coincident_peak_is_the_sum_of_nominal_kw(year1, year1_loads, feeder):
    # Load allocation: the feeder's yearly peak is the model's peak load, shared in proportion to kW.
    nominal = feeder[0]
    total = year1_loads.sum(axis=1, dtype=np.float64)
    assert total.max() == pytest.approx(nominal.sum(), rel=1e-4)
    ratio = year1_loads.max(axis=0) / nominal
    assert np.all(ratio > 1.0)  # every customer peaks above its allocated share: diversity
    assert 1.3 < np.median(ratio) < 2.5


def test_load_factors(year1_loads):
    # Individual customers at 1-minute resolution have low load factors; the feeder's is higher
    # because customers peak at different times (measured: individual median ~0.25, feeder ~0.45).
    energy = year1_loads.sum(axis=0, dtype=np.float64)
    lf = energy / len(year1_loads) / year1_loads.max(axis=0)
    assert 0.05 < lf.min() and lf.max() < 0.6
    assert 0.15 < np.median(lf) < 0.4
    total = year1_loads.sum(axis=1, dtype=np.float64)
    assert 0.35 < total.mean() / total.max() < 0.6
    # Diversity: the feeder peak is well below the sum of the customers' peaks.
    assert total.max() < 0.8 * year1_loads.max(axis=0).sum()


def test_winter_and_summer_peaks(year1, year1_loads):
    total = year1_loads.sum(axis=1, dtype=np.float64)
    peak = {
        s: total[month_steps(year1, season_month(s)).start : month_steps(year1, season_month(s)).stop].max()
        for s in ("winter", "spring", "summer", "fall")
    }
    assert peak["winter"] > 1.15 * max(peak["spring"], peak["fall"])
    assert peak["summer"] > 1.15 * max(peak["spring"], peak["fall"])


def test_weekday_weekend(year1):
    # Small commercial: weekday noon (Wed 4 Jan 2023) far above Sunday noon (1 Jan 2023).
    com = year1.archetype_pu[ARCHETYPES.index("small_commercial")]
    assert com[3 * 1440 + 12 * 60] > 1.5 * com[12 * 60]


def test_load_center_moves_through_the_year(year1, year1_loads, feeder):
    # Paper eq. (1): D_L = sum(D_i L_i) / sum(L_i). Real diversity makes it move.
    distance = feeder[1]
    d_l = (year1_loads @ distance.astype(np.float32)) / year1_loads.sum(axis=1)
    p1, p50, p99 = np.percentile(d_l, [1, 50, 99])
    assert (p99 - p1) / p50 > 0.08
    monthly = [d_l[month_steps(year1, m).start : month_steps(year1, m).stop].mean() for m in (1, 7)]
    assert abs(monthly[1] - monthly[0]) / p50 > 0.02


def test_pv_bounds_and_night(year1):
    pv = year1.pv_kw(0, year1.n_steps)
    assert pv.min() >= 0.0
    assert np.all(pv.max(axis=0) <= PMPP_KW + 1e-3)
    assert np.all(pv.max(axis=0) > 0.9 * PMPP_KW)  # the plants reach their rating on good days
    midnight = np.arange(0, year1.n_steps, 1440)
    assert np.all(pv[midnight] == 0.0)


def test_pv_capacity_factor_by_season(year1, year2):
    # Fixed-tilt plants in central North Carolina with DC/AC 1.2 (measured: winter 0.14-0.19,
    # summer 0.20-0.23, annual 0.18-0.21 for seeds 1-3).
    for p in (year1, year2):
        pv = p.pv_kw(0, p.n_steps).astype(np.float64)
        for season in ("winter", "spring", "summer", "fall"):
            r = month_steps(p, season_month(season))
            cf = pv[r.start : r.stop].mean(axis=0) / PMPP_KW
            assert np.all((cf > 0.10) & (cf < 0.28)), (season, cf)
        annual = pv.mean(axis=0) / PMPP_KW
        assert np.all((annual > 0.15) & (annual < 0.23)), annual
        jul, jan = (pv[month_steps(p, m).start : month_steps(p, m).stop].mean() for m in (7, 1))
        assert jul > jan


def test_pv_plants_correlated_not_identical(year1, year2):
    for p in (year1, year2):
        pv = p.pv_kw(0, p.n_steps).astype(np.float64)
        day = pv.sum(axis=1) > 0
        corr = np.corrcoef(pv[day].T)[np.triu_indices(p.n_pv, 1)]
        assert np.all((corr > 0.5) & (corr < 0.95)), corr
        # Minute-scale cloud transients: ramps of several % of Pmpp happen at every plant.
        ramp = np.abs(np.diff(pv, axis=0)) / PMPP_KW
        assert np.all((ramp > 0.1).sum(axis=0) > 1000)


def test_same_seed_same_year_any_window_order(year1, feeder):
    nominal, distance = feeder
    again = make_profiles(seed=1, load_kw_nominal=nominal, pv_pmpp_kw=PMPP_KW, load_distance_ohm=distance)
    a = 200_000
    np.testing.assert_array_equal(again.load_kw(a, a + 3000), year1.load_kw(a, a + 3000))
    np.testing.assert_array_equal(again.pv_kw(0, again.n_steps), year1.pv_kw(0, year1.n_steps))
    # Step by step, after visiting other days, gives the same numbers as one window.
    year1.load_kw(5, 10)
    steps = np.concatenate([year1.load_kw(s, s + 1) for s in range(a + 1430, a + 1450)])
    np.testing.assert_array_equal(steps, again.load_kw(a + 1430, a + 1450))
    assert year1.load_kw(10, 10).shape == (0, N_LOADS)


def test_second_seed_is_another_year_of_the_same_customers(year1, year2, feeder):
    np.testing.assert_array_equal(year1.load_archetype, year2.load_archetype)
    a = 300_000
    l1, l2 = year1.load_kw(a, a + 1440), year2.load_kw(a, a + 1440)
    assert np.mean(np.abs(l1 - l2)) > 0.05 * np.mean(l1)
    assert not np.array_equal(year1.day_type, year2.day_type)
    assert np.mean(np.abs(year1.pv_kw(0, year1.n_steps) - year2.pv_kw(0, year2.n_steps))) > 10.0
    other = make_profiles(
        seed=1, load_kw_nominal=feeder[0], pv_pmpp_kw=PMPP_KW, load_distance_ohm=feeder[1], customer_seed=5
    )
    assert not np.array_equal(other.load_archetype, year1.load_archetype)


def test_low_rank_memory(year1):
    # Stored: archetypes (5 x year), dense PV (3 plants) and per-load parameters; not year x loads.
    roots = {}
    for v in vars(year1).values():
        while isinstance(v, np.ndarray) and isinstance(v.base, np.ndarray):
            v = v.base
        if isinstance(v, np.ndarray) and v.flags.owndata:  # strided window views own nothing
            roots[id(v)] = v.nbytes
    stored = sum(roots.values())  # every array the object holds, views counted once (measured ~35 MB)
    dense_loads = year1.n_steps * year1.n_loads * 4
    assert stored < 60e6
    assert stored < 0.2 * dense_loads
    assert year1.archetype_pu.shape == (len(ARCHETYPES), year1.n_steps)


def test_save_load_roundtrip(year1, tmp_path):
    path = tmp_path / "year.npz"
    year1.save(path)
    back = YearProfiles.load(path)
    assert (back.seed, back.start_t_ns, back.n_steps, back.n_loads) == (1, year1.start_t_ns, 525_600, N_LOADS)
    np.testing.assert_array_equal(back.load_kw(100_000, 101_500), year1.load_kw(100_000, 101_500))
    np.testing.assert_array_equal(back.pv_kw(0, back.n_steps), year1.pv_kw(0, year1.n_steps))


def _small(**overrides):
    n = 2000
    args = dict(
        seed=0,
        start_t_ns=0,
        archetype_pu=np.ones((1, n)),
        load_archetype=np.zeros(2, dtype=int),
        load_shift_steps=np.zeros(2, dtype=int),
        load_scale_kw=np.ones(2),
        load_noise_sigma=np.zeros(2),
        pv_kw=np.zeros((n, 1)),
        pv_pmpp_kw=np.ones(1),
        day_type=np.zeros(2, dtype=int),
        archetype_names=("flat",),
    )
    args.update(overrides)
    return YearProfiles(**args)


def test_small_profile_without_noise_is_its_archetype():
    p = _small(load_scale_kw=np.array([2.0, 3.0]))
    np.testing.assert_allclose(p.load_kw(1430, 1450), np.tile([2.0, 3.0], (20, 1)))
    assert p.n_steps == 2000


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"pv_kw": np.where(np.arange(2000)[:, None] == 77, np.nan, 0.0)}, r"pv_kw of plant 0 has 1 NaN.*index 77"),
        ({"archetype_pu": np.ones((1, 2000)) * np.r_[np.ones(1999), np.inf]}, r"archetype 'flat' has 1 NaN"),
        ({"pv_kw": np.zeros((1990, 1))}, r"pv_kw has shape \(1990, 1\); expected \(2000, n_pv\)"),
        ({"load_scale_kw": np.ones(3)}, r"load_scale_kw has shape \(3,\); expected \(2,\)"),
        ({"load_archetype": np.array([0, 1])}, r"load_archetype has values outside"),
        ({"pv_kw": np.full((2000, 1), 1.5)}, r"peaks at 1.500 kW above its Pmpp"),
        ({"load_scale_kw": np.array([1.0, -1.0])}, r"load_scale_kw has negative"),
        ({"day_type": np.zeros(5, dtype=int)}, r"day_type has shape"),
    ],
)
def test_bad_profiles_are_rejected_by_name(overrides, message):
    with pytest.raises(ProfileError, match=message):
        _small(**overrides)


def test_profile_error_is_a_cvvc_error():
    assert issubclass(ProfileError, CvvcError)


def test_bad_files_name_the_file(tmp_path):
    p = _small()
    path = tmp_path / "ok.npz"
    p.save(path)
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    data["pv_kw"] = data["pv_kw"][:-10]  # a gap at the end
    bad = tmp_path / "gap.npz"
    np.savez(bad, **data)
    with pytest.raises(ProfileError, match=r"gap\.npz: pv_kw has shape"):
        YearProfiles.load(bad)
    del data["pv_kw"]
    np.savez(tmp_path / "missing.npz", **data)
    with pytest.raises(ProfileError, match=r"missing\.npz: profiles file lacks array 'pv_kw'"):
        YearProfiles.load(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_text("not a zip")
    with pytest.raises(ProfileError, match=r"junk\.npz: cannot read"):
        YearProfiles.load(tmp_path / "junk.npz")
    with pytest.raises(ProfileError, match="outside"):
        p.load_kw(1990, 2001)


def test_bad_generation_inputs():
    with pytest.raises(ProfileError, match="load_kw_nominal has 1 NaN"):
        make_profiles(seed=0, load_kw_nominal=np.array([1.0, np.nan]), pv_pmpp_kw=PMPP_KW)
    with pytest.raises(ProfileError, match="pv_pmpp_kw has negative"):
        make_profiles(seed=0, load_kw_nominal=np.ones(2), pv_pmpp_kw=-PMPP_KW)
    with pytest.raises(ProfileError, match="load_distance_ohm has 3 entries for 2 loads"):
        make_profiles(seed=0, load_kw_nominal=np.ones(2), pv_pmpp_kw=PMPP_KW, load_distance_ohm=np.ones(3))
    with pytest.raises(ProfileError, match="latitude"):
        make_profiles(seed=0, load_kw_nominal=np.ones(2), pv_pmpp_kw=PMPP_KW, latitude_deg=95.0)
