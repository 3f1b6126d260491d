"""Does depth line up with colour? Edges of depth against edges of colour, over all shifts.

A depth image registered to its colour image has its jump edges (a person against the
wall behind him) where the colour image has edges too. When the registration is off (no
calibration, or the wrong one) the depth edges land a few pixels beside them, and every
pixel the RGB-D models read is the wrong one without any other sign.

Conventions (those of ``cpf_jax.types.Frame``): colour ``[H, W, 3] uint8`` RGB, depth
``[H, W]`` millimetres, 0 = missing. A shift ``(dx, dy)`` in pixels says that the
colour edge at ``(x + dx, y + dy)`` matches the depth edge at ``(x, y)``: ``dx = 11``
means that depth lies 11 px left of the colour.

* :func:`colour_edges`: the gradient magnitude of the grey image (central differences),
  scaled by its mean and clipped at 1, so that a textured wall does not outweigh a
  silhouette.
* :func:`depth_edges`: 1 on both pixels of a jump, where two neighbours (across or along)
  are both measured and differ by more than ``max(step_mm, step_rel * z)``, the foreground
  rule of ``kernels.background`` applied between neighbours; both sides, as the central
  differences of the colour edges, so that the scores peak at one shift, not two.
* :func:`shift_scores`: ``score[dy + S, dx + S] = sum_p D(p) C(p + (dx, dy)) / sum_p D(p)``
  for ``|dx|, |dy| <= S``, one zero-padded FFT cross-correlation for every shift at once.

Everything is static-shaped and works under ``jit`` and ``vmap`` (over frames).
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array

from . import color

__all__ = ["colour_edges", "depth_edges", "shift_scores", "edge_shift_scores"]

# A jump of at least this much between neighbours is an edge (the background rule's 150 mm
# is for frame against background; between neighbours a body's own relief is below this).
DEPTH_STEP_MM = 100.0
DEPTH_STEP_REL = 0.04


def colour_edges(colour: Array) -> Array:
    """``[H, W] float32`` in [0, 1]: grey gradient magnitude over three times its mean."""
    grey = color.grey(colour)
    gx = jnp.zeros_like(grey).at[:, 1:-1].set(grey[:, 2:] - grey[:, :-2])
    gy = jnp.zeros_like(grey).at[1:-1, :].set(grey[2:, :] - grey[:-2, :])
    mag = jnp.sqrt(gx * gx + gy * gy)
    return jnp.clip(mag / (3.0 * jnp.mean(mag) + 1e-6), 0.0, 1.0)


def depth_edges(
    depth: Array, step_mm: float = DEPTH_STEP_MM, step_rel: float = DEPTH_STEP_REL
) -> Array:
    """``[H, W] float32``, 1 on both pixels of each jump edge of measured depth."""
    z = jnp.asarray(depth, jnp.float32)

    def jump(a: Array, b: Array) -> Array:
        both = (a > 0) & (b > 0)
        return both & (jnp.abs(a - b) > jnp.maximum(step_mm, step_rel * jnp.minimum(a, b)))

    across = jump(z[:, :-1], z[:, 1:])  # [H, W - 1]: between x and x + 1
    along = jump(z[:-1, :], z[1:, :])  # [H - 1, W]: between y and y + 1
    edge = jnp.zeros(z.shape, bool)
    edge = edge.at[:, :-1].max(across).at[:, 1:].max(across)
    edge = edge.at[:-1, :].max(along).at[1:, :].max(along)
    return edge.astype(jnp.float32)


def shift_scores(colour_edge: Array, depth_edge: Array, max_shift: int) -> Array:
    """``[2S + 1, 2S + 1]`` mean colour edge under the depth edges moved by each shift
    (module docstring; 0 everywhere without depth edges)."""
    s = int(max_shift)
    h, w = depth_edge.shape
    shape = (h + s, w + s)  # zero padding: no shift wraps around
    fc = jnp.fft.rfft2(colour_edge, shape)
    fd = jnp.fft.rfft2(depth_edge, shape)
    corr = jnp.fft.irfft2(fc * jnp.conj(fd), shape)  # corr[k] = sum_p D(p) C(p + k)
    rows = jnp.arange(-s, s + 1) % shape[0]
    cols = jnp.arange(-s, s + 1) % shape[1]
    window = corr[rows[:, None], cols[None, :]]
    return window / jnp.maximum(jnp.sum(depth_edge), 1.0)


def edge_shift_scores(colour: Array, depth: Array, max_shift: int) -> Array:
    """:func:`shift_scores` of one frame's :func:`colour_edges` and :func:`depth_edges`."""
    return shift_scores(colour_edges(colour), depth_edges(depth), max_shift)
