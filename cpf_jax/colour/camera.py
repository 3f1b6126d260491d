"""The colour layer's camera-motion stage: the whole image's shift since the last frame
(``kernels.motion``, phase correlation of downscaled grey frames) carried into the state
before the motion model runs.

A camera that pans or shakes moves the target with the whole scene; the random walk's
noise, sized for a walker's own motion, cannot follow a jump of tens of pixels. Moving
every particle, the particles' previous positions (so their velocities stay the target's
own) and the last estimate (so the guide measures the target's own displacement) by the
image's shift leaves the dynamics only the target's motion relative to the scene.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array

from cpf_jax.kernels import color
from cpf_jax.kernels.motion import downscale, phase_correlation

__all__ = ["DOWNSCALE", "CameraTrack", "camera_init", "camera_shift", "shift_state"]

#: Downscale factor of the grey frames the shift is measured on (``ColourConfig.camera_motion``):
#: 512 x 424 becomes 128 x 106, which resolves about a pixel of full-frame shift.
DOWNSCALE = 4


class CameraTrack(NamedTuple):
    previous: Array  # [H // f, W // f] float32 downscaled grey of the last frame
    shift: Array  # [2] (dx, dy) px: the image's shift at the last step


def _small(colour: Array, factor: int) -> Array:
    return downscale(color.grey(colour), factor)


def camera_init(factor: int | None, colour: Array) -> CameraTrack:
    """The first frame's downscaled grey image (a 1 x 1 placeholder without the stage)."""
    if factor is None:
        return CameraTrack(jnp.zeros((1, 1), jnp.float32), jnp.zeros(2, jnp.float32))
    return CameraTrack(_small(colour, factor), jnp.zeros(2, jnp.float32))


def camera_shift(factor: int, track: CameraTrack, colour: Array, min_peak: float) -> CameraTrack:
    """The image's shift from the last frame to ``colour`` in full-frame pixels (zero when
    the correlation peak is below ``min_peak``: no single shift explains the frames)."""
    small = _small(colour, factor)
    shift, peak = phase_correlation(track.previous, small)
    shift = jnp.where(peak >= min_peak, shift * factor, 0.0)
    return CameraTrack(small, shift.astype(jnp.float32))


def shift_state(state, shift: Array):
    """``state`` (a box filter's: ``cloud``, ``estimate``) with every particle, previous
    position and the estimate moved by ``shift`` (dx, dy)."""
    move = jnp.zeros(state.cloud.particles.shape[-1], jnp.float32).at[:2].set(shift)
    cloud = state.cloud._replace(
        particles=state.cloud.particles + move, previous=state.cloud.previous + move
    )
    estimate = state.estimate.at[:2].add(shift)
    return state._replace(cloud=cloud, estimate=estimate)
