"""Spin images and their similarity (thesis 4.2, App. G; Johnson 1997).

An oriented point ``(p, n)`` maps every surface point ``x`` to

    beta  = n . (x - p)                          (signed height above the tangent plane)
    alpha = sqrt(|x - p|^2 - beta^2)             (distance from the normal line)

and the spin image is the 2D histogram of ``(alpha, beta)`` with bilinear
accumulation (thesis eq. 4.5). Bins are square, ``bin_size`` mm (a multiple
of the mesh resolution); the image is ``width x width``. Image coordinates:

    a = alpha / bin_size                 (column, 0 at the normal line)
    b = width / 2 - beta / bin_size      (row, 0 at the top = largest beta)

A point is accumulated when ``0 <= a < width - 1`` and ``0 <= b < width - 1``
(its four bilinear corners fall inside the image; App. G's C++ code tests the
same) and when the angle between its normal and ``n`` is below the support
angle (App. G, eq. G.2). The support is therefore a cylinder of radius
``(width - 1) * bin_size`` and half-height ``width / 2 * bin_size`` around the
normal line.

Points live on the pixel grid of a depth window (``points [H, W, 3]``,
``normals [H, W, 3]``, ``valid [H, W]``) and queries are window pixels. Each
query only visits the ``(2R + 1)^2`` pixels of a square patch around it
(``patch_radius = R``). With bins tied to the mesh resolution, the support of
a spin image covers about the same number of window pixels at any distance
(about 30 for ``width = 20`` and one mesh resolution per bin), so a fixed
patch replaces a pass over all points of the body. ``complete`` reports,
per query, that no pixel on the patch border is inside the support; for a
connected surface this means the support fits in the patch and the image
equals the one computed over every point.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax import Array, lax

__all__ = [
    "spin_coordinates",
    "support_patch_radius",
    "spin_images",
    "overlap_count",
    "spin_correlation",
    "johnson_lambda",
    "spin_similarity",
]


_MISS = 2**30  # cell index of a point outside the image (dropped by the scatter)


def spin_coordinates(points: Array, p: Array, n: Array) -> tuple[Array, Array]:
    """``(alpha, beta)`` of ``points [..., 3]`` in the spin map of the oriented point ``(p, n)``.

    Thesis eq. 4.4.
    """
    d = jnp.asarray(points, jnp.float32) - p
    beta = jnp.sum(d * n, -1)
    alpha = jnp.sqrt(jnp.maximum(jnp.sum(d * d, -1) - beta * beta, 0.0))
    return alpha, beta


def support_patch_radius(bin_size: float, width: int, z_near_mm: float, focal_px: float) -> int:
    """The smallest ``patch_radius`` holding the support of any query at depth >= ``z_near_mm``.

    The support reaches ``bin_size * sqrt((width - 1)^2 + (width / 2)^2)`` mm from
    the query point; a pixel offset of ``k`` pixels at depth ``z`` is at least
    ``k * z / focal_px`` mm away laterally, so the support spans at most that
    distance over ``z_near_mm / focal_px`` pixels (one pixel of slack). Pure
    Python (static): call it outside ``jit``; ``complete`` still checks it.
    """
    reach = float(bin_size) * math.hypot(width - 1, width / 2)
    pitch = float(z_near_mm) / float(focal_px)
    return int(math.ceil(reach / pitch)) + 1


def _spin_one(
    feat: Array, q: Array, bin_size: Array, width: int, cos_support: float, radius: int
) -> tuple[Array, Array]:
    """One spin image from a padded ``feat [6, H + 2R, W + 2R]`` (xyz, normal; NaN = invalid)."""
    side = 2 * radius + 1
    patch = lax.dynamic_slice(feat, (0, q[0], q[1]), (6, side, side)).reshape(6, side * side)
    cen = feat[:, q[0] + radius, q[1] + radius]
    inv = 1.0 / bin_size
    dx = patch[0] - cen[0]
    dy = patch[1] - cen[1]
    dz = patch[2] - cen[2]
    beta = dx * cen[3] + dy * cen[4] + dz * cen[5]
    alpha = jnp.sqrt(jnp.maximum(dx * dx + dy * dy + dz * dz - beta * beta, 0.0))
    cosn = patch[3] * cen[3] + patch[4] * cen[4] + patch[5] * cen[5]
    # Points outside the support angle (or invalid: NaN) are pushed out of the image.
    a = jnp.where(cosn >= cos_support, alpha * inv, jnp.inf)
    b = width / 2 - beta * inv
    # Materialise (a, b) once: later expressions each read them instead of
    # recomputing the geometry (XLA on CPU would otherwise duplicate it per output).
    ab = lax.optimization_barrier(jnp.stack([a, b]))
    a, b = ab[0], ab[1]
    m = width - 1
    inside = (a >= 0) & (a < m) & (b >= 0) & (b < m)
    j0 = jnp.floor(a)
    i0 = jnp.floor(b)
    fa = a - j0
    fb = b - i0
    # Misses (most of the patch lies off the support) get an index past the end: XLA on
    # CPU skips a dropped update's write, where a dump cell would take every one.
    idx = jnp.where(inside, i0 * m + j0, _MISS).astype(jnp.int32)
    vals = jnp.stack([(1 - fb) * (1 - fa), (1 - fb) * fa, fb * (1 - fa), fb * fa], -1)
    # One scatter of 4-vectors into the (width-1)^2 cells ...
    h4 = jnp.zeros((m * m, 4), jnp.float32).at[idx].add(vals, mode="drop").reshape(m, m, 4)
    # ... then each corner histogram is shifted into place.
    img = (
        jnp.pad(h4[..., 0], ((0, 1), (0, 1)))
        + jnp.pad(h4[..., 1], ((0, 1), (1, 0)))
        + jnp.pad(h4[..., 2], ((1, 0), (0, 1)))
        + jnp.pad(h4[..., 3], ((1, 0), (1, 0)))
    )
    border = inside.reshape(side, side)
    touches = (
        jnp.any(border[0]) | jnp.any(border[-1]) | jnp.any(border[:, 0]) | jnp.any(border[:, -1])
    )
    return img, ~touches


def spin_images(
    points: Array,
    normals: Array,
    valid: Array,
    queries: Array,
    bin_size: Array,
    *,
    width: int = 20,
    support_angle_deg: float = 60.0,
    patch_radius: int = 32,
    batch_size: int = 32,
    needed: Array | None = None,
) -> tuple[Array, Array]:
    """Spin images of query pixels over the valid points of a depth window.

    points / normals: ``[H, W, 3]`` mm / unit vectors; valid: ``[H, W] bool``
    (body pixels with a normal). queries: ``[N, 2] int32`` (row, col) window
    pixels, clipped into the window; the oriented point of a query is its
    pixel's point and normal (an invalid query pixel gives an empty image).
    bin_size: mm (scalar, traced). Returns ``(images [N, width, width]
    float32, complete [N] bool)``. Each distinct query pixel is computed once
    (particles share pixels), ``batch_size`` pixels at a time in a loop that
    stops after the last distinct one; results do not depend on either.
    ``needed [N] bool`` (optional) names the queries whose images the caller reads:
    the others get an empty image and ``complete`` False without being computed (they
    stand in for a needed pixel, so they add no distinct pixel to the loop).
    """
    p = jnp.asarray(points, jnp.float32)
    nrm = jnp.asarray(normals, jnp.float32)
    ok = jnp.asarray(valid, bool)
    h, w = ok.shape
    r = patch_radius
    feat = jnp.concatenate([jnp.where(ok[..., None], p, jnp.nan), nrm], -1)
    feat = jnp.pad(feat, ((r, r), (r, r), (0, 0)), constant_values=jnp.nan).transpose(2, 0, 1)
    q = jnp.asarray(queries, jnp.int32)
    q = jnp.stack([jnp.clip(q[..., 0], 0, h - 1), jnp.clip(q[..., 1], 0, w - 1)], -1)
    cos_support = math.cos(math.radians(support_angle_deg))
    bin_size = jnp.asarray(bin_size, jnp.float32)

    def one(qq):
        return _spin_one(feat, qq, bin_size, width, cos_support, r)

    shape = q.shape[:-1]
    qf = q.reshape(-1, 2)
    batch = min(batch_size, max(qf.shape[0], 1))
    if needed is None:
        imgs, complete = _map_distinct(one, qf, w, batch, (width, width))
        return imgs.reshape(shape + (width, width)), complete.reshape(shape)
    need = jnp.broadcast_to(jnp.asarray(needed, bool), shape).reshape(-1)
    qf = jnp.where(need[:, None], qf, qf[jnp.argmax(need)])
    imgs, complete = _map_distinct(one, qf, w, batch, (width, width))
    imgs = jnp.where(need[:, None, None], imgs, 0.0)
    return imgs.reshape(shape + (width, width)), (complete & need).reshape(shape)


def _map_distinct(one, queries: Array, w: int, batch: int, image_shape: tuple[int, int]):
    """``one`` (pixel -> (image, complete)) at every row of ``queries [Q, 2]``, computed once
    per distinct pixel: the distinct pixels are packed first (sorted by ``row * w + col``),
    ``batch`` at a time, for as many batches as there are distinct pixels, then each query
    reads its pixel's result."""
    n = queries.shape[0]
    n_pad = -(-n // batch) * batch
    flat = queries[:, 0] * w + queries[:, 1]
    order = jnp.argsort(flat)
    sorted_flat = flat[order]
    new = jnp.concatenate([jnp.ones((1,), bool), sorted_flat[1:] != sorted_flat[:-1]])
    slot_sorted = jnp.cumsum(new.astype(jnp.int32)) - 1
    slot = jnp.zeros((n,), jnp.int32).at[order].set(slot_sorted)
    distinct = jnp.zeros((n_pad, 2), jnp.int32).at[slot].set(queries)
    n_batches = (slot_sorted[-1] + batch) // batch
    out = (jnp.zeros((n_pad, *image_shape), jnp.float32), jnp.zeros((n_pad,), bool))

    def body(i, acc):
        rows = lax.dynamic_slice_in_dim(distinct, i * batch, batch)
        imgs, complete = jax.vmap(one)(rows)
        return (
            lax.dynamic_update_slice_in_dim(acc[0], imgs, i * batch, 0),
            lax.dynamic_update_slice_in_dim(acc[1], complete, i * batch, 0),
        )

    imgs, complete = lax.fori_loop(0, n_batches, body, out)
    return imgs[slot], complete[slot]


def overlap_count(a: Array, b: Array) -> Array:
    """Number of bins filled (``> 0``) in both images ``[..., W, W]``."""
    return jnp.sum((a > 0) & (b > 0), axis=(-2, -1))


def spin_correlation(a: Array, b: Array) -> tuple[Array, Array]:
    """Linear correlation R (thesis eq. 4.6) over the bins filled in both images, and their count N.

    Images ``[..., W, W]`` broadcast. R is 0 when N < 2 or either image is
    constant over the overlap (no evidence either way).
    """
    a = jnp.asarray(a, jnp.float32)
    b = jnp.asarray(b, jnp.float32)
    both = (a > 0) & (b > 0)
    n = jnp.sum(both, axis=(-2, -1)).astype(jnp.float32)
    aa = jnp.where(both, a, 0.0)
    bb = jnp.where(both, b, 0.0)
    sa = jnp.sum(aa, (-2, -1))
    sb = jnp.sum(bb, (-2, -1))
    sab = jnp.sum(aa * bb, (-2, -1))
    saa = jnp.sum(aa * aa, (-2, -1))
    sbb = jnp.sum(bb * bb, (-2, -1))
    num = n * sab - sa * sb
    va = n * saa - sa * sa
    vb = n * sbb - sb * sb
    den2 = va * vb
    ok = (n >= 2) & (va > 0) & (vb > 0)
    r = jnp.where(ok, num / jnp.sqrt(jnp.where(ok, den2, 1.0)), 0.0)
    return jnp.clip(r, -1.0, 1.0), n


def johnson_lambda(overlaps: Array, axis=-1) -> Array:
    """lambda = half the median overlap count of the images compared (thesis 4.2.2, Johnson)."""
    return 0.5 * jnp.median(jnp.asarray(overlaps, jnp.float32), axis=axis)


def spin_similarity(a: Array, b: Array, lam: Array, max_r: float = 0.999) -> Array:
    """Similarity ``C = atanh(R)^2 - lam / (N - 3)`` (thesis eq. 4.7 read as Johnson's criterion).

    The printed eq. 4.7 puts the whole expression inside atanh; Johnson's
    original (and the thesis text around it) is the squared Fisher transform
    of R minus a variance penalty, used here. Two guards make it a similarity:
    R is clipped at 0 from below (``atanh(R)^2`` would score anti-correlated
    images as highly as correlated ones) and at ``max_r`` from above (finite
    values), and ``N <= 3`` overlapping bins give ``-inf`` (no valid match).
    """
    r, n = spin_correlation(a, b)
    r = jnp.clip(r, 0.0, max_r)
    z = jnp.arctanh(r)
    return jnp.where(n > 3, z * z - lam / jnp.maximum(n - 3, 1.0), -jnp.inf)
