"""Globally best one-to-one links between two sets under a gate (sparse, by connected parts).

Each candidate pair ``(i, j)`` costs its squared normalised distance; leaving any member of either
set unlinked costs ``gate**2 / 2``, so a pair is only worth linking below the gate. The candidate
graph falls apart into small connected parts; a part with one pair is linked at once, the others
by the Hungarian method on the part alone (``scipy.optimize.linear_sum_assignment`` on the matrix
extended with the "unlinked" choices), so the cost grows with the number of particles, not its
square.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

_FORBIDDEN = 1e12


def assign(rows: np.ndarray, cols: np.ndarray, cost: np.ndarray, n_rows: int, n_cols: int, *,
           unlinked_cost: float) -> tuple[np.ndarray, np.ndarray]:
    """The links of least total cost.

    Parameters
    ----------
    rows, cols : ndarray of int, shape (e,)
        Candidate pairs (each pair at most once).
    cost : ndarray of shape (e,)
        Their costs (already gated: every pair is allowed).
    n_rows, n_cols : int
        Sizes of the two sets.
    unlinked_cost : float
        Cost of leaving one member unlinked.

    Returns
    -------
    linked_rows, linked_cols : ndarray of int
        The chosen pairs.

    Examples
    --------
    >>> r, c = assign(np.array([0, 0, 1]), np.array([0, 1, 0]), np.array([1.0, 2.0, 1.5]), 2, 2,
    ...               unlinked_cost=10.0)
    >>> sorted(zip(r.tolist(), c.tolist()))
    [(0, 1), (1, 0)]
    """
    rows, cols, cost = np.asarray(rows, np.int64), np.asarray(cols, np.int64), np.asarray(cost, float)
    worth = cost < 2 * unlinked_cost
    rows, cols, cost = rows[worth], cols[worth], cost[worth]
    if rows.size == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    graph = coo_matrix((np.ones(rows.size), (rows, n_rows + cols)), shape=(n_rows + n_cols,) * 2)
    _, label = connected_components(graph, directed=False)
    part = label[rows]
    order = np.argsort(part, kind="stable")
    rows, cols, cost, part = rows[order], cols[order], cost[order], part[order]
    starts = np.flatnonzero(np.r_[True, part[1:] != part[:-1]])
    sizes = np.diff(np.r_[starts, rows.size])
    single = starts[sizes == 1]
    out_rows, out_cols = [rows[single]], [cols[single]]
    for start, size in zip(starts[sizes > 1], sizes[sizes > 1]):
        r, c, w = rows[start:start + size], cols[start:start + size], cost[start:start + size]
        ur, ri = np.unique(r, return_inverse=True)
        uc, ci = np.unique(c, return_inverse=True)
        m, n = ur.size, uc.size
        # [[pairs, row unlinked], [column unlinked, 0]]: every member may stay unlinked.
        full = np.full((m + n, n + m), _FORBIDDEN)
        full[ri, ci] = w
        full[np.arange(m), n + np.arange(m)] = unlinked_cost
        full[m + np.arange(n), np.arange(n)] = unlinked_cost
        full[m:, n:] = 0.0
        a, b = linear_sum_assignment(full)
        keep = (a < m) & (b < n)
        out_rows.append(ur[a[keep]])
        out_cols.append(uc[b[keep]])
    return np.concatenate(out_rows), np.concatenate(out_cols)
