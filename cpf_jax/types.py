"""Shared data types: one registered RGB-D frame, camera intrinsics, a filter."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
from jax import Array

__all__ = ["Frame", "Intrinsics", "Filter", "KINECT_V2_DEPTH", "memoised_build", "scan_filter"]


class Frame(NamedTuple):
    """One registered RGB-D frame.

    colour: ``[H, W, 3] uint8``, RGB order.
    depth: ``[H, W] uint16``, millimetres, 0 = missing. Colour-only sources
    give an all-zero depth of the same size.
    """

    colour: Array
    depth: Array


class Intrinsics(NamedTuple):
    """Pinhole intrinsics, 0-based pixel convention: ``u = fx * X / Z + cx``."""

    fx: float
    fy: float
    cx: float
    cy: float


# Kinect v2 depth camera, thesis Table 4.1 (512 x 424 depth image).
KINECT_V2_DEPTH = Intrinsics(fx=365.0, fy=365.0, cx=255.0, cy=205.0)


class Filter(NamedTuple):
    """A particle filter as a pure ``init`` / ``step`` pair (blackjax-style).

    ``init(params, key, frame, box) -> state``
    ``step(params, key, state, frame) -> (state, info)``

    ``params`` is a pytree of continuous (tunable) parameters; the static
    configuration is closed over by the builder that made the filter.
    """

    init: Callable[..., Any]
    step: Callable[..., Any]


#: How many filters (the most recently used configs) each ``memoised_build`` builder keeps.
BUILD_CACHE_SIZE = 32


def memoised_build(build: Callable[[Any], Filter]) -> Callable[[Any], Filter]:
    """A filter builder that returns the same ``Filter`` object for equal configs.

    JAX keys its trace, lowering and compile caches on the function object, so
    ``jax.jit(filt.step)`` of a filter built again from an equal config traces, lowers
    and compiles it again (a cascade step: tens of seconds on a laptop CPU; the disk
    cache saves only the compile), while the same ``step`` object reuses all of it.
    Every builder here is pure in its (frozen, hashable) config, so sharing the result
    is safe: a script that tracks recording after recording (``cpf-track``'s ``main``), a
    test suite building one config in many tests. (A new ``lambda`` around ``step`` is a
    new function: JAX traces it again.)
    ``build.cache_info()`` / ``build.cache_clear()`` as in ``functools.lru_cache``.
    """
    return functools.lru_cache(maxsize=BUILD_CACHE_SIZE)(build)


def scan_filter(filt: Filter, params: Any, key: Array, inputs: Any, *init_args: Any):
    """Run ``filt`` over ``inputs`` (a pytree with a leading time axis ``[T, ...]``) as one
    ``lax.scan``: ``filt.init(params, k, inputs[0], *init_args)``, then ``filt.step`` on
    ``inputs[1:]``, one key each (``key`` split into an init key and a run key).
    Returns ``(final_state, infos)`` with infos ``[T - 1, ...]``; works under ``jit``
    and ``vmap``. Every filter's ``track`` function is this with its own init arguments.
    """
    k_init, k_run = jax.random.split(key)
    first = jax.tree_util.tree_map(lambda x: x[0], inputs)
    rest = jax.tree_util.tree_map(lambda x: x[1:], inputs)
    state = filt.init(params, k_init, first, *init_args)
    keys = jax.random.split(k_run, jax.tree_util.tree_leaves(rest)[0].shape[0])

    def body(s, xs):
        k, x = xs
        return filt.step(params, k, s, x)

    return jax.lax.scan(body, state, (keys, rest))
