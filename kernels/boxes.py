"""Box geometry.

Conventions (used throughout cpf_jax):

* Image coordinates are 0-based pixels; pixel ``(row r, col c)`` covers the
  continuous square ``[c, c+1) x [r, r+1)``.
* ``xywh``: top-left form ``(x, y, w, h)`` float32, the form of CSV output and
  ground truth after converting OTB's 1-based corners.
* ``cxcywh``: centre form ``(cx, cy, w, h)`` float32, the form of filter states.
* ``rect``: integer pixel rectangle ``(x0, y0, x1, y1)`` int32, half-open
  ``[x0, x1) x [y0, y1)``; obtained by rounding the continuous corners to the
  nearest pixel boundary. Histogram kernels count exactly the pixels of a rect.

Every function works on ``[..., 4]`` arrays, so one call handles one box, N
boxes or a batch of sequences.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array

__all__ = [
    "cxcywh_to_xywh",
    "xywh_to_cxcywh",
    "xywh_to_rect",
    "clip_rect",
    "xywh_columns_to_rect",
    "clip_xywh",
    "iou",
    "box_area",
    "centre_distance",
]


def cxcywh_to_xywh(boxes: Array) -> Array:
    """``[..., 4] (cx, cy, w, h)`` -> ``[..., 4] (x, y, w, h)``."""
    cx, cy, w, h = jnp.moveaxis(jnp.asarray(boxes), -1, 0)
    return jnp.stack([cx - w / 2, cy - h / 2, w, h], axis=-1)


def xywh_to_cxcywh(boxes: Array) -> Array:
    """``[..., 4] (x, y, w, h)`` -> ``[..., 4] (cx, cy, w, h)``."""
    x, y, w, h = jnp.moveaxis(jnp.asarray(boxes), -1, 0)
    return jnp.stack([x + w / 2, y + h / 2, w, h], axis=-1)


def xywh_to_rect(boxes: Array) -> Array:
    """``[..., 4] (x, y, w, h)`` float -> ``[..., 4] (x0, y0, x1, y1)`` int32, unclipped.

    Corners are rounded half-up to the nearest pixel boundary (``floor(v + 0.5)``),
    so a box whose corners are integers maps to exactly those pixels.
    """
    x, y, w, h = jnp.moveaxis(jnp.asarray(boxes, jnp.float32), -1, 0)
    return jnp.stack(xywh_columns_to_rect(x, y, w, h), axis=-1)


def xywh_columns_to_rect(x: Array, y: Array, w: Array, h: Array) -> tuple[Array, ...]:
    """``xywh_to_rect`` on separate float arrays: ``(x0, y0, x1, y1)`` int32 arrays (the
    form ``histogram.RectColumns`` takes, no ``[..., 4]`` stack)."""

    def corner(v: Array) -> Array:
        return jnp.floor(v + 0.5).astype(jnp.int32)

    return corner(x), corner(y), corner(x + w), corner(y + h)


def clip_rect(rects: Array, width: int, height: int) -> Array:
    """Clip ``[..., 4]`` integer rects to the frame; empty rects get ``x1 == x0`` / ``y1 == y0``."""
    x0, y0, x1, y1 = jnp.moveaxis(jnp.asarray(rects), -1, 0)
    x0 = jnp.clip(x0, 0, width)
    y0 = jnp.clip(y0, 0, height)
    x1 = jnp.clip(x1, x0, width)
    y1 = jnp.clip(y1, y0, height)
    return jnp.stack([x0, y0, x1, y1], axis=-1)


def clip_xywh(boxes: Array, width: float, height: float) -> Array:
    """Clip ``[..., 4] (x, y, w, h)`` boxes to ``[0, width] x [0, height]`` (may become empty)."""
    x, y, w, h = jnp.moveaxis(jnp.asarray(boxes), -1, 0)
    x0 = jnp.clip(x, 0.0, width)
    y0 = jnp.clip(y, 0.0, height)
    x1 = jnp.clip(x + w, x0, width)
    y1 = jnp.clip(y + h, y0, height)
    return jnp.stack([x0, y0, x1 - x0, y1 - y0], axis=-1)


def box_area(boxes: Array) -> Array:
    """Area of ``[..., 4] (x, y, w, h)`` boxes; negative sizes count as zero."""
    boxes = jnp.asarray(boxes)
    return jnp.maximum(boxes[..., 2], 0.0) * jnp.maximum(boxes[..., 3], 0.0)


def iou(a: Array, b: Array) -> Array:
    """Intersection over union of ``[..., 4] (x, y, w, h)`` boxes (broadcasting), thesis eq. 3.18.

    Two empty boxes give 0, never NaN.
    """
    a = jnp.asarray(a, jnp.float32)
    b = jnp.asarray(b, jnp.float32)
    ix0 = jnp.maximum(a[..., 0], b[..., 0])
    iy0 = jnp.maximum(a[..., 1], b[..., 1])
    ix1 = jnp.minimum(a[..., 0] + a[..., 2], b[..., 0] + b[..., 2])
    iy1 = jnp.minimum(a[..., 1] + a[..., 3], b[..., 1] + b[..., 3])
    inter = jnp.maximum(ix1 - ix0, 0.0) * jnp.maximum(iy1 - iy0, 0.0)
    union = box_area(a) + box_area(b) - inter
    # Safe division: where the union is empty the ratio is defined as 0.
    return jnp.where(union > 0, inter / jnp.where(union > 0, union, 1.0), 0.0)


def centre_distance(a: Array, b: Array) -> Array:
    """Euclidean distance between the centres of ``[..., 4] (x, y, w, h)`` boxes."""
    a = jnp.asarray(a, jnp.float32)
    b = jnp.asarray(b, jnp.float32)
    dx = (a[..., 0] + a[..., 2] / 2) - (b[..., 0] + b[..., 2] / 2)
    dy = (a[..., 1] + a[..., 3] / 2) - (b[..., 1] + b[..., 3] / 2)
    return jnp.sqrt(dx * dx + dy * dy)
