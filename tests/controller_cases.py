"""The synthetic model's controllers and snapshots the controller's tests share."""

import dataclasses

import msgspec
import numpy as np

from agent.controller import CvvcController, MeasurementSnapshot
from benchmarks.synthetic import synthetic_model
from regression.estimator import estimate_voltages_pu
from regression.model import ModelArrays, features
from schemas.settings import PAPER_AGENT, AgentOptions

MODEL = synthetic_model(0)
ARRAYS = ModelArrays.of(MODEL)
K, R = len(MODEL.pv), len(MODEL.regulators)


def snapshot(
    t_ns: int = 0,
    *,
    head_p_kw: float = 800.0,
    pv_p_kw: float = 900.0,
    taps: np.ndarray | None = None,
    reading_error_pu: np.ndarray | None = None,
    **changes,
) -> MeasurementSnapshot:
    """A snapshot consistent with the model: regulator readings = estimate + ``reading_error_pu``."""
    taps = np.zeros(R, int) if taps is None else taps
    head_q = np.full(3, 200.0)
    pv_p, pv_q = np.full(K, pv_p_kw), np.zeros(K)
    v_hat = estimate_voltages_pu(ARRAYS, features(np.full(3, head_p_kw), head_q, pv_p, pv_q), taps)
    err = np.zeros(R) if reading_error_pu is None else reading_error_pu
    raw = (v_hat[ARRAYS.reg_secondary_node] + err) / ARRAYS.reg_pu_per_v120
    snap = MeasurementSnapshot(
        t_ns=t_ns,
        head_p_kw=np.full(3, head_p_kw),
        head_q_kvar=head_q,
        pv_p_kw=pv_p,
        pv_q_kvar=pv_q,
        pv_kva_available=np.full(K, 1200.0),
        pv_q_setpoint_kvar=np.full(K, np.nan),
        reg_v120=raw,
        reg_v120_compared=raw + 0.5,  # line-drop compensation
        reg_tap=taps,
        head_valid=True,
        pv_valid=np.ones(K, bool),
        reg_valid=np.ones(R, bool),
    )
    return dataclasses.replace(snap, **changes)


def controller_with(model, base: AgentOptions, kw: dict) -> CvvcController:
    """A controller in taps mode with the correction; ``kw``: ``mode``, ``correction``, ``meters`` or options set on
    top of ``base``."""
    own = {k: kw.pop(k) for k in ("mode", "correction", "meters") if k in kw}
    return CvvcController(model, msgspec.structs.replace(base, **kw), **{"mode": "taps", "correction": True, **own})


def controller(**kw) -> CvvcController:
    """The shipped controller (``schemas.settings.AgentOptions``' defaults), in taps mode with the correction."""
    return controller_with(MODEL, AgentOptions(), kw)


def paper_controller(model=MODEL, **kw) -> CvvcController:
    """The paper's controller (``PAPER_AGENT``: every option beyond the paper off) in taps mode with the correction;
    ``kw`` sets options on top."""
    return controller_with(model, PAPER_AGENT, kw)


HIGH = np.full(R, 0.01)  # regulator readings 1 % above the estimate: corrected estimate over 1.04 pu
