"""Person-shaped blobs of a foreground mask, in JAX: the person detector's rules on arrays.

The rules are those of ``cpf_jax.detect`` (its module docstring), and the person rule
and confidence below are the ones the host detector calls:

1. A morphological opening (``open_px``) and closing (``close_px``) of the mask, with
   OpenCV's conventions (a ``k``-pixel square, anchor ``k // 2``, the frame's outside
   never erodes nor dilates).
2. 8-connected components, each cut to its main depth: the part within
   ``max(depth_gap, depth_gap_rel * z)`` of its median depth ``z`` (with the parts that have
   no depth), its largest connected piece kept and the rest examined again in the next
   round, for a fixed number of ``rounds``.
3. A person is at least ``min_area`` of the frame's pixels, ``min_height`` of its height
   and no wider than ``max_aspect`` times his height (:func:`person_shaped`); his
   confidence is :func:`person_confidence`.

Steps 2-3 run on blocks of ``block x block`` pixels (a block is foreground when any of
its pixels is, and near a depth when any of its pixels is or has no depth; a blob's median depth
is that of its blocks' mean depths, weighted by their measured pixels), because the
connected-components kernel (``graph.connected_components``) takes rows of at most 250
cells and its cost grows with the area. Blocks keep the components of the cleaned mask:
pixels that touch lie in touching blocks, and after a closing of ``close_px`` two blobs
are at least ``close_px`` pixels apart, which holds a whole block between them when
``2 * block - 1 <= close_px`` (``block <= 4`` for the default 7). Areas and boxes are
counted on the pixels of the kept blocks, so a box is exact when its blob is at least a
block away from any other; where a depth cut runs through a block, the whole block goes
to one side. Boxes are ``(x, y, w, h)`` pixels, top-left corner, the tight box.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax.numpy as jnp
from jax import Array, lax

from .graph import connected_components, pixel_graph

__all__ = [
    "closing",
    "confidence_shares",
    "detector_block",
    "erode",
    "dilate",
    "group_median",
    "weighted_median",
    "opening",
    "person_blobs",
    "person_confidence",
    "person_shaped",
]

#: Widest block grid the detector works on (columns); ``graph.connected_components`` takes 250.
MAX_BLOCK_COLUMNS = 160


def detector_block(width: int) -> int:
    """The block size (pixels) of :func:`person_blobs` for frames ``width`` pixels wide: the
    smallest one that keeps the grid within ``MAX_BLOCK_COLUMNS`` columns."""
    return max(1, math.ceil(width / MAX_BLOCK_COLUMNS))


def _window(mask: Array, size: int, op, init) -> Array:
    """``out[r, c] = op`` over ``mask[r - a : r - a + size, c - a : c - a + size]``, ``a =
    size // 2``, the outside taken as ``init`` (separable: rows, then columns)."""
    a = size // 2
    x = mask.astype(jnp.int32)
    x = lax.reduce_window(x, init, op, (size, 1), (1, 1), ((a, size - 1 - a), (0, 0)))
    x = lax.reduce_window(x, init, op, (1, size), (1, 1), ((0, 0), (a, size - 1 - a)))
    return x.astype(bool)


def erode(mask: Array, size: int) -> Array:
    """``[H, W] bool`` erosion by a ``size`` square (``cv2.erode``, default border)."""
    return _window(mask, size, lax.min, 1)


def dilate(mask: Array, size: int) -> Array:
    """``[H, W] bool`` dilation by a ``size`` square (``cv2.dilate``, default border)."""
    return _window(mask, size, lax.max, 0)


def opening(mask: Array, size: int) -> Array:
    """``cv2.morphologyEx(mask, MORPH_OPEN, ones((size, size)))`` as ``[H, W] bool``."""
    return dilate(erode(mask, size), size)


def closing(mask: Array, size: int) -> Array:
    """``cv2.morphologyEx(mask, MORPH_CLOSE, ones((size, size)))`` as ``[H, W] bool``."""
    return erode(dilate(mask, size), size)


def person_shaped(w, h, area, frame_hw, min_area, min_height, max_aspect):
    """Whether a blob of ``area`` pixels with a ``w x h`` box in a ``frame_hw`` frame is a
    person (rule 3): NumPy or JAX scalars and arrays alike."""
    frame_h, frame_w = frame_hw
    return (
        (area >= min_area * frame_h * frame_w) & (h >= min_height * frame_h) & (w <= max_aspect * h)
    )


def confidence_shares(box, area, frame_hw) -> Array:
    """``[..., 4]`` shares in [0, 1] of a person's confidence for tight boxes ``[..., 4]``
    xywh of blobs of ``area [...]`` pixels: fill (the blob's share of its box, full from
    40 %), uprightness (height over width, full from 1.8), height (of the frame's, full
    from 30 %) and 0.6 for each frame edge the box touches (``cpf_jax.detect``)."""
    box = jnp.asarray(box, jnp.float32)
    x, y, w, h = (box[..., i] for i in range(4))
    frame_h, frame_w = frame_hw
    fill = jnp.asarray(area, jnp.float32) / jnp.maximum(w * h, 1.0)
    upright = h / jnp.maximum(w, 1.0)
    edges = (x <= 0).astype(jnp.int32) + (y <= 0) + (x + w >= frame_w) + (y + h >= frame_h)
    return jnp.stack(
        [
            jnp.clip((fill - 0.15) / 0.25, 0.0, 1.0),
            jnp.clip((upright - 0.9) / 0.9, 0.0, 1.0),
            jnp.clip((h / frame_h - 0.15) / 0.15, 0.0, 1.0),
            0.6 ** edges.astype(jnp.float32),
        ],
        axis=-1,
    )


def person_confidence(box, area, frame_hw) -> Array:
    """``[...]`` how sure the detector is that each blob is a whole upright person: the
    product of :func:`confidence_shares`."""
    return jnp.prod(confidence_shares(box, area, frame_hw), axis=-1)


def _bisect_median(weight_below, total: Array, top: float) -> Array:
    """The least ``m`` in ``[0, top)`` (to ``top / 2**20``) where ``weight_below(m)``, the
    weight at or below ``m`` (same shape as ``total``), reaches half of ``total``; 0 where
    ``total`` is 0. Bisection: a sort costs more on a CPU."""

    def halve(_, bounds):
        lo, hi = bounds
        mid = 0.5 * (lo + hi)
        enough = 2.0 * weight_below(mid) >= total
        return jnp.where(enough, lo, mid), jnp.where(enough, mid, hi)

    lo = jnp.zeros_like(total)
    _, hi = lax.fori_loop(0, 20, halve, (lo, jnp.full_like(total, top)))
    return jnp.where(total > 0, hi, 0.0)


def group_median(
    groups: Array, values: Array, weights: Array, n_groups: int, top: float = 65536.0
) -> Array:
    """``[n_groups]`` weighted lower median of ``values [N]`` in ``[0, top)`` within each
    group (``groups [N]`` int in ``[0, n_groups)``, ``weights [N]`` >= 0), to
    ``top / 2**20`` (0.06 mm for depths in mm); 0 for a group without weight."""
    groups = groups.astype(jnp.int32)
    weights = weights.astype(jnp.float32)
    total = jnp.zeros(n_groups, jnp.float32).at[groups].add(weights)

    def below(m):
        w = jnp.where(values <= m[groups], weights, 0.0)
        return jnp.zeros(n_groups, jnp.float32).at[groups].add(w)

    return _bisect_median(below, total, top)


def weighted_median(values: Array, weights: Array, top: float = 65536.0) -> Array:
    """``[...]`` weighted lower median of ``values [N]`` in ``[0, top)`` under each row of
    ``weights [..., N]`` >= 0 (as :func:`group_median`); 0 for a row without weight."""
    weights = weights.astype(jnp.float32)

    def below(m):
        return jnp.sum(jnp.where(values <= m[..., None], weights, 0.0), axis=-1)

    return _bisect_median(below, jnp.sum(weights, axis=-1), top)


class _Grid(NamedTuple):
    """The frame cut into blocks: ``[Hb, Wb, block * block]`` per pixel of each block."""

    depth: Array  # mm (0: none)
    col: Array  # int32 pixel column
    row: Array  # int32 pixel row


def _grid(z: Array, block: int) -> _Grid:
    """``_Grid`` of ``z [H, W]`` mm; the frame is padded to whole blocks (no depth)."""
    h, w = z.shape
    hb, wb = -(-h // block), -(-w // block)
    z = jnp.pad(z, ((0, hb * block - h), (0, wb * block - w)))
    rows, cols = jnp.meshgrid(jnp.arange(hb * block), jnp.arange(wb * block), indexing="ij")
    return _Grid(*(_cells(a, block) for a in (z, cols, rows)))


def _cells(a: Array, block: int) -> Array:
    """``[H, W] -> [H / block, W / block, block * block]`` (``H``, ``W`` whole blocks)."""
    hb, wb = a.shape[0] // block, a.shape[1] // block
    a = a.reshape(hb, block, wb, block).transpose(0, 2, 1, 3)
    return a.reshape(hb, wb, block * block)


def _pad_cells(mask: Array, block: int) -> Array:
    h, w = mask.shape
    pad = ((0, -h % block), (0, -w % block))
    return _cells(jnp.pad(mask, pad), block)


def _components(active: Array) -> Array:
    """``[Hb, Wb] int32`` 8-connected component labels of ``active`` (smallest flat index)."""
    return connected_components(pixel_graph(jnp.zeros(active.shape), active, 1.0))


def _sum_by(labels: Array, values: Array) -> Array:
    """``[Hb * Wb]`` sums of ``values [Hb, Wb]`` by ``labels [Hb, Wb]``."""
    n = labels.size
    return jnp.zeros(n, values.dtype).at[labels.reshape(-1)].add(values.reshape(-1))


def _main_part(pixels, labels, grid: _Grid, min_pixels, depth_gap, depth_gap_rel):
    """One round of the depth cut on every blob of ``pixels [Hb, Wb, B] bool`` at once
    (``labels``: their blocks' components): ``(main, rest)`` pixels, the main part of
    each blob of at least ``min_pixels`` pixels (its largest connected piece of pixels
    near its median depth or without depth, or all of it when it has too little depth or
    nothing is cut) and what is left of it. A blob's median depth is that of its blocks'
    mean depths, weighted by their measured pixels."""
    n = labels.size
    measured_px = pixels & (grid.depth > 0)
    count = jnp.sum(pixels, axis=-1, dtype=jnp.int32)
    n_measured = jnp.sum(measured_px, axis=-1, dtype=jnp.int32)
    mean = jnp.sum(jnp.where(measured_px, grid.depth, 0.0), axis=-1) / jnp.maximum(n_measured, 1)
    area = _sum_by(labels, count)
    big = (count > 0) & (area[labels] >= min_pixels)
    weights = jnp.where(big, n_measured, 0).reshape(-1)
    med = group_median(labels.reshape(-1), mean.reshape(-1), weights, n)
    med = med[labels][..., None]
    tol = jnp.maximum(depth_gap, depth_gap_rel * med)
    near_px = pixels & big[..., None] & ((grid.depth == 0) | (jnp.abs(grid.depth - med) <= tol))
    near = jnp.any(near_px, axis=-1)
    # The largest connected piece of each blob's near part (ties: smallest label).
    sub = _components(near)
    sub_area = _sum_by(sub, jnp.sum(near_px, axis=-1, dtype=jnp.int32))
    parent = jnp.zeros(n, jnp.int32).at[sub.reshape(-1)].max(jnp.where(near, labels, 0).reshape(-1))
    best_area = jnp.zeros(n, jnp.int32).at[parent].max(sub_area)
    is_best = (sub_area > 0) & (sub_area == best_area[parent])
    best = jnp.full(n, n, jnp.int32).at[parent].min(jnp.where(is_best, jnp.arange(n), n))
    piece = near_px & (sub == best[labels])[..., None]
    piece_area = _sum_by(labels, jnp.sum(piece, axis=-1, dtype=jnp.int32))[labels]
    cut = (
        (5 * _sum_by(labels, n_measured)[labels] >= area[labels])  # a fifth has depth
        & (piece_area > 0)
        & (piece_area < area[labels])
    )[..., None]
    blob = pixels & big[..., None]
    return jnp.where(cut, piece, blob), blob & cut & ~piece


def _round_blobs(main, labels, grid: _Grid, frame_hw, n_out, rules):
    """The ``n_out`` largest person-shaped main parts ``main [Hb, Wb, B]`` of one round:
    ``(area [n_out], box [n_out, 4])`` (area -1: none)."""
    n = labels.size
    flat = labels.reshape(-1)
    area = _sum_by(labels, jnp.sum(main, axis=-1, dtype=jnp.int32))
    big = jnp.int32(1 << 30)
    # Each block's tight box of its pixels, then one scatter-min of (x0, y0, -x1, -y1).
    sides = [
        jnp.min(jnp.where(main, grid.col, big), axis=-1),
        jnp.min(jnp.where(main, grid.row, big), axis=-1),
        jnp.min(jnp.where(main, -grid.col, big), axis=-1),
        jnp.min(jnp.where(main, -grid.row, big), axis=-1),
    ]
    sides = jnp.stack([a.reshape(-1) for a in sides], axis=-1)
    lo = jnp.full((n, 4), big).at[flat].min(sides)
    box = jnp.stack([lo[:, 0], lo[:, 1], -lo[:, 2] - lo[:, 0] + 1, -lo[:, 3] - lo[:, 1] + 1], -1)
    box = box.astype(jnp.float32)
    person = (area > 0) & person_shaped(box[:, 2], box[:, 3], area, frame_hw, *rules)
    score = jnp.where(person, area, -1)
    idx = []
    for _ in range(n_out):  # a few argmaxes cost less than top_k over every label on a CPU
        i = jnp.argmax(score)
        idx.append(i)
        score = score.at[i].set(-2)
    idx = jnp.stack(idx)
    return jnp.where(person[idx], area[idx], -1), box[idx]


def person_blobs(
    mask: Array,
    depth: Array,
    n: int,
    *,
    open_px: int,
    close_px: int,
    depth_gap: float,
    depth_gap_rel: float,
    min_area: float,
    min_height: float,
    max_aspect: float,
    block: int,
    rounds: int = 3,
) -> tuple[Array, Array, Array, Array]:
    """The ``n`` largest person-shaped blobs of a foreground ``mask [H, W] bool`` over
    ``depth [H, W]`` mm (0: missing), by the rules of the module docstring.

    Returns ``(box [n, 4] float32 xywh, area [n] int32 pixels, depth [n] float32 mm,
    confidence [n] float32)``, largest first; rows without a blob are zeros. ``depth`` is
    the median depth of the cleaned mask's measured pixels in the box (of the block means,
    each weighted by its pixel count). ``block``, ``rounds`` and ``n`` are static.
    """
    mask = jnp.asarray(mask, bool)
    z = jnp.asarray(depth, jnp.float32)
    frame_hw = mask.shape
    clean = closing(opening(mask, open_px), close_px)
    min_pixels = min_area * frame_hw[0] * frame_hw[1]

    def blobs(clean, z):
        return _blobs(clean, z, n, block, rounds, depth_gap, depth_gap_rel, min_pixels, rules)

    def nobody(clean, z):
        zeros = jnp.zeros((n,), jnp.float32)
        return jnp.zeros((n, 4), jnp.float32), jnp.zeros((n,), jnp.int32), zeros, zeros

    rules = (min_area, min_height, max_aspect)
    # Fewer cleaned pixels than the least person: nobody (unbatched, the rounds are skipped).
    return lax.cond(jnp.sum(clean) >= min_pixels, blobs, nobody, clean, z)


def _blobs(clean, z, n, block, rounds, depth_gap, depth_gap_rel, min_pixels, rules):
    """:func:`person_blobs` after the opening and closing."""
    frame_hw = clean.shape
    grid = _grid(z, block)
    pixels = _pad_cells(clean, block)
    areas, boxes = [], []
    for _ in range(rounds):  # static and small: unrolled
        labels = _components(jnp.any(pixels, axis=-1))
        main, pixels = _main_part(pixels, labels, grid, min_pixels, depth_gap, depth_gap_rel)
        a, b = _round_blobs(main, labels, grid, frame_hw, n, rules)
        areas.append(a)
        boxes.append(b)
    area, idx = lax.top_k(jnp.concatenate(areas), n)
    found = area > 0
    box = jnp.where(found[:, None], jnp.concatenate(boxes)[idx], 0.0)
    area = jnp.maximum(area, 0)
    confidence = jnp.where(found, person_confidence(box, area, frame_hw), 0.0)
    return box, area, _box_depths(box, found, _pad_cells(clean, block), grid), confidence


def _box_depths(box, found, clean, grid: _Grid) -> Array:
    """``[n]`` median depth of the measured pixels of ``clean [Hb, Wb, B]`` in each box,
    to a block: the blocks whose pixels lie in the box, each its mean depth weighted by
    its measured pixels (0: none)."""
    measured = clean & (grid.depth > 0)
    n_measured = jnp.sum(measured, axis=-1)
    mean = jnp.sum(jnp.where(measured, grid.depth, 0.0), axis=-1) / jnp.maximum(n_measured, 1)
    big = jnp.int32(1 << 30)
    x0 = jnp.min(jnp.where(clean, grid.col, big), axis=-1).reshape(-1)
    y0 = jnp.min(jnp.where(clean, grid.row, big), axis=-1).reshape(-1)
    x1 = jnp.max(jnp.where(clean, grid.col, -1), axis=-1).reshape(-1)
    y1 = jnp.max(jnp.where(clean, grid.row, -1), axis=-1).reshape(-1)
    b = box[:, :, None]
    inside = (x0 >= b[:, 0]) & (x1 < b[:, 0] + b[:, 2]) & (y0 >= b[:, 1]) & (y1 < b[:, 1] + b[:, 3])
    weights = jnp.where(inside, n_measured.reshape(-1), 0)  # [n, Hb * Wb]
    return jnp.where(found, weighted_median(mean.reshape(-1), weights), 0.0)
