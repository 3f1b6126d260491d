"""Motion models of the box particle filters (thesis ch. 3).

Every particle carries the 8-tuple state of thesis eq. 3.1 as one row of an
``[N, 8]`` float32 array, in centre form and pixels per frame::

    (cx, cy, vx, vy, w, h, vw, vh)        # x, y, x', y', w, h, w', h'

All models share that layout (fixed-size models keep ``vw = vh = 0`` and never change
``w, h``) and one call, ``propagate(key, particles, previous, motion, model=...)``;
``previous`` is each particle one frame earlier (resampled with it), which the
second-order models need. Noise is ``n_i = tau_i N(0, 1)`` (thesis eq. 3.13).

Models
------
``ar1``          8-tuple first-order AR, thesis eqs. 3.14-3.17 (the printed matrix 3.11
                 is a typo; the equations are used).
``ar1_fixed``    4-tuple (x, y, x', y') first-order AR with fixed box size, eqs. 3.21-3.23.
``ar2``          8-tuple second-order model ``s_t = s + A'(s - s_prev) + n``, eqs.
                 3.25-3.28, with A' of eq. 3.26 applied blockwise to (x, y, x', y') and
                 (w, h, w', h').
``ar2_fixed``    the same on the 4-tuple (fixed size).
``random_walk``  ``s_t = s_{t-1} + n`` on (x, y, w, h), no velocity (eq. 3.33).

Motion-guided sampling (thesis 2.2 and 3.4, eqs. 3.30-3.32)
----------------------------------------------------------
The thesis puts more particles along the previous direction of motion and lets the box
size change with motion along image y (towards or away from the camera) rather than
along x. Eqs. 3.31-3.32 add ``a (x')^-1 + b (y')`` to ``w'`` and ``h'``, which divides by
a velocity that is often zero; we use a bounded form:

* a share ``guided_fraction`` of the particles takes position noise stretched along its
  own motion direction by ``g(s) = 1 + guide_gain s / (s + guide_speed)`` (speed ``s``)
  and shrunk across it by ``1 / g(s)``: the same area, redistributed;
* their size-velocity noise is scaled by ``(1 + size_gain_y |y'|) / (1 + size_gain_x
  |x'|)``, the never-dividing form of ``a (x')^-1 + b (y')``;
* ``size_hold`` h in [0, 1] multiplies a guided particle's inherited size velocity by
  ``1 - h (1 - min(r, 1))`` (``r`` the scale above): a box moving across the image keeps
  its size, the thesis's "fewer samples associated with the width and height changes".

Guidance applies to ``ar1`` and ``ar1_fixed``, and to ``random_walk`` when the caller
passes ``guide``, the target's estimated velocity: the guided share then drifts by it.

Size noise: the width and height noises are correlated by ``size_correlation`` and the
width's is scaled by the box's aspect / 0.41, so that a box grows or shrinks as a whole.
``size_velocity_decay`` multiplies the size velocities after each step: a first-order
AR velocity instead of the thesis's random walk (1 is the thesis's model).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .kernels import fastrand
from .params import P

__all__ = [
    "THESIS_TAU",
    "DEFAULT_TAU",
    "MODELS",
    "SIZE_VELOCITY_MODELS",
    "RNGS",
    "MotionParams",
    "MOTION",
    "guide_frame",
    "size_scale",
    "height_scale",
    "propagate",
]

#: Thesis 3.3.1: tau1 = tau2 = 10, tau3 = tau4 = 1, tau5..tau8 = 0.1.
THESIS_TAU = (10.0, 10.0, 1.0, 1.0, 0.1, 0.1, 0.1, 0.1)
#: The library's noise for a 200 px tall box (``ColourConfig.tau_height``), chosen on the
#: synthetic training scenes: the thesis's 0.1 px size noise cannot follow a person who
#: walks towards the camera.
DEFAULT_TAU = (15.0, 15.0, 0.6, 0.6, 5.5, 5.5, 0.8, 0.8)

MODELS = ("ar1", "ar1_fixed", "ar2", "ar2_fixed", "random_walk")
#: The models whose state carries a size velocity ``(w', h')``.
SIZE_VELOCITY_MODELS = ("ar1", "ar2")

#: Generators of the motion noise: "jax" (``jax.random``) or "hash" (``kernels.fastrand``,
#: a counter hash seeded by one threefry call: about 3x cheaper for the bulk draw).
RNGS = ("jax", "hash")


def _pick(x: Array, columns: tuple[int, ...] | None) -> Array:
    return x if columns is None else x[..., list(columns)]


def _draws(rng: str):
    """``(normal, uniform)`` samplers of an ``RNGS`` name: ``normal(key, shape, columns=None)``
    (``columns``: only those indices of the last axis, the numbers of the full draw) and
    ``uniform(key, shape)``."""
    if rng == "jax":
        return (
            lambda k, shape, columns=None: _pick(jax.random.normal(k, shape, jnp.float32), columns),
            lambda k, shape: jax.random.uniform(k, shape),
        )
    if rng == "hash":
        return fastrand.normal, fastrand.uniform
    raise ValueError(f"unknown rng {rng!r}; expected one of {RNGS}")


# Thesis eq. 3.26, applied to (x, y, x', y') and to (w, h, w', h'); a NumPy constant, so
# that importing the library starts no JAX backend.
_A2 = np.array(
    [[0.5, 0.0, 0.5, 0.0], [0.0, 0.5, 0.0, 0.5], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]],
    np.float32,
)


class MotionParams(NamedTuple):
    """Continuous parameters of the motion model and its motion-guided proposal."""

    tau: Array  # [8] noise scales (thesis eq. 3.13), for a box of ``tau_height`` px
    guided_fraction: Array  # share of particles that take the guided proposal, in [0, 1]
    guide_gain: Array  # largest extra stretch along the motion direction (>= 0)
    guide_speed: Array  # speed (px/frame) at which half of the stretch is reached (> 0)
    size_gain_x: Array  # how strongly motion along x damps size-velocity noise (>= 0)
    size_gain_y: Array  # how strongly motion along y excites size-velocity noise (>= 0)
    size_correlation: Array  # correlation of the width and height noise, in [0, 1)
    size_hold: Array  # how far a guided particle moving along x keeps its size, in [0, 1]
    size_velocity_decay: Array  # share of the size velocities kept per frame (1: thesis)


#: The library's motion parameters. ``size_hold`` is tuned unconstrained and clipped to
#: [0, 1] in ``propagate``, so that a default on a bound can be tuned from.
MOTION = MotionParams(
    tau=P(DEFAULT_TAU, "softplus"),
    guided_fraction=P(0.5, "sigmoid"),
    guide_gain=P(2.0, "softplus"),
    guide_speed=P(4.0, "softplus"),
    size_gain_x=P(0.5, "softplus"),
    size_gain_y=P(0.5, "softplus"),
    size_correlation=P(0.8, "sigmoid"),
    size_hold=P(0.0),
    size_velocity_decay=P(0.9, "sigmoid"),
)


def _ar1(particles: Array, noise: Array) -> Array:
    cx, cy, vx, vy, w, h, vw, vh = jnp.moveaxis(particles, -1, 0)
    n = jnp.moveaxis(noise, -1, 0)
    return jnp.stack(
        [
            cx + vx + n[0],
            cy + vy + n[1],
            vx + n[2],
            vy + n[3],
            w + vw + n[4],
            h + vh + n[5],
            vw + n[6],
            vh + n[7],
        ],
        axis=-1,
    )


def _ar2(particles: Array, previous: Array, noise: Array) -> Array:
    diff = particles - previous
    pos = particles[:, :4] + diff[:, :4] @ _A2.T
    size = particles[:, 4:] + diff[:, 4:] @ _A2.T
    return jnp.concatenate([pos, size], axis=-1) + noise


def guide_frame(vx: Array, vy: Array, motion: MotionParams) -> tuple[Array, Array, Array]:
    """Unit motion direction ``(ex, ey)`` and the guided proposal's stretch along it.

    Safe direction: a stationary particle gets an arbitrary (x-axis) frame, where
    the stretch is 1 anyway, so the guided noise is isotropic there. Shared by
    ``propagate`` and the closed-form proposal density of ``cpf_jax.rgbd``.
    """
    speed = jnp.sqrt(vx * vx + vy * vy)
    safe = speed > 1e-6
    ex = jnp.where(safe, vx / jnp.where(safe, speed, 1.0), 1.0)
    ey = jnp.where(safe, vy / jnp.where(safe, speed, 1.0), 0.0)
    stretch = 1.0 + motion.guide_gain * speed / (speed + motion.guide_speed)
    return ex, ey, stretch


def size_scale(vx: Array, vy: Array, motion: MotionParams) -> Array:
    """The guided proposal's size-velocity noise scale ``(1 + gy |y'|) / (1 + gx |x'|)``."""
    return (1.0 + motion.size_gain_y * jnp.abs(vy)) / (1.0 + motion.size_gain_x * jnp.abs(vx))


def _guided_noise(key: Array, particles: Array, noise: Array, motion: MotionParams, uniform):
    """Replace the position / size-velocity noise of guided particles (see module docstring)."""
    n = particles.shape[0]
    vx, vy = particles[:, 2], particles[:, 3]
    ex, ey, stretch = guide_frame(vx, vy, motion)
    # The noise is already scaled; stretch it along the motion direction.
    along = noise[:, 0] * stretch
    across = noise[:, 1] / stretch
    dx = along * ex - across * ey
    dy = along * ey + across * ex
    r = size_scale(vx, vy, motion)
    guided = noise.at[:, 0].set(dx).at[:, 1].set(dy)
    guided = guided.at[:, 6].multiply(r).at[:, 7].multiply(r)
    is_guided = uniform(key, (n,)) < motion.guided_fraction
    return jnp.where(is_guided[:, None], guided, noise), is_guided, r


def height_scale(particles: Array, tau_height: float | None) -> Array | None:
    """``[N]`` noise multipliers ``h / tau_height`` (``motion.tau`` holds for a box of
    ``tau_height`` px, so larger boxes move and grow proportionally more), or None for
    unscaled noise."""
    return None if tau_height is None else particles[:, 5] / tau_height


def propagate(
    key: Array,
    particles: Array,
    previous: Array,
    motion: MotionParams,
    *,
    model: str = "ar1",
    hierarchical: bool = False,
    scale: Array | None = None,
    rng: str = "jax",
    guide: Array | None = None,
) -> Array:
    """Draw the next particle states from the motion model; ``[N, 8] -> [N, 8]``.

    ``model``, ``hierarchical`` and ``rng`` (one of ``RNGS``) are static. ``scale [N]``
    (optional) multiplies every particle's noise, so that ``motion.tau`` holds for a
    reference box; ``guide [2]`` (px/frame, optional) is the target's estimated velocity,
    which guides the random walk under ``hierarchical``. Sizes are not clipped here.
    """
    if model not in MODELS:
        raise ValueError(f"unknown motion model {model!r}; expected one of {MODELS}")
    particles, previous = jnp.asarray(particles), jnp.asarray(previous)
    normal, uniform = _draws(rng)
    k_noise, k_guide = jax.random.split(key)
    tau = jnp.asarray(motion.tau, jnp.float32)
    if model == "random_walk":
        # Only positions and sizes move (the velocity columns are zeroed below): their
        # normals are the full draw's, the others are not drawn.
        n = particles.shape[0]
        zs = normal(k_noise, particles.shape, (0, 1, 4, 5))
        zero = jnp.zeros((n,), jnp.float32)
        z = jnp.stack([zs[:, 0], zs[:, 1], zero, zero, zs[:, 2], zs[:, 3], zero, zero], axis=1)
    else:
        z = normal(k_noise, particles.shape)
    # Correlated size noise: width noise = rho * (height's normal) + sqrt(1 - rho^2) * own,
    # scaled by the box's aspect so that w and h change in proportion.
    rho = jnp.clip(jnp.asarray(motion.size_correlation, jnp.float32), 0.0, 0.999)
    aspect = particles[:, 4] / jnp.maximum(particles[:, 5], 1e-3)
    mix = jnp.sqrt(1.0 - rho * rho)
    zw = (rho * z[:, 5] + mix * z[:, 4]) * jnp.where(rho > 0, aspect / 0.41, 1.0)
    zvw = (rho * z[:, 7] + mix * z[:, 6]) * jnp.where(rho > 0, aspect / 0.41, 1.0)
    z = z.at[:, 4].set(zw).at[:, 6].set(zvw)
    noise = z * tau
    if scale is not None:
        noise = noise * jnp.asarray(scale, jnp.float32)[:, None]
    fixed = model.endswith("_fixed")
    if fixed:
        noise = noise.at[:, 4:].set(0.0)
    if hierarchical and model in ("ar1", "ar1_fixed"):
        noise, is_guided, r = _guided_noise(k_guide, particles, noise, motion, uniform)
        if fixed:
            noise = noise.at[:, 4:].set(0.0)
        # Size hold: guided particles moving along x damp their inherited size velocity.
        hold = jnp.clip(jnp.asarray(motion.size_hold, jnp.float32), 0.0, 1.0)
        keep = jnp.where(is_guided, 1.0 - hold * (1.0 - jnp.minimum(r, 1.0)), 1.0)
        particles = particles.at[:, 6:8].multiply(keep[:, None])
    if model in ("ar1", "ar1_fixed"):
        out = _ar1(particles, noise)
    elif model in ("ar2", "ar2_fixed"):
        out = _ar2(particles, previous, noise)
    else:  # random walk: positions and sizes diffuse, velocities stay zero
        step = noise.at[:, 2:4].set(0.0).at[:, 6:8].set(0.0)
        if hierarchical and guide is not None:
            # Motion-guided random walk: the guided share drifts by the target's
            # estimated velocity, its position noise stretched along it.
            v = jnp.broadcast_to(jnp.asarray(guide, jnp.float32), (particles.shape[0], 2))
            moving = particles.at[:, 2:4].set(v)
            guided, is_guided, _ = _guided_noise(k_guide, moving, noise, motion, uniform)
            drift = jnp.where(is_guided[:, None], v, 0.0)
            step = step.at[:, :2].set(guided[:, :2] + drift)
        out = particles + step
        out = out.at[:, 2:4].set(0.0).at[:, 6:8].set(0.0)
    if fixed:
        out = out.at[:, 4:6].set(particles[:, 4:6]).at[:, 6:8].set(0.0)
    return out.at[:, 6:8].multiply(jnp.asarray(motion.size_velocity_decay, out.dtype))
