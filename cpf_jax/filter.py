"""The one shape of every filter: ``Filter(init, step)``, run over a sequence by ``track``.

Every builder (``build_colour_filter``, ``build_rgbd_filter``, ``build_point_filter``,
``build_cascade``) takes a frozen config and returns a :class:`Filter`::

    state = filt.init(params, key, frame, box, context)
    state, info = filt.step(params, key, state, frame)
    state, infos = track(filt, params, key, frames, box, context)   # one lax.scan

``params`` is the filter's tree of continuous parameters (``cpf_jax.params``), ``frame``
one observation (a :class:`~cpf_jax.types.Frame` for the box filters and the cascade,
a ``PointFrame`` for the point filter), ``box`` the initial ``(x, y, w, h)`` box and
``context`` a :class:`Context`: what a filter needs beyond the frame.

Every box filter's state holds its particle cloud as ``state.cloud`` (:class:`Cloud`),
and every box filter's info starts with the fields of ``BOX_INFO_FIELDS``: ``box`` (the
box to score, ``[4]`` xywh), ``lost``, ``ess``, ``log_evidence``, ``estimate`` and
``windowed``, then its own extras, the last of which is ``weighed_cloud``: the particles
after they are weighed and before they are resampled (:class:`WeighedCloud`) when the config's
``report_weights`` is on, else None.
The command line, the Rerun logger, the tuner and the batch runner read only these.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from cpf_jax.kernels import boxes as box_ops
from cpf_jax.kernels.background import Background

__all__ = [
    "BOX_INFO_FIELDS",
    "Filter",
    "Cloud",
    "WeighedCloud",
    "weighed_cloud",
    "Context",
    "at_rest",
    "uniform_cloud",
    "track",
    "track_boxes",
    "particle_boxes",
    "cloud_boxes",
    "memoised_build",
]

#: The fields every box filter's info starts with, in this order: the box to score
#: ``[4]`` xywh, whether the target is lost (no box to score), the effective sample size
#: before resampling, the log mean likelihood of the propagated particles, the state
#: estimate as a box (the weighted mean; the RGB-D filter's whole-body box), and whether
#: the particles' histograms came from the static window (False: the exact whole-frame
#: path ran, which is slower).
BOX_INFO_FIELDS = ("box", "lost", "ess", "log_evidence", "estimate", "windowed")


class Filter(NamedTuple):
    """A particle filter as a pure ``init`` / ``step`` pair (blackjax's ``SamplingAlgorithm``).

    ``init(params, key, frame, box, context=None) -> state``
    ``step(params, key, state, frame) -> (state, info)``

    The static configuration is closed over by the builder that made the filter.
    """

    init: Callable[..., Any]
    step: Callable[..., Any]


class Cloud(NamedTuple):
    """The weighted particles of a box filter, in the state layout of ``cpf_jax.dynamics``."""

    particles: Array  # [N, 8] (cx, cy, vx, vy, w, h, vw, vh), pixels and pixels per frame
    previous: Array  # [N, 8] each particle one frame earlier (second-order models)
    log_weights: Array  # [N] normalised


class WeighedCloud(NamedTuple):
    """A box filter's propagated particles and their weights before resampling, which
    resets the weights to uniform: what a viewer colours the particles by."""

    particles: Array  # [N, 8] as in Cloud
    log_weights: Array  # [N] normalised


def weighed_cloud(config: Any, particles: Array, log_weights: Array) -> WeighedCloud | None:
    """The info's ``weighed_cloud`` field: the particles and weights when ``config.report_weights``
    asks for them (an ``[N, 8]`` and an ``[N]`` array more per step), else None."""
    return WeighedCloud(particles, log_weights) if config.report_weights else None


class Context(NamedTuple):
    """What a filter needs beyond the frame; each filter reads the fields it documents.

    background: the scene without the target (``kernels.background.median_background``),
      read by the RGB-D filter and the cascade (None: every pixel counts as foreground).
    points: ``[P, 2]`` frame positions (box convention) of the body points layer 2 tracks.
    """

    background: Background | None = None
    points: Array | None = None


def at_rest(box_xywh: Array, n: int) -> Array:
    """``[n, 8]`` particles: ``n`` copies of one ``(x, y, w, h)`` box with zero velocities."""
    c = box_ops.xywh_to_cxcywh(box_xywh)
    one = jnp.array([c[0], c[1], 0.0, 0.0, c[2], c[3], 0.0, 0.0], jnp.float32)
    return jnp.tile(one, (n, 1))


def uniform_cloud(particles: Array) -> Cloud:
    """A cloud of ``particles [N, 8]`` with uniform weights, each its own previous state."""
    n = particles.shape[0]
    return Cloud(particles, particles, jnp.full((n,), -jnp.log(jnp.float32(n))))


def track(filt: Filter, params: Any, key: Array, frames: Any, box: Array, context=None):
    """Run ``filt`` over ``frames`` (a pytree with a leading time axis ``[T, ...]``) as one
    ``lax.scan``: ``init`` on ``frames[0]`` with ``box`` and ``context``, then ``step`` on
    ``frames[1:]``, one key each (``key`` split into an init key and a run key).

    Returns ``(final_state, infos)`` with ``infos`` of length ``T - 1``. Works under
    ``jit`` and ``vmap`` (over keys, parameters or sequences).
    """
    k_init, k_run = jax.random.split(key)
    first = jax.tree_util.tree_map(lambda x: x[0], frames)
    rest = jax.tree_util.tree_map(lambda x: x[1:], frames)
    state = filt.init(params, k_init, first, box, context)
    keys = jax.random.split(k_run, jax.tree_util.tree_leaves(rest)[0].shape[0])

    def body(s, xs):
        k, x = xs
        return filt.step(params, k, s, x)

    return jax.lax.scan(body, state, (keys, rest))


def track_boxes(
    filt: Filter, params: Any, key: Array, frames: Any, box: Array, context=None
) -> tuple[Array, Array]:
    """``([T, 4] boxes, [T] lost)`` of a box filter: the initial box (not lost), then every
    step's ``info.box`` and ``info.lost``."""
    _, infos = track(filt, params, key, frames, box, context)
    first = jnp.asarray(box, jnp.float32)[None]
    boxes = jnp.concatenate([first, infos.box], axis=0)
    lost = jnp.concatenate([jnp.zeros((1,), bool), infos.lost])
    return boxes, lost


def cloud_boxes(cloud: Cloud | WeighedCloud) -> tuple[Array, Array]:
    """``([N, 4] xywh boxes, [N] log-weights)`` of a particle cloud."""
    cols = jnp.array([0, 1, 4, 5])
    return box_ops.cxcywh_to_xywh(cloud.particles[:, cols]), cloud.log_weights


def particle_boxes(state: Any) -> tuple[Array, Array]:
    """``([N, 4] xywh boxes, [N] log-weights)`` of a box filter's particle cloud."""
    return cloud_boxes(state.cloud)


#: How many filters (the most recently used configs) each ``memoised_build`` builder keeps.
BUILD_CACHE_SIZE = 32


def memoised_build(build: Callable[[Any], Filter]) -> Callable[[Any], Filter]:
    """A filter builder that returns the same ``Filter`` object for equal configs.

    JAX keys its trace, lowering and compile caches on the function object, so the same
    ``step`` object reuses all of them while a filter built again from an equal config
    would be traced and compiled again. Builders are pure in their frozen, hashable
    config, so sharing the result is safe.
    """
    return functools.lru_cache(maxsize=BUILD_CACHE_SIZE)(build)
