"""Motion models for the box particle filter (thesis ch. 3).

Every particle carries the 8-tuple state of thesis eq. 3.1 as one row of an
``[N, 8]`` float32 array, in centre form and pixels per frame::

    (cx, cy, vx, vy, w, h, vw, vh)        # x, y, x', y', w, h, w', h'

All models share that layout (fixed-size models keep ``vw = vh = 0`` and never
change ``w, h``), and one signature::

    model(key, particles [N, 8], previous [N, 8], tau [8], motion: MotionParams)
        -> particles [N, 8]

``previous`` is each particle's own state one frame earlier (resampled together
with it), which the second-order models need. Noise is ``n_i = tau_i N(0, 1)``
(thesis eq. 3.13) with the thesis's ``tau = (10, 10, 1, 1, 0.1, 0.1, 0.1, 0.1)`` available as
``THESIS_TAU`` (thesis 3.3.1) and a tuned ``DEFAULT_TAU``.

Models
------
``ar1``          8-tuple first-order AR, thesis eqs. 3.14-3.17 (the printed
                 matrix 3.11 is a typo; the equations are used).
``ar1_fixed``    4-tuple (x, y, x', y') first-order AR with fixed box size,
                 thesis eqs. 3.21-3.23.
``ar2``          8-tuple second-order model s_t = s + A'(s - s_prev) + n,
                 thesis eqs. 3.25-3.28, with A' of eq. 3.26 applied blockwise to
                 (x, y, x', y') and (w, h, w', h').
``ar2_fixed``    the same on the 4-tuple (fixed size).
``random_walk``  s_t = s_{t-1} + n on (x, y, w, h), no velocity (thesis eq. 3.33).

Hierarchical (motion-guided) sampling, thesis 2.2 and 3.4, eqs. 3.30-3.32
--------------------------------------------------------------------------
The thesis's idea: put more particles along the previous direction of motion,
and let the box size change with motion towards/away from the camera (image y)
rather than with motion across it (image x). Eqs. 3.31-3.32 add
``a (x')^-1 + b (y')`` with ``a, b ~ N(1, 1)`` to ``w'`` and ``h'``; taken
literally this divides by a velocity that is often zero. Our reading, in a
numerically safe form:

* Position noise is anisotropic in each particle's own motion frame. With speed
  ``s = |(x', y')|``, direction ``e`` and normal ``e_perp``, the position noise
  is ``tau_x * (g(s) n_along e + n_across e_perp / g(s))`` with
  ``g(s) = 1 + guide_gain * s / (s + guide_speed)``: a stationary particle
  gets the isotropic noise of ``ar1``; a moving one spreads up to
  ``1 + guide_gain`` times further along its motion and proportionally less
  across it (the covered area stays the same, so the particles are
  *redistributed*, not added).
* Size-velocity noise is scaled by ``(1 + size_gain_y * |y'|) /
  (1 + size_gain_x * |x'|)``: the bounded, never-dividing-by-zero form of
  ``a (x')^-1 + b (y')`` — size changes are likelier when the box moves along y
  and less likely when it moves fast along x.
* Size hold (``size_hold`` h in [0, 1], default 0): the thesis's other half of
  the idea, "more particles ... in the expected direction of the velocity vector
  but fewer samples associated with the width and height changes" when the box
  moves across the image. A guided particle's inherited size velocity
  ``(w', h')`` is multiplied by ``1 - h (1 - min(r, 1))`` before the step, with
  ``r`` the size-noise scale above: a box moving fast along x keeps its size
  (and stops carrying a stale size velocity); a particle at rest or moving
  mostly along y (``r >= 1``) is unaffected. The velocities are each particle's
  own, noise included, so around a standing person the guided share's size
  velocities are damped too. Under the thesis's undamped AR1 the size
  velocity is a random walk, and on a walk across the image the box's width
  and height drift to 0.1-2.8 and 0.2-2.2 of the person's (walk_across_fast,
  N = 50); the guided share then keeps the sizes that fit. The colour filter's
  default is h = 1 (``cpf_jax.colour``); the RGB-D filter keeps 0 (its
  importance weights use the proposal's closed-form density, which assumes it).
  ``size_hold`` is tuned unconstrained and clipped to [0, 1] here.
* A fraction ``1 - guided_fraction`` of the particles keeps the plain ``ar1``
  noise, so the population never loses its isotropic diversity.

Size noise (all models): the width and height noises are correlated with
``motion.size_correlation`` (0: the thesis's independent noise) and the width's
is scaled by the box's aspect / 0.41, so a box mostly grows or shrinks as a
whole, as a person's does when the distance to the camera changes.

Guidance applies on top of ``ar1`` or ``ar1_fixed`` (the models the thesis
used it with), and to ``random_walk`` when the caller passes ``guide``, the
target's estimated velocity ``[2]`` (the colour filter's smoothed estimate
motion): the random walk has no velocity of its own, so the guided share of its
particles drifts by ``guide`` and takes the position noise above with ``guide``
as its motion (sizes diffuse as before). The rest diffuse around where they
were, so a walker who stops or turns round keeps particles on him, which the
ar1 velocity does not. Without ``guide`` the random walk is unguided.

Damped size velocity (all models): ``size_velocity_decay`` (default 1, the
thesis's models) multiplies the new state's size velocities ``(w', h')`` after
the step, so they follow ``w'_t = decay (w'_{t-1} + n)``: a first-order AR
velocity instead of a random walk. A cloud that was shrinking with a narrowing
silhouette then stops shrinking after it instead of keeping its inherited
velocity. The filters pass their ``params.size_velocity_decay`` (0.9). In
``ar2`` the same two columns of the state are multiplied (eq. 3.26 reads them
through ``s - s_prev``). Models without size velocities (``random_walk`` and
the ``_fixed`` ones keep them at 0) are unaffected.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .kernels import fastrand

__all__ = [
    "THESIS_TAU",
    "DEFAULT_TAU",
    "MODELS",
    "SIZE_VELOCITY_MODELS",
    "RNGS",
    "MotionParams",
    "guide_frame",
    "propagate",
]

# thesis 3.3.1: tau1 = tau2 = 10, tau3 = tau4 = 1, tau5..tau8 = 0.1
THESIS_TAU = (10.0, 10.0, 1.0, 1.0, 0.1, 0.1, 0.1, 0.1)
# The library's default (for a 200 px tall box, see ColourConfig.tau_height):
# found by a random search on synthetic training scenes (scene seeds 100-103,
# never used in the reported tables). The thesis's 0.1 px size noise cannot
# follow a person walking towards the camera or changing lanes.
DEFAULT_TAU = (15.0, 15.0, 0.6, 0.6, 5.5, 5.5, 0.8, 0.8)

MODELS = ("ar1", "ar1_fixed", "ar2", "ar2_fixed", "random_walk")
#: The models whose state carries a size velocity ``(w', h')`` (``size_velocity_decay``
#: acts on these; the others keep it at 0).
SIZE_VELOCITY_MODELS = ("ar1", "ar2")

#: Generators of the motion noise: "jax" (``jax.random``, threefry) or "hash"
#: (``kernels.fastrand``: one threefry call for two seeds, then a counter hash;
#: about 3x cheaper for the bulk draw, same keys-in, numbers-out contract).
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
        # Counter-based: the columns cost only themselves.
        return fastrand.normal, fastrand.uniform
    raise ValueError(f"unknown rng {rng!r}; expected one of {RNGS}")


# thesis eq. 3.26, applied to (x, y, x', y') and to (w, h, w', h')
# (a NumPy constant: importing the library must not start a JAX backend, so that
# XLA_FLAGS and cpu_tuning.tune_malloc set after the import still take effect)
_A2 = np.array(
    [[0.5, 0.0, 0.5, 0.0], [0.0, 0.5, 0.0, 0.5], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]],
    np.float32,
)


class MotionParams(NamedTuple):
    """Continuous parameters of the hierarchical (motion-guided) proposal."""

    guided_fraction: Array  # share of particles that use the guided proposal, in [0, 1]
    guide_gain: Array  # maximal extra stretch along the motion direction (>= 0)
    guide_speed: Array  # speed (px/frame) at which half of the stretch is reached (> 0)
    size_gain_x: Array  # how strongly motion along x damps size-velocity noise (>= 0)
    size_gain_y: Array  # how strongly motion along y excites size-velocity noise (>= 0)
    # Correlation of the width and height noise (and of their velocities), in
    # [0, 1): a person's box mostly scales as a whole when the distance changes.
    size_correlation: Array = 0.0
    # How much a guided particle moving along x keeps its size (module docstring,
    # "Size hold"), in [0, 1]; 0: the size velocity is carried unchanged.
    size_hold: Array = 0.0


#: How each motion parameter is tuned by gradient (``cpf_jax.tuning`` bijectors), shared
#: by the colour and RGB-D filters' ``PARAM_CONSTRAINTS``. ``size_hold``: identity,
#: clipped to [0, 1] in ``propagate``, so the defaults on its bounds (colour 1, RGB-D 0)
#: can be tuned from.
MOTION_CONSTRAINTS = MotionParams(
    "sigmoid", "softplus", "softplus", "softplus", "softplus", "sigmoid", "identity"
)


def default_motion_params() -> MotionParams:
    f = jnp.float32
    return MotionParams(f(0.5), f(2.0), f(4.0), f(0.5), f(0.5), f(0.8), f(0.0))


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


def propagate(
    key: Array,
    particles: Array,
    previous: Array,
    tau: Array,
    motion: MotionParams,
    *,
    model: str = "ar1",
    hierarchical: bool = False,
    scale: Array | None = None,
    rng: str = "jax",
    guide: Array | None = None,
    size_velocity_decay: Array | float = 1.0,
) -> Array:
    """Draw the next particle states from the motion model; ``[N, 8] -> [N, 8]``.

    ``model``, ``hierarchical`` and ``rng`` (one of ``RNGS``) are static.
    ``guide`` (``[2]`` px/frame, optional): the target's estimated velocity, which
    guides the random walk under ``hierarchical`` (module docstring).
    ``scale`` (``[N]``, optional) multiplies every particle's noise, e.g. by
    its box size relative to a reference so that ``tau`` is expressed for a
    reference box. Sizes are not clipped here; the filter keeps them in range.
    ``size_velocity_decay`` (scalar, may be traced) multiplies the new size
    velocities ``(w', h')``; 1 (default) is the thesis's undamped model (module
    docstring, "Damped size velocity").
    """
    if model not in MODELS:
        raise ValueError(f"unknown motion model {model!r}; expected one of {MODELS}")
    normal, uniform = _draws(rng)
    k_noise, k_guide = jax.random.split(key)
    tau = jnp.asarray(tau, jnp.float32)
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
    return out.at[:, 6:8].multiply(jnp.asarray(size_velocity_decay, out.dtype))
