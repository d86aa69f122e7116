"""The random models behind the profiles: weather, load archetypes, customers, appliance noise and PV plants.

``profiles.make_profiles`` draws a year from these; ``docs/profiles-and-metrics.md`` explains each model and
lists its measured statistics. Each function takes its own random generator (streams are seeded by the caller),
so a model can change without shifting the others' draws.
"""

from __future__ import annotations

import calendar
import datetime as dt
import functools

import numpy as np
from scipy.signal import lfilter

__all__ = [
    "ARCHETYPES", "DAY_TYPES", "MAX_SHIFT_STEPS", "NOISE_POOL_LEN", "STEPS_PER_DAY", "UTC_OFFSET_H", "archetypes_pu",
    "draw_customers", "draw_day_types", "draw_temperature_c", "noise_pool", "pv_available_kw",
]

UTC_OFFSET_H = -5
"""Fixed offset of the profiles' local standard time from UTC [h] (UTC-5, no daylight saving)."""

ARCHETYPES = (
    "residential_heat_pump",
    "residential_gas_heat",
    "small_commercial",
    "agricultural_pumping",
    "farm_ventilation",
)
"""Names of the load archetypes, in the order of ``YearProfiles.archetype_pu`` rows."""

DAY_TYPES = ("clear", "partly_cloudy", "overcast")
"""Names of the weather day types, the values of ``YearProfiles.day_type``."""

STEPS_PER_DAY = 1440
MAX_SHIFT_STEPS = 60  # per-load time shift is within +-60 min
NOISE_POOL_LEN = 1 << 21  # AR(1) noise pool [samples], 8 MiB of float32
_NOISE_TAU_STEPS = 10.0  # appliance-scale correlation time [min]
_TAG_POOL = 0x9001  # seed of the noise pool's stream (fixed forever for reproducibility)
# PV plant model.
_DC_AC_RATIO = 1.2  # array DC rating / inverter AC rating (Pmpp)
_INVERTER_EFFICIENCY = 0.97
_SYSTEM_LOSS = 0.10  # soiling, wiring, mismatch, availability (PVWatts uses 14 %)
_GAMMA_PER_K = -0.0037  # module power temperature coefficient [1/K]
_ROSS_K_M2_PER_W = 0.03  # cell temperature rise per irradiance [K m2/W]
_ALBEDO = 0.2


def draw_day_types(rng: np.random.Generator, n_days: int, latitude_deg: float) -> np.ndarray:
    """Markov chain of weather day types (clear, partly cloudy, overcast), seasonal transitions."""
    winter = np.array([[0.50, 0.25, 0.25], [0.30, 0.35, 0.35], [0.20, 0.25, 0.55]])
    summer = np.array([[0.45, 0.45, 0.10], [0.25, 0.60, 0.15], [0.25, 0.45, 0.30]])
    s = _summerness(np.arange(n_days), latitude_deg)
    out = np.empty(n_days, dtype=np.int8)
    state = 1
    u = rng.random(n_days)
    for d in range(n_days):
        p = (1 - s[d]) * winter[state] + s[d] * summer[state]
        state = min(int(np.searchsorted(np.cumsum(p), u[d] * p.sum())), 2)
        out[d] = state
    return out


def _summerness(day: np.ndarray, latitude_deg: float) -> np.ndarray:
    """0 in mid-winter, 1 in mid-summer (the hottest time lags the solstice by about a month)."""
    s = 0.5 * (1.0 - np.cos(2.0 * np.pi * (day - 18.0) / 365.25))
    return s if latitude_deg >= 0 else 1.0 - s


def draw_temperature_c(rng: np.random.Generator, day_type: np.ndarray, latitude_deg: float) -> np.ndarray:
    """Outdoor air temperature of every minute [degC].

    A humid subtropical climatology (annual mean 15.5 degC, seasonal amplitude 10.5 degC, as central
    North Carolina) plus an AR(1) day-to-day anomaly; the daily swing is smaller on cloudy days. The
    climatology does not change with the site: only its hemisphere.
    """
    n_days = day_type.size
    day = np.arange(n_days)
    anomaly = lfilter([np.sqrt(1 - 0.75**2) * 3.5], [1.0, -0.75], rng.standard_normal(n_days))
    mean = 15.5 - 10.5 * (1.0 - 2.0 * _summerness(day, latitude_deg)) + anomaly
    swing = np.array([7.0, 5.0, 2.5])[day_type]
    t = np.arange(n_days * STEPS_PER_DAY) / STEPS_PER_DAY  # [days]
    centres = day + 0.5
    hour = (t % 1.0) * 24.0
    temp = np.interp(t, centres, mean) + np.interp(t, centres, swing) * np.cos(2 * np.pi * (hour - 15.0) / 24.0)
    return temp


def _bump(hour: np.ndarray, centre_h: float | np.ndarray, width_h: float) -> np.ndarray:
    d = (hour - centre_h + 12.0) % 24.0 - 12.0
    return np.exp(-0.5 * (d / width_h) ** 2)


def _ramp(hour: np.ndarray, at_h: float) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-(hour - at_h) / 0.4))


def archetypes_pu(temp_c: np.ndarray, day_type: np.ndarray, year: int, latitude_deg: float) -> np.ndarray:
    """The archetype shapes: daily shape x season (heating, cooling) x weekday/weekend, peak 1 each."""
    n = temp_c.size
    minute = np.arange(n)
    day = minute // STEPS_PER_DAY
    hour = (minute % STEPS_PER_DAY) / 60.0
    weekday = (dt.date(year, 1, 1).weekday() + day) % 7  # Monday 0 .. Sunday 6
    weekend = (weekday >= 5).astype(float)
    hdd = np.maximum(0.0, 16.0 - temp_c)  # heating degrees [K]
    cdd = np.maximum(0.0, temp_c - 22.0)  # cooling degrees [K]
    cold = np.maximum(0.0, -3.0 - temp_c)  # heat pump auxiliary strip heat [K]

    res_base = (
        0.28
        + 0.18 * _bump(hour, 7.0 + 1.5 * weekend, 1.3)
        + 0.10 * weekend * _bump(hour, 13.0, 3.0)
        + 0.35 * _bump(hour, 19.0, 2.5)
        - 0.08 * _bump(hour, 3.5, 2.0)
    )
    cooling_shape = 0.5 + 0.5 * _bump(hour, 17.0, 4.0)
    heat_pump = res_base + 0.04 * hdd * (1.0 + 0.6 * _bump(hour, 7.0, 2.0)) + 0.05 * cold + 0.04 * cdd * cooling_shape
    gas_heat = res_base + 0.008 * hdd + 0.06 * cdd * cooling_shape

    occ = np.where(weekday < 5, _ramp(hour, 7.5) - _ramp(hour, 18.5), 0.0)
    occ = occ + np.where(weekday == 5, 0.4 * (_ramp(hour, 9.0) - _ramp(hour, 14.0)), 0.0)
    commercial = 0.22 + 0.55 * occ + 0.015 * hdd * (0.3 + 0.7 * occ) + 0.045 * cdd * (0.3 + 0.7 * occ)

    summer = _summerness(day.astype(float), latitude_deg)
    irrigation = np.exp(-0.5 * ((day - (190 if latitude_deg >= 0 else 10)) / 40.0) ** 2)
    dry = np.array([1.0, 0.7, 0.2])[day_type][day]
    schedule = np.minimum(1.0, _bump(hour, 10.0, 3.0) + 0.7 * _bump(hour, 21.0, 2.5))
    pumping = 0.06 + 0.02 * summer + 0.9 * irrigation * dry * schedule

    ventilation = 0.35 + 0.08 * _bump(hour, 12.0, 5.0) + 0.035 * np.maximum(0.0, temp_c - 18.0) + 0.02 * hdd

    shapes = np.stack([heat_pump, gas_heat, commercial, pumping, ventilation])
    shapes /= shapes.max(axis=1, keepdims=True)
    return shapes.astype(np.float32)


def draw_customers(
    rng: np.random.Generator, nominal_kw: np.ndarray, distance_ohm: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Archetype, time shift [steps] and variation size [pu] of each load."""
    n = nominal_kw.size
    if distance_ohm is None or n == 0 or np.ptp(distance_ohm) == 0:
        q = np.full(n, 0.5)
    else:
        q = np.argsort(np.argsort(distance_ohm)) / max(n - 1, 1)  # distance quantile 0 (head) .. 1 (end)
    # Weights of (heat pump, gas heat, commercial, agricultural, farm) by distance quantile.
    w = np.stack(
        [
            np.full(n, 0.38),
            np.full(n, 0.22),
            0.30 * (1.0 - q) + 0.02,
            0.04 + 0.20 * q,
            0.03 + 0.12 * q,
        ],
        axis=1,
    )
    w /= w.sum(axis=1, keepdims=True)
    u = rng.random(n)
    archetype = np.minimum((w.cumsum(axis=1) < u[:, None]).sum(axis=1), len(ARCHETYPES) - 1)
    shift = np.clip(np.rint(rng.normal(0.0, 20.0, n)), -MAX_SHIFT_STEPS, MAX_SHIFT_STEPS).astype(np.int64)
    base_sigma = np.array([0.15, 0.15, 0.06, 0.12, 0.06])[archetype]
    sigma = (base_sigma * rng.uniform(0.7, 1.3, n)).astype(np.float32)
    return archetype.astype(np.int64), shift, sigma


@functools.lru_cache(maxsize=2)
def noise_pool(seed: int) -> np.ndarray:
    """A fixed pool of unit-variance AR(1) noise with a 10-minute correlation time, from ``seed``."""
    rng = np.random.default_rng([seed, _TAG_POOL])
    rho = np.exp(-1.0 / _NOISE_TAU_STEPS)
    e = rng.standard_normal(NOISE_POOL_LEN)
    c = np.sqrt(1.0 - rho**2)
    z = lfilter([c], [1.0, -rho], e, zi=[e[0] * (1.0 - c)])[0]  # z[0] = e[0]: stationary start
    pool = z.astype(np.float32)
    pool.flags.writeable = False
    return pool


@functools.lru_cache(maxsize=2)
def _clear_sky(latitude_deg: float, longitude_deg: float, year: int) -> dict[str, np.ndarray]:
    """Sun position and Ineichen clear-sky irradiance of every minute of ``year`` (pvlib)."""
    import pandas as pd
    import pvlib

    n_days = 366 if calendar.isleap(year) else 365
    tz = f"Etc/GMT{-UTC_OFFSET_H:+d}"  # POSIX sign: Etc/GMT+5 is UTC-5
    times = pd.date_range(f"{year}-01-01 00:00", periods=n_days * STEPS_PER_DAY, freq="1min", tz=tz)
    altitude = pvlib.location.lookup_altitude(latitude_deg, longitude_deg)
    site = pvlib.location.Location(latitude_deg, longitude_deg, tz=tz, altitude=altitude)
    sun = site.get_solarposition(times)
    sky = site.get_clearsky(times, model="ineichen", solar_position=sun)
    out = {
        "zenith": sun["apparent_zenith"].to_numpy(),
        "azimuth": sun["azimuth"].to_numpy(),
        "dni": sky["dni"].to_numpy(),
        "ghi": sky["ghi"].to_numpy(),
        "dhi": sky["dhi"].to_numpy(),
    }
    for a in out.values():
        a.flags.writeable = False
    return out


def _cloud_cover(rng: np.random.Generator, n: int, fraction: float, cloud_dwell_min: float) -> np.ndarray:
    """A 0/1 cloud-shadow sequence of ``n`` minutes: alternating exponential dwell times."""
    if fraction <= 0.0:
        return np.zeros(n)
    if fraction >= 1.0:
        return np.ones(n)
    clear_dwell = cloud_dwell_min * (1.0 - fraction) / fraction
    state = float(rng.random() < fraction)
    parts: list[np.ndarray] = []
    total = 0
    while total < n:
        m = int(2 * n / (cloud_dwell_min + clear_dwell)) + 8
        states = (np.arange(m) + state) % 2
        means = np.where(states == 1, cloud_dwell_min, clear_dwell)
        lengths = np.maximum(1, np.rint(rng.exponential(means))).astype(np.int64)
        parts.append(np.repeat(states, lengths))
        total += int(lengths.sum())
        state = float(1 - states[-1])
    return np.concatenate(parts)[:n].astype(float)


def _clear_sky_index(rng: np.random.Generator, day_type: np.ndarray, n_pv: int, lags: np.ndarray) -> np.ndarray:
    """Clear-sky index of every minute and plant: shared lagged cloud field + each plant's own clouds."""
    n_days = day_type.size
    spd = STEPS_PER_DAY
    max_lag = int(lags.max(initial=0))
    shared_weight = rng.uniform(0.25, 0.5, n_pv)
    k = np.empty((n_days * spd, n_pv))
    smooth = np.ones(3) / 3.0  # a plant's area averages a cloud edge over a few minutes
    for d in range(n_days):
        match int(day_type[d]):
            case 0:  # clear: a few small clouds
                frac, dwell, k_sun, k_shade = rng.uniform(0.0, 0.06), 2.0, rng.uniform(0.97, 1.02), 0.6
            case 1:  # partly cloudy: cumulus transients at minute scale
                frac, dwell = rng.uniform(0.2, 0.65), rng.uniform(3.0, 12.0)
                k_sun, k_shade = rng.uniform(0.95, 1.03), rng.uniform(0.25, 0.55)
            case _:  # overcast: thick deck with rare breaks
                frac, dwell = rng.uniform(0.85, 0.98), rng.uniform(30.0, 90.0)
                k_sun, k_shade = rng.uniform(0.7, 1.0), rng.uniform(0.12, 0.4)
        shared = _cloud_cover(rng, spd + max_lag, frac, dwell)
        for p in range(n_pv):
            # Each plant's own clouds: the day's weather, locally a little thicker or thinner.
            own = _cloud_cover(rng, spd, float(np.clip(frac + rng.uniform(-0.15, 0.15), 0.0, 1.0)), dwell)
            lagged = shared[max_lag - int(lags[p]) : max_lag - int(lags[p]) + spd]
            cover = shared_weight[p] * lagged + (1.0 - shared_weight[p]) * own
            cover = np.convolve(np.pad(cover, 1, mode="edge"), smooth, mode="valid")
            shade = float(np.clip(k_shade + rng.uniform(-0.1, 0.1), 0.05, 0.9))
            k[d * spd : (d + 1) * spd, p] = k_sun + (shade - k_sun) * cover
    return k


def pv_available_kw(
    rng: np.random.Generator,
    pmpp_kw: np.ndarray,
    lags: np.ndarray | None,
    temp_c: np.ndarray,
    day_type: np.ndarray,
    latitude_deg: float,
    longitude_deg: float,
    year: int,
) -> np.ndarray:
    """Available AC power of each plant [kW], shape (n_steps, n_pv).

    Plane-of-array clear-sky irradiance (pvlib, Ineichen, isotropic sky, fixed tilt facing the equator
    with a small per-plant tilt/azimuth spread) x the clear-sky index, a temperature-derated DC array of
    ``_DC_AC_RATIO`` x Pmpp, system losses, inverter efficiency, clipped at Pmpp.
    """
    import pvlib

    n_pv = pmpp_kw.size
    if lags is None:
        lags = rng.integers(0, 31, n_pv).astype(float)
    sky = _clear_sky(latitude_deg, longitude_deg, year)
    k = _clear_sky_index(rng, day_type, n_pv, lags)
    out = np.empty((temp_c.size, n_pv), dtype=np.float32)
    facing = 180.0 if latitude_deg >= 0 else 0.0
    for p in range(n_pv):
        tilt = float(np.clip(abs(latitude_deg) * 0.7 + rng.uniform(-5.0, 5.0), 0.0, 60.0))
        azimuth = facing + rng.uniform(-15.0, 15.0)
        poa = pvlib.irradiance.get_total_irradiance(
            tilt, azimuth, sky["zenith"], sky["azimuth"], sky["dni"], sky["ghi"], sky["dhi"], albedo=_ALBEDO
        )["poa_global"]
        poa = np.nan_to_num(np.asarray(poa, dtype=float), nan=0.0).clip(min=0.0) * k[:, p]
        cell_c = temp_c + _ROSS_K_M2_PER_W * poa
        dc = pmpp_kw[p] * _DC_AC_RATIO * poa / 1000.0 * (1.0 + _GAMMA_PER_K * (cell_c - 25.0))
        out[:, p] = np.clip(dc * (1.0 - _SYSTEM_LOSS) * _INVERTER_EFFICIENCY, 0.0, pmpp_kw[p])
    return out
