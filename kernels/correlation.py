"""A discriminative appearance model learnt online: a multi-channel correlation filter.

The filter is the ridge regression of a Gaussian response ``g`` on the features ``x`` of a
patch around the target, solved in the Fourier domain per frequency (Bolme et al. 2010,
MOSSE; Danelljan et al. 2014, DSST, eqs. 3-5 for several channels)::

    A_c = conj(G) X_c                 numerator, one per feature channel c
    B   = sum_c conj(X_c) X_c         denominator, shared
    y   = F^-1( sum_c conj(A_c) Z_c / (B + lambda) )     response to features z

``A`` and ``B`` are running averages over frames (``blend``), so the filter learns the
target against its surround as the run goes. A shift of the target by ``d`` cells shifts
the response's peak by ``d``: the response map, centred on zero displacement, scores
every candidate position of the search patch at once, and a particle reads it at its
centre in O(1) (``read_response``).

Features (``features``), per ``cell x cell`` pixel cell of a patch resampled to a fixed
size: 9 unsigned gradient-orientation channels (magnitude split linearly between the two
nearest bins, as HOG), normalised by the cell's gradient energy; the cell's mean luma
(centred) and its hue as a saturation-weighted unit vector (2 channels), which carry the
colour a grey-level filter misses. The patch is ``padding`` times the target's box in each
direction, resampled anisotropically to ``n x n`` cells, so a box of any aspect gives
static shapes. A cosine window tapers the patch's borders (the correlation is circular).

Conventions: images ``[H, W, 3]`` RGB (uint8 or float 0-255), pixel centres at integer
coordinates, centres and displacements ``(x, y)``. Everything is static-shaped and works
under ``jit`` and ``vmap``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array

from . import color

__all__ = [
    "N_ORIENTATIONS",
    "N_CHANNELS",
    "CorrelationFilter",
    "sample_patch",
    "features",
    "cosine_window",
    "label_spectrum",
    "fit",
    "blend",
    "response",
    "read_response",
]

N_ORIENTATIONS = 9
N_CHANNELS = N_ORIENTATIONS + 3


class CorrelationFilter(NamedTuple):
    numerator: Array  # [C, n, n // 2 + 1] complex64: A_c
    denominator: Array  # [n, n // 2 + 1] float32: B


def sample_patch(image: Array, centre: Array, size: Array, pixels: int) -> Array:
    """``[pixels, pixels, C] float32`` bilinear samples of ``image [H, W, C]`` over the
    axis-aligned rectangle of ``size (w, h)`` centred on ``centre (x, y)``; samples
    outside the image repeat its border."""
    height, width = image.shape[:2]
    t = (jnp.arange(pixels, dtype=jnp.float32) + 0.5) / pixels - 0.5
    xs = centre[0] + t * size[0]
    ys = centre[1] + t * size[1]
    x0 = jnp.floor(xs)
    y0 = jnp.floor(ys)
    fx = (xs - x0)[None, :, None]
    fy = (ys - y0)[:, None, None]
    xa = jnp.clip(x0, 0, width - 1).astype(jnp.int32)
    xb = jnp.clip(x0 + 1, 0, width - 1).astype(jnp.int32)
    ya = jnp.clip(y0, 0, height - 1).astype(jnp.int32)
    yb = jnp.clip(y0 + 1, 0, height - 1).astype(jnp.int32)
    img = jnp.asarray(image, jnp.float32)
    top = img[ya][:, xa] * (1 - fx) + img[ya][:, xb] * fx
    bottom = img[yb][:, xa] * (1 - fx) + img[yb][:, xb] * fx
    return top * (1 - fy) + bottom * fy


def _cells(plane: Array, cell: int) -> Array:
    """``[P / cell, P / cell, ...]`` sums over ``cell x cell`` blocks of ``plane [P, P, ...]``."""
    p = plane.shape[0] // cell
    return plane.reshape(p, cell, p, cell, *plane.shape[2:]).sum(axis=(1, 3))


def features(patch: Array, cell: int) -> Array:
    """``[P / cell, P / cell, N_CHANNELS] float32`` features of ``patch [P, P, 3]`` RGB
    0-255 (module docstring)."""
    luma = color.grey(patch) / 255.0
    padded = jnp.pad(luma, 1, mode="edge")
    gx = 0.5 * (padded[1:-1, 2:] - padded[1:-1, :-2])
    gy = 0.5 * (padded[2:, 1:-1] - padded[:-2, 1:-1])
    magnitude = jnp.sqrt(gx * gx + gy * gy)
    angle = jnp.mod(jnp.arctan2(gy, gx), jnp.pi) * (N_ORIENTATIONS / jnp.pi)
    lower = jnp.floor(angle)
    frac = angle - lower
    bins = jnp.arange(N_ORIENTATIONS, dtype=jnp.float32)
    lo = jnp.mod(lower, N_ORIENTATIONS)[..., None] == bins
    hi = jnp.mod(lower + 1, N_ORIENTATIONS)[..., None] == bins
    votes = magnitude[..., None] * (lo * (1 - frac)[..., None] + hi * frac[..., None])
    hog = _cells(votes, cell)
    energy = jnp.sqrt(jnp.sum(hog * hog, axis=-1, keepdims=True) + 1e-4)
    hsv = color.rgb_to_hsv_float(jnp.clip(patch, 0.0, 255.0) / 255.0)
    hue = 2 * jnp.pi * hsv[..., 0]
    planes = jnp.stack(
        [luma - 0.5, hsv[..., 1] * jnp.cos(hue), hsv[..., 1] * jnp.sin(hue)], axis=-1
    )
    colour = _cells(planes, cell) / (cell * cell)
    return jnp.concatenate([hog / energy, colour], axis=-1)


def cosine_window(n: int) -> Array:
    """``[n, n]`` Hann window, the taper against the circular correlation's wrap."""
    w = 0.5 - 0.5 * jnp.cos(2.0 * jnp.pi * (jnp.arange(n) + 0.5) / n)
    return w[:, None] * w[None, :]


def label_spectrum(n: int, sigma: float) -> Array:
    """``[n, n // 2 + 1] complex64`` spectrum of the desired response: a Gaussian of
    ``sigma`` cells peaked at zero displacement (index ``(0, 0)``, wrapped)."""
    d = jnp.arange(n, dtype=jnp.float32)
    d = jnp.minimum(d, n - d)
    g = jnp.exp(-(d[:, None] ** 2 + d[None, :] ** 2) / (2.0 * sigma * sigma))
    return jnp.fft.rfft2(g)


def _spectra(feats: Array) -> Array:
    """``[C, n, n // 2 + 1]`` spectra of the windowed feature channels of ``[n, n, C]``."""
    n = feats.shape[0]
    windowed = jnp.moveaxis(feats, -1, 0) * cosine_window(n)
    return jnp.fft.rfft2(windowed)


def fit(feats: Array, label: Array) -> CorrelationFilter:
    """The one-frame filter of features ``feats [n, n, C]`` (module docstring, A and B)."""
    x = _spectra(feats)
    num = jnp.conj(label)[None] * x
    den = jnp.sum(jnp.real(x * jnp.conj(x)), axis=0)
    return CorrelationFilter(num.astype(jnp.complex64), den.astype(jnp.float32))


def blend(old: CorrelationFilter, new: CorrelationFilter, rate: Array) -> CorrelationFilter:
    """``(1 - rate) old + rate new``, term by term (the running averages of A and B)."""
    return CorrelationFilter(
        ((1 - rate) * old.numerator + rate * new.numerator).astype(jnp.complex64),
        ((1 - rate) * old.denominator + rate * new.denominator).astype(jnp.float32),
    )


def response(filt: CorrelationFilter, feats: Array, lam: float) -> Array:
    """``[n, n] float32`` response to features ``feats [n, n, C]``, zero displacement at
    index ``(n // 2, n // 2)``: entry ``[n // 2 + dy, n // 2 + dx]`` scores the target
    displaced by ``(dx, dy)`` cells."""
    z = _spectra(feats)
    n = feats.shape[0]
    spectrum = jnp.sum(jnp.conj(filt.numerator) * z, axis=0) / (filt.denominator + lam)
    resp = jnp.fft.irfft2(spectrum, s=(n, n))
    return jnp.roll(resp, (n // 2, n // 2), axis=(0, 1)).astype(jnp.float32)


def read_response(resp: Array, disp: Array) -> Array:
    """``[...]`` bilinear reads of ``resp [n, n]`` (``response``'s layout) at displacements
    ``disp [..., 2]`` ``(dx, dy)`` in cells; a displacement outside the map reads its
    smallest value (the filter has no evidence there)."""
    n = resp.shape[0]
    x = disp[..., 0] + n // 2
    y = disp[..., 1] + n // 2
    inside = (x >= 0) & (x <= n - 1) & (y >= 0) & (y <= n - 1)
    x = jnp.clip(x, 0, n - 1)
    y = jnp.clip(y, 0, n - 1)
    x0 = jnp.clip(jnp.floor(x), 0, n - 2)
    y0 = jnp.clip(jnp.floor(y), 0, n - 2)
    fx, fy = x - x0, y - y0
    xi, yi = x0.astype(jnp.int32), y0.astype(jnp.int32)
    top = resp[yi, xi] * (1 - fx) + resp[yi, xi + 1] * fx
    bottom = resp[yi + 1, xi] * (1 - fx) + resp[yi + 1, xi + 1] * fx
    value = top * (1 - fy) + bottom * fy
    return jnp.where(inside, value, jnp.min(resp))
