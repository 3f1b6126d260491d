"""Counter-based random numbers from an integer hash: the particle filter's bulk draws.

JAX's default generator (threefry-2x32, 20 rounds) is the right default for
keys and splitting, but its 20 rounds per word make bulk draws on a CPU (the
motion noise of 100,000 eight-dimensional particles is 800,000 normals) a large
share of a filter step. Here one threefry call turns the caller's key into two
32-bit seeds, and the bulk bits are a hash of the element's index:

    bits[i] = pcg(pcg(i ^ s0) + s1)

with ``pcg`` the PCG-RXS-M-XS output permutation applied to one LCG step
(the "pcg" hash of Jarzynski and Olano, "Hash Functions for GPU Rendering",
JCGT 2020, which they recommend for its quality per cost; the statistical
checks made here are in the tests named below). Every stage is a bijection of
32-bit words, so the ``2**32`` counters of one key give distinct words (no
collisions within a draw). The same few integer operations vectorise on CPU and
GPU; normals use the ``erf_inv`` transform of ``jax.random.normal``.

Keys behave as usual: the same key gives the same numbers, ``jax.random.split``
/ ``fold_in`` give independent streams (through the seeds), and everything
works under ``jit`` and ``vmap``. Draws are limited to ``2**32`` elements.
Quality tests: ``tests/test_fastrand.py`` (uniformity, normality, serial and
cross-stream correlation against NumPy/SciPy references).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax import Array, lax

__all__ = ["bits", "uniform", "normal"]


def _pcg(x: Array) -> Array:
    """PCG-RXS-M-XS 32-bit hash (one LCG step, then the output permutation)."""
    state = x * jnp.uint32(747796405) + jnp.uint32(2891336453)
    word = ((state >> ((state >> 28) + jnp.uint32(4))) ^ state) * jnp.uint32(277803737)
    return (word >> 22) ^ word


def bits(key: Array, shape: tuple[int, ...], columns: tuple[int, ...] | None = None) -> Array:
    """``uint32`` random words of ``shape`` from a JAX PRNG ``key`` (typed or raw).

    ``columns`` (static, optional): only these indices of the last axis, shape
    ``shape[:-1] + (len(columns),)``. The words are those of the full draw
    (``bits(key, shape)[..., columns]``: the same counters), at the cost of the
    columns drawn.
    """
    shape = tuple(int(s) for s in shape)
    size = math.prod(shape)
    if size > 2**32:
        raise ValueError(f"fastrand draws at most 2**32 numbers at once, asked for {size}")
    seeds = jax.random.bits(key, (2,), jnp.uint32)
    if columns is None:
        counter = lax.iota(jnp.uint32, size).reshape(shape)
    else:
        if not shape or not all(0 <= c < shape[-1] for c in columns):
            raise ValueError(f"columns {columns} must index the last axis of shape {shape}")
        rows = lax.iota(jnp.uint32, size // shape[-1]).reshape(shape[:-1] + (1,))
        counter = rows * jnp.uint32(shape[-1]) + jnp.asarray(columns, jnp.uint32)
    return _pcg(_pcg(counter ^ seeds[0]) + seeds[1])


def _odd_fraction(b: Array) -> Array:
    """Top 23 bits ``k`` -> ``(2k + 1)`` as float32 (exact: below ``2**24``)."""
    return ((b >> 9) * jnp.uint32(2) + jnp.uint32(1)).astype(jnp.int32).astype(jnp.float32)


def uniform(key: Array, shape: tuple[int, ...], minval: float = 0.0, maxval: float = 1.0) -> Array:
    """Float32 uniforms on ``(minval, maxval)``: ``minval + (maxval - minval) u`` with
    ``u = (2k + 1) / 2**24`` for a 23-bit ``k`` (``u`` is exact and never 0 or 1; after
    scaling, float rounding can reach an endpoint of a wide or offset interval)."""
    u = _odd_fraction(bits(key, shape)) * jnp.float32(2.0**-24)
    return minval + (maxval - minval) * u


def normal(key: Array, shape: tuple[int, ...], columns: tuple[int, ...] | None = None) -> Array:
    """Float32 standard normals ``sqrt(2) erfinv(v)`` of ``v = (2k + 1) / 2**23 - 1``, exact
    and inside ``(-1, 1)`` (the transform ``jax.random.normal`` uses; ``|z| < 5.4``).
    ``columns``: only these indices of the last axis, as in ``bits`` (the ``erf_inv`` is
    most of the cost)."""
    v = _odd_fraction(bits(key, shape, columns)) * jnp.float32(2.0**-23) - jnp.float32(1.0)
    return jnp.float32(math.sqrt(2.0)) * lax.erf_inv(v)
