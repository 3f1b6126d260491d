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

#: A whitened correlation surface of ``n`` cells has RMS ``1 / sqrt(n)`` (Parseval); a peak
#: counts as a shift only above this many RMS, so that on a small frame (few cells) the
#: largest of the noise's values is not taken for the camera's motion.
NOISE_SIGMAS = 9.0


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


def _outside(shape: tuple[int, int], box: Array, factor: int, grow: float) -> Array:
    """``[h, w]`` 1 outside ``box`` (xywh, full-frame px) grown by ``grow`` of its size on
    every side, 0 inside, on the grid downscaled by ``factor``."""
    centre = (box[:2] + box[2:4] / 2) / factor
    half = box[2:4] * (0.5 + grow) / factor
    ys = jnp.arange(shape[0], dtype=jnp.float32) + 0.5
    xs = jnp.arange(shape[1], dtype=jnp.float32) + 0.5
    inside_y = jnp.abs(ys - centre[1]) <= half[1]
    inside_x = jnp.abs(xs - centre[0]) <= half[0]
    return 1.0 - (inside_y[:, None] & inside_x[None, :]).astype(jnp.float32)


def camera_shift(
    factor: int, track: CameraTrack, colour: Array, estimate: Array, min_peak: float
) -> CameraTrack:
    """The image's shift from the last frame to ``colour`` in full-frame pixels, measured
    on the scene around the target: the last ``estimate``'s box (xywh, grown by a quarter
    on every side) is blanked in both frames, so that a target large in the image does
    not pass its own motion off as the camera's. Zero when the correlation peak is below
    ``min_peak`` or within :data:`NOISE_SIGMAS` of the surface's noise floor: no single
    shift explains the frames."""
    small = _small(colour, factor)
    keep = _outside(small.shape, estimate, factor, 0.25)
    kept = jnp.maximum(jnp.sum(keep), 1.0)
    a = (track.previous - jnp.sum(track.previous * keep) / kept) * keep
    b = (small - jnp.sum(small * keep) / kept) * keep
    shift, peak = phase_correlation(a, b)
    floor = NOISE_SIGMAS / jnp.sqrt(jnp.float32(small.size))
    shift = jnp.where(peak >= jnp.maximum(min_peak, floor), shift * factor, 0.0)
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
