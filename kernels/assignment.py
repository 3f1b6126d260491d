"""Minimum-cost assignment (linear sum assignment) in JAX, with static shapes.

:func:`linear_assignment` matches the rows of a cost matrix ``[n, m]`` to its columns at
the least total cost, as ``scipy.optimize.linear_sum_assignment`` does, inside ``jit``,
``vmap`` and ``lax.scan``: the matrix is padded to a square of side ``max(n, m)`` with
zero-cost dummy rows or columns, and the shortest-augmenting-path method with dual
potentials (Jonker and Volgenant 1987; the Hungarian method in the O(n^3) form) adds one
row at a time, each phase a ``lax.while_loop`` of at most ``max(n, m)`` Dijkstra steps
vectorised over the columns. Forbidden pairs are non-finite costs: they are priced so that
no assignment uses one while another exists with more allowed pairs (py-motmetrics'
rule), then dropped from the result. Costs are float32; the tracker's matrices are a few
slots by a few candidates.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

__all__ = ["Assignment", "linear_assignment"]


class Assignment(NamedTuple):
    row_to_col: Array  # [n] int32: the column matched to each row, -1 for none
    col_to_row: Array  # [m] int32: the row matched to each column, -1 for none


def _augment_row(a: Array, carry, i: Array):
    """Add row ``i`` (1-based) to the matching: Dijkstra over the columns with reduced
    costs ``a[r, j] - u[r] - v[j]``, then flip the alternating path it found."""
    u, v, match, way = carry
    size = a.shape[1]
    match = match.at[0].set(i)
    inf = jnp.float32(jnp.inf)

    def search(state):
        j0, minv, used, u, v, way = state
        used = used.at[j0].set(True)
        i0 = match[j0]
        cur = a[i0 - 1] - u[i0] - v[1:]  # [size]
        free = ~used[1:]
        better = free & (cur < minv[1:])
        minv = minv.at[1:].set(jnp.where(better, cur, minv[1:]))
        way = way.at[1:].set(jnp.where(better, j0, way[1:]))
        j1 = 1 + jnp.argmin(jnp.where(free, minv[1:], inf)).astype(jnp.int32)
        delta = minv[j1]
        # The used columns' rows are distinct; the other entries add nothing.
        u = u.at[match].add(jnp.where(used, delta, 0.0))
        v = v - jnp.where(used, delta, 0.0)
        minv = jnp.where(used, minv, minv - delta)
        return j1, minv, used, u, v, way

    def searching(state):
        return match[state[0]] != 0

    start = (
        jnp.int32(0),
        jnp.full((size + 1,), inf),
        jnp.zeros((size + 1,), bool),
        u,
        v,
        way,
    )
    # The first step always runs (column 0 holds the new row).
    j0, _, _, u, v, way = jax.lax.while_loop(searching, search, search(start))

    def flip(state):
        j0, match = state
        j1 = way[j0]
        return j1, match.at[j0].set(match[j1])

    _, match = jax.lax.while_loop(lambda s: s[0] != 0, flip, (j0, match))
    return u, v, match, way


def linear_assignment(cost: Array) -> Assignment:
    """The minimum-cost matching of ``cost [n, m]`` (module docstring): each row matched to
    at most one column and each column to at most one row, as many pairs as the allowed
    (finite) entries permit, and of those matchings the cheapest. Ties are broken
    arbitrarily; the total cost equals ``scipy.optimize.linear_sum_assignment``'s."""
    cost = jnp.asarray(cost, jnp.float32)
    n, m = cost.shape
    size = max(n, m)
    if n == 0 or m == 0:
        return Assignment(jnp.full((n,), -1, jnp.int32), jnp.full((m,), -1, jnp.int32))
    ok = jnp.isfinite(cost)
    finite = jnp.where(ok, cost, 0.0)
    # Any matching with a forbidden pair costs more than any with one allowed pair more.
    span = jnp.max(jnp.abs(finite)) + 1.0
    large = 2.0 * size * span + 1.0
    a = jnp.zeros((size, size), jnp.float32).at[:n, :m].set(jnp.where(ok, finite, large))
    carry = (
        jnp.zeros((size + 1,), jnp.float32),
        jnp.zeros((size + 1,), jnp.float32),
        jnp.zeros((size + 1,), jnp.int32),
        jnp.zeros((size + 1,), jnp.int32),
    )

    def body(i, carry):
        return _augment_row(a, carry, i + 1)

    _, _, match, _ = jax.lax.fori_loop(0, size, body, carry)
    row_of_col = match[1:] - 1  # [size]: the (padded) row matched to each column
    cols = jnp.arange(size, dtype=jnp.int32)
    real = (row_of_col < n) & (cols < m)
    allowed = real & ok[jnp.clip(row_of_col, 0, n - 1), jnp.clip(cols, 0, m - 1)]
    col_to_row = jnp.where(allowed, row_of_col, -1)[:m].astype(jnp.int32)
    row_to_col = (
        jnp.full((n,), -1, jnp.int32).at[jnp.where(allowed, row_of_col, n)].set(cols, mode="drop")
    )
    return Assignment(row_to_col, col_to_row)
