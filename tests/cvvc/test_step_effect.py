"""Each regulator's tap step against the model, measured from truth frames (``cvvc.step_effect``)."""

from __future__ import annotations

import numpy as np
import pytest

from cvvc.step_effect import TapStepAccumulator, tap_steps_text

MINUTE_NS = 60_000_000_000
NODES = ["src.1", "a.1", "b.1", "c.1"]  # the truth's order; a, b, c the critical nodes
CRITICAL = ["a.1", "b.1", "c.1"]
# the model's change per step up of regulator r1 (column 0) and r2 (column 1) at a, b, c [pu/step]
DV_DTAP = np.array([[0.006, 0.0], [0.005, 0.0], [0.001, 0.007]])


def _run(frames: list[tuple[list[int], float, list[float], list[int]]], share: dict[str, float]) -> TapStepAccumulator:
    """Truth frames one minute apart: ``(taps, trend [pu], plants' Q [kvar], banks)``; every node follows the trend
    (a load ramp, 0.002 pu a minute) plus ``share`` of the model's change for each step taken so far."""
    acc = TapStepAccumulator(NODES, CRITICAL, DV_DTAP, ["r1", "r2"])
    taps0 = np.array(frames[0][0])
    for i, (taps, trend, q, caps) in enumerate(frames):
        d = np.array(taps) - taps0
        v = np.full(4, 1.0 - trend * i)
        v[1:] += DV_DTAP @ (d * np.array([share["r1"], share["r2"]]))
        acc.add(i * MINUTE_NS, v, np.array(taps), np.array(q), np.array(caps))
    return acc


def test_a_single_step_is_measured_as_a_share_of_the_model_with_the_trend_taken_out():
    still = ([0, 0], 0.002, [0.0], [1])
    frames = [still, still, ([1, 0], 0.002, [0.0], [1]), ([1, 0], 0.002, [0.0], [1]),
              ([1, 0], 0.002, [0.0], [1]), ([1, -1], 0.002, [0.0], [1])]
    effects = {e.regulator: e for e in _run(frames, {"r1": 0.8, "r2": 1.1}).result()}
    assert effects["r1"].steps == 1 and effects["r1"].share_of_model == pytest.approx(0.8, abs=1e-9)
    assert effects["r2"].steps == 1 and effects["r2"].share_of_model == pytest.approx(1.1, abs=1e-9)
    # r1 reaches a and b (c moves 1/6 of a), r2 only c: the trend (0.002 pu a minute, as large as a step) is not in it
    text = tap_steps_text(tuple(effects.values()))
    assert "r1 0.80 (1 step)" in text and "r2 1.10 (1 step)" in text


def test_steps_the_truth_cannot_tell_apart_are_not_measured():
    still = ([0, 0], 0.002, [0.0], [1])
    cases = {
        "two regulators in one minute": [still, still, ([1, 1], 0.002, [0.0], [1])],
        "two steps in one minute": [still, still, ([2, 0], 0.002, [0.0], [1])],
        "a plant's Q moved with the step": [still, still, ([1, 0], 0.002, [50.0], [1])],
        "a bank switched with the step": [still, still, ([1, 0], 0.002, [0.0], [0])],
        "the minute before was not still": [still, ([0, 1], 0.002, [0.0], [1]), ([1, 1], 0.002, [0.0], [1])],
        "a step after the first frame only": [still, ([1, 0], 0.002, [0.0], [1])],
    }
    for why, frames in cases.items():
        assert _run(frames, {"r1": 0.8, "r2": 1.0}).result() == (), why


def test_a_gap_in_the_truth_is_not_a_minute():
    acc = TapStepAccumulator(NODES, CRITICAL, DV_DTAP, ["r1", "r2"])
    v = np.ones(4)
    acc.add(0, v, np.array([0, 0]), np.zeros(1), np.ones(1, int))
    acc.add(MINUTE_NS, v, np.array([0, 0]), np.zeros(1), np.ones(1, int))
    stepped = v.copy()
    stepped[1:] += DV_DTAP[:, 0]
    acc.add(5 * MINUTE_NS, stepped, np.array([1, 0]), np.zeros(1), np.ones(1, int))  # four minutes lost before it
    assert acc.result() == ()
