"""Estimation error of a recorded run with and without the capacitor-bank terms of the estimate.

Reads one run folder of ``cvvc evaluate``/``cvvc run`` (``session.mcap`` and ``model.json``): for every decision,
the estimates it carries against the truth frame of the same step (critical nodes), and the same estimates
with the bank terms taken out again (``regression.capbanks``: the banks' kvar added back to the head's Q and
``dv_dcap @ (C - C0)``), as the estimator would have given them without them. Offline; no bus, no OpenDSS.

Run ``python -m benchmarks.cap_estimate RUN_FOLDER [RUN_FOLDER ...]``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from mcap.reader import make_reader

from regression.capbanks import bank_voltage_pu, head_q_at_training_banks
from regression.model import ModelArrays, read_model
from schemas import messages as m
from schemas.bus import codec_for
from schemas.truth import TruthArrays, decode_truth

__all__ = ["estimate_errors", "main"]


def _read(run: Path) -> tuple[dict[int, m.Decision], dict[int, TruthArrays], dict[int, dict[str, int]], list[str]]:
    """Decisions by the step they answer, truth frames and bank states by time, and the truth's node names."""
    decisions: dict[int, m.Decision] = {}
    truth: dict[int, TruthArrays] = {}
    banks: dict[int, dict[str, int]] = {}
    node_names: list[str] = []
    dec, cap = codec_for(m.Decision), codec_for(m.CapFrame)
    with (run / "session.mcap").open("rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
            topic = channel.topic
            if topic.endswith("/agent/decision"):
                d = dec.decode(message.data)
                decisions[d.step_t_ns] = d
            elif topic.endswith("/sim/truth"):
                tr = decode_truth(message.data, channel.message_encoding)
                truth[tr.t_ns] = tr
                node_names = node_names or list(tr.node_names or [])
            elif "/meas/cap/" in topic:
                c = cap.decode(message.data)
                banks.setdefault(c.t_ns, {})[c.capacitor_id] = c.closed_steps
    return decisions, truth, banks, node_names


def estimate_errors(run: Path) -> dict[str, tuple[float, float, float]]:
    """``{"with": (rmse, max, share within 0.01), "without": (...)}`` of the critical-node estimates [pu]."""
    model = read_model(run / "model.json")
    arrays = ModelArrays.of(model)
    ids = [c.id for c in model.capacitors]
    decisions, truth, banks, node_names = _read(run)
    err: dict[str, list[np.ndarray]] = {"with": [], "without": []}
    index = {n: i for i, n in enumerate(node_names)}
    for t, d in sorted(decisions.items()):
        tr = truth.get(t)
        if tr is None or not d.estimates or any(i not in banks.get(t, {}) for i in ids):
            continue
        v = np.asarray(tr.v_pu)[[index[e.node] for e in d.estimates]]
        est = np.array([e.v_pu for e in d.estimates])
        closed = np.array([banks[t][i] for i in ids])
        dq = head_q_at_training_banks(arrays, np.zeros(3), closed)
        head_q = [model.feature_names.index(f"head_q_kvar_{p}") for p in "abc"]
        without = est - bank_voltage_pu(arrays, closed) - arrays.alpha[:, head_q] @ dq
        err["with"].append(est - v)
        err["without"].append(without - v)
    out = {}
    for k, parts in err.items():
        e = np.concatenate(parts) if parts else np.zeros(0)
        out[k] = (float(np.sqrt(np.mean(e**2))), float(np.max(np.abs(e))), float(np.mean(np.abs(e) <= 0.01))) \
            if e.size else (float("nan"),) * 3
    return out


def main(argv: list[str] | None = None) -> int:
    """Print the table for the run folders of ``argv`` (default: ``sys.argv[1:]``); 2 without any."""
    runs = [Path(a) for a in (sys.argv[1:] if argv is None else argv)]
    if not runs:
        print(__doc__.strip().splitlines()[-1], file=sys.stderr)
        return 2
    print("| run | bank terms | RMSE [pu] | max [pu] | within ±0.01 pu |\n|---|---|---|---|---|")
    for run in runs:
        for k, (rmse, mx, within) in estimate_errors(run).items():
            print(f"| {run.name} | {k} | {rmse:.4f} | {mx:.4f} | {100 * within:.2f} % |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
