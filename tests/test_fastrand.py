"""cpf_jax.kernels.fastrand against SciPy's distributions, under jit and vmap.

The draws are deterministic per key, so every statistical threshold below is
checked on fixed keys (no flaky tests); the thresholds are ones a biased or
correlated generator fails (e.g. the raw counter, or a hash of it without the
seed, fails the serial and cross-stream tests).
"""

from __future__ import annotations

import jax
import numpy as np
import pytest
from scipy import stats

from cpf_jax.kernels import fastrand as fr

N = 200_000


def test_deterministic_and_keyed():
    k = jax.random.key(7)
    a = np.asarray(fr.bits(k, (1000,)))
    np.testing.assert_array_equal(a, np.asarray(fr.bits(k, (1000,))))
    b = np.asarray(fr.bits(jax.random.fold_in(k, 1), (1000,)))
    assert np.mean(a == b) < 0.01
    # raw uint32 keys work too
    np.testing.assert_array_equal(
        np.asarray(fr.bits(jax.random.PRNGKey(3), (10,))),
        np.asarray(fr.bits(jax.random.wrap_key_data(jax.random.PRNGKey(3)), (10,))),
    )


def test_jit_and_vmap_match_direct():
    keys = jax.random.split(jax.random.key(0), 3)
    direct = np.stack([np.asarray(fr.normal(k, (50, 8))) for k in keys])
    jitted = np.stack([np.asarray(jax.jit(fr.normal, static_argnums=1)(k, (50, 8))) for k in keys])
    mapped = np.asarray(jax.vmap(lambda k: fr.normal(k, (50, 8)))(keys))
    np.testing.assert_array_equal(direct, jitted)
    np.testing.assert_array_equal(direct, mapped)


def test_bits_are_distinct_within_a_draw():
    # every stage is a bijection of 32-bit words: no repeated word among 2^16
    b = np.asarray(fr.bits(jax.random.key(1), (1 << 16,)))
    assert len(np.unique(b)) == b.size


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_uniform_distribution(seed):
    u = np.asarray(fr.uniform(jax.random.key(seed), (N,)))
    assert u.dtype == np.float32
    assert u.min() > 0.0 and u.max() < 1.0
    assert stats.kstest(u, "uniform").pvalue > 1e-3
    assert abs(u.mean() - 0.5) < 4 * np.sqrt(1 / 12 / N)
    # equidistribution over 64 cells of consecutive pairs (serial test)
    pairs = (u[: N // 2 * 2].reshape(-1, 2) * 8).astype(int)
    counts = np.bincount(pairs[:, 0] * 8 + pairs[:, 1], minlength=64)
    assert stats.chisquare(counts).pvalue > 1e-3
    scaled = np.asarray(fr.uniform(jax.random.key(seed), (1000,), -2.0, 3.0))
    assert scaled.min() > -2.0 and scaled.max() < 3.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_normal_distribution(seed):
    z = np.asarray(fr.normal(jax.random.key(seed), (N,)))
    assert z.dtype == np.float32 and np.all(np.isfinite(z))
    assert stats.kstest(z, "norm").pvalue > 1e-3
    assert abs(z.mean()) < 4 / np.sqrt(N)
    assert abs(z.var() - 1.0) < 4 * np.sqrt(2 / N)
    tail = np.mean(np.abs(z) > 3.0)
    expected = 2 * stats.norm.sf(3.0)
    assert abs(tail - expected) < 4 * np.sqrt(expected / N)


def test_no_serial_or_cross_stream_correlation():
    key = jax.random.key(11)
    z = np.asarray(fr.normal(key, (N // 8, 8)))
    bound = 4 / np.sqrt(N // 8)
    # between the columns of a particle's noise vector
    c = np.corrcoef(z.T)
    assert np.max(np.abs(c - np.eye(8))) < bound
    # lag-1 along the flat stream
    flat = z.ravel()
    assert abs(np.corrcoef(flat[:-1], flat[1:])[0, 1]) < 4 / np.sqrt(flat.size)
    # between streams of split keys (same counters, different seeds)
    k1, k2 = jax.random.split(key)
    a = np.asarray(fr.normal(k1, (N,)))
    b = np.asarray(fr.normal(k2, (N,)))
    assert abs(np.corrcoef(a, b)[0, 1]) < 4 / np.sqrt(N)


def test_too_many_numbers_is_a_clear_error():
    with pytest.raises(ValueError, match="2\\*\\*32"):
        jax.eval_shape(lambda k: fr.bits(k, (1 << 17, 1 << 16)), jax.random.key(0))


@pytest.mark.parametrize(
    "shape,columns", [((50, 8), (0, 1, 4, 5)), ((3, 4, 6), (5, 2)), ((7, 1), (0,))]
)
def test_columns_are_those_of_the_full_draw(shape, columns):
    """``columns`` draws the full draw's numbers at those last-axis indices, under jit
    and vmap too; an index outside the last axis is a clear error."""
    key = jax.random.key(4)
    full_bits = np.asarray(fr.bits(key, shape))
    np.testing.assert_array_equal(np.asarray(fr.bits(key, shape, columns)), full_bits[..., columns])
    full = np.asarray(fr.normal(key, shape))
    some = jax.jit(fr.normal, static_argnums=(1, 2))(key, shape, columns)
    np.testing.assert_array_equal(np.asarray(some), full[..., columns])
    keys = jax.random.split(key, 2)
    mapped = np.asarray(jax.vmap(lambda k: fr.normal(k, shape, columns))(keys))
    np.testing.assert_array_equal(mapped[1], np.asarray(fr.normal(keys[1], shape))[..., columns])
    with pytest.raises(ValueError, match="columns"):
        fr.bits(key, shape, (shape[-1],))
