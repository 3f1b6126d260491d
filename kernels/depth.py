"""Depth pre-processing in a fixed-size window: crop/resample, hole filling,
back-projection, vertex normals, head/neck split (thesis 4.1-4.2).

Conventions
-----------
* Frame images are ``[H, W]``; pixel ``(row r, col c)`` covers the continuous
  square ``[c, c+1) x [r, r+1)`` (``cpf_jax.kernels.boxes``). The pinhole
  model uses the pixel *index* as image coordinate, ``u = fx X / Z + cx`` with
  ``u = c``, ``v = r`` (``cpf_jax.types.Intrinsics``), so a continuous position
  ``(x, y)`` corresponds to ``u = x - 0.5``, ``v = y - 0.5``.
* Camera coordinates are millimetres, X right, Y down, Z forward.
* Every kernel works on a **window** of static shape ``[Hw, Ww]`` (e.g.
  ``256 x 192``) cut from the frame around a box. Window pixel ``(i, j)``
  samples the frame pixel containing ``(x0 + (j + 0.5) s, y0 + (i + 0.5) s)``
  (nearest neighbour: depth is never interpolated across edges), where
  ``(x0, y0)`` is the window origin and ``s >= 1`` the number of frame pixels
  per window pixel (``Window``). When the box fits, ``s = 1`` and the window
  is an exact crop. Window pixels outside the frame or outside the (slightly
  enlarged) box are invalid (depth 0), with static shapes and masks instead
  of dynamic crops.
* Depth ``0`` means missing.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array, lax

from .graph import FORWARD, neighbour

__all__ = [
    "Window",
    "window_geometry",
    "window_pixels",
    "crop_window",
    "frame_to_window",
    "window_to_frame",
    "fill_holes",
    "back_project",
    "project",
    "vertex_normals",
    "silhouette_widths",
    "HeadSplit",
    "head_neck_split",
    "nearest_true",
    "erode",
    "foreground_mask",
]

# The 8 neighbours in angular order around a pixel (d_row, d_col): E, SE, S, SW, W, NW, N, NE.
RING: tuple[tuple[int, int], ...] = (
    (0, 1),
    (1, 1),
    (1, 0),
    (1, -1),
    (0, -1),
    (-1, -1),
    (-1, 0),
    (-1, 1),
)


class Window(NamedTuple):
    """Where a ``[Hw, Ww]`` window sits in the frame.

    origin: ``[2] float32`` ``(x0, y0)``, continuous frame coordinates of the window's
    top-left corner.
    scale: ``[] float32`` frame pixels per window pixel.
    """

    origin: Array
    scale: Array


def window_geometry(
    box: Array, shape: tuple[int, int], margin: float = 0.1, min_scale: float = 1.0
) -> Window:
    """Window of static ``shape = (Hw, Ww)`` centred on ``box: [4] (x, y, w, h)``.

    The box is enlarged by ``margin`` of its size on every side; the scale is
    the smallest ``s >= min_scale`` at which the enlarged box fits. The origin
    is snapped to whole pixels so that ``s = 1`` gives an exact crop.
    """
    hw, ww = shape
    x, y, w, h = jnp.moveaxis(jnp.asarray(box, jnp.float32), -1, 0)
    w2 = jnp.maximum(w, 1.0) * (1 + 2 * margin)
    h2 = jnp.maximum(h, 1.0) * (1 + 2 * margin)
    s = jnp.maximum(jnp.maximum(h2 / hw, w2 / ww), min_scale)
    cx, cy = x + w / 2, y + h / 2
    x0 = jnp.floor(cx - ww * s / 2 + 0.5)
    y0 = jnp.floor(cy - hw * s / 2 + 0.5)
    return Window(jnp.stack([x0, y0], -1), s)


def window_pixels(win: Window, shape: tuple[int, int]) -> tuple[Array, Array]:
    """Frame pixel indices sampled by the window: rows ``[Hw] int32``, cols ``[Ww] int32``.

    Indices may lie outside the frame.
    """
    hw, ww = shape
    x0, y0 = win.origin[..., 0], win.origin[..., 1]
    rows = jnp.floor(y0 + (jnp.arange(hw, dtype=jnp.float32) + 0.5) * win.scale).astype(jnp.int32)
    cols = jnp.floor(x0 + (jnp.arange(ww, dtype=jnp.float32) + 0.5) * win.scale).astype(jnp.int32)
    return rows, cols


def frame_to_window(win: Window, xy: Array) -> Array:
    """Continuous frame ``(x, y) [..., 2]`` -> continuous window ``(j, i)`` = (col, row)."""
    return (jnp.asarray(xy, jnp.float32) - win.origin) / win.scale


def window_to_frame(win: Window, ji: Array) -> Array:
    """Continuous window ``(j, i)`` ``[..., 2]`` -> continuous frame ``(x, y)`` ``[..., 2]``."""
    return jnp.asarray(ji, jnp.float32) * win.scale + win.origin


def crop_window(
    depth: Array, box: Array, shape: tuple[int, int], margin: float = 0.1, min_scale: float = 1.0
):
    """Cut a ``[Hw, Ww]`` window around ``box`` from a ``[H, W]`` depth frame.

    Returns ``(win_depth [Hw, Ww] float32 mm, window, rows [Hw], cols [Ww], roi [Hw, Ww] bool)``.
    ``roi`` marks window pixels inside the frame and the enlarged box;
    ``win_depth`` is 0 outside it and where the frame depth is missing.
    """
    depth = jnp.asarray(depth)
    hf, wf = depth.shape
    win = window_geometry(box, shape, margin, min_scale)
    rows, cols = window_pixels(win, shape)
    x, y, w, h = jnp.asarray(box, jnp.float32)
    mx, my = margin * w, margin * h
    # Window pixel centres in frame coordinates decide membership of the enlarged box.
    yc = win.origin[1] + (jnp.arange(shape[0], dtype=jnp.float32) + 0.5) * win.scale
    xc = win.origin[0] + (jnp.arange(shape[1], dtype=jnp.float32) + 0.5) * win.scale
    in_r = (rows >= 0) & (rows < hf) & (yc >= y - my) & (yc < y + h + my)
    in_c = (cols >= 0) & (cols < wf) & (xc >= x - mx) & (xc < x + w + mx)
    roi = in_r[:, None] & in_c[None, :]
    d = jnp.take(depth, jnp.clip(rows, 0, hf - 1), axis=0)
    d = jnp.take(d, jnp.clip(cols, 0, wf - 1), axis=1)
    d = jnp.where(roi, d.astype(jnp.float32), 0.0)
    return d, win, rows, cols, roi


_SORT8 = (
    (0, 1),
    (2, 3),
    (4, 5),
    (6, 7),
    (0, 2),
    (1, 3),
    (4, 6),
    (5, 7),
    (1, 2),
    (5, 6),
    (0, 4),
    (3, 7),
    (1, 5),
    (2, 6),
    (1, 4),
    (3, 6),
    (2, 4),
    (3, 5),
    (3, 4),
)


def fill_holes(depth: Array, region: Array | None = None) -> Array:
    """Fill missing (0) pixels with the median of their non-missing 3x3 neighbours.

    Thesis 4.1.1, eq. 4.1.

    depth: ``[H, W]`` mm. region: optional ``[H, W] bool`` (the ROI): only
    region pixels are filled and only region pixels count as neighbours.
    One pass, as in the thesis: a hole pixel with no valid neighbour stays 0.
    An even number of neighbours gives the mean of the two middle values
    (``numpy.median``). Returns ``[H, W] float32``.
    """
    z = jnp.asarray(depth, jnp.float32)
    region = jnp.ones(z.shape, bool) if region is None else jnp.asarray(region, bool)
    ok = region & (z > 0)
    v = [neighbour(jnp.where(ok, z, jnp.inf), dr, dc, jnp.inf) for dr, dc in RING]
    # Batcher's 19-comparator sorting network: elementwise min/max, no sort op.
    for a, b in _SORT8:
        v[a], v[b] = jnp.minimum(v[a], v[b]), jnp.maximum(v[a], v[b])
    k = sum(jnp.isfinite(x).astype(jnp.int32) for x in v)  # missing (inf) sort last
    i_lo = jnp.maximum((k - 1) // 2, 0)
    i_hi = jnp.maximum(k // 2, 0)
    lo = sum(jnp.where(i_lo == j, v[j], 0.0) for j in range(8))
    hi = sum(jnp.where(i_hi == j, jnp.where(jnp.isfinite(v[j]), v[j], 0.0), 0.0) for j in range(8))
    med = jnp.where(k > 0, 0.5 * (lo + jnp.where(k > 1, hi, lo)), 0.0)
    return jnp.where(region & (z <= 0), med, jnp.where(region, z, 0.0))


def back_project(depth: Array, rows: Array, cols: Array, intrinsics) -> Array:
    """``[Hw, Ww, 3]`` camera points of window pixels (thesis 4.2, eq. 4.2).

    ``X = Z (u - cx) / fx, Y = Z (v - cy) / fy, Z = depth``.

    rows ``[Hw]`` / cols ``[Ww]``: the frame pixel indices ``v`` / ``u`` the window sampled.
    """
    fx, fy, cx, cy = intrinsics
    z = jnp.asarray(depth, jnp.float32)
    u = jnp.asarray(cols, jnp.float32)[None, :]
    v = jnp.asarray(rows, jnp.float32)[:, None]
    return jnp.stack([z * (u - cx) / fx, z * (v - cy) / fy, z], axis=-1)


def project(points: Array, intrinsics) -> Array:
    """Camera points ``[..., 3]`` -> pixel coordinates ``(u, v) [..., 2]`` (index convention)."""
    fx, fy, cx, cy = intrinsics
    p = jnp.asarray(points, jnp.float32)
    z = jnp.where(p[..., 2] > 0, p[..., 2], 1.0)
    return jnp.stack([fx * p[..., 0] / z + cx, fy * p[..., 1] / z + cy], axis=-1)


def _spokes(weights: Array) -> Array:
    """``[8, H, W] bool``: the surface-graph edge from each pixel towards ``RING[k]`` exists."""
    fwd = {d: jnp.isfinite(weights[k]) for k, d in enumerate(FORWARD)}
    out = []
    for dr, dc in RING:
        if (dr, dc) in fwd:
            out.append(fwd[(dr, dc)])
        else:  # the reverse edge is stored at the neighbour
            out.append(neighbour(fwd[(-dr, -dc)], dr, dc, False))
    return jnp.stack(out)


def vertex_normals(points: Array, weights: Array, smooth: int = 0) -> tuple[Array, Array]:
    """Unit vertex normals oriented towards the sensor (thesis 4.2.1, eq. 4.3).

    Mean of the face normals weighted by their angle at the vertex (MWA).

    points: ``[H, W, 3]`` mm; weights: ``[4, H, W]`` surface graph (``inf`` = no edge).
    The faces around a pixel are the 8 triangles of its one-ring fan
    ``(p, n_k, n_k+1)`` over the neighbours in angular order; a face counts
    when both of its spokes are surface-graph edges. Where a diagonal spoke is
    missing, the right-angle triangle between the two straight spokes around
    it is used instead (far surfaces lose their diagonal edges first). Each face normal is
    oriented towards the sensor (``n . p < 0``) before the weighted sum, as
    Johnson does for single-view surfaces, so folds cannot cancel out.
    ``smooth = k > 0`` sums the angle-weighted face normals over the
    ``(2k+1)^2`` neighbourhood (pixels with faces only) before normalising:
    the same estimator over a larger patch, which tames depth noise (Kinect v2
    at 3-4 m: per-pixel normals are off by tens of degrees). ``smooth = 0``
    is the thesis's one-ring normal.
    Returns ``(normals [H, W, 3] float32, valid [H, W] bool)``; pixels without
    any face get the unit vector towards the sensor and ``valid = False``.
    """
    p = jnp.asarray(points, jnp.float32)
    spokes = _spokes(jnp.asarray(weights))
    # Work on the three coordinate planes separately: [H, W] arrays vectorise far
    # better on CPU than [H, W, 3] with reductions over a length-3 minor axis.
    px, py, pz = p[..., 0], p[..., 1], p[..., 2]
    vecs = [tuple(neighbour(c, dr, dc, 0.0) - c for c in (px, py, pz)) for dr, dc in RING]
    lens = [jnp.sqrt(a * a + b * b + c * c) for a, b, c in vecs]
    # Each spoke serves two or three faces: materialise the spokes once (fused into every
    # face, XLA on CPU would recompute them).
    spokes, vecs, lens = lax.optimization_barrier((spokes, vecs, lens))
    ax = ay = az = jnp.zeros_like(px)
    nfaces = jnp.zeros(px.shape, jnp.int32)
    # Faces: consecutive spokes (k, k+1); where a diagonal spoke k+1 is missing,
    # the right-angle face between its straight neighbours (k, k+2) instead, so
    # that a graph without diagonal edges (far surfaces) still has faces.
    faces = [(k, (k + 1) % 8, spokes[k] & spokes[(k + 1) % 8]) for k in range(8)]
    faces += [
        (k, (k + 2) % 8, spokes[k] & spokes[(k + 2) % 8] & ~spokes[k + 1]) for k in (0, 2, 4, 6)
    ]
    for ka, kb, ok in faces:
        (a1, a2, a3), (b1, b2, b3) = vecs[ka], vecs[kb]
        c1 = a2 * b3 - a3 * b2
        c2 = a3 * b1 - a1 * b3
        c3 = a1 * b2 - a2 * b1
        ncr = jnp.sqrt(c1 * c1 + c2 * c2 + c3 * c3)
        ok = ok & (ncr > 0)
        cosang = (a1 * b1 + a2 * b2 + a3 * b3) / jnp.where(ok, lens[ka] * lens[kb], 1.0)
        ang = _acos(cosang)
        # orient towards the sensor (n . p < 0) and weight by the angle
        sgn = jnp.where(c1 * px + c2 * py + c3 * pz > 0, -1.0, 1.0)
        f = jnp.where(ok, sgn * ang / jnp.where(ok, ncr, 1.0), 0.0)
        ax, ay, az = ax + f * c1, ay + f * c2, az + f * c3
        nfaces = nfaces + ok.astype(jnp.int32)
    if smooth > 0:
        own = nfaces > 0
        ax, ay, az = (jnp.where(own, _box_sum(c, smooth), 0.0) for c in (ax, ay, az))
    acc = jnp.stack([ax, ay, az], -1)
    norm = jnp.sqrt(jnp.sum(acc * acc, -1, keepdims=True))
    valid = (nfaces > 0) & (norm[..., 0] > 0)
    pn = jnp.sqrt(jnp.sum(p * p, -1, keepdims=True))
    towards = -p / jnp.where(pn > 0, pn, 1.0)
    towards = jnp.where(pn > 0, towards, jnp.array([0.0, 0.0, -1.0], jnp.float32))
    n = jnp.where(valid[..., None], acc / jnp.where(norm > 0, norm, 1.0), towards)
    return n, valid


_ACOS = (
    1.5707963050,
    -0.2145988016,
    0.0889789874,
    -0.0501743046,
    0.0308918810,
    -0.0170881256,
    0.0066700901,
    -0.0012624911,
)


def _acos(x: Array) -> Array:
    """arccos by Abramowitz & Stegun 4.4.46 (|error| <= 2e-8 rad).

    XLA's arccos on CPU is a scalar library call per element; this polynomial
    vectorises.
    """
    x = jnp.clip(x, -1.0, 1.0)
    t = jnp.abs(x)
    poly = _ACOS[7]
    for c in _ACOS[6::-1]:
        poly = poly * t + c
    r = jnp.sqrt(1.0 - t) * poly
    return jnp.where(x < 0, jnp.pi - r, r)


def _box_sum(a: Array, k: int) -> Array:
    """Sum of an ``[H, W]`` array over the ``(2k+1)^2`` neighbourhood (zero padding), separable."""
    h, w = a.shape
    p = jnp.pad(a, k)
    rows = sum(p[i : i + h] for i in range(2 * k + 1))
    return sum(rows[:, j : j + w] for j in range(2 * k + 1))


def silhouette_widths(mask: Array) -> Array:
    """``[H] int32`` silhouette widths (thesis 4.1.3): last minus first mask column plus one.

    Empty rows have width 0.
    """
    m = jnp.asarray(mask, bool)
    w = m.shape[1]
    any_ = jnp.any(m, axis=1)
    first = jnp.argmax(m, axis=1)
    last = w - 1 - jnp.argmax(m[:, ::-1], axis=1)
    return jnp.where(any_, last - first + 1, 0).astype(jnp.int32)


class HeadSplit(NamedTuple):
    """Result of ``head_neck_split``.

    neck_row: ``[] int32`` first row below the head (-1 when the mask is empty).
    head: ``[H, W] bool`` mask pixels above ``neck_row``.
    head_centre: ``[2] float32`` (row, col) centroid of ``head``.
    top: ``[] int32`` first mask row. widths: ``[H] int32`` silhouette widths.
    """

    neck_row: Array
    head: Array
    head_centre: Array
    top: Array
    widths: Array


def head_neck_split(mask: Array) -> HeadSplit:
    """Split the head from the body at the narrowest row of the top third (thesis 4.1.3).

    The thesis takes the global minimum of the silhouette width in the top
    third of the body. Read literally that minimum is the crown of the head
    (a few pixels wide), so the search starts below the widest row of the top
    eighth (the head's widest row) and ends at one third of the body height;
    empty rows inside the range are skipped.
    """
    m = jnp.asarray(mask, bool)
    h = m.shape[0]
    widths = silhouette_widths(m)
    rows = jnp.arange(h)
    has = widths > 0
    top = jnp.where(jnp.any(has), jnp.argmax(has), -1)
    bottom = jnp.where(jnp.any(has), h - 1 - jnp.argmax(has[::-1]), -1)
    height = bottom - top + 1
    eighth = top + jnp.maximum(height // 8, 1)
    third = top + jnp.maximum(height // 3, 2)
    in_head = (rows >= top) & (rows < eighth)
    widest = jnp.argmax(jnp.where(in_head, widths, -1))
    cand = (rows > widest) & (rows <= third) & has
    big = jnp.iinfo(jnp.int32).max
    neck = jnp.where(jnp.any(cand), jnp.argmin(jnp.where(cand, widths, big)), third)
    neck = jnp.where(top >= 0, neck, -1).astype(jnp.int32)
    head = m & (rows[:, None] < neck)
    n = jnp.sum(head)
    rr, cc = jnp.meshgrid(
        jnp.arange(h, dtype=jnp.float32), jnp.arange(m.shape[1], dtype=jnp.float32), indexing="ij"
    )
    centre = jnp.stack([jnp.sum(jnp.where(head, rr, 0.0)), jnp.sum(jnp.where(head, cc, 0.0))])
    centre = jnp.where(n > 0, centre / jnp.maximum(n, 1), jnp.full(2, -1.0))
    return HeadSplit(neck, head, centre, top.astype(jnp.int32), widths)


def nearest_true(mask: Array, rc: Array) -> tuple[Array, Array]:
    """Nearest ``True`` pixel of ``mask: [H, W]`` to ``rc: [..., 2]`` (row, col), in pixels.

    Returns ``(pixel [..., 2] int32, found [...] bool)``; ``found`` is False for an empty mask.
    """
    m = jnp.asarray(mask, bool)
    h, w = m.shape
    rc = jnp.asarray(rc, jnp.float32)
    rr = jnp.arange(h, dtype=jnp.float32)
    cc = jnp.arange(w, dtype=jnp.float32)
    d2 = (rr[:, None] - rc[..., 0, None, None]) ** 2 + (cc[None, :] - rc[..., 1, None, None]) ** 2
    d2 = jnp.where(m, d2, jnp.inf)
    flat = jnp.argmin(d2.reshape(d2.shape[:-2] + (h * w,)), axis=-1)
    pix = jnp.stack([flat // w, flat % w], axis=-1).astype(jnp.int32)
    return pix, jnp.broadcast_to(jnp.any(m), pix.shape[:-1])


def erode(mask: Array) -> Array:
    """3x3 binary erosion of ``[H, W] bool`` (outside the image counts as False)."""
    m = jnp.asarray(mask, bool)
    out = m
    for dr, dc in RING:
        out = out & neighbour(m, dr, dc, False)
    return out


def foreground_mask(
    depth: Array, background: Array, min_diff_mm: float = 100.0, rel_diff: float = 0.03
) -> Array:
    """Background subtraction in depth (P 2.3): nearer than the background by ``max(min, rel * z)``.

    depth, background: ``[H, W]`` mm, 0 = missing. Pixels without a background
    value count as foreground when their depth is valid (nothing to compare to).
    """
    z = jnp.asarray(depth, jnp.float32)
    bg = jnp.asarray(background, jnp.float32)
    near = z < bg - jnp.maximum(min_diff_mm, rel_diff * bg)
    return (z > 0) & ((bg <= 0) | near)
