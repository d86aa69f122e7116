"""The extended feature sets (beyond the paper, docs/method.md "Extended features"): banks, readings, cover.

The paper's eq. (5) regresses each critical node's voltage on the feeder head's and the PV plants' P and Q, with
regulators frozen at ``tap0`` and eq. (4)'s static tap term. On real feeders this breaks:

- **Switched capacitor banks** under local control (``extended``): a bank of 1200 kvar switching changes the
  head's Q by as much and the regression, which learned Q from the plants' sweeps, reads it as a large voltage
  change (epri-m1: the estimate fell by 0.15 pu when one bank opened). A bank enters like a regulator: a static
  perturbation per closed step (``dv_dcap``), and every feature is mapped back to the training state of the banks
  and the taps (a tap step also moves the head's P and Q a little through voltage-dependent loads).
- **What the features cannot see** (``extended_readings``): load beside the head meter, the source voltage. The
  field devices' own voltage readings (regulator secondaries, capacitor bus voltages; ``RegFrame``/``CapFrame``)
  enter eq. (5) as regressors. Measured fragile: in training the readings barely move apart from the other
  features, and a reading outside that range extrapolates badly; eq. (6)-(7)'s correction is the robust use.
- **The extreme node moves among many secondaries** (``near_extreme_cover``): more critical nodes.

Pure functions of arrays plus one function that drives the engine for the perturbations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from regression.model import features
from schemas.settings import FeatureOptions
from simulator_bridge.opendss.sensitivities import one_step_each

__all__ = ["EXTENDED_OPTIONS", "PAPER_OPTIONS", "SINGLE_TAP_SHIFTS", "TAP_SHIFTS", "FeatureOptions", "Perturbations",
           "default_feature_options", "device_shifted_voltages", "near_extreme_cover", "perturb_devices",
           "reading_matrix", "zone_extreme_cover"]


#: The paper's method (eq. (5) on head and plant P, Q; the paper's extreme nodes).
PAPER_OPTIONS = FeatureOptions()
#: The extended set as measured on the real feeders (docs/method.md): banks, tap/bank mapping, calendar and the
#: near-extreme cover at 0.001 pu; since training revision 8 the calendar cover (one minute per month and hour),
#: the seasonal (two daily harmonics x the yearly one) and the weekly calendar terms (docs/method.md, "The deep
#: secondaries' calendar bias").
EXTENDED_OPTIONS = FeatureOptions(feature_set="extended", calendar=True, critical_margin_pu=0.001,
                                  calendar_cover_per_cell=1, calendar_seasonal=2, calendar_weekly=True)


def default_feature_options(device_map) -> FeatureOptions:
    """What ``cvvc train --features auto`` and ``cvvc run``/``evaluate`` train: the extended set on a feeder with a
    bank that switches on its own (a ``[[capacitor]]`` with a ``capcontrol``) or without a regulator (the paper's
    correction needs one), the paper's method otherwise.

    Judged one feeder left out on the seven shared feeders (docs/method.md, "Choosing the feature set"): offline the
    extended set estimates better on every one of them, but in closed loop (case D, first 3 days of each season,
    16 goals per feeder) this rule is the one chosen on the other six in six folds of seven: the extended set raised
    epri-ckt24's NVV (winter 1,415 against 1,208) and epri-k1's and IEEE 123's Q cost. The seventh fold is IEEE
    8500's, the one feeder whose banks switching on their own break the paper's method (NVV 104,462 against 8 in
    three winter days): left out, the others cannot tell the two rules apart.
    """
    switching = any(c.capcontrol for c in device_map.capacitor)
    return EXTENDED_OPTIONS if switching or (device_map.capacitor and not device_map.regulator) else PAPER_OPTIONS

#: Tap offsets from ``tap0`` (every regulator at once) under which the near-extreme cover also looks for extremes:
#: out of training, local control runs the regulators several steps from ``tap0`` (IEEE 8500: 3-7).
TAP_SHIFTS = (-6, -3, 3, 6)
#: Offsets of one regulator at a time (the others at ``tap0``): a zone boosted alone moves the extreme there.
SINGLE_TAP_SHIFTS = (-4, 4)


@dataclass(frozen=True)
class Perturbations:
    """Per-step changes of every node voltage and every feature, from one scenario at ``tap0``/``cap0``."""

    dv_dcap_pu: np.ndarray  # (n_nodes, C) [pu per closed step]
    feature_dtap: np.ndarray  # (M_paper + R + C, R): paper features, reg readings [pu], cap readings [V]
    feature_dcap: np.ndarray  # (M_paper + R + C, C)


def _raw(engine) -> np.ndarray:
    """Paper features, regulator readings [pu] and capacitor bus readings [V] of the engine's solved state."""
    r = engine.readings()
    paper = features(r.head_p_kw, r.head_q_kvar, r.pv_p_kw.sum(axis=1), r.pv_q_kvar.sum(axis=1))
    reg = np.asarray(r.reg_v120, float) * np.asarray(engine.reg_pu_per_v120, float)
    return np.concatenate([paper, reg, np.asarray(r.cap_v_v, float)])


def perturb_devices(engine, load_kw: np.ndarray, pv_kw: np.ndarray, tap0: np.ndarray) -> Perturbations:
    """One tap step of each regulator and one closed step of each map bank, one at a time (like eq. (4)).

    A device at its top position steps down and the change is divided by -1. The engine is left at ``tap0`` and
    its banks as it found them (``cap0``).
    """
    engine.set_loads_kw(load_kw)
    engine.set_pv(pv_kw, np.zeros(len(pv_kw)))
    engine.set_taps(tap0)
    cap0 = engine.cap_states()
    engine.solve()
    v0, f0 = engine.node_voltages_pu(), _raw(engine)
    f_tap = one_step_each(engine, tap0, engine.reg_tap_max, engine.set_taps, lambda: _raw(engine), f0)
    engine.set_taps(tap0)
    both = one_step_each(engine, cap0, engine.cap_steps, engine.set_cap_states,
                         lambda: np.concatenate([engine.node_voltages_pu(), _raw(engine)]), np.concatenate([v0, f0]))
    dv_cap, f_cap = both[:v0.size], both[v0.size:]
    engine.set_cap_states(cap0)
    engine.solve()
    return Perturbations(dv_dcap_pu=dv_cap, feature_dtap=f_tap, feature_dcap=f_cap)


def reading_matrix(reg_pu: np.ndarray, cap_v_v: np.ndarray, cap_v_ref_v: np.ndarray) -> np.ndarray:
    """(F, R + C) readings as features: regulator readings [pu] then bank readings over their reference [pu]."""
    return np.concatenate([np.asarray(reg_pu, float), np.asarray(cap_v_v, float) / cap_v_ref_v], axis=-1)


def near_extreme_cover(v_pu: np.ndarray, eligible: np.ndarray, margin_pu: float) -> np.ndarray:
    """A small set of nodes that holds, in every flow, a node within ``margin_pu`` of its highest and its lowest.

    Beyond the paper (II.C takes only each flow's max and min node): with customer-level load diversity the
    extreme node changes from minute to minute among many secondaries, and out of sample the true extreme is
    often a node that was never *the* extreme in training. Greedy set cover, separately for the high and the low
    side: repeatedly take the node that is within ``margin_pu`` of the extreme in the most flows not yet covered.

    Parameters
    ----------
    v_pu : (F, n) node voltages of the training flows [pu].
    eligible : (n,) bool, nodes that may be chosen.
    margin_pu : how close to a flow's extreme a node must be to cover it [pu].

    Returns
    -------
    Sorted unique node indices.
    """
    v = np.asarray(v_pu)
    v = np.where(np.asarray(eligible, bool)[None, :], v if np.issubdtype(v.dtype, np.floating) else v.astype(float),
                 np.nan)
    chosen: set[int] = set()
    for near in (v >= np.nanmax(v, axis=1, keepdims=True) - margin_pu,
                 v <= np.nanmin(v, axis=1, keepdims=True) + margin_pu):
        open_rows = np.ones(near.shape[0], bool)
        while open_rows.any():
            counts = near[open_rows].sum(axis=0)
            best = int(np.argmax(counts))
            if counts[best] == 0:
                break
            chosen.add(best)
            open_rows &= ~near[:, best]
    return np.asarray(sorted(chosen), int)


def zone_extreme_cover(v_pu: np.ndarray, eligible: np.ndarray, upstream_of: np.ndarray, margin_pu: float) -> np.ndarray:
    """:func:`near_extreme_cover` within each regulator's zone: the nodes near each flow's highest and lowest *of
    the zone*, for every regulator.

    Beyond the paper: the feeder-wide cover sees the extremes of the states training made, where every regulator
    holds its zone in band. The controller then moves regulators apart (on IEEE 8500 in winter, case D put the
    feeder regulators 2-7 steps down and the downstream ones 5-10 up), and a zone whose regulator it lowers
    brings up a lowest node that was never the feeder's: under case D the lowest critical node sat 0.0128 pu
    (median) above the zone's lowest and all 199 violating nodes were non-critical. Covering each zone's own
    extremes gives the controller the node its move exposes.

    Parameters
    ----------
    v_pu : (F, n) node voltages of the training flows [pu].
    eligible : (n,) bool, nodes that may be chosen.
    upstream_of : (n,) int, each node's nearest upstream regulator (``training.critical.upstream_regulators``), -1
        for none.
    margin_pu : as for :func:`near_extreme_cover` [pu].

    Returns
    -------
    Sorted unique node indices (empty without regulators).
    """
    v = np.asarray(v_pu)
    chosen = [np.zeros(0, int)]
    for r in np.unique(upstream_of[upstream_of >= 0]):
        zone = np.flatnonzero(np.asarray(eligible, bool) & (upstream_of == r))
        if zone.size:
            chosen.append(zone[near_extreme_cover(v[:, zone], np.ones(zone.size, bool), margin_pu)])
    return np.unique(np.concatenate(chosen))


def device_shifted_voltages(
    v_pu: np.ndarray,
    dv_dtap_pu: np.ndarray,
    tap0: np.ndarray,
    tap_max: np.ndarray,
    dv_dcap_pu: np.ndarray | None = None,
    tap_shifts: tuple[int, ...] = TAP_SHIFTS,
    single_shifts: tuple[int, ...] = (),
) -> np.ndarray:
    """Training voltages as they would be at other taps and with each bank switched, by the static terms.

    Beyond the paper: the critical nodes are chosen among training flows at ``tap0`` and the banks as compiled, but
    the extreme node depends on which regulator zone is boosted and which bank is closed. Each flow is repeated with
    every regulator moved by each of ``tap_shifts`` (clipped to its range), then with one regulator at a time moved
    by each of ``single_shifts`` (when there are several), and with each bank one step switched either way, by
    eq. (4)'s ``dv_dtap`` and the banks' ``dv_dcap`` (linear, first order).

    Parameters
    ----------
    v_pu : (F, n) flows' voltages [pu]. dv_dtap_pu : (n, R) [pu/step]. tap0, tap_max : (R,) int.
    dv_dcap_pu : (n, C) [pu per closed step], or None (no banks).
    tap_shifts : offsets from ``tap0`` applied to every regulator at once [steps].

    Returns
    -------
    ((1 + len(tap_shifts) + R len(single_shifts) + 2 C) F, n) float32 voltages [pu]: the flows themselves
    first (the single shifts only when R > 1).
    """
    v = np.asarray(v_pu, np.float32)
    d_tap = np.asarray(dv_dtap_pu, np.float32)
    t0 = np.asarray(tap0, int)
    out = [v]
    if d_tap.shape[1]:
        for s in tap_shifts:
            delta = np.clip(t0 + s, -np.asarray(tap_max), np.asarray(tap_max)) - t0
            out.append(v + (d_tap @ delta.astype(np.float32))[None, :])
    if d_tap.shape[1] > 1:
        for r in range(d_tap.shape[1]):
            for s in single_shifts:
                step = int(np.clip(t0[r] + s, -tap_max[r], tap_max[r]) - t0[r])
                out.append(v + step * d_tap[None, :, r])
    if dv_dcap_pu is not None:
        d_cap = np.asarray(dv_dcap_pu, np.float32)
        for c in range(d_cap.shape[1]):
            out += [v + d_cap[None, :, c], v - d_cap[None, :, c]]
    return np.concatenate(out, axis=0)
