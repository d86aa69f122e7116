"""How a dense constraint matrix's rows go to DAQP: single-entry rows as variable bounds, the others as rows.

It depends on the matrix alone, so a problem solved many times with one matrix (the rounding's tap-fixed re-solves)
splits it once (``agent.cvvc_qp.CvvcQp.dense_split``) and ``agent.solve.active_set.solve_dense_qp`` takes it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["DenseSplit", "dense_split"]


@dataclass(frozen=True)
class DenseSplit:
    """How ``solve_dense_qp`` hands a matrix's rows to DAQP, which depends on the matrix alone.

    ``bound_rows``: the rows that become variable bounds (one per variable at most: a single non-zero entry, in
    column ``column`` with value ``coef``); ``general``: the other rows, whose copy ``a_rows`` DAQP takes;
    ``order``: the rows in that order (the bound rows, then the others); ``rows_of``: DAQP's constraint index of each
    row of ``order`` (a bound row's is its column's, the others follow the ``n`` bounds).
    """

    bound_rows: np.ndarray
    general: np.ndarray
    column: np.ndarray
    coef: np.ndarray
    order: np.ndarray
    rows_of: np.ndarray
    a_rows: np.ndarray


def dense_split(a: np.ndarray) -> DenseSplit:
    """The ``DenseSplit`` of the (m, n) matrix ``a``: one single-entry row per variable becomes a simple bound
    (scaled by its entry), the first one where a variable has several; the others stay rows.
    """
    n = a.shape[1]
    nonzero = a != 0.0
    single = nonzero.sum(axis=1) == 1
    singles = single.nonzero()[0]
    column = nonzero[singles].argmax(axis=1)  # the variable of each single-entry row
    if singles.size and np.bincount(column, minlength=n).max() > 1:  # a variable with two: its first row is the bound
        _, first = np.unique(column, return_index=True)
        is_bound = np.zeros(a.shape[0], bool)
        is_bound[singles[first]] = True
        bound_rows, general = is_bound.nonzero()[0], (~is_bound).nonzero()[0]
        column = nonzero[bound_rows].argmax(axis=1)
    else:
        bound_rows, general = singles, (~single).nonzero()[0]
    a_rows = np.array(a[general], float)  # writable: DAQP's interface takes no read-only buffer (it only reads it)
    return DenseSplit(bound_rows=bound_rows, general=general, column=column, coef=a[bound_rows, column],
                      order=np.concatenate([bound_rows, general]),
                      rows_of=np.concatenate([column, n + np.arange(general.size)]), a_rows=a_rows)
