"""kernels.assignment.linear_assignment against SciPy and a brute force, plainly, under jit
and under vmap (tests/checks.check_kernel)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from checks import check_kernel
from scipy.optimize import linear_sum_assignment

from cpf_jax.kernels.assignment import linear_assignment


def _from_pairs(rows, cols, n, m):
    r2c = np.full(n, -1, np.int32)
    c2r = np.full(m, -1, np.int32)
    r2c[rows], c2r[cols] = cols, rows
    return r2c, c2r


def _scipy(cost):
    rows, cols = linear_sum_assignment(cost)
    return _from_pairs(rows, cols, *cost.shape)


def _brute(cost):
    """Every partial matching: the most allowed pairs, then the least cost."""
    n, m = cost.shape
    ok = np.isfinite(cost)
    best, best_key = ([], []), (0, 0.0)
    for k in range(1, min(n, m) + 1):
        for rows in itertools.combinations(range(n), k):
            for cols in itertools.permutations(range(m), k):
                if all(ok[r, c] for r, c in zip(rows, cols, strict=True)):
                    key = (k, -sum(cost[r, c] for r, c in zip(rows, cols, strict=True)))
                    if key > best_key:
                        best, best_key = (list(rows), list(cols)), key
    return _from_pairs(np.array(best[0], int), np.array(best[1], int), n, m)


def _kernel(cost):
    a = linear_assignment(cost)
    return a.row_to_col, a.col_to_row


@pytest.mark.parametrize("shape", [(4, 4), (3, 6), (6, 2), (1, 5), (7, 7)])
def test_linear_assignment_matches_scipy(shape):
    rng = np.random.default_rng(sum(shape))
    args = [rng.normal(size=shape).astype(np.float32) for _ in range(3)]
    check_kernel(_kernel, _scipy, args[:1], batch=[args[1:2], args[2:3]])


@pytest.mark.parametrize("shape", [(3, 3), (2, 4), (4, 3)])
def test_linear_assignment_forbidden_pairs_match_brute_force(shape):
    rng = np.random.default_rng(10 + sum(shape))
    cases = []
    for _ in range(3):
        c = rng.uniform(0, 5, size=shape).astype(np.float32)
        c[rng.uniform(size=shape) < 0.4] = np.inf
        cases.append(c)
    check_kernel(_kernel, _brute, cases[:1], batch=[cases[1:2], cases[2:3]])


def test_linear_assignment_many_random_matrices():
    import jax

    rng = np.random.default_rng(0)
    fn = jax.jit(_kernel)
    for _ in range(60):
        n, m = rng.integers(1, 6, 2)
        c = rng.uniform(-3, 3, size=(n, m)).astype(np.float32)
        c[rng.uniform(size=(n, m)) < 0.3] = np.inf
        got = [np.asarray(x) for x in fn(c)]
        want = _brute(c)
        # Equal cost and count (ties are possible only in measure zero, but be exact).
        for r2c in (got[0], want[0]):
            assert np.all(np.isfinite(c[np.flatnonzero(r2c >= 0), r2c[r2c >= 0]]))
        assert (got[0] >= 0).sum() == (want[0] >= 0).sum()
        cost = [c[np.flatnonzero(r >= 0), r[r >= 0]].sum() for r in (got[0], want[0])]
        np.testing.assert_allclose(cost[0], cost[1], rtol=1e-5, atol=1e-5)
        np.testing.assert_array_equal(got[1][got[0][got[0] >= 0]], np.flatnonzero(got[0] >= 0))


def test_linear_assignment_all_forbidden_and_empty():
    r2c, c2r = _kernel(np.full((3, 2), np.inf, np.float32))
    assert np.all(np.asarray(r2c) == -1) and np.all(np.asarray(c2r) == -1)
    r2c, c2r = _kernel(np.zeros((0, 3), np.float32))
    assert r2c.shape == (0,) and np.all(np.asarray(c2r) == -1)
