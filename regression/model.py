"""The trained model file: everything the agent needs from training, versioned and fingerprinted.

One msgspec-encoded JSON document (readable, diffable, small). Arrays are nested lists in the file
and numpy arrays in memory (``ModelArrays``). Written by ``training``; read by ``agent`` and
``recordings`` (offline replay). No OpenDSS here.

Index conventions used by every array:
- ``n`` = critical node, in ``critical_nodes`` order;
- ``k`` = PV plant, in ``pv`` order;
- ``r`` = regulator (one tap changer), in ``regulators`` order;
- ``m`` = regression feature, in ``feature_names`` order (see ``features``);
- ``c`` = capacitor bank, in ``capacitors`` order;
- ``j`` = field reading used as a feature (``feature_set == "extended_readings"``), in ``readings`` order.

Format versions: 1 (the paper's features only) and 2 (adds the optional extended feature sets: the capacitor
banks' state term, the tap/bank feature mapping, calendar features, field-device readings as regressors;
docs/method.md). A version-1 file reads as a version-2 model with ``feature_set = "paper"``; any other version
is refused with a clear error.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import msgspec
import numpy as np
from msgspec import Meta

from regression.errors import ModelError
from schemas.settings import FeatureSet

__all__ = [
    "MODEL_FORMAT_VERSION",
    "READABLE_FORMAT_VERSIONS",
    "CapacitorInfo",
    "CriticalNode",
    "CvvcModel",
    "EstimateBounds",
    "FitStats",
    "ModelArrays",
    "FeatureSet",
    "ModelError",
    "PvInfo",
    "RegulatorInfo",
    "SensitivityFit",
    "TrainingSettings",
    "HEAD_Q_COLUMNS",
    "features",
    "CALENDAR_FEATURES",
    "SEASONAL_CALENDAR_FEATURES",
    "WEEKLY_CALENDAR_FEATURES",
    "calendar_features",
    "n_calendar_features",
    "extended_feature_names",
    "feature_names",
    "read_model",
    "write_model",
]

MODEL_FORMAT_VERSION = 2
READABLE_FORMAT_VERSIONS = (1, 2)  # 1: written before the extended feature set; reads with its defaults

Finite = Annotated[float, Meta(ge=-1e12, le=1e12)]


NodeKind = Literal["head", "reg_primary", "reg_secondary", "pv", "extreme", "near_extreme"]

#: ``paper``: eq. (5) on the feeder head's and the plants' P and Q (the paper's limited measurement set).
#: ``extended``: those plus a capacitor-state term like eq. (4)'s tap term, with every feature mapped back to the
#: training taps and banks (beyond the paper, docs/method.md).
#: ``extended_readings``: ``extended`` plus the field devices' voltage readings (regulator secondaries, capacitor
#: buses) as regressors: measured fragile, a reading outside its training range extrapolates badly.


class CriticalNode(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A node (one phase of one bus) whose voltage the agent estimates and constrains.

    ``upstream_regulator`` is the index (into ``regulators``) of the nearest regulator upstream on the
    same phase, used for the correction of paper eq. (6)-(7); ``None`` when no regulator is upstream.
    """

    name: str  # "bus.phase", lower case, as OpenDSS names nodes
    phase: Literal[1, 2, 3]
    kinds: list[NodeKind]
    upstream_regulator: int | None = None


class RegulatorInfo(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A controllable tap changer as the agent sees it.

    ``secondary_node`` indexes ``critical_nodes``. ``pu_per_v120`` converts the controller's raw
    120 V-base reading to per-unit of the secondary node's base (ptratio / (kV_LN base * 1000)).
    ``step_v120`` is the voltage of one tap step on the 120 V base (0.75 V for +/-10 %, 32 steps).
    """

    id: str
    secondary_node: int
    pu_per_v120: float
    tap_min: int = -16
    tap_max: int = 16
    step_v120: float = 0.75
    cost_per_tap: float = 0.14
    max_taps_per_interval: int = 4
    default_setpoint_v120: float = 120.0
    default_band_v120: float = 2.0


class CapacitorInfo(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A switched capacitor bank the agent controls (beyond the paper; docs/method.md "Capacitor decisions").

    ``steps`` of ``kvar_rated / steps`` each; ``closed0`` is the number of closed steps every training power
    flow ran at (the state eq. (5) has built in); ``phases`` are the bank's phases (1-3), over which its
    kvar is spread. ``cost_per_switch`` is per step opened or closed (the device map's). ``v_ref_v`` divides the
    bank's bus voltage reading (``CapFrame.v_v``, line-to-neutral [V]) into the per-unit reading that the
    ``extended_readings`` feature set regresses on (0 otherwise). ``control_*``: the bank's local control, so the
    agent can keep its own actions from making it switch (its type, ON/OFF settings and the controlled quantity's
    linear sensitivities to the plants' Q and the regulators' taps).
    """

    id: str
    steps: Annotated[int, Meta(ge=1, le=64)]
    kvar_rated: Annotated[float, Meta(gt=0.0, le=1e6)]
    phases: list[Literal[1, 2, 3]]
    closed0: Annotated[int, Meta(ge=0, le=64)]
    cost_per_switch: Annotated[float, Meta(ge=0.0, le=1e6)] = 1.0
    max_switches_per_interval: Annotated[int, Meta(ge=0, le=64)] = 1
    v_ref_v: float = 0.0  # extended_readings: the bank's median bus voltage over the training flows [V]
    # its local CapControl, as the agent predicts it (training.capbanks.bank_controls; "none": not predicted)
    control_kind: Literal["voltage", "kvar", "current", "none"] = "none"
    control_on: float = 0.0  # ON setting, in the control's unit (CapFrame.control_value's)
    control_off: float = 0.0  # OFF setting
    control_dq: list[float] = []  # (K,) change of the controlled quantity per kvar of each plant's Q [unit/kvar]
    control_dtap: list[float] = []  # (R,) ... per tap step of each regulator [unit/step]
    # its control's VoltOverride (a kvar or current control that a low voltage closes and a high one opens, whatever
    # its own quantity): limits on the PT base [V] (0: none), the tested voltage per volt of the bank's bus reading
    # (CapFrame.v_v), and that voltage's sensitivities to the plants' Q [V/kvar] and the taps [V/step]
    override_vmin_v: float = 0.0
    override_vmax_v: float = 0.0
    override_per_v: float = 0.0
    override_dq: list[float] = []
    override_dtap: list[float] = []


class PvInfo(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A PV plant as the agent sees it: rating and the cost of its reactive power."""

    id: str
    kva: float
    pmpp_kw: float
    cost_per_kvar: float
    phases: int = 3


class SensitivityFit(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """dV/dQ of one critical node to one plant's Q [pu/kvar], as a function of feeder-head Q [kvar].

    ``form == "power"``: paper eq. (3) ``a / (c + q_head_kvar) ** b``;
    ``form == "linear"``: ``a + b * q_head_kvar`` (c unused);
    ``form == "constant"``: ``a``.
    ``q_head_kvar`` is clipped to ``[q_min_kvar, q_max_kvar]`` (the training range) before evaluation.
    """

    form: Literal["power", "linear", "constant"]
    a: float
    b: float = 0.0
    c: float = 0.0
    q_min_kvar: float = -1e9
    q_max_kvar: float = 1e9


class TrainingSettings(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The training run that made a model: seeds, scenario selection and fit settings."""

    year_seed: int
    selection: Literal["guided", "random"]
    blocks: tuple[int, int]
    q_steps_pct: list[float]
    scenarios: int
    power_flows: int
    seconds: float
    # added by training (additive, with defaults): the rest of what produced the model
    combined_pct: list[float] = []  # all-plant Q perturbations [% of each plant's headroom]
    rcond: float = 0.0  # truncation of the eq. (5) least squares (0: not recorded)
    tolerance: float = 0.0  # OpenDSS solve tolerance of the training flows (0: not recorded)
    critical_margin_pu: float = 0.0  # near-extreme nodes within this of a flow's extreme are critical (0: none)
    calendar_cover_per_cell: int = 0  # base-flow minutes per (month, hour) cell beyond the scenarios (0: none)


class FitStats(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Training-set fit statistics [pu]."""

    voltage_rmse_pu: float
    voltage_max_abs_pu: float
    sensitivity_median_rel_err: float
    per_node_rmse_pu: list[float] = []
    # added by training (additive, with defaults): error on held-out scenarios, conditioning
    validation_rmse_pu: float = 0.0  # eq. (5) fitted on 4 of 5 scenarios, error on the 5th
    validation_max_abs_pu: float = 0.0
    condition_number: float = 0.0  # of the standardised eq. (5) design matrix


class EstimateBounds(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Calibrated error bounds of the corrected estimates and the envelope of the training inputs.

    Conformal on minutes of the training year that no training scenario used (``training.calibration``,
    ``training.conformal``): for critical node ``n``, the interval ``[estimate - lower_pu[n], estimate + upper_pu[n]]``
    holds the true voltage in at least ``1 - alpha`` of a held-out calibration window's node-minutes (the windows'
    minutes are correlated in time: the guarantee is approximate; ``cvvc report accuracy`` measures it on another
    year, every run live).
    ``envelope_lo``/``envelope_hi``: the range of each regression feature over the training power flows; inputs
    outside it are extrapolation.
    """

    alpha: float
    upper_pu: list[Finite]
    lower_pu: list[Finite]
    calibration_minutes: int
    envelope_lo: list[Finite]
    envelope_hi: list[Finite]
    # the one-sided quantile level the bounds were taken at (``training.conformal``: raised above 1 - alpha / 2 until
    # held-out calibration windows miss at most alpha) and that level's held-out miss rate; 0: a model calibrated
    # before (per-node quantiles at 1 - alpha / 2)
    level: Finite = 0.0
    held_out_miss: Finite = 0.0
    # AMI meters (explicit option, ``agent.ami``): the same bounds for a node whose estimate is moved by a meter reading
    # at most ``ami_interval_s`` old (empty lists: a model calibrated before meters existed)
    ami_interval_s: int = 0
    ami_upper_pu: list[Finite] = []
    ami_lower_pu: list[Finite] = []


class CvvcModel(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Everything the online agent needs. See the module docstring for index conventions.

    - ``alpha[n]``: linear coefficients over ``feature_names`` plus a trailing intercept (eq. 5) [pu].
    - ``tap0[r]``: the taps the training power flows ran at (eq. 5's T_r^0).
    - ``dv_dtap_pu[n][r]``: static voltage change per tap step (eq. 4) [pu/step].
    - ``sens_q[n][k]``: dV_n/dQ_k fits (eq. 3) [pu/kvar].
    - ``dv_dcap_pu[n][c]``: static voltage change per closed step of bank ``c`` [pu/step] (beyond the paper;
      empty in models without ``capacitors``).

    Extended feature sets only (empty for ``paper``):

    - ``readings[j]``: ``"reg:<id>"`` (the regulator's raw secondary voltage in pu of its secondary node) or
      ``"cap:<id>"`` (the bank's bus voltage over ``CapacitorInfo.v_ref_v``); they enter eq. (5) after the
      paper features (``extended_feature_names``).
    - ``cap0[c]``: the banks' closed steps in training (each bank's ``closed0``; empty in paper models).
    - ``feature_dtap[m][r]``, ``feature_dcap[m][c]``: each feature's change per tap step / closed step, from
      the same perturbations [kW, kvar or pu per step]: features are mapped back to ``tap0``/``cap0`` before
      eq. (5), so that a tap or a bank acts only through its own static term (a bank's kvar at the head would
      otherwise read as a load change).
    - ``reading_alpha[j]``: each (mapped) reading regressed on the (mapped) paper features (coefficients then
      intercept), used in place of a reading that is missing.
    """

    format_version: int = MODEL_FORMAT_VERSION
    feeder_name: str
    fingerprint: str
    cvvc_version: str
    settings: TrainingSettings
    feature_names: list[str]
    critical_nodes: list[CriticalNode]
    regulators: list[RegulatorInfo]
    pv: list[PvInfo]
    alpha: list[list[Finite]]
    tap0: list[int]
    dv_dtap_pu: list[list[Finite]]
    sens_q: list[list[SensitivityFit]]
    optimization_limits_pu: tuple[float, float] = (0.975, 1.04)
    judged_limits_pu: tuple[float, float] = (0.965, 1.05)
    control_period_s: int = 300
    node_count: int = 0  # single-phase nodes in the whole feeder, for reporting the critical share
    fit: FitStats | None = None
    bounds: EstimateBounds | None = None  # calibrated estimate bounds (None: a model trained without them)
    # format 2 (additive, with defaults): the extended feature sets
    feature_set: FeatureSet = "paper"
    capacitors: list[CapacitorInfo] = []
    cap0: list[int] = []
    dv_dcap_pu: list[list[Finite]] = []
    readings: list[str] = []
    feature_dtap: list[list[Finite]] = []
    feature_dcap: list[list[Finite]] = []
    reading_alpha: list[list[Finite]] = []
    calendar: bool = False  # the calendar features follow the paper's (``CALENDAR_FEATURES``)
    utc_offset_h: float = 0.0  # local standard time of the feeder minus UTC [h], for the calendar features
    calendar_seasonal: int = 0  # ... followed by the first so many daily harmonics times the yearly one
    calendar_weekly: bool = False  # ... and by the weekend and its daily harmonics (``WEEKLY_CALENDAR_FEATURES``)


def feature_names(n_pv: int) -> list[str]:
    """Regression features M of eq. (5), as we read it (see docs/method.md).

    Feeder-head per-phase P and Q, then per-plant *total* P and Q. Per-phase P/Q of a balanced
    three-phase plant are collinear (reference experiment, trap 1), so the plant enters by its totals.
    """
    names = [f"head_p_kw_{ph}" for ph in "abc"] + [f"head_q_kvar_{ph}" for ph in "abc"]
    for k in range(n_pv):
        names += [f"pv{k}_p_kw", f"pv{k}_q_kvar"]
    return names


CALENDAR_FEATURES = ("tod_cos1", "tod_sin1", "tod_cos2", "tod_sin2", "doy_cos", "doy_sin")
"""Calendar features of the extended sets: time of day (two harmonics) and day of year (one)."""
SEASONAL_CALENDAR_FEATURES = tuple(f"tod_{f}{h}_doy_{g}" for h in (1, 2) for g in ("cos", "sin")
                                   for f in ("cos", "sin"))
"""Seasonal calendar features (after ``CALENDAR_FEATURES``): each daily harmonic times the yearly one, so that the
daily shape a node's voltage learns may change with the season; a model takes the first 4 (harmonic 1) or all 8."""


WEEKLY_CALENDAR_FEATURES = ("weekend", "weekend_tod_cos1", "weekend_tod_sin1", "weekend_tod_cos2", "weekend_tod_sin2")
"""Weekly calendar features (after the seasonal ones): 1 on Saturdays and Sundays (local time), alone and times
the daily harmonics, so that a weekend day may have its own daily shape (a shop's, an office's load)."""
_EPOCH_WEEKDAY = 3  # 1970-01-01 was a Thursday (Monday 0)


def n_calendar_features(calendar: bool, seasonal: int, weekly: bool = False) -> int:
    """Number of calendar features of a model with these settings (0, or 6 + 4 seasonal + 5 weekly)."""
    return len(CALENDAR_FEATURES) + 4 * seasonal + len(WEEKLY_CALENDAR_FEATURES) * int(weekly) if calendar else 0


def extended_feature_names(n_pv: int, readings: list[str], calendar: bool = False, seasonal: int = 0,
                           weekly: bool = False) -> list[str]:
    """Features of the extended sets: the paper's (``feature_names``), the calendar's, one per field reading."""
    cal = (list(CALENDAR_FEATURES) + list(SEASONAL_CALENDAR_FEATURES[: 4 * seasonal])
           + (list(WEEKLY_CALENDAR_FEATURES) if weekly else [])) if calendar else []
    return feature_names(n_pv) + cal + [f"reading_{r}" for r in readings]


def calendar_features(t_ns: np.ndarray, utc_offset_h: float, seasonal: int = 0, weekly: bool = False) -> np.ndarray:
    """Time of day and day of year as harmonics, ``CALENDAR_FEATURES`` order (beyond the paper).

    Parameters
    ----------
    t_ns : (...,) UTC epoch nanoseconds.
    utc_offset_h : the feeder's local standard time minus UTC [h] (the load follows local time).
    seasonal : also the products of the first ``seasonal`` daily harmonics (0, 1 or 2) with the yearly one
        (``SEASONAL_CALENDAR_FEATURES``).
    weekly : also the weekend indicator and its products with the two daily harmonics (``WEEKLY_CALENDAR_FEATURES``).

    Returns
    -------
    (..., ``n_calendar_features(True, seasonal, weekly)``) array in [-1, 1].
    """
    local_s = np.asarray(t_ns, float) / 1e9 + float(utc_offset_h) * 3600.0
    day = 2.0 * np.pi * (local_s % 86400.0) / 86400.0
    year = 2.0 * np.pi * (local_s % (365.2425 * 86400.0)) / (365.2425 * 86400.0)
    cols = [np.cos(day), np.sin(day), np.cos(2 * day), np.sin(2 * day), np.cos(year), np.sin(year)]
    for h in range(int(seasonal)):
        cols += [cols[2 * h] * cols[4], cols[2 * h + 1] * cols[4], cols[2 * h] * cols[5], cols[2 * h + 1] * cols[5]]
    if weekly:
        weekend = ((np.floor(local_s / 86400.0) + _EPOCH_WEEKDAY) % 7 >= 5).astype(float)
        cols += [weekend] + [weekend * c for c in cols[:4]]
    return np.stack(cols, axis=-1)


#: Columns of the feeder head's Q per phase in ``features``' output (head P, head Q, then each plant's P and Q).
HEAD_Q_COLUMNS = slice(3, 6)


def features(
    head_p_kw: np.ndarray, head_q_kvar: np.ndarray, pv_p_kw: np.ndarray, pv_q_kvar: np.ndarray
) -> np.ndarray:
    """Feature vector(s) M in ``feature_names`` order.

    Parameters
    ----------
    head_p_kw, head_q_kvar : (..., 3) per-phase feeder-head power [kW], [kvar] (generator convention
        is NOT used here: the head delivers power, positive into the feeder).
    pv_p_kw, pv_q_kvar : (..., K) per-plant total output [kW], [kvar], generator convention.

    Returns
    -------
    (..., 6 + 2K) array.
    """
    pv = np.stack([np.asarray(pv_p_kw, float), np.asarray(pv_q_kvar, float)], axis=-1)
    pv = pv.reshape(*pv.shape[:-2], -1)
    return np.concatenate([np.asarray(head_p_kw, float), np.asarray(head_q_kvar, float), pv], axis=-1)


@dataclass(frozen=True)
class ModelArrays:
    """The model's numbers as numpy arrays, built once at load."""

    alpha: np.ndarray  # (N, M+1)
    tap0: np.ndarray  # (R,)
    dv_dtap_pu: np.ndarray  # (N, R)
    upstream_regulator: np.ndarray  # (N,) int, -1 where none
    reg_secondary_node: np.ndarray  # (R,) int
    reg_pu_per_v120: np.ndarray  # (R,)
    extended: bool = False  # features are mapped back to tap0/cap0 (``regression.estimator.extended_features``)
    n_calendar: int = 0  # calendar features after the paper's (``n_calendar_features``)
    calendar_seasonal: int = 0  # the model's calendar settings (``CvvcModel``'s of the same names)
    calendar_weekly: bool = False
    utc_offset_h: float = 0.0
    # the extended feature set (defaults: none, as for a paper model)
    cap0: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (C,) closed steps in training (closed0)
    cap_v_ref_v: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (C,) each bank's reading reference [V]
    cap_head_q_kvar: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (C, 3) kvar per closed step,
    # spread evenly over the bank's phases: what a step does to the feeder head's Q per phase
    dv_dcap_pu: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # (N, C) [pu/step]
    feature_dtap: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # (M, R) per tap step
    feature_dcap: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # (M, C) per closed step
    reading_alpha: np.ndarray = field(default_factory=lambda: np.zeros((0, 1)))  # (J, M_paper + 1)

    @property
    def n_readings(self) -> int:
        """Field readings among the features (0 for the paper's feature set)."""
        return int(self.reading_alpha.shape[0])

    @classmethod
    def of(cls, model: CvvcModel) -> ModelArrays:
        """The model's coefficients as numpy arrays, for evaluation."""
        n_reg = len(model.regulators)
        n_cap, n_read = len(model.capacitors), len(model.readings)
        n_paper = len(feature_names(len(model.pv)))
        n_feat = n_paper + n_read + n_calendar_features(model.calendar, model.calendar_seasonal, model.calendar_weekly)
        extended = model.feature_set != "paper"
        try:
            return cls._of(model, n_reg, n_cap, n_read, n_paper, n_feat, extended)
        except ValueError as e:  # a reshape: the coefficient lists do not fit the model's devices and features
            raise ModelError(f"the model's arrays do not fit its {len(model.critical_nodes)} critical nodes, "
                             f"{n_reg} regulators, {n_cap} banks and {n_feat} features ({e}); retrain it "
                             "with `cvvc train`") from e

    @classmethod
    def _of(cls, model: CvvcModel, n_reg: int, n_cap: int, n_read: int, n_paper: int, n_feat: int,
            extended: bool) -> ModelArrays:
        return cls(
            alpha=np.asarray(model.alpha, float),
            tap0=np.asarray(model.tap0, float),
            dv_dtap_pu=np.asarray(model.dv_dtap_pu, float).reshape(len(model.critical_nodes), n_reg),
            upstream_regulator=np.asarray(
                [-1 if c.upstream_regulator is None else c.upstream_regulator for c in model.critical_nodes],
                int,
            ),
            reg_secondary_node=np.asarray([r.secondary_node for r in model.regulators], int),
            reg_pu_per_v120=np.asarray([r.pu_per_v120 for r in model.regulators], float),
            extended=extended,
            n_calendar=n_calendar_features(model.calendar, model.calendar_seasonal, model.calendar_weekly),
            calendar_seasonal=model.calendar_seasonal,
            calendar_weekly=model.calendar_weekly,
            utc_offset_h=model.utc_offset_h,
            cap0=np.asarray([c.closed0 for c in model.capacitors], float),
            cap_v_ref_v=np.asarray([c.v_ref_v for c in model.capacitors], float),
            cap_head_q_kvar=np.array([[c.kvar_rated / c.steps / len(c.phases) if ph in c.phases else 0.0
                                       for ph in (1, 2, 3)] for c in model.capacitors], float).reshape(n_cap, 3),
            dv_dcap_pu=_dv_dcap(model),
            feature_dtap=np.asarray(model.feature_dtap, float).reshape(n_feat, n_reg) if extended
            else np.zeros((n_feat, n_reg)),
            feature_dcap=np.asarray(model.feature_dcap, float).reshape(n_feat, n_cap) if extended
            else np.zeros((n_feat, n_cap)),
            reading_alpha=np.asarray(model.reading_alpha, float).reshape(n_read, n_paper + 1),
        )


def _dv_dcap(model: CvvcModel) -> np.ndarray:
    """(N, C) per-step bank sensitivities of ``model``; a clear error when the grid does not fit its banks."""
    n, c = len(model.critical_nodes), len(model.capacitors)
    a = np.asarray(model.dv_dcap_pu, float)
    if c == 0 and a.size == 0:
        return np.zeros((n, 0))
    if a.shape != (n, c):
        raise ModelError(f"model has {c} capacitor bank(s) but dv_dcap_pu has shape {a.shape}, expected ({n}, {c}); "
                         "retrain with `cvvc train`")
    return a


def write_model(model: CvvcModel, path: str | Path) -> None:
    """Write ``model`` as JSON, refusing non-finite numbers (msgspec would write them as null)."""
    for row in model.alpha + model.dv_dtap_pu + model.dv_dcap_pu + model.reading_alpha:
        if not np.all(np.isfinite(row)):
            raise ModelError("refusing to write a model with non-finite coefficients")
    Path(path).write_bytes(msgspec.json.format(msgspec.json.encode(model), indent=1))


def read_model(path: str | Path, *, expect_fingerprint: str | None = None) -> CvvcModel:
    """Read and validate a model file; with ``expect_fingerprint``, refuse a model of another feeder."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise ModelError(f"{path}: cannot read model: {e}") from e
    try:
        head = msgspec.json.decode(raw, type=dict)
    except msgspec.DecodeError as e:
        raise ModelError(f"{path}: not a model file (invalid JSON): {e}") from e
    version = head.get("format_version")
    if version not in READABLE_FORMAT_VERSIONS:
        raise ModelError(
            f"{path}: model format {version!r}, this cvvc-edge reads formats {list(READABLE_FORMAT_VERSIONS)}; "
            "retrain with `cvvc train`"
        )
    try:
        model = msgspec.json.decode(raw, type=CvvcModel)
    except msgspec.ValidationError as e:
        raise ModelError(f"{path}: invalid model file: {e}") from e
    _dv_dcap(model)  # banks and their sensitivities agree, or a clear error now rather than in the agent
    _check_extended(model, path)
    if expect_fingerprint is not None and model.fingerprint != expect_fingerprint:
        raise ModelError(
            f"{path}: model was trained for feeder {model.feeder_name!r} (fingerprint {model.fingerprint}), "
            f"not this feeder (fingerprint {expect_fingerprint}); train a model for it with `cvvc train`"
        )
    return model


def _check_extended(model: CvvcModel, path: Path) -> None:
    """Refuse a model whose extended-feature arrays do not agree in size with each other."""
    n_node, n_reg = len(model.critical_nodes), len(model.regulators)
    n_cap, n_read = len(model.capacitors), len(model.readings)
    n_paper = len(feature_names(len(model.pv)))
    n_feat = n_paper + n_read + n_calendar_features(model.calendar, model.calendar_seasonal, model.calendar_weekly)
    checks = [
        (len(model.feature_names) == n_feat, f"{len(model.feature_names)} feature names for {n_feat} features"),
        (all(len(a) == n_feat + 1 for a in model.alpha), f"alpha rows are not {n_feat} + 1 long"),
        (not model.cap0 or model.cap0 == [c.closed0 for c in model.capacitors],
         "cap0 differs from the banks' closed0"),
        (n_cap == 0 or (len(model.dv_dcap_pu) == n_node and all(len(r) == n_cap for r in model.dv_dcap_pu)),
         "dv_dcap_pu is not (nodes x capacitors)"),
        (model.feature_set == "paper" or (len(model.feature_dtap) == n_feat
                                           and all(len(r) == n_reg for r in model.feature_dtap)),
         "feature_dtap is not (features x regulators)"),
        (model.feature_set == "paper" or (len(model.feature_dcap) == n_feat
                                           and all(len(r) == n_cap for r in model.feature_dcap)),
         "feature_dcap is not (features x capacitors)"),
        (len(model.reading_alpha) == n_read and all(len(r) == n_paper + 1 for r in model.reading_alpha),
         "reading_alpha is not (readings x paper features + 1)"),
        (model.feature_set == "extended_readings" or n_read == 0, "field readings in a model without them"),
        (model.feature_set != "paper" or not model.calendar, "calendar features in a paper model"),
        (model.calendar or not (model.calendar_seasonal or model.calendar_weekly),
         "seasonal or weekly calendar features without the calendar's"),
        (0 <= model.calendar_seasonal <= 2, f"calendar_seasonal {model.calendar_seasonal} is not 0, 1 or 2"),
    ]
    bad = [what for ok, what in checks if not ok]
    if bad:
        raise ModelError(f"{path}: inconsistent model file ({'; '.join(bad)}); retrain with `cvvc train`")
