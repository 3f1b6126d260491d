"""The colour layer's appearance model: stripe histograms, centre-surround contrast weights
and the layout template, with the per-pixel planes and per-box scores they give.

Boxes are ``(x, y, w, h)`` top-left pixels; ``[N, 8]`` particles are in the centre-form
state layout of ``cpf_jax.dynamics``. Counts are exact (``kernels.histogram``).
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array

from cpf_jax.colour.config import (
    COLOUR_BINS,
    LAYOUT_FEATURES,
    UNSEEN,
    ColourConfig,
    bin_index,
    n_bins_of,
)
from cpf_jax.kernels import boxes as box_ops
from cpf_jax.kernels.histogram import (
    box_histograms,
    grid_ncc,
    grid_sums,
    integral_image,
    normalise_counts,
    rect_sums,
    squared_bhattacharyya,
)
from cpf_jax.types import Frame

__all__ = [
    "CONTRAST_SCALE",
    "MIXTURE_MAX",
    "RING_EXTRAPOLATION_MAX",
    "box_columns",
    "box_parts",
    "stripe_rects",
    "reference_histogram",
    "stripe_distances",
    "contrast_weights",
    "mixture_weights",
    "contrast_values",
    "contrast_table",
    "contrast_scores",
    "luminance",
    "layout_values",
    "layout_table",
    "layout_vectors",
    "mirror_layout",
    "layout_scores",
]

#: Largest factor by which the in-frame part of a ring cut off by the frame is scaled up
#: to the ring's full area (a sliver of ring is a poor sample).
RING_EXTRAPOLATION_MAX = 4.0
#: Bound of the "mixture" weights (log-likelihood ratios), so that integer sums stay exact.
MIXTURE_MAX = 4.0
#: Contrast weights are summed as integers in units of ``1 / CONTRAST_SCALE``: with
#: ``|weight| <= MIXTURE_MAX`` the int32 four-corner difference is exact (modular
#: arithmetic) for any rect of fewer than 2^31 / 4096 = 524,288 pixels.
CONTRAST_SCALE = 1024.0

# tan(22.5 deg): the edges between the four unsigned orientation bins of "gradient".
_TAN_22_5 = 0.41421356


def box_parts(boxes_xywh: Array, parts: int) -> Array:
    """Split ``[..., 4]`` xywh boxes into ``parts`` horizontal stripes ``[..., parts, 4]``.

    Stripe edges are shared, so after corner rounding the stripes' pixels partition the
    box's pixels exactly.
    """
    b = jnp.asarray(boxes_xywh, jnp.float32)[..., None, :]
    k = jnp.arange(parts, dtype=jnp.float32)
    y = b[..., 1] + b[..., 3] * k / parts
    h = jnp.broadcast_to(b[..., 3] / parts, y.shape)
    x = jnp.broadcast_to(b[..., 0], y.shape)
    w = jnp.broadcast_to(b[..., 2], y.shape)
    return jnp.stack([x, y, w, h], axis=-1)


def box_columns(particles: Array) -> tuple[Array, Array, Array, Array]:
    """``(x, y, w, h)`` columns ``[N]`` of ``[N, 8]`` particle boxes."""
    cx, cy, w, h = particles[..., 0], particles[..., 1], particles[..., 4], particles[..., 5]
    return cx - w / 2, cy - h / 2, w, h


def stripe_rects(boxes: tuple[Array, Array, Array, Array], parts: int | None = None):
    """``RectColumns`` of ``(x, y, w, h)`` box columns ``[N]``: ``[N]`` each, or ``[N, parts]``
    for the stripes of ``box_parts`` (the same pixels, without a ``[..., 4]`` stack)."""
    x, y, w, h = boxes
    if parts is None:
        return box_ops.xywh_columns_to_rect(x, y, w, h)
    k = jnp.arange(parts, dtype=jnp.float32)
    ys = y[:, None] + h[:, None] * k / parts
    hs = jnp.broadcast_to(h[:, None] / parts, ys.shape)
    xs, ws = (jnp.broadcast_to(v[:, None], ys.shape) for v in (x, w))
    return box_ops.xywh_columns_to_rect(xs, ys, ws, hs)


def reference_histogram(
    frame: Frame, box_xywh: Array, bins: tuple[int, ...] = COLOUR_BINS, parts: int = 1
) -> Array:
    """Normalised H-S(V) histograms ``[parts, B]`` of the stripes of an ``(x, y, w, h)`` box."""
    idx = bin_index(frame.colour, bins)
    rects = box_ops.xywh_to_rect(box_parts(box_xywh, parts))
    return normalise_counts(box_histograms(idx, rects, n_bins_of(bins)))


def stripe_distances(sqrt_q: Array, counts: Array, total: Array) -> Array:
    """Mean over the stripes of the squared Bhattacharyya distance (thesis eq. 3.7) of
    stripe counts ``[c, K, B]`` (``total [c, K]`` pixels) to references ``sqrt(q) [K, B]``:
    ``[c]``. With one stripe it is the thesis's distance."""
    return jnp.mean(squared_bhattacharyya(counts, sqrt_q, total), axis=-1)


def _box_and_ring_counts(
    frame: Frame, box_xywh: Array, bins: tuple[int, ...], margin: float
) -> tuple[Array, Array]:
    """Bin counts ``[B]`` inside a box and in the ring around it (the box grown by
    ``margin`` of its size per side, minus the box); a ring cut off by the frame has its
    counts scaled to its full area (at most ``RING_EXTRAPOLATION_MAX`` times), so that a
    colour's background share does not depend on how much of the surround is in view."""
    idx = bin_index(frame.colour, bins)
    box = jnp.asarray(box_xywh, jnp.float32)
    grow = jnp.array([-margin, -margin, 2 * margin, 2 * margin], jnp.float32)
    grown = box + grow * box[jnp.array([2, 3, 2, 3])]
    rects = box_ops.xywh_to_rect(jnp.stack([box, grown]))
    h = box_histograms(idx, rects, n_bins_of(bins))
    ring = jnp.maximum(h[1] - h[0], 0.0)
    intended = grown[2] * grown[3] - box[2] * box[3]
    seen = jnp.sum(ring)  # every pixel has a bin: the ring's in-frame area
    ring = ring * jnp.clip(intended / jnp.maximum(seen, 1.0), 1.0, RING_EXTRAPOLATION_MAX)
    return h[0], ring


def contrast_weights(
    frame: Frame,
    box_xywh: Array,
    bins: tuple[int, ...] = COLOUR_BINS,
    margin: float = 0.5,
    threshold: float | Array = 0.4,
    unseen: str = "background",
) -> Array:
    """Linear per-bin contrast weights ``[B] = P(person | bin) - threshold`` of a box and
    its surround (``ColourConfig.contrast = "linear"``).

    ``P(person | b) = (n_in(b) + k p0) / (n_in(b) + n_ring(b) + k)`` with the pixel counts
    inside the box and in the ring around it (distractor-aware colour tracking, Possegger
    et al. 2015) and a prior of ``k`` pixels (1 % of the box's) at ``p0``: 0 for
    ``unseen = "background"`` (unseen colours weigh ``-threshold``), ``threshold`` for
    ``"neutral"`` (they weigh 0). A box's summed weights peak at the person's extent,
    where a histogram distance alone is blind to scale.
    """
    if unseen not in UNSEEN:
        raise ValueError(f"unseen must be one of {UNSEEN}, got {unseen!r}")
    inside, ring = _box_and_ring_counts(frame, box_xywh, bins, margin)
    k = 0.01 * jnp.maximum(jnp.sum(inside), 1.0)
    prior = k * threshold if unseen == "neutral" else 0.0
    return (inside + prior) / (inside + ring + k) - threshold


def mixture_weights(
    frame: Frame,
    box_xywh: Array,
    bins: tuple[int, ...] = COLOUR_BINS,
    margin: float = 0.5,
    fill: float | Array = 0.7,
) -> Array:
    """Per-bin log-likelihood ratios ``[B]`` of a person-box pixel against a background
    pixel (``ColourConfig.contrast = "mixture"``).

    A person's box holds a share ``1 - fill`` of background, so its colours follow
    ``p_box = fill p_obj + (1 - fill) p_bg`` with ``p_bg`` the ring's (smoothed) colours
    and ``p_obj`` the box's less the background's share; a pixel of bin ``b`` weighs
    ``log((1 - fill) + fill p_obj(b) / p_bg(b))``, clipped to ``[-MIXTURE_MAX,
    MIXTURE_MAX]``. Background colours that also fill the initial box (the floor between
    the legs) weigh about ``log(1 - fill)``, where the linear weights give them about 0.
    """
    inside, ring = _box_and_ring_counts(frame, box_xywh, bins, margin)
    fill = jnp.clip(jnp.asarray(fill, jnp.float32), 0.01, 0.99)
    n = inside.shape[0]
    p_bg = ring + 1e-3 * jnp.maximum(jnp.sum(ring), 1.0) / n + 1e-6
    p_bg = p_bg / jnp.sum(p_bg)
    p_box = inside / jnp.maximum(jnp.sum(inside), 1.0)
    p_obj = jnp.maximum(p_box - (1.0 - fill) * p_bg, 0.0) + 1e-6
    p_obj = p_obj / jnp.sum(p_obj)
    w = jnp.log((1.0 - fill) + fill * p_obj / p_bg)
    return jnp.clip(w, -MIXTURE_MAX, MIXTURE_MAX)


def contrast_values(bin_idx: Array, contrast: Array) -> Array:
    """Per-pixel contrast weight and its positive part ``[H, W, 2] int32``, in units of
    ``1 / CONTRAST_SCALE`` (pixels with no bin weigh 0)."""
    w = jnp.stack([contrast, jnp.maximum(contrast, 0.0)], axis=-1)
    w = jnp.round(w * CONTRAST_SCALE).astype(jnp.int32)  # [B, 2]
    ok = (bin_idx >= 0) & (bin_idx < contrast.shape[0])
    return jnp.where(ok[..., None], w[jnp.clip(bin_idx, 0, contrast.shape[0] - 1)], 0)


def contrast_table(bin_idx: Array, contrast: Array) -> Array:
    """Summed-area table ``[H+1, W+1, 2] int32`` of ``contrast_values``."""
    return integral_image(contrast_values(bin_idx, contrast))


def contrast_scores(
    config: ColourConfig, table: Array, boxes: tuple[Array, ...], area: Array
) -> Array:
    """Centre-surround scores ``[N]`` of box columns from a contrast table: the box's summed
    weights less the person-coloured pixels of a ring ``ring_margin`` wide around it,
    over ``area`` (the previous estimate's, so that the score's scale does not change as
    the person comes closer)."""
    sums = rect_sums(table, stripe_rects(boxes), 2, config.chunk) / CONTRAST_SCALE
    score = sums[:, 0]
    if config.ring_margin > 0:
        m = config.ring_margin
        x, y, w, h = boxes
        grown = (x + -m * w, y + -m * h, w + 2 * m * w, h + 2 * m * h)
        grown_sums = rect_sums(table, stripe_rects(grown), 2, config.chunk) / CONTRAST_SCALE
        score = score - (grown_sums[:, 1] - sums[:, 1])
    return score / jnp.maximum(area, 1.0)


def luminance(colour: Array) -> Array:
    """``[H, W, 3] uint8`` RGB -> ``[H, W] int32`` luma ``round(0.299 R + 0.587 G + 0.114 B)``
    (ITU-R BT.601, OpenCV's ``COLOR_RGB2GRAY``)."""
    c = colour.astype(jnp.int32)
    return (299 * c[..., 0] + 587 * c[..., 1] + 114 * c[..., 2] + 500) // 1000


def layout_values(colour: Array, feature: str = "luminance") -> Array:
    """The layout term's per-pixel feature ``[H, W, c] int32``.

    ``"luminance"`` (c = 1): ``luminance``. ``"gradient"`` (c = 4): the luminance's
    gradient magnitude (central differences, edges replicated), rounded, in one of four
    unsigned orientation bins centred on 0, 45, 90 and 135 degrees: hard-binned HOG
    (Dalal and Triggs 2005), the figure's outline when its clothes are the background's
    colours.
    """
    lum = luminance(colour)
    if feature == "luminance":
        return lum[..., None]
    if feature != "gradient":
        raise ValueError(f"feature must be one of {LAYOUT_FEATURES}, got {feature!r}")
    p = jnp.pad(lum, 1, mode="edge").astype(jnp.float32)
    gx = (p[1:-1, 2:] - p[1:-1, :-2]) * 0.5
    gy = (p[2:, 1:-1] - p[:-2, 1:-1]) * 0.5
    ax, ay = jnp.abs(gx), jnp.abs(gy)
    diagonal = jnp.where(gx * gy > 0, 1, 3)
    b = jnp.where(ay <= _TAN_22_5 * ax, 0, jnp.where(ax <= _TAN_22_5 * ay, 2, diagonal))
    mag = jnp.round(jnp.sqrt(gx * gx + gy * gy)).astype(jnp.int32)
    return jnp.where(b[..., None] == jnp.arange(4), mag[..., None], 0)


def layout_table(colour: Array, feature: str = "luminance") -> Array:
    """Summed-area table ``[H+1, W+1, c] int32`` of ``layout_values``."""
    return integral_image(layout_values(colour, feature))


def layout_vectors(table: Array, boxes_xywh: Array, grid: tuple[int, int]) -> Array:
    """Zero-mean, unit-norm vectors ``[..., rows * cols * c]`` of the mean feature in each
    box's ``grid`` cells (row-major, channels last), from a summed-area table.

    Their dot product is the normalised cross-correlation of two boxes' cell means,
    invariant to a gain and an offset of the feature. Cells outside the frame count as
    zero; a box of uniform feature gives the zero vector (correlation 0).
    """
    rows, cols = grid
    sums, counts = grid_sums(table, boxes_xywh, rows, cols)
    means = sums.astype(jnp.float32) / jnp.maximum(counts, 1).astype(jnp.float32)[..., None]
    v = means.reshape(*means.shape[:-3], -1)
    v = v - jnp.mean(v, axis=-1, keepdims=True)
    norm = jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True))
    return v / jnp.maximum(norm, 1e-3)


def mirror_layout(template: Array, grid: tuple[int, int], feature: str = "luminance") -> Array:
    """The layout template ``[rows * cols * c]`` of the horizontally mirrored box: columns
    reversed and, for ``"gradient"``, the 45 and 135 degree bins swapped."""
    rows, cols = grid
    c = 4 if feature == "gradient" else 1
    t = template.reshape(rows, cols, c)[:, ::-1]
    if feature == "gradient":
        t = t[..., jnp.array([0, 3, 2, 1])]
    return t.reshape(template.shape)


def layout_scores(
    config: ColourConfig, table: Array, boxes: tuple[Array, ...], template: Array
) -> Array:
    """Normalised cross-correlation ``[N]`` of the boxes' layout vectors with the template
    (the better of it and its mirror image with ``layout_mirror``)."""
    if config.layout_mirror:
        mirror = mirror_layout(template, config.layout, config.layout_feature)
        template = jnp.stack([template, mirror])
    ncc = grid_ncc(table, boxes, template, *config.layout, config.chunk)
    return jnp.max(ncc, axis=-1) if config.layout_mirror else ncc
