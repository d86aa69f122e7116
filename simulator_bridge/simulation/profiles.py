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
import os
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Literal

import numpy as np

from simulator_bridge.errors import SimulatorError
from simulator_bridge.rural.synthesis import (
    ARCHETYPES,
    DAY_TYPES,
    MAX_SHIFT_STEPS,
    NOISE_POOL_LEN,
    STEPS_PER_DAY,
    UTC_OFFSET_H,
    archetypes_pu,
    draw_customers,
    draw_day_types,
    draw_temperature_c,
    noise_pool,
    pv_available_kw,
)

__all__ = [
    "feeder_profiles",
    "ARCHETYPES",
    "DAY_TYPES",
    "UTC_OFFSET_H",
    "ProfileError",
    "YearProfiles",
    "make_profiles",
    "month_steps",
    "profiles_cache_path",
    "season_month",
]


Season = Literal["winter", "spring", "summer", "fall"]

_FORMAT = "cvvc-profiles/1"
_STEP_S = 60
_DAILY_LEVEL_PER_SIGMA = 0.5  # day-to-day level variation of a load / its minute-scale variation
_CACHE_DAYS = 2
# Seeds of the independent random streams (arbitrary constants, fixed forever for reproducibility).
_TAG_WEATHER, _TAG_CUSTOMERS, _TAG_DAY, _TAG_PV = 0x57EA, 0xC057, 0xDA1, 0x9F
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
        pad = MAX_SHIFT_STEPS
        spd = self.steps_per_day
        # Circular padding so that shifted day windows never fall off the ends of the year.
        row_len = self.n_steps + 2 * pad + spd
        self._arch_padded = np.pad(self.archetype_pu, ((0, 0), (pad, pad + spd)), mode="wrap").ravel()
        self._col_base = self.load_archetype * row_len + pad - self.load_shift_steps
        self._pool = noise_pool(self.seed)
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
        if n_steps <= 2 * MAX_SHIFT_STEPS:
            raise ProfileError(f"archetype_pu has {n_steps} steps; need more than {2 * MAX_SHIFT_STEPS}")
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
        if n_loads and np.abs(self.load_shift_steps).max() > MAX_SHIFT_STEPS:
            raise ProfileError(f"load_shift_steps exceeds +-{MAX_SHIFT_STEPS} steps")
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
        offsets = rng.integers(0, NOISE_POOL_LEN - spd, size=self.n_loads)
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
    day_type = draw_day_types(weather_rng, n_days, latitude_deg)
    temp_c = draw_temperature_c(weather_rng, day_type, latitude_deg)
    archetypes = archetypes_pu(temp_c, day_type, year, latitude_deg)

    cust = np.random.default_rng([0 if customer_seed is None else customer_seed, _TAG_CUSTOMERS])
    load_archetype, shift, sigma = draw_customers(cust, nominal, distance)

    pv_rng = np.random.default_rng([seed, _TAG_PV])
    pv = pv_available_kw(pv_rng, pmpp, lags, temp_c, day_type, latitude_deg, longitude_deg, year)

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
        day = p.load_kw(d * STEPS_PER_DAY, (d + 1) * STEPS_PER_DAY)
        peak = max(peak, float(day.sum(axis=1, dtype=np.float64).max()))
    return peak


def _peak_pu(unscaled: YearProfiles) -> np.ndarray:
    """Each load's exact yearly peak of the unscaled profile (one pass over the year's days)."""
    peak = np.zeros(unscaled.n_loads, dtype=np.float32)
    for d in range(unscaled.day_type.size):
        np.maximum(peak, unscaled._raw_day(d).max(axis=0), out=peak)
    return np.maximum(peak.astype(np.float64), 1e-6)

# ---------------------------------------------------------------------------------------------------
# Small helpers
# ---------------------------------------------------------------------------------------------------


def _frozen(a: np.ndarray, dtype: type) -> np.ndarray:
    out: np.ndarray = np.array(a, dtype=dtype, copy=True)
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


def profiles_cache_path(device_map, seed: int, cache_dir: str | Path) -> Path:
    """Where :func:`feeder_profiles` caches a feeder's year profiles of ``seed``: keyed by the map's fingerprint."""
    return Path(cache_dir) / f"profiles-{device_map.feeder.name}-{device_map.fingerprint()}-{seed}.npz"


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
        path = profiles_cache_path(device_map, seed, cache_dir)
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
