"""Calibrated estimate bounds: conformal, on held-out minutes of the training year.

After the regressions are fitted, the feeder is simulated (QSTS, regulators on local control, PV at unity power
factor) over windows of the training year that no training scenario used: one per month, the hour of day moving
through the day (four seasonal windows under-covered: 4.0 % of January's node-minutes outside 1 % bounds on the rural
feeder, against 0.6 % with twelve). The corrected estimate (eq. 5-7, as the agent computes it) of every critical
node is compared with OpenDSS's voltage, minute by minute, and the bounds are conformal quantiles of those errors
(``training.conformal``): each node's errors scaled by its own RMS error and pooled over the nodes, at the one-sided
level at which bounds computed without a window miss at most ``alpha`` of that window's node-minutes:

    upper[n] = scale[n] * q_level((true - estimate) / scale)   over every node and minute   (0 at least)
    lower[n] = scale[n] * q_level((estimate - true) / scale)

so ``[estimate - lower, estimate + upper]`` holds the true voltage in at least ``1 - alpha`` of a window's
node-minutes the bounds did not see. ``cvvc report accuracy`` reports the realised rate on another year, every run
the rate live. The agent tightens each critical node's limits by its bounds (``agent.controller``), and widens them
when its inputs leave the training envelope.

Calibration sees the tap states the agent creates: in every other window each regulator's local set point is moved by
a whole number of its tap steps, drawn uniformly within ``±setpoint_offset_taps`` (seeded), so its taps rest away from
where local control keeps them, as they do under the agent's set points. Calibrated on local control alone, the
bounds missed 10.7 % of IEEE 8500's node-decisions in a day of case D (the nodes between the substation and the line
regulators estimated 0.002 pu high with the line regulators' taps 1.5-6.4 steps from local control's), against 2.3 %
on the same day under local control (docs/method.md, "Bounds in closed loop").

The same minutes give each node's bounds when an AMI meter reads it every 15 minutes (explicit option,
``agent.ami``): the quantiles of ``err(t) - err(r) - noise`` with ``r`` the latest reading before ``t``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from regression.model import CvvcModel, EstimateBounds, ModelArrays
from training.ami import ami_estimate_v_pu
from training.conformal import pooled_bounds

__all__ = [
    "AMI_INTERVAL_S", "CALIBRATION_WINDOWS", "CalibrationResiduals", "ami_residual", "calibrate_bounds",
    "calibration_residuals", "envelope",
]

#: (month, day, local hour) of the calibration windows: one per month, the hour moving through the day.
CALIBRATION_WINDOWS = tuple((month, 10 + month, (5 + 2 * month) % 24) for month in range(1, 13))
_WARMUP_MIN = 30  # minutes simulated and dropped before each window: the regulators settle from training's taps
_ENVELOPE_SLACK = 0.05  # the envelope is the training range widened by this share of it on each side
#: AMI bounds (explicit option, ``agent.ami``): a reading every 15 minutes, revenue-meter noise (0.1 %), seeded.
AMI_INTERVAL_S = 900
AMI_NOISE_PU = 0.001
AMI_NOISE_SEED = 20261127
SETPOINT_OFFSET_TAPS = 8  # the largest set-point offset of a calibration window, in tap steps (0: local control only)
# (chosen on IEEE 8500, case D, 1 July, estimates of the live recording re-judged: 10.7 % of node-decisions outside the
# bounds with 0, 5.9 % with 4, 3.1 % with 8; median bound 0.0031 -> 0.0034 -> 0.0043 pu below)
_SETPOINT_SEED = 20261128


def envelope(features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of each feature over ``features`` (F, M), widened by 5 % of its range on each side."""
    lo, hi = features.min(axis=0), features.max(axis=0)
    pad = _ENVELOPE_SLACK * np.maximum(hi - lo, 1e-9)
    return lo - pad, hi + pad


class CalibrationResiduals(NamedTuple):
    """The calibration minutes' errors ``true - corrected estimate`` [pu] at the critical nodes.

    ``err`` (T, N); ``window`` (T,) the calibration window of each row (rows of one window are correlated);
    ``ami`` (T', N) the same after an AMI reading's correction (``ami_residual``), ``ami_window`` (T',) theirs.
    """

    err: np.ndarray
    window: np.ndarray
    ami: np.ndarray
    ami_window: np.ndarray


def calibration_residuals(model: CvvcModel, engine, profiles, *, training_steps: np.ndarray, minutes: int = 1440,
                          progress: bool = False,
                          setpoint_offset_taps: int = SETPOINT_OFFSET_TAPS) -> CalibrationResiduals:
    """Simulate the calibration windows (module docstring) and return the corrected estimates' errors.

    Parameters as :func:`calibrate_bounds`.
    """
    from simulator_bridge.simulation.profiles import month_steps
    from training.accuracy import simulate_month

    per_window = max(1, int(minutes) // len(CALIBRATION_WINDOWS))
    names = {n: i for i, n in enumerate(engine.node_names)}
    nodes = np.asarray([names[c.name] for c in model.critical_nodes], int)
    arrays = ModelArrays.of(model)
    held_out = set(np.asarray(training_steps, int).tolist())
    residuals, windows, ami_residuals, ami_windows = [], [], [], []
    rng = np.random.default_rng(AMI_NOISE_SEED)
    offsets = _setpoint_offsets_v120(model, len(CALIBRATION_WINDOWS), setpoint_offset_taps)
    for w, (month, day, hour) in enumerate(CALIBRATION_WINDOWS):
        first = month_steps(profiles, month).start + (day - 1) * 1440 + hour * 60
        steps = range(first - _WARMUP_MIN, min(first + per_window, profiles.n_steps))
        truth = simulate_month(engine, profiles, steps, nodes, sens_minutes=0, progress=progress,
                               setpoint_offset_v120=offsets[w])
        keep = np.array([s >= first and s not in held_out for s in truth.steps])
        est = truth.corrected_estimate(arrays)  # row by row: the warm-up rows too
        err = truth.v_pu - est
        residuals.append(err[keep])
        windows.append(np.full(int(keep.sum()), w, int))
        ami_residuals.append(ami_residual(err, truth.t_ns, keep, AMI_INTERVAL_S, AMI_NOISE_PU, rng))
        ami_windows.append(np.full(ami_residuals[-1].shape[0], w, int))
    return CalibrationResiduals(err=np.concatenate(residuals), window=np.concatenate(windows),
                                ami=np.concatenate(ami_residuals), ami_window=np.concatenate(ami_windows))


def calibrate_bounds(model: CvvcModel, engine, profiles, *, training_steps: np.ndarray,
                     training_features: np.ndarray, minutes: int = 1440, alpha: float = 0.01,
                     progress: bool = False, setpoint_offset_taps: int = SETPOINT_OFFSET_TAPS) -> EstimateBounds:
    """The bounds of ``model``'s corrected estimates, calibrated on ``minutes`` held-out minutes of ``profiles``.

    Parameters
    ----------
    model : the model just trained (critical nodes, regressions).
    engine : the training ``FeederEngine`` (its taps are the starting point of each window's local control).
    profiles : the training year.
    training_steps : the steps the training scenarios used: left out of the calibration.
    training_features : (F, M) features of the training power flows (the envelope).
    minutes : calibration minutes in all, split over the windows of :data:`CALIBRATION_WINDOWS`.
    alpha : miscoverage of the two-sided interval (0 < alpha < 1).
    setpoint_offset_taps : every other window moves each regulator's set point by up to this many of its tap steps
        (module docstring); 0: every window under local control at the default set points.
    """
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha {alpha} must be in (0, 1)")
    res = calibration_residuals(model, engine, profiles, training_steps=training_steps, minutes=minutes,
                                progress=progress, setpoint_offset_taps=setpoint_offset_taps)
    lo, hi = envelope(np.asarray(training_features, float))
    b = pooled_bounds(res.err, res.window, alpha)
    ami = pooled_bounds(res.ami, res.ami_window, alpha) if res.ami.shape[0] else None
    return EstimateBounds(
        alpha=float(alpha),
        upper_pu=[float(x) for x in b.upper],
        lower_pu=[float(x) for x in b.lower],
        calibration_minutes=int(res.err.shape[0]),
        envelope_lo=[float(x) for x in lo],
        envelope_hi=[float(x) for x in hi],
        level=b.level,
        held_out_miss=b.held_out_miss,
        ami_interval_s=AMI_INTERVAL_S if ami is not None else 0,
        ami_upper_pu=[] if ami is None else [float(x) for x in ami.upper],
        ami_lower_pu=[] if ami is None else [float(x) for x in ami.lower],
    )


def _setpoint_offsets_v120(model: CvvcModel, windows: int, max_taps: int) -> list[np.ndarray | None]:
    """Per window, the regulators' set-point offsets [V on 120 V]: None (local control as configured) in even
    windows, whole tap steps uniform in ``±max_taps`` in odd ones (seeded: the same model trains the same bounds).
    """
    if max_taps < 0:
        raise ValueError(f"setpoint_offset_taps {max_taps} must be >= 0")
    steps = np.array([r.step_v120 for r in model.regulators], float)
    rng = np.random.default_rng(_SETPOINT_SEED)
    out: list[np.ndarray | None] = []
    for w in range(windows):
        taps = rng.integers(-max_taps, max_taps + 1, steps.size)  # drawn every window: the sequence does not shift
        out.append(taps * steps if w % 2 and max_taps and steps.size else None)
    return out


def ami_residual(err: np.ndarray, t_ns: np.ndarray, keep: np.ndarray, interval_s: int, noise_pu: float,
                 rng: np.random.Generator) -> np.ndarray:
    """Errors (true - estimate) of the ``keep`` rows after an AMI reading's correction (``agent.ami``).

    ``err`` (T, N) over consecutive minutes at ``t_ns`` (T,). A meter reads at the minutes whose time is a multiple
    of ``interval_s``, with Gaussian noise ``noise_pu``; a kept row ``t`` is corrected by the latest reading strictly
    before it (the agent may not have a reading of its own minute yet): ``err(t) - err(r) - noise(r)``. Kept rows
    without an earlier reading in the window are left out. The rule is ``training.ami.ami_estimate_v_pu``'s (the
    accuracy report's) with a minute of latency, from the window's first reading on.
    """
    read = np.flatnonzero((np.asarray(t_ns, np.int64) // 1_000_000_000) % interval_s == 0)
    if read.size == 0:
        return np.zeros((0, err.shape[1]))
    first = int(read[0])
    # estimate 0 and truth err: the shifted estimate is err(r) + noise(r), so err - shifted is the residual
    shifted = ami_estimate_v_pu(np.zeros_like(err[first:]), err[first:], interval_min=interval_s // 60,
                                noise_pu=noise_pu, latency_min=1, rng=rng)
    rows = np.flatnonzero(keep)
    rows = rows[rows > first]
    return err[rows] - shifted[rows - first]
