"""Minimum-cost assignment (the Hungarian method) for the multi-object metrics.

NumPy, not JAX: the metrics run once per evaluated sequence on host arrays of any size,
and the assignment they need is exact (shortest augmenting paths with potentials, as in
Jonker and Volgenant 1987; O(n^2 m) for an n x m matrix, the inner loop vectorised).
"""

from __future__ import annotations

import numpy as np

__all__ = ["min_cost_assignment"]


def min_cost_assignment(cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(rows, cols)`` of a minimum-cost matching of ``cost [n, m]`` in which pairs with
    a non-finite cost are forbidden: as many pairs as can be matched, and of those the
    cheapest (forbidden pairs priced so that one never beats a match, as py-motmetrics
    does), forbidden pairs left out of the result. Rows sorted."""
    cost = np.asarray(cost, np.float64)
    if cost.size == 0:
        return np.zeros(0, int), np.zeros(0, int)
    valid = np.isfinite(cost)
    if not valid.any():
        return np.zeros(0, int), np.zeros(0, int)
    flip = cost.shape[0] > cost.shape[1]
    c = cost.T if flip else cost
    ok = valid.T if flip else valid
    r = min(c.shape)
    # One forbidden pair and r - 1 best pairs cost more than r worst ones.
    large = 2 * r * (np.abs(c[ok]).max() + 1) + 1
    rows_of_cols = _hungarian(np.where(ok, c, large))
    cols = np.flatnonzero(rows_of_cols >= 0)
    rows = rows_of_cols[cols]
    keep = ok[rows, cols]
    rows, cols = rows[keep], cols[keep]
    if flip:
        rows, cols = cols, rows
    order = np.argsort(rows)
    return rows[order], cols[order]


def _hungarian(a: np.ndarray) -> np.ndarray:
    """The row matched to each column of ``a [n, m]``, ``n <= m`` (-1: none), every row
    matched at the minimum total cost: one shortest augmenting path per row, with dual
    potentials ``u`` (rows) and ``v`` (columns) kept feasible."""
    n, m = a.shape
    u = np.zeros(n + 1)
    v = np.zeros(m + 1)
    match = np.zeros(m + 1, int)  # column j (1-based) -> row (1-based), 0: free
    way = np.zeros(m + 1, int)
    for i in range(1, n + 1):
        match[0] = i
        j0 = 0
        minv = np.full(m + 1, np.inf)
        used = np.zeros(m + 1, bool)
        while True:
            used[j0] = True
            i0 = match[j0]
            free = ~used[1:]
            cur = a[i0 - 1] - u[i0] - v[1:]
            better = free & (cur < minv[1:])
            minv[1:] = np.where(better, cur, minv[1:])
            way[1:] = np.where(better, j0, way[1:])
            j1 = 1 + int(np.argmin(np.where(free, minv[1:], np.inf)))
            delta = minv[j1]
            u[match[used]] += delta
            v[used] -= delta
            minv[~used] -= delta
            j0 = j1
            if match[j0] == 0:
                break
        while j0:
            j1 = way[j0]
            match[j0] = match[j1]
            j0 = j1
    return match[1:] - 1
