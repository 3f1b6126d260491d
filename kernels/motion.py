"""How the whole image moved between two frames: phase correlation of downscaled grey frames.

A camera that pans moves every pixel of the scene by about the same amount; the
normalised cross-power spectrum of two frames (Kuglin and Hines 1975) keeps only the
phase, whose inverse transform peaks at that shift whatever the scene's contrast. A Hann
window stops the image borders from voting for no motion, and a 3 x 3 centroid around the
peak gives sub-pixel precision.

Convention: ``shift = (dx, dy)`` pixels is how far the content moved from the first image
to the second, ``b(x, y) ~ a(x - dx, y - dy)`` (a camera panning right moves the scene
left: ``dx < 0``). Shifts up to half the image size are told apart (the correlation is
circular). Everything is static-shaped and works under ``jit`` and ``vmap``.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array

from . import color

__all__ = ["downscale", "phase_correlation", "frame_motion"]


def downscale(image: Array, factor: int) -> Array:
    """``[H // f, W // f]`` block means of ``image [H, W]`` (the remainder rows and columns
    dropped)."""
    f = int(factor)
    h, w = image.shape[0] // f, image.shape[1] // f
    blocks = jnp.asarray(image, jnp.float32)[: h * f, : w * f].reshape(h, f, w, f)
    return blocks.mean(axis=(1, 3))


def _hann(n: int) -> Array:
    return 0.5 - 0.5 * jnp.cos(2.0 * jnp.pi * jnp.arange(n) / n)


def phase_correlation(a: Array, b: Array) -> tuple[Array, Array]:
    """``(shift [2] (dx, dy), peak [])`` of ``b [h, w]`` against ``a [h, w]`` (module
    convention); ``peak`` in [0, 1] is the correlation at the shift, near 1 for a clean
    translation and near 0 without one."""
    h, w = a.shape
    window = _hann(h)[:, None] * _hann(w)[None, :]
    fa = jnp.fft.fft2(jnp.asarray(a, jnp.float32) * window)
    fb = jnp.fft.fft2(jnp.asarray(b, jnp.float32) * window)
    cross = fb * jnp.conj(fa)
    surface = jnp.real(jnp.fft.ifft2(cross / jnp.maximum(jnp.abs(cross), 1e-12)))
    py, px = jnp.unravel_index(jnp.argmax(surface), surface.shape)
    offsets = jnp.arange(-1, 2)
    rows = (py + offsets) % h
    cols = (px + offsets) % w
    patch = jnp.maximum(surface[rows[:, None], cols[None, :]], 0.0)
    total = jnp.maximum(jnp.sum(patch), 1e-12)
    dy = py + jnp.sum(patch.sum(1) * offsets) / total
    dx = px + jnp.sum(patch.sum(0) * offsets) / total
    wrap = jnp.array([w, h], jnp.float32)
    shift = jnp.stack([dx, dy]).astype(jnp.float32)
    shift = jnp.where(shift > wrap / 2, shift - wrap, shift)
    return shift, surface[py, px]


def frame_motion(colour_a: Array, colour_b: Array, factor: int = 4) -> tuple[Array, Array]:
    """``(shift [2] (dx, dy) px, peak [])``: :func:`phase_correlation` of two ``[H, W, 3]``
    RGB frames' grey images downscaled by ``factor``, the shift in full-frame pixels."""
    a = downscale(color.grey(colour_a), factor)
    b = downscale(color.grey(colour_b), factor)
    shift, peak = phase_correlation(a, b)
    return shift * factor, peak
