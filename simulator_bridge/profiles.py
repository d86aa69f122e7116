"""One year of 1-minute load and PV profiles, low rank, generated from a seed.

The paper (IV.A) drives its rural feeder with one year of 1-minute per-customer load (disaggregated
with its ref. [13]) and measured PV (Pecan Street, its ref. [14]). We have neither, so we synthesise
both; ``docs/profiles-and-metrics.md`` explains the model and lists its measured statistics.

Loads are low rank: a handful of archetype shapes (one full-year 1-minute float32 series each) times a
per-load scale, with a per-load time shift, a per-load daily level and per-load "appliance-scale"
variation. The variation is generated on demand for whole days from a counter-based key
``(seed, day)`` and a fixed pool of AR(1) noise, so any window is reproducible without storing a
dense year x loads matrix. PV plants are few, so their available AC power is stored densely.

Time: step 0 is local *standard* time midnight on 1 January of ``year`` in the fixed zone UTC-5
(``UTC_OFFSET_H``; no daylight saving). ``t_ns`` is UTC epoch nanoseconds.
"""

from __future__ import annotations

import calendar
import datetime as dt
import functools
import os
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Literal

import numpy as np
from scipy.signal import lfilter

from simulator_bridge.errors import SimulatorError

__all__ = [
    "feeder_profiles",
    "ARCHETYPES",
    "DAY_TYPES",
    "UTC_OFFSET_H",
    "ProfileError",
    "YearProfiles",
    "make_profiles",
    "month_steps",
    "season_month",
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

Season = Literal["winter", "spring", "summer", "fall"]

_FORMAT = "cvvc-profiles/1"
_STEP_S = 60
_STEPS_PER_DAY = 1440
_MAX_SHIFT_STEPS = 60  # per-load time shift is within +-60 min
_NOISE_POOL_LEN = 1 << 21  # AR(1) noise pool [samples], 8 MiB of float32
_NOISE_TAU_STEPS = 10.0  # appliance-scale correlation time [min]
_DAILY_LEVEL_PER_SIGMA = 0.5  # day-to-day level variation of a load / its minute-scale variation
_CACHE_DAYS = 2
# Seeds of the independent random streams (arbitrary constants, fixed forever for reproducibility).
_TAG_WEATHER, _TAG_CUSTOMERS, _TAG_DAY, _TAG_POOL, _TAG_PV = 0x57EA, 0xC057, 0xDA1, 0x9001, 0x9F
# PV plant model.
_DC_AC_RATIO = 1.2  # array DC rating / inverter AC rating (Pmpp)
_INVERTER_EFFICIENCY = 0.97
_SYSTEM_LOSS = 0.10  # soiling, wiring, mismatch, availability (PVWatts uses 14 %)
_GAMMA_PER_K = -0.0037  # module power temperature coefficient [1/K]
_ROSS_K_M2_PER_W = 0.03  # cell temperature rise per irradiance [K m2/W]
_ALBEDO = 0.2
_SEASON_MONTH = {"winter": 1, "spring": 4, "summer": 7, "fall": 10}


class ProfileError(SimulatorError):
    """A profile that is malformed (gaps, NaN, wrong lengths) or a request outside it."""


# ---------------------------------------------------------------------------------------------------
# The container
# ---------------------------------------------------------------------------------------------------


class YearProfiles:
    """One year of load and PV profiles at ``step_s`` resolution.

    Build it with :func:`make_profiles` or :meth:`load`; the constructor validates its arrays.
    ``load_kw`` keeps a small cache of the last computed days, so an instance is not thread safe.

    Parameters
    ----------
    seed : int
        Seed of the weather and of the per-day load variation.
    start_t_ns : int
        UTC epoch time of step 0 [ns].
    archetype_pu : ndarray, shape (n_archetypes, n_steps)
        Archetype shapes, each with peak 1 [pu of its own peak].
    load_archetype : ndarray of int, shape (n_loads,)
        Row of ``archetype_pu`` that each load follows.
    load_shift_steps : ndarray of int, shape (n_loads,)
        Per-load time shift [steps]; positive is later. Wraps around the ends of the year.
    load_scale_kw : ndarray, shape (n_loads,)
        Per-load scale [kW]: the load's power before variation is ``scale * archetype``.
    load_noise_sigma : ndarray, shape (n_loads,)
        Relative standard deviation of the appliance-scale variation [pu].
    pv_kw : ndarray, shape (n_steps, n_pv)
        Available AC power of each PV plant [kW].
    pv_pmpp_kw : ndarray, shape (n_pv,)
        Plant ratings [kW]; ``pv_kw`` never exceeds them.
    day_type : ndarray of int, shape (n_days,)
        Weather day type per day, an index into ``DAY_TYPES``.
    step_s : int
        Step length [s]; 60.
    archetype_names : tuple of str
        One name per archetype row.
    """

    def __init__(
        self,
        *,
        seed: int,
        start_t_ns: int,
        archetype_pu: np.ndarray,
        load_archetype: np.ndarray,
        load_shift_steps: np.ndarray,
        load_scale_kw: np.ndarray,
        load_noise_sigma: np.ndarray,
        pv_kw: np.ndarray,
        pv_pmpp_kw: np.ndarray,
        day_type: np.ndarray,
        step_s: int = _STEP_S,
        archetype_names: tuple[str, ...] = ARCHETYPES,
    ) -> None:
        self.seed = int(seed)
        self.start_t_ns = int(start_t_ns)
        self.step_s = int(step_s)
        self.archetype_names = tuple(str(n) for n in archetype_names)
        self.archetype_pu = _frozen(archetype_pu, np.float32)
        self.load_archetype = _frozen(load_archetype, np.int64)
        self.load_shift_steps = _frozen(load_shift_steps, np.int64)
        self.load_scale_kw = _frozen(load_scale_kw, np.float64)
        self.load_noise_sigma = _frozen(load_noise_sigma, np.float32)
        self.pv_kw_year = _frozen(pv_kw, np.float32)
        self.pv_pmpp_kw = _frozen(pv_pmpp_kw, np.float64)
        self.day_type = _frozen(day_type, np.int8)
        self.validate()
        self.n_steps = int(self.archetype_pu.shape[1])
        self.n_loads = int(self.load_archetype.shape[0])
        self.n_pv = int(self.pv_kw_year.shape[1])
        self.steps_per_day = 86_400 // self.step_s
        pad = _MAX_SHIFT_STEPS
        spd = self.steps_per_day
        # Circular padding so that shifted day windows never fall off the ends of the year.
        row_len = self.n_steps + 2 * pad + spd
        self._arch_padded = np.pad(self.archetype_pu, ((0, 0), (pad, pad + spd)), mode="wrap").ravel()
        self._col_base = self.load_archetype * row_len + pad - self.load_shift_steps
        self._pool = _noise_pool(self.seed)
        self._arch_windows = np.lib.stride_tricks.sliding_window_view(self._arch_padded, spd)
        self._pool_windows = np.lib.stride_tricks.sliding_window_view(self._pool, spd)
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()

    # -- validation --------------------------------------------------------------------------------

    def validate(self) -> None:
        """Check shapes, lengths, gaps and ranges; raise :class:`ProfileError` naming what is wrong."""
        arch, pv = self.archetype_pu, self.pv_kw_year
        if self.step_s <= 0 or 86_400 % self.step_s:
            raise ProfileError(f"step_s = {self.step_s}: must be a positive divisor of 86400 s")
        if arch.ndim != 2 or arch.shape[0] < 1 or arch.shape[1] < 1:
            raise ProfileError(f"archetype_pu has shape {arch.shape}; expected (n_archetypes, n_steps)")
        n_arch, n_steps = arch.shape
        if len(self.archetype_names) != n_arch:
            raise ProfileError(f"{len(self.archetype_names)} archetype names for {n_arch} archetype rows")
        for i, name in enumerate(self.archetype_names):
            _check_finite_nonneg(arch[i], f"archetype {name!r}")
        if n_steps <= 2 * _MAX_SHIFT_STEPS:
            raise ProfileError(f"archetype_pu has {n_steps} steps; need more than {2 * _MAX_SHIFT_STEPS}")
        n_loads = self.load_archetype.shape[0] if self.load_archetype.ndim == 1 else -1
        for name in ("load_archetype", "load_shift_steps", "load_scale_kw", "load_noise_sigma"):
            a = getattr(self, name)
            if a.ndim != 1 or a.shape[0] != n_loads:
                raise ProfileError(
                    f"{name} has shape {a.shape}; expected ({n_loads},), one entry per load "
                    "(all per-load arrays must have the same length)"
                )
        if n_loads and (self.load_archetype.min() < 0 or self.load_archetype.max() >= n_arch):
            raise ProfileError(f"load_archetype has values outside 0..{n_arch - 1}")
        if n_loads and np.abs(self.load_shift_steps).max() > _MAX_SHIFT_STEPS:
            raise ProfileError(f"load_shift_steps exceeds +-{_MAX_SHIFT_STEPS} steps")
        _check_finite_nonneg(self.load_scale_kw, "load_scale_kw")
        _check_finite_nonneg(self.load_noise_sigma, "load_noise_sigma")
        if pv.ndim != 2 or pv.shape[0] != n_steps:
            raise ProfileError(
                f"pv_kw has shape {pv.shape}; expected ({n_steps}, n_pv), the same number of steps "
                "as the load archetypes (a profile with missing steps must be regenerated or filled)"
            )
        if self.pv_pmpp_kw.shape != (pv.shape[1],):
            raise ProfileError(f"pv_pmpp_kw has shape {self.pv_pmpp_kw.shape}; expected ({pv.shape[1]},)")
        _check_finite_nonneg(self.pv_pmpp_kw, "pv_pmpp_kw")
        for k in range(pv.shape[1]):
            _check_finite_nonneg(pv[:, k], f"pv_kw of plant {k}")
            peak = float(pv[:, k].max()) if n_steps else 0.0
            if peak > self.pv_pmpp_kw[k] * (1 + 1e-5) + 1e-6:
                raise ProfileError(f"pv_kw of plant {k} peaks at {peak:.3f} kW above its Pmpp {self.pv_pmpp_kw[k]}")
        n_days = -(-n_steps // (86_400 // self.step_s))
        if self.day_type.shape != (n_days,):
            raise ProfileError(f"day_type has shape {self.day_type.shape}; expected ({n_days},), one per day")

    # -- time --------------------------------------------------------------------------------------

    def t_ns(self, step: int) -> int:
        """UTC epoch time of ``step`` [ns]; ``step`` may equal ``n_steps`` (the end of the year)."""
        if not 0 <= step <= self.n_steps:
            raise ProfileError(f"step {step} outside the profile's 0..{self.n_steps}")
        return self.start_t_ns + int(step) * self.step_s * 1_000_000_000

    @property
    def year(self) -> int:
        """Calendar year of step 0 in local standard time."""
        return _local_datetime(self.start_t_ns).year

    # -- data --------------------------------------------------------------------------------------

    def load_kw(self, start: int, stop: int) -> np.ndarray:
        """Active power of every load for steps ``start <= step < stop`` [kW].

        Returns a new float32 array of shape ``(stop - start, n_loads)``. The same window always gives
        the same numbers, whatever windows were asked for before.
        """
        self._check_window(start, stop)
        out = np.empty((stop - start, self.n_loads), dtype=np.float32)
        spd = self.steps_per_day
        step = start
        while step < stop:
            day = step // spd
            block = self._day_block(day)
            lo = step - day * spd
            hi = min(stop - day * spd, block.shape[0])
            out[step - start : step - start + hi - lo] = block[lo:hi]
            step += hi - lo
        return out

    def pv_kw(self, start: int, stop: int) -> np.ndarray:
        """Available AC power of every PV plant for steps ``start <= step < stop`` [kW].

        Returns a new float32 array of shape ``(stop - start, n_pv)``; ``0 <= pv_kw <= pv_pmpp_kw``.
        """
        self._check_window(start, stop)
        return self.pv_kw_year[start:stop].copy()

    def _check_window(self, start: int, stop: int) -> None:
        if not 0 <= start <= stop <= self.n_steps:
            raise ProfileError(
                f"window [{start}, {stop}) outside the profile's 0..{self.n_steps} steps; "
                "ask for 0 <= start <= stop <= n_steps"
            )

    def _day_block(self, day: int) -> np.ndarray:
        block = self._cache.get(day)
        if block is None:
            block = self._raw_day(day)
            block *= self.load_scale_kw.astype(np.float32)[None, :]
            block.flags.writeable = False
            self._cache[day] = block
            while len(self._cache) > _CACHE_DAYS:
                self._cache.popitem(last=False)
        return block

    def _raw_day(self, day: int) -> np.ndarray:
        """Unscaled loads of one day: archetype x daily level x appliance variation [pu of scale]."""
        spd = self.steps_per_day
        t0 = day * spd
        n = min(spd, self.n_steps - t0)
        rng = np.random.default_rng([self.seed, _TAG_DAY, day])
        offsets = rng.integers(0, _NOISE_POOL_LEN - spd, size=self.n_loads)
        level = 1.0 + _DAILY_LEVEL_PER_SIGMA * self.load_noise_sigma * rng.standard_normal(self.n_loads)
        level = np.clip(level, 0.7, 1.3).astype(np.float32)
        # Rows of sliding-window views: one contiguous day per load, shape (n_loads, n).
        base = self._arch_windows[self._col_base + t0, :n]
        z = self._pool_windows[offsets, :n]
        z *= self.load_noise_sigma[:, None]
        z += 1.0
        np.maximum(z, 0.0, out=z)
        z *= base
        z *= level[:, None]
        return np.ascontiguousarray(z.T)

    # -- files -------------------------------------------------------------------------------------

    def save(self, path: str | Path) -> None:
        """Write the profiles to an ``.npz`` file (about 17 MB for a year), after validating them."""
        self.validate()
        path = Path(path)
        try:
            with open(path, "wb") as f:
                np.savez(
                    f,
                    format=np.array(_FORMAT),
                    seed=np.array(self.seed, dtype=np.int64),
                    start_t_ns=np.array(self.start_t_ns, dtype=np.int64),
                    step_s=np.array(self.step_s, dtype=np.int64),
                    archetype_names=np.array(self.archetype_names),
                    archetype_pu=self.archetype_pu,
                    load_archetype=self.load_archetype,
                    load_shift_steps=self.load_shift_steps,
                    load_scale_kw=self.load_scale_kw,
                    load_noise_sigma=self.load_noise_sigma,
                    pv_kw=self.pv_kw_year,
                    pv_pmpp_kw=self.pv_pmpp_kw,
                    day_type=self.day_type,
                )
        except OSError as e:
            raise ProfileError(f"{path}: cannot write profiles: {e}") from e

    @classmethod
    def load(cls, path: str | Path) -> YearProfiles:
        """Read profiles written by :meth:`save`; raise :class:`ProfileError` naming the file if bad."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except (OSError, ValueError) as e:
            raise ProfileError(f"{path}: cannot read profiles: {e}") from e
        fmt = str(data.get("format", ""))
        if fmt != _FORMAT:
            raise ProfileError(f"{path}: not a profiles file of format {_FORMAT!r} (found {fmt!r}); regenerate it")
        try:
            return cls(
                seed=int(data["seed"]),
                start_t_ns=int(data["start_t_ns"]),
                step_s=int(data["step_s"]),
                archetype_names=tuple(str(s) for s in data["archetype_names"]),
                archetype_pu=data["archetype_pu"],
                load_archetype=data["load_archetype"],
                load_shift_steps=data["load_shift_steps"],
                load_scale_kw=data["load_scale_kw"],
                load_noise_sigma=data["load_noise_sigma"],
                pv_kw=data["pv_kw"],
                pv_pmpp_kw=data["pv_pmpp_kw"],
                day_type=data["day_type"],
            )
        except KeyError as e:
            raise ProfileError(f"{path}: profiles file lacks array {e}; regenerate it") from e
        except ProfileError as e:
            raise ProfileError(f"{path}: {e}") from e


# ---------------------------------------------------------------------------------------------------
# Calendar helpers
# ---------------------------------------------------------------------------------------------------


def season_month(season: Season) -> int:
    """The month that represents a season in the evaluation: winter 1, spring 4, summer 7, fall 10."""
    try:
        return _SEASON_MONTH[season]
    except KeyError:
        raise ProfileError(f"unknown season {season!r}; use one of {sorted(_SEASON_MONTH)}") from None


def month_steps(profiles: YearProfiles, month: int) -> range:
    """Steps of ``profiles`` that fall in calendar ``month`` (1-12) of local standard time.

    The range is clipped to the profile; a month the profile does not cover raises :class:`ProfileError`.
    """
    if not 1 <= month <= 12:
        raise ProfileError(f"month {month} is not in 1..12")
    year = profiles.year
    first = _local_midnight_t_ns(year, month, 1)
    last_day = calendar.monthrange(year, month)[1]
    end = _local_midnight_t_ns(year, month, last_day) + 86_400 * 1_000_000_000
    step_ns = profiles.step_s * 1_000_000_000
    a = max(0, (first - profiles.start_t_ns) // step_ns)
    b = min(profiles.n_steps, (end - profiles.start_t_ns) // step_ns)
    if b <= a:
        raise ProfileError(f"month {month} of {year} is not covered by the profile's {profiles.n_steps} steps")
    return range(int(a), int(b))


def _local_midnight_t_ns(year: int, month: int, day: int) -> int:
    tz = dt.timezone(dt.timedelta(hours=UTC_OFFSET_H))
    return int(dt.datetime(year, month, day, tzinfo=tz).timestamp()) * 1_000_000_000


def _local_datetime(t_ns: int) -> dt.datetime:
    tz = dt.timezone(dt.timedelta(hours=UTC_OFFSET_H))
    return dt.datetime.fromtimestamp(t_ns // 1_000_000_000, tz=tz)


# ---------------------------------------------------------------------------------------------------
# Generation
# ---------------------------------------------------------------------------------------------------


def make_profiles(
    *,
    seed: int,
    load_kw_nominal: np.ndarray,
    pv_pmpp_kw: np.ndarray,
    latitude_deg: float = 35.8,
    longitude_deg: float = -78.6,
    year: int = 2023,
    load_distance_ohm: np.ndarray | None = None,
    pv_lag_min: np.ndarray | None = None,
    customer_seed: int | None = None,
) -> YearProfiles:
    """Generate one year of 1-minute load and PV profiles.

    Parameters
    ----------
    seed : int
        Seed of the weather (temperature, cloud day types and transients) and of the per-day load
        variation. A different seed gives an out-of-sample year of the same feeder.
    load_kw_nominal : ndarray, shape (n_loads,)
        Each load's nominal power [kW], as allocated in the feeder model. Profiles are scaled the way load
        allocation works (paper ref. [13]): the feeder's *coincident* yearly peak equals the sum of the
        nominal powers, and the loads share it in proportion to their nominal power. Because customers
        do not peak together, each load's own yearly peak is above its nominal kW (about 1.7x).
    pv_pmpp_kw : ndarray, shape (n_pv,)
        Each plant's rating [kW]; its available AC power never exceeds it.
    latitude_deg, longitude_deg : float
        Site of the feeder [deg], for the sun's position.
    year : int
        Calendar year (sets the weekdays, leap days and the sun's position).
    load_distance_ohm : ndarray, shape (n_loads,), optional
        Electrical distance of each load from the feeder head [ohm]. When given, commercial customers
        are more likely near the head and agricultural ones far out, as on a rural feeder.
    pv_lag_min : ndarray, shape (n_pv,), optional
        Lag of each plant behind the shared cloud field [min]; drawn from ``seed`` when omitted.
    customer_seed : int, optional
        Seed of the customers (archetype, shift, variation size of each load). Defaults to 0 for every
        ``seed``, so that years of different seeds describe the same customers.

    Returns
    -------
    YearProfiles
    """
    nominal = _vector(load_kw_nominal, "load_kw_nominal")
    pmpp = _vector(pv_pmpp_kw, "pv_pmpp_kw")
    if not -90.0 <= latitude_deg <= 90.0 or not -180.0 <= longitude_deg <= 180.0:
        raise ProfileError(f"site ({latitude_deg}, {longitude_deg}) deg is not a valid latitude, longitude")
    if not 1901 <= year <= 2099:
        raise ProfileError(f"year {year} outside 1901..2099")
    distance = None if load_distance_ohm is None else _vector(load_distance_ohm, "load_distance_ohm")
    if distance is not None and distance.shape != nominal.shape:
        raise ProfileError(f"load_distance_ohm has {distance.size} entries for {nominal.size} loads")
    lags = None if pv_lag_min is None else _vector(pv_lag_min, "pv_lag_min")
    if lags is not None and (lags.shape != pmpp.shape or lags.max(initial=0) > 120):
        raise ProfileError(f"pv_lag_min must have {pmpp.size} entries in 0..120 min")

    n_days = 366 if calendar.isleap(year) else 365
    start_t_ns = _local_midnight_t_ns(year, 1, 1)
    weather_rng = np.random.default_rng([seed, _TAG_WEATHER])
    day_type = _day_types(weather_rng, n_days, latitude_deg)
    temp_c = _temperature_c(weather_rng, day_type, latitude_deg)
    archetypes = _archetypes_pu(temp_c, day_type, year, latitude_deg)

    cust = np.random.default_rng([0 if customer_seed is None else customer_seed, _TAG_CUSTOMERS])
    load_archetype, shift, sigma = _customers(cust, nominal, distance)

    pv_rng = np.random.default_rng([seed, _TAG_PV])
    pv = _pv_kw(pv_rng, pmpp, lags, temp_c, day_type, latitude_deg, longitude_deg, year)

    unscaled = YearProfiles(
        seed=seed,
        start_t_ns=start_t_ns,
        archetype_pu=archetypes,
        load_archetype=load_archetype,
        load_shift_steps=shift,
        load_scale_kw=np.ones_like(nominal),
        load_noise_sigma=sigma,
        pv_kw=pv,
        pv_pmpp_kw=pmpp,
        day_type=day_type,
    )
    peak = _peak_pu(unscaled)
    per_load = _with_scale(unscaled, nominal / peak)
    coincidence = _total_peak_kw(per_load) / float(nominal.sum())
    return YearProfiles(
        seed=seed,
        start_t_ns=start_t_ns,
        archetype_pu=unscaled.archetype_pu,
        load_archetype=load_archetype,
        load_shift_steps=shift,
        load_scale_kw=nominal / peak / coincidence,
        load_noise_sigma=sigma,
        pv_kw=unscaled.pv_kw_year,
        pv_pmpp_kw=pmpp,
        day_type=day_type,
    )


def _with_scale(p: YearProfiles, scale_kw: np.ndarray) -> YearProfiles:
    """The same profiles with another per-load scale [kW]."""
    return YearProfiles(
        seed=p.seed,
        start_t_ns=p.start_t_ns,
        archetype_pu=p.archetype_pu,
        load_archetype=p.load_archetype,
        load_shift_steps=p.load_shift_steps,
        load_scale_kw=scale_kw,
        load_noise_sigma=p.load_noise_sigma,
        pv_kw=p.pv_kw_year,
        pv_pmpp_kw=p.pv_pmpp_kw,
        day_type=p.day_type,
    )


def _total_peak_kw(p: YearProfiles) -> float:
    """The feeder's coincident yearly peak [kW] (one pass over the year's days)."""
    peak = 0.0
    for d in range(p.day_type.size):
        day = p.load_kw(d * _STEPS_PER_DAY, (d + 1) * _STEPS_PER_DAY)
        peak = max(peak, float(day.sum(axis=1, dtype=np.float64).max()))
    return peak


def _peak_pu(unscaled: YearProfiles) -> np.ndarray:
    """Each load's exact yearly peak of the unscaled profile (one pass over the year's days)."""
    peak = np.zeros(unscaled.n_loads, dtype=np.float32)
    for d in range(unscaled.day_type.size):
        np.maximum(peak, unscaled._raw_day(d).max(axis=0), out=peak)
    return np.maximum(peak.astype(np.float64), 1e-6)


def _day_types(rng: np.random.Generator, n_days: int, latitude_deg: float) -> np.ndarray:
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


def _temperature_c(rng: np.random.Generator, day_type: np.ndarray, latitude_deg: float) -> np.ndarray:
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
    t = np.arange(n_days * _STEPS_PER_DAY) / _STEPS_PER_DAY  # [days]
    centres = day + 0.5
    hour = (t % 1.0) * 24.0
    temp = np.interp(t, centres, mean) + np.interp(t, centres, swing) * np.cos(2 * np.pi * (hour - 15.0) / 24.0)
    return temp


def _bump(hour: np.ndarray, centre_h: float | np.ndarray, width_h: float) -> np.ndarray:
    d = (hour - centre_h + 12.0) % 24.0 - 12.0
    return np.exp(-0.5 * (d / width_h) ** 2)


def _ramp(hour: np.ndarray, at_h: float) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-(hour - at_h) / 0.4))


def _archetypes_pu(temp_c: np.ndarray, day_type: np.ndarray, year: int, latitude_deg: float) -> np.ndarray:
    """The archetype shapes: daily shape x season (heating, cooling) x weekday/weekend, peak 1 each."""
    n = temp_c.size
    minute = np.arange(n)
    day = minute // _STEPS_PER_DAY
    hour = (minute % _STEPS_PER_DAY) / 60.0
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


def _customers(
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
    shift = np.clip(np.rint(rng.normal(0.0, 20.0, n)), -_MAX_SHIFT_STEPS, _MAX_SHIFT_STEPS).astype(np.int64)
    base_sigma = np.array([0.15, 0.15, 0.06, 0.12, 0.06])[archetype]
    sigma = (base_sigma * rng.uniform(0.7, 1.3, n)).astype(np.float32)
    return archetype.astype(np.int64), shift, sigma


@functools.lru_cache(maxsize=2)
def _noise_pool(seed: int) -> np.ndarray:
    """A fixed pool of unit-variance AR(1) noise with a 10-minute correlation time, from ``seed``."""
    rng = np.random.default_rng([seed, _TAG_POOL])
    rho = np.exp(-1.0 / _NOISE_TAU_STEPS)
    e = rng.standard_normal(_NOISE_POOL_LEN)
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
    times = pd.date_range(f"{year}-01-01 00:00", periods=n_days * _STEPS_PER_DAY, freq="1min", tz=tz)
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
    spd = _STEPS_PER_DAY
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


def _pv_kw(
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


# ---------------------------------------------------------------------------------------------------
# Small helpers
# ---------------------------------------------------------------------------------------------------


def _frozen(a: np.ndarray, dtype: type) -> np.ndarray:
    out = np.array(a, dtype=dtype, copy=True)
    out.flags.writeable = False
    return out


def _vector(a: np.ndarray, name: str) -> np.ndarray:
    v = np.asarray(a, dtype=float)
    if v.ndim != 1:
        raise ProfileError(f"{name} must be one-dimensional, got shape {v.shape}")
    _check_finite_nonneg(v, name)
    return v


def _check_finite_nonneg(a: np.ndarray, name: str) -> None:
    bad = ~np.isfinite(a)
    if bad.any():
        first = int(np.flatnonzero(bad.ravel())[0])
        raise ProfileError(
            f"{name} has {int(bad.sum())} NaN/infinite values (first at index {first}): a profile must "
            "have no gaps; fill or regenerate it"
        )
    if a.size and a.min() < 0:
        first = int(np.flatnonzero(a.ravel() < 0)[0])
        raise ProfileError(f"{name} has negative values (first at index {first}, {a.ravel()[first]})")


def feeder_profiles(device_map, engine, *, seed: int, cache_dir: str | Path | None) -> YearProfiles:
    """The year profiles of a feeder for ``seed``, cached as ``.npz`` in ``cache_dir`` (None: no cache).

    The one place profiles of a feeder are made: training, the bridge and the launcher share the cache.
    The key is the device map's fingerprint and the seed, so a changed feeder regenerates. Loads get
    their electrical distance (commercial customers near the head, agricultural far out) and plants the
    device map's lags. Written to a temporary file and renamed, so concurrent processes never read a
    half-written cache.
    """
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f"profiles-{device_map.feeder.name}-{device_map.fingerprint()}-{seed}.npz"
        if path.is_file():
            return YearProfiles.load(path)
    lags = np.asarray([p.profile_lag_min for p in device_map.pv], float)
    profiles = make_profiles(
        seed=seed,
        load_kw_nominal=engine.load_kw_nominal,
        pv_pmpp_kw=engine.pv_pmpp_kw,
        load_distance_ohm=engine.load_distance_ohm,
        pv_lag_min=lags if np.any(lags > 0) else None,
    )
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.stem}.{os.getpid()}.{threading.get_ident()}.tmp.npz")
        profiles.save(tmp)
        os.replace(tmp, path)
    return profiles
