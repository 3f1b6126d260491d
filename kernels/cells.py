"""Grid cells of boxes and the per-cell statistics of the RGB-D likelihood (P 2.2-2.4).

Conventions (those of ``cpf_jax.kernels.boxes``): boxes are ``[..., 4] (x, y,
w, h)`` top-left float pixels; depth is ``uint16`` millimetres, 0 = missing.

* :func:`grid_cells` splits each box into ``k x k`` cells, row-major (cell
  ``i = row * k + col``, row 0 at the top). Cell edges are shared, so after
  ``boxes.xywh_to_rect`` rounding the cells' pixels tile the box's pixels.
* Depth statistics per cell come from **histograms of depth** (counted
  exactly by ``histogram.rect_reduce``, like the colour histograms), with
  ``n`` bins spaced evenly in ``log z`` between ``z_min`` and ``z_max``
  (:func:`depth_bin_index`): each bin spans the same relative depth,
  ``(z_max / z_min)^(1/n) - 1`` (5.2 % for 64 bins over 0.4-10 m), which
  matches a depth sensor whose error grows with distance. Depths outside the
  range fall into the first / last bin.
* :func:`histogram_quantile` reads a quantile (the median) off the counts,
  interpolating linearly *in bin coordinates* (i.e. geometrically in depth)
  inside the bin that holds the quantile's rank. **Approximation**: the
  estimate lies in the same bin as the lower median (the sample of rank
  ``ceil(n / 2)``, which is ``np.median`` for an odd count; for an even count
  ``np.median`` averages it with the next sample), so it is within one relative
  bin width of it; against ``np.median`` the error is a small fraction of a
  bin on cells of tens of pixels or more (both tested).
* :func:`histogram_fraction_below` is the share of the counted pixels nearer
  than a threshold, with the same in-bin interpolation: the depth-ordering
  evidence ("something in this cell is nearer than the target").
* :func:`strip_table` / :func:`strip_counts` give, for many rects at once, two
  scalar counts where a whole histogram would be wasted: the foreground pixels
  and the depth-counted pixels not nearer than a threshold (the latter with
  :func:`histogram_fraction_below`'s in-bin interpolation), from one
  four-channel ``int32`` summed-area table (the border strips of
  ``cpf_jax.rgbd``).
* :func:`beta_log_density` is the log of the Beta density of paper eq. 2, on a
  ratio clipped to ``[eps, 1 - eps]`` (a ratio of exactly 0 or 1 would give an
  infinite log-density for shapes below or above 1).

Coarse maps (the data-driven proposal of ``cpf_jax.rgbd``): :func:`coarse_counts`
sums a mask over ``s x s`` blocks (``[H // s, W // s]``; the last ``H % s`` rows
and ``W % s`` columns are dropped), :func:`window_sums` sums such a map over a
``(2 ry + 1) x (2 rx + 1)`` window centred on every cell (clipped at the map's
edges; the radii may be traced values), with a summed-area table, and
:func:`map_cell_of` is the flat cell index of a pixel position (-1 outside).

Everything is pure, static-shaped and works under ``jit`` and ``vmap``; the
bin layout ``(n_bins, z_min, z_max)`` is static.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.scipy.special import betaln

from .histogram import integral_image, rect_sums

__all__ = [
    "grid_cells",
    "border_strips",
    "side_cells",
    "depth_bin_edges",
    "depth_bin_index",
    "depth_to_bin_coord",
    "bin_coord_to_depth",
    "histogram_quantile",
    "histogram_fraction_below",
    "strip_table",
    "strip_counts",
    "beta_log_density",
    "coarse_counts",
    "window_sums",
    "window_areas",
    "map_cell_of",
]


def grid_cells(boxes_xywh: Array, k: int) -> Array:
    """``[..., 4]`` xywh boxes -> ``[..., k * k, 4]`` xywh cells, row-major (``k`` static)."""
    b = jnp.asarray(boxes_xywh, jnp.float32)
    f = jnp.arange(k, dtype=jnp.float32) / k
    cw = b[..., 2:3] / k
    ch = b[..., 3:4] / k
    xs = b[..., 0:1] + b[..., 2:3] * f  # [..., k] left edges of the columns
    ys = b[..., 1:2] + b[..., 3:4] * f  # [..., k] top edges of the rows
    x = jnp.tile(xs, (1,) * (b.ndim - 1) + (k,))
    y = jnp.repeat(ys, k, axis=-1)
    w = jnp.broadcast_to(cw, x.shape)
    h = jnp.broadcast_to(ch, y.shape)
    return jnp.stack([x, y, w, h], axis=-1)


def border_strips(boxes_xywh: Array, thickness: float) -> Array:
    """``[..., 4]`` xywh boxes -> ``[..., 8, 4]`` xywh strips along their edges.

    Order: inner top, bottom, left, right (inside the box, along each edge),
    then outer top, bottom, left, right (just outside). Top/bottom strips are
    ``thickness * h`` tall, left/right strips ``thickness * w`` wide.
    """
    b = jnp.asarray(boxes_xywh, jnp.float32)
    x, y, w, h = (b[..., i] for i in range(4))
    th, tw = thickness * h, thickness * w
    rows = [
        (x, y, w, th),
        (x, y + h - th, w, th),
        (x, y, tw, h),
        (x + w - tw, y, tw, h),
        (x, y - th, w, th),
        (x, y + h, w, th),
        (x - tw, y, tw, h),
        (x + w, y, tw, h),
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def side_cells(k: int) -> np.ndarray:
    """``[4, k*k] bool``: which grid cells touch the top, bottom, left and right edge."""
    idx = np.arange(k * k)
    row, col = idx // k, idx % k
    return np.stack([row == 0, row == k - 1, col == 0, col == k - 1])


def depth_bin_edges(n_bins: int, z_min: float, z_max: float) -> np.ndarray:
    """``[n_bins + 1]`` float64 bin edges (mm), evenly spaced in ``log z``."""
    if not (0 < z_min < z_max) or n_bins < 1:
        raise ValueError(f"need 0 < z_min < z_max and n_bins >= 1, got {z_min}, {z_max}, {n_bins}")
    return z_min * (z_max / z_min) ** (np.arange(n_bins + 1) / n_bins)


def depth_to_bin_coord(z: Array, n_bins: int, z_min: float, z_max: float) -> Array:
    """Continuous bin coordinate ``n log(z / z_min) / log(z_max / z_min)`` (unclipped)."""
    scale = n_bins / math.log(z_max / z_min)
    return (jnp.log(jnp.maximum(jnp.asarray(z, jnp.float32), 1e-3)) - math.log(z_min)) * scale


def bin_coord_to_depth(p: Array, n_bins: int, z_min: float, z_max: float) -> Array:
    """Inverse of :func:`depth_to_bin_coord`: ``z_min (z_max / z_min)^(p / n)`` (mm)."""
    return z_min * jnp.exp(jnp.asarray(p, jnp.float32) * (math.log(z_max / z_min) / n_bins))


def depth_bin_index(
    depth: Array, mask: Array | None, n_bins: int, z_min: float, z_max: float
) -> Array:
    """``[H, W] int32`` depth bin per pixel; ``-1`` (not counted) where depth is 0 or ``~mask``."""
    z = jnp.asarray(depth)
    p = depth_to_bin_coord(z, n_bins, z_min, z_max)
    idx = jnp.clip(jnp.floor(p), 0, n_bins - 1).astype(jnp.int32)
    ok = z > 0
    if mask is not None:
        ok = ok & jnp.asarray(mask, bool)
    return jnp.where(ok, idx, -1)


def histogram_quantile(
    counts: Array, n_bins: int, z_min: float, z_max: float, q: float = 0.5
) -> tuple[Array, Array]:
    """Quantile ``q`` of depth histograms ``counts [..., n_bins]`` -> ``(value, total) [...]``.

    The value (mm) is interpolated inside the bin holding rank ``q * total``
    (module docstring for the error bound); 0 where the histogram is empty.
    """
    c = jnp.asarray(counts, jnp.float32)
    total = jnp.sum(c, axis=-1)
    cum = jnp.cumsum(c, axis=-1)
    rank = q * total
    # First bin whose cumulative count reaches the rank (strictly positive counts).
    j = jnp.sum((cum < rank[..., None]).astype(jnp.int32), axis=-1)
    j = jnp.clip(j, 0, n_bins - 1)
    below = (
        jnp.take_along_axis(cum, j[..., None], axis=-1)[..., 0]
        - jnp.take_along_axis(c, j[..., None], axis=-1)[..., 0]
    )
    in_bin = jnp.take_along_axis(c, j[..., None], axis=-1)[..., 0]
    frac = jnp.clip((rank - below) / jnp.maximum(in_bin, 1e-9), 0.0, 1.0)
    value = bin_coord_to_depth(j.astype(jnp.float32) + frac, n_bins, z_min, z_max)
    return jnp.where(total > 0, value, 0.0), total


def histogram_fraction_below(
    counts: Array, threshold: Array, n_bins: int, z_min: float, z_max: float
) -> Array:
    """Share ``[...]`` of the counted pixels nearer than ``threshold [...]`` mm (0 if empty).

    The bin holding the threshold contributes the part of its count below it,
    assuming its pixels spread evenly in bin coordinates.
    """
    c = jnp.asarray(counts, jnp.float32)
    p = depth_to_bin_coord(threshold, n_bins, z_min, z_max)
    w = jnp.clip(p[..., None] - jnp.arange(n_bins, dtype=jnp.float32), 0.0, 1.0)
    total = jnp.sum(c, axis=-1)
    return jnp.where(total > 0, jnp.sum(c * w, axis=-1) / jnp.maximum(total, 1.0), 0.0)


def strip_table(
    colour_bins: Array,
    n_colour: int,
    depth_bins: Array,
    threshold: Array,
    n_bins: int,
    z_min: float,
    z_max: float,
) -> tuple[Array, Array]:
    """Summed-area table ``[H + 1, W + 1, 4] int32`` and in-bin fraction ``[]`` for
    :func:`strip_counts`.

    Channels, per pixel: a colour bin in ``[0, n_colour)`` (foreground); a depth bin
    in ``[0, n_bins)``; a depth bin wholly nearer than ``threshold`` (mm); the depth
    bin holding ``threshold``. The fraction is the threshold's position inside that
    bin (the share of its count :func:`histogram_fraction_below` takes as nearer).
    ``n_colour`` and the bin layout are static.
    """
    p = depth_to_bin_coord(threshold, n_bins, z_min, z_max)
    # Clipped so the cast stays in range: below -1 no bin is nearer, from n_bins on all are.
    k = jnp.floor(jnp.clip(p, -1.0, float(n_bins))).astype(jnp.int32)
    c = jnp.asarray(colour_bins)
    d = jnp.asarray(depth_bins)
    counted = (d >= 0) & (d < n_bins)
    planes = (
        (c >= 0) & (c < n_colour),
        counted,
        counted & (d < k),
        counted & (d == k),
    )
    table = integral_image(jnp.stack(planes, axis=-1).astype(jnp.int32))
    return table, p - jnp.floor(p)


def strip_counts(table: Array, frac: Array, rects: Array) -> tuple[Array, Array]:
    """``(foreground, far) [...]`` float32 counts of ``rects [..., 4] (x0, y0, x1, y1)``
    (clipped to the frame) from :func:`strip_table`: the foreground pixels, and the
    depth-counted pixels not nearer than the threshold (``total * (1 -
    histogram_fraction_below)`` of the rect's depth histogram, without the histogram)."""
    s = rect_sums(table, rects).astype(jnp.float32)
    return s[..., 0], s[..., 1] - s[..., 2] - frac * s[..., 3]


def beta_log_density(ratio: Array, a: Array, b: Array, eps: float = 1e-3) -> Array:
    """``log Beta(r; a, b)`` with ``r`` clipped to ``[eps, 1 - eps]`` (paper eq. 2, normalised)."""
    r = jnp.clip(jnp.asarray(ratio, jnp.float32), eps, 1.0 - eps)
    return (a - 1.0) * jnp.log(r) + (b - 1.0) * jnp.log1p(-r) - betaln(a, b)


def coarse_counts(mask: Array, stride: int) -> Array:
    """``[H, W]`` mask -> ``[H // s, W // s] float32`` count of True pixels per ``s x s`` block."""
    m = jnp.asarray(mask).astype(jnp.float32)
    hh, ww = m.shape[0] // stride, m.shape[1] // stride
    return m[: hh * stride, : ww * stride].reshape(hh, stride, ww, stride).sum((1, 3))


def window_sums(grid: Array, ry: Array, rx: Array) -> Array:
    """``[h, w]`` map -> ``[h, w]`` sums over the ``(2 ry + 1) x (2 rx + 1)`` window at each cell.

    ``ry``, ``rx``: non-negative integer radii (scalars, may be traced). The
    window is clipped at the map's edges (cells outside count as 0).
    """
    g = jnp.asarray(grid, jnp.float32)
    h, w = g.shape
    sat = jnp.pad(jnp.cumsum(jnp.cumsum(g, 0), 1), ((1, 0), (1, 0)))  # [h + 1, w + 1]
    ry = jnp.maximum(jnp.asarray(ry, jnp.int32), 0)
    rx = jnp.maximum(jnp.asarray(rx, jnp.int32), 0)
    i = jnp.arange(h)
    j = jnp.arange(w)
    y0 = jnp.clip(i - ry, 0, h)[:, None]
    y1 = jnp.clip(i + ry + 1, 0, h)[:, None]
    x0 = jnp.clip(j - rx, 0, w)[None]
    x1 = jnp.clip(j + rx + 1, 0, w)[None]
    return sat[y1, x1] - sat[y0, x1] - sat[y1, x0] + sat[y0, x0]


def window_areas(shape: tuple[int, int], ry: Array, rx: Array) -> Array:
    """``[h, w]`` cell counts of the windows of ``window_sums`` (its sums over a map of
    ones), as products of the clipped row and column spans: exact integers, no gather."""
    h, w = shape
    ry = jnp.maximum(jnp.asarray(ry, jnp.int32), 0)
    rx = jnp.maximum(jnp.asarray(rx, jnp.int32), 0)
    i = jnp.arange(h)
    j = jnp.arange(w)
    rows = jnp.clip(i + ry + 1, 0, h) - jnp.clip(i - ry, 0, h)
    cols = jnp.clip(j + rx + 1, 0, w) - jnp.clip(j - rx, 0, w)
    return (rows[:, None] * cols[None]).astype(jnp.float32)


def map_cell_of(xy: Array, stride: int, shape: tuple[int, int]) -> Array:
    """Flat index ``[...] int32`` of the ``stride`` block holding pixel position ``xy [..., 2]``.

    ``shape = (h, w)`` of the coarse map; ``-1`` for positions outside it.
    """
    p = jnp.asarray(xy, jnp.float32)
    col = jnp.floor(p[..., 0] / stride)
    row = jnp.floor(p[..., 1] / stride)
    h, w = shape
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    idx = (jnp.clip(row, 0, h - 1) * w + jnp.clip(col, 0, w - 1)).astype(jnp.int32)
    return jnp.where(inside, idx, -1)
