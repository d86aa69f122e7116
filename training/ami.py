"""A few AMI meters at critical nodes: an explicit option of the accuracy report (not of the paper).

The paper's estimator (eq. (5)-(7)) sees only feeder-level measurements, so a critical node deep in a
240 V / 120 V customer secondary, whose voltage follows its own customer's load, keeps an error no
feeder-level measurement removes. This module is that option for the accuracy report (the live agent's is
``agent.ami``, same rule):

* placement, from training information only: the ``K`` critical nodes with the widest calibrated bounds
  (``upper_pu + lower_pu`` of ``CvvcModel.bounds``), ties broken by the lower critical-node index;
* meter model: meter ``i`` reads its node's true voltage at minutes ``t_r = 0, I, 2I, ...`` (``I`` the
  interval, counted from the first simulated minute) plus Gaussian noise of standard deviation
  ``noise_pu``; a reading is usable from minute ``t_r + latency`` on;
* estimate at a metered node at minute ``t``: ``v(t) = est(t) + (reading(t_r) - est(t_r))`` with ``est`` the
  corrected estimate (eq. (6)-(7)) and ``t_r`` the latest usable reading; before the first usable reading
  ``v(t) = est(t)``. It is computed as ``reading(t_r) + (est(t) - est(t_r))`` (the same value) so that a
  noiseless reading is reproduced exactly at ``t = t_r``. Unmetered nodes keep ``est``.
"""

from __future__ import annotations

import numpy as np

from training.errors import TrainingError

__all__ = ["AMI_SEED", "ami_estimate_v_pu", "ami_placement", "check_ami_options"]

AMI_SEED = 20260116  # fixed seed of the meters' noise: the report is reproducible


def ami_placement(upper_pu: np.ndarray, lower_pu: np.ndarray, meters: int) -> np.ndarray:
    """Indices (into the critical nodes) of the ``meters`` nodes with the widest calibrated bounds.

    Parameters
    ----------
    upper_pu, lower_pu : (N,) calibrated bounds of each critical node [pu on the node's base]
        (``CvvcModel.bounds``: the truth lies within ``[est - lower, est + upper]``).
    meters : how many meters, 0..N.

    Returns
    -------
    (meters,) int array, widest first; ties in the lower index first.
    """
    up, lo = np.asarray(upper_pu, float), np.asarray(lower_pu, float)
    if up.ndim != 1 or up.shape != lo.shape:
        raise TrainingError(f"bounds of shapes {up.shape} and {lo.shape}: expected two (N,) arrays")
    if not 0 <= meters <= up.size:
        raise TrainingError(
            f"{meters} AMI meters asked for, but the model has {up.size} critical nodes: choose 0..{up.size}"
        )
    return np.argsort(-(up + lo), kind="stable")[:meters].astype(int)


def check_ami_options(interval_min: int, noise_pu: float, latency_min: int) -> None:
    """Raise ``TrainingError`` unless interval >= 1 min, latency >= 0 min and noise a finite std >= 0 [pu]."""
    if interval_min < 1:
        raise TrainingError(f"AMI interval {interval_min} min: give at least 1 minute")
    if latency_min < 0:
        raise TrainingError(f"AMI latency {latency_min} min: give 0 or more minutes")
    if not (np.isfinite(noise_pu) and noise_pu >= 0):
        raise TrainingError(f"AMI noise {noise_pu} pu: give a finite standard deviation >= 0")


def ami_estimate_v_pu(
    est_pu: np.ndarray,
    true_pu: np.ndarray,
    *,
    interval_min: int,
    noise_pu: float,
    latency_min: int,
    seed: int = AMI_SEED,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Corrected estimates at metered nodes, shifted by the latest usable meter reading's residual.

    Parameters
    ----------
    est_pu : (T, K) corrected estimates (eq. (6)-(7)) at the K metered nodes, one row per consecutive minute [pu].
    true_pu : (T, K) true voltages at the same nodes and minutes (what the meters read) [pu].
    interval_min : minutes between readings (>= 1); readings at rows 0, I, 2I, ...
    noise_pu : standard deviation of the Gaussian reading noise [pu] (>= 0).
    latency_min : minutes from a reading to its use (>= 0).
    seed : seed of the noise. rng : draw the noise from this generator instead (a caller's run of windows).

    Returns
    -------
    (T, K) new array: ``reading(t_r) + (est(t) - est(t_r))`` where a reading is usable, ``est(t)`` before.
    """
    est, true = np.asarray(est_pu, float), np.asarray(true_pu, float)
    if est.ndim != 2 or est.shape != true.shape:
        raise TrainingError(f"estimates {est.shape} and truth {true.shape}: expected two (T, K) arrays")
    check_ami_options(interval_min, noise_pu, latency_min)
    t = np.arange(est.shape[0])
    read_rows = t[::interval_min]
    readings = true[read_rows].copy()
    if noise_pu > 0:
        readings += (np.random.default_rng(seed) if rng is None else rng).normal(0.0, noise_pu, size=readings.shape)
    out = est.copy()
    usable = t >= latency_min
    if not usable.any():
        return out
    k = (t[usable] - latency_min) // interval_min  # index of the latest usable reading
    r = read_rows[k]
    out[usable] = readings[k] + (est[usable] - est[r])
    return out
