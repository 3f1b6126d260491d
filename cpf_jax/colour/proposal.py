"""The colour layer's proposal: the motion model, the re-draws of a lost target, and the
bounds that keep every box countable (inside the frame, and inside the histogram window).

Particles are ``[N, 8]`` rows of the ``cpf_jax.dynamics`` state layout, in pixels.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array

from cpf_jax.colour.config import ColourConfig
from cpf_jax.dynamics import MotionParams, height_scale, propagate

__all__ = ["clamp", "contain", "recovery_draw", "propose"]


def clamp(config: ColourConfig, particles: Array, width: int, height: int) -> Array:
    """Centres inside the frame and sides in ``[min_size, frame size]``; velocities free."""
    inf, m = jnp.inf, config.min_size
    lo = jnp.array([0.0, 0.0, -inf, -inf, m, m, -inf, -inf], jnp.float32)
    hi = jnp.array([width, height, inf, inf, width, height, inf, inf], jnp.float32)
    return jnp.clip(particles, lo, hi)


def contain(
    config: ColourConfig,
    particles: Array,
    log_weights: Array,
    lost: Array,
    width: int,
    height: int,
) -> tuple[Array, Array]:
    """Place the histogram window on the cloud's weighted mean and keep the boxes inside it
    (one pixel of slack for corner rounding); returns ``(particles, origin (oy, ox))``.

    A window edge on the frame's edge does not bound the boxes (the part of a box beyond
    the frame is not counted anyway), and a lost target's frame-wide search is left free.
    """
    particles = jnp.asarray(particles)
    wh, ww = min(config.window[0], height), min(config.window[1], width)
    w = jax.nn.softmax(log_weights)
    mean = w @ particles[:, :2]
    ox = jnp.clip(jnp.round(mean[0] - ww / 2), 0, width - ww)
    oy = jnp.clip(jnp.round(mean[1] - wh / 2), 0, height - wh)
    half = particles[:, 4:6] / 2 + 1.0
    lo = jnp.where(jnp.stack([ox, oy]) > 0, jnp.stack([ox, oy]) + half, -jnp.inf)
    far = jnp.stack([ox + ww, oy + wh])
    hi = jnp.where(far < jnp.array([width, height]), far - half, jnp.inf)
    inside = jnp.where(lo <= hi, jnp.clip(particles[:, :2], lo, hi), particles[:, :2])
    kept = particles.at[:, :2].set(inside)
    particles = jnp.where(lost, particles, kept)
    return particles, jnp.stack([oy, ox]).astype(jnp.int32)


def recovery_draw(
    config: ColourConfig,
    key: Array,
    particles: Array,
    estimate: Array,
    size0: Array,
    width: int,
    height: int,
) -> Array:
    """Re-draw a share ``recovery_fraction`` of the particles of a lost target: half
    uniformly over the frame, half around the last estimate (a collapsed cloud still sits
    on the person), all at the initial box's size +-20 % (the automatic re-initialisation
    of thesis 3.5)."""
    n = particles.shape[0]
    k1, k2, k3, k4 = jax.random.split(key, 4)
    redraw = jax.random.uniform(k1, (n,)) < config.recovery_fraction
    anywhere = jax.random.uniform(k2, (n, 2)) * jnp.array([width, height], jnp.float32)
    z = jax.random.normal(k3, (n, 3))
    centre = estimate[:2] + estimate[2:4] / 2
    nearby = centre + 0.25 * size0 * z[:, :2]
    near = jax.random.uniform(k4, (n,)) < 0.5
    centres = jnp.where(near[:, None], nearby, anywhere)
    sizes = size0 * jnp.exp(0.2 * z[:, 2:3])
    fresh = jnp.concatenate([centres, jnp.zeros((n, 2)), sizes, jnp.zeros((n, 2))], axis=1)
    return jnp.where(redraw[:, None], fresh, particles)


def propose(
    config: ColourConfig,
    motion: MotionParams,
    keys: tuple[Array, Array],
    state,
    width: int,
    height: int,
) -> tuple[Array, Array | None]:
    """New particles ``[N, 8]`` and the histogram window's origin (None without one).

    The motion model with noise scaled by each particle's height over ``tau_height`` and
    the random walk guided by the estimate's velocity; re-draws while the target is lost
    (a ``lax.cond``: only a lost frame pays for them); then ``clamp`` and ``contain``.
    ``keys``: the motion key and the re-draw key.
    """
    k_prop, k_rec = keys
    cloud = state.cloud
    particles = propagate(
        k_prop,
        cloud.particles,
        cloud.previous,
        motion,
        model=config.model,
        hierarchical=config.hierarchical,
        scale=height_scale(cloud.particles, config.tau_height),
        rng=config.rng,
        guide=state.guide.velocity if config.hierarchical else None,
    )
    if config.recovery_fraction > 0:
        particles = jax.lax.cond(
            state.lost,
            lambda p: recovery_draw(config, k_rec, p, state.estimate, state.size0, width, height),
            lambda p: p,
            particles,
        )
    particles = clamp(config, particles, width, height)
    origin = None
    if config.window is not None and config.contain:
        particles, origin = contain(config, particles, cloud.log_weights, state.lost, width, height)
    return particles, origin
