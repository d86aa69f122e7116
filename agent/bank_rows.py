"""Capacitor banks under their own local control, predicted: rows of the CVVC problem that keep the agent's actions
from making a bank switch that would not switch anyway (beyond the paper).

A bank on its ``CapControl`` switches on its own quantity ``x`` (a voltage, a current or a kvar flow, in the
control's unit, ``CapFrame.control_value``): a voltage control closes a step below its ON setting and opens above its
OFF setting, a current or kvar control the other way round. The agent's Q set points and taps move ``x`` by
``control_dq @ dQ + control_dtap @ dT`` (``training.capbanks.bank_controls``), so a decision that ignores the bank
can push it across a setting, and its switching then moves every voltage (the "fight": more switchings than with no
control, 1-minute dips the 10-minute metrics do not see). While ``x`` lies where the control would not switch, the
predicted ``x`` after the decision is kept there, ``BANK_MARGIN_SHARE`` of the ON-OFF gap inside each setting (or
half-way from ``x`` to the setting, if ``x`` is already closer); a bank whose control is about to switch anyway, one
the agent commands, or one without a reading gets a row that never binds.

Each row is a pseudo-node of the problem, scaled so that the ON-OFF gap spans ``ROW_SPAN_PU``, like a band of
voltages: ``u = 1 + ROW_SPAN_PU * (x - mid) / |on - off|``.

A kvar or current control with ``VoltOverride`` closes its bank below ``Vmin`` and opens it above ``Vmax`` whatever
its kvar; its kvar rule then often undoes the switching at once, and the override does it again: hunting (IEEE 8500,
first three October days of case D: one bank 59 switchings, 3 with no control, the agent holding its bus at 0.984 pu,
under its 0.9875 pu ``Vmin``, at night). Such a bank gets a second row, on the voltage its override tests (its bus
reading times ``override_per_v``, scaled the same way over ``Vmin..Vmax``): an open bank's kept ``OVERRIDE_MARGIN``
above ``Vmin``, a closed one's below ``Vmax``, always binding (a voltage already past the limit is brought back if
the actions can: the override would switch the bank again at every decision otherwise).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from regression.model import CapacitorInfo

__all__ = ["BANK_MARGIN_SHARE", "OVERRIDE_MARGIN", "ROW_SPAN_PU", "BankRows", "bank_row_names", "local_bank_rows",
           "predicted_banks"]

BANK_MARGIN_SHARE = 0.1  # of the ON-OFF gap, kept between the predicted quantity and a setting
ROW_SPAN_PU = 0.05  # the ON-OFF gap in the rows' scaled unit (a band of voltages' width)
OVERRIDE_MARGIN = 0.0025  # of the override's limit, kept between the tested voltage and it (18 V of 7,110 V)
_FREE = 10.0  # a limit that never binds, in the scaled unit


@dataclass(frozen=True)
class BankRows:
    """The rows of the predicted banks (B of them): scaled value now ``u0`` (B,), its sensitivities to the plants' Q
    ``du_dq`` (B, K) [1/kvar] and to the taps ``du_dtap`` (B, R + C) [1/step] (zero for the banks' own columns), and
    its limits ``lo``, ``hi`` (B,); ``binding`` (B,) marks the rows with a limit that can bind.
    """

    u0: np.ndarray
    du_dq: np.ndarray
    du_dtap: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    binding: np.ndarray


def predicted_banks(banks: Sequence[CapacitorInfo]) -> np.ndarray:
    """Indices of the banks whose local control the agent predicts (a voltage, current or kvar control)."""
    return np.array([c for c, b in enumerate(banks) if b.control_kind != "none" and b.control_on != b.control_off],
                    dtype=np.intp)


def bank_row_names(banks: Sequence[CapacitorInfo]) -> list[str]:
    """A name for each row of :func:`local_bank_rows`, in its order: ``bank <id>``, then ``bank <id> override``."""
    idx = predicted_banks(banks)
    return [f"bank {banks[c].id}" for c in idx] + [f"bank {banks[c].id} override" for c in _overridden(banks, idx)]


def _overridden(banks: Sequence[CapacitorInfo], idx: np.ndarray) -> list[int]:
    """The banks of ``idx`` whose control has a ``VoltOverride`` (their second rows, in this order)."""
    return [int(c) for c in idx if banks[c].override_vmin_v > 0]


def local_bank_rows(banks: Sequence[CapacitorInfo], value: np.ndarray, closed: np.ndarray, held: np.ndarray,
                    n_pv: int, n_reg: int, v_v: np.ndarray | None = None) -> BankRows:
    """The rows of every predicted bank (:func:`predicted_banks` order), then the override rows of those with a
    ``VoltOverride`` (same order).

    Parameters
    ----------
    banks : the model's banks (``CvvcModel.capacitors``).
    value : (C,) each bank's controlled quantity now, in its control's unit; NaN: unknown or not on local control.
    closed : (C,) closed steps of each bank now.
    held : (C,) bool, banks this decision may command (their local control does not act): no binding row.
    n_pv, n_reg : plants and regulators of the problem.
    v_v : (C,) each bank's bus reading [V] (``CapFrame.v_v``); NaN or absent: its override row is free.
    """
    idx = predicted_banks(banks)
    n_cap = len(banks)
    u0, lo, hi = np.ones(idx.size), np.full(idx.size, 1.0 - _FREE), np.full(idx.size, 1.0 + _FREE)
    du_dq, du_dtap = np.zeros((idx.size, n_pv)), np.zeros((idx.size, n_reg + n_cap))
    binding = np.zeros(idx.size, bool)
    for j, c in enumerate(idx):
        b = banks[c]
        on, off = b.control_on, b.control_off
        gain = ROW_SPAN_PU / abs(on - off)
        mid = 0.5 * (on + off)
        x = float(value[c]) if c < len(value) else float("nan")
        if np.isfinite(x):
            u0[j] = 1.0 + gain * (x - mid)
        du_dq[j, : len(b.control_dq)] = gain * np.asarray(b.control_dq, float)
        du_dtap[j, : len(b.control_dtap)] = gain * np.asarray(b.control_dtap, float)
        if not np.isfinite(x) or bool(held[c]):
            continue
        keep = _keep_between(b, x, int(closed[c]))
        if keep is None:  # the control switches on its own now, whatever the decision
            continue
        low, high = keep
        if np.isfinite(low):
            lo[j] = 1.0 + gain * (low - mid)
        if np.isfinite(high):
            hi[j] = 1.0 + gain * (high - mid)
        binding[j] = True
    rows = BankRows(u0=u0, du_dq=du_dq, du_dtap=du_dtap, lo=lo, hi=hi, binding=binding)
    v_v = np.zeros(0) if v_v is None else v_v
    over = [_override_row(banks[c], float(v_v[c]) if c < len(v_v) else float("nan"), int(closed[c]), bool(held[c]),
                          n_pv, n_reg + n_cap) for c in _overridden(banks, idx)]
    if not over:
        return rows
    return BankRows(**{f.name: np.concatenate([getattr(rows, f.name), *(getattr(o, f.name) for o in over)])
                       for f in dataclasses.fields(BankRows)})


def _override_row(bank: CapacitorInfo, v_v: float, closed: int, held: bool, n_pv: int, n_dev: int) -> BankRows:
    """The one row of ``bank``'s ``VoltOverride`` (see the module docstring); free when ``held`` or unread."""
    vmin, vmax = bank.override_vmin_v, bank.override_vmax_v
    gain, mid = ROW_SPAN_PU / (vmax - vmin), 0.5 * (vmin + vmax)
    du_dq, du_dtap = np.zeros((1, n_pv)), np.zeros((1, n_dev))
    du_dq[0, : len(bank.override_dq)] = gain * np.asarray(bank.override_dq, float)
    du_dtap[0, : len(bank.override_dtap)] = gain * np.asarray(bank.override_dtap, float)
    v = bank.override_per_v * v_v
    u0, lo, hi = np.ones(1), np.full(1, 1.0 - _FREE), np.full(1, 1.0 + _FREE)
    bind = bool(np.isfinite(v)) and not held
    if bind:
        u0[0] = 1.0 + gain * (v - mid)
        if closed < bank.steps:  # the override may close it
            lo[0] = 1.0 + gain * (vmin * (1.0 + OVERRIDE_MARGIN) - mid)
        if closed > 0:  # or open it
            hi[0] = 1.0 + gain * (vmax * (1.0 - OVERRIDE_MARGIN) - mid)
    return BankRows(u0=u0, du_dq=du_dq, du_dtap=du_dtap, lo=lo, hi=hi, binding=np.full(1, bind))


def _keep_between(bank: CapacitorInfo, x: float, closed: int) -> tuple[float, float] | None:
    """Where the controlled quantity must stay for the control not to switch, with the margin (half-way from ``x``
    to the setting where it is already inside the margin); None when it switches at ``x`` already.
    """
    on, off = bank.control_on, bank.control_off
    margin = BANK_MARGIN_SHARE * abs(on - off)
    can_close, can_open = closed < bank.steps, closed > 0
    if bank.control_kind == "voltage":  # low closes, high opens
        if (can_close and x < on) or (can_open and x > off):
            return None
        low = _limit(on, on + margin, x) if can_close else -np.inf
        high = _limit(off, off - margin, x) if can_open else np.inf
    else:  # current, kvar: high closes, low opens
        if (can_close and x > on) or (can_open and x < off):
            return None
        high = _limit(on, on - margin, x) if can_close else np.inf
        low = _limit(off, off + margin, x) if can_open else -np.inf
    return low, high


def _limit(setting: float, inner: float, x: float) -> float:
    """The limit ``inner`` (the setting less the margin), or half-way from ``x`` to the setting when ``x`` lies between
    the two already.
    """
    between = (setting < x < inner) or (inner < x < setting)
    return 0.5 * (x + setting) if between else inner
