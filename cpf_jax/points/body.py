"""The segmented body in layer 2's depth window (thesis 4.1-4.3): hole filling, floor
removal, segmentation, back-projection, surface graph, normals and geodesic distances.

Coordinates: frame positions ``(x, y)`` are continuous depth-frame pixels in the box
convention of ``cpf_jax.kernels.boxes`` (pixel ``(r, c)`` covers ``[c, c+1) x [r, r+1)``);
window pixels are ``(row, col)`` of the fixed ``config.window`` grid; 3D points are
camera millimetres. Thresholds are given per frame pixel at ``threshold_depth_mm`` and
scale with the pixel pitch (depth x window scale / f): Kinect noise and neighbour spacing
grow with depth, and the thesis's 10 / 15 mm cut a person at 3-4 m into pieces.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax.numpy as jnp
from jax import Array, lax

from cpf_jax.kernels import depth as dk
from cpf_jax.kernels import graph as gk
from cpf_jax.points.config import PointConfig

__all__ = [
    "BodyModel",
    "Segmentation",
    "Surface",
    "body_centroid",
    "segment_body",
    "body_surface_graph",
    "body_geodesics",
    "assemble_body",
    "body_points_3d",
    "roi_border_median",
    "body_model",
    "body_extremities",
    "window_pixels",
    "pixel_centre",
    "surface_depth",
]


class BodyModel(NamedTuple):
    """The segmented body in the window of one frame (all ``[Hw, Ww]`` unless noted)."""

    window: dk.Window
    rows: Array  # [Hw] frame rows sampled
    cols: Array  # [Ww] frame cols sampled
    depth: Array  # hole-filled depth, mm
    body: Array  # bool, the segmented body
    points: Array  # [Hw, Ww, 3] mm
    normals: Array  # [Hw, Ww, 3]
    spin_valid: Array  # bool: body pixel with a normal
    weights: Array  # [4, Hw, Ww] surface graph
    mesh_resolution: Array  # [] mm
    reference_pixels: Array  # [R, 2] int32 (row, col) of the geodesic references
    geodesic: Array  # [R, Hw, Ww] mm from each reference (zeros if unused)
    sweeps: Array  # [] relaxation sweeps run


def _component_sizes(labels: Array, valid: Array) -> Array:
    """Per pixel, the number of valid pixels in its component."""
    flat = labels.reshape(-1)
    cnt = jnp.zeros(flat.size, jnp.float32).at[flat].add(valid.reshape(-1).astype(jnp.float32))
    return cnt[flat].reshape(labels.shape)


def _without_floor(config: PointConfig, pts: Array, valid: Array, tscale: Array) -> Array:
    """``valid`` less the floor: pixels whose smoothed normal lies within
    ``floor_max_tilt_deg`` of ``up`` (the floor touches the feet and, where its depth
    changes slowly from row to row, joins the body or outgrows it)."""
    w_all = lax.optimization_barrier(
        gk.surface_graph(pts, valid, config.surface_max_dist_mm * tscale)
    )  # materialised once (``body_surface_graph``)
    n_all, ok_all = dk.vertex_normals(pts, w_all, max(config.normal_smoothing, 1))
    up = jnp.asarray(config.up, jnp.float32)
    up = up / jnp.linalg.norm(up)
    floor = ok_all & (n_all @ up > math.cos(math.radians(config.floor_max_tilt_deg)))
    return valid & ~floor


def _span(mask: Array) -> tuple[Array, Array]:
    """First and last index of a ``[n] bool`` run (0 and ``n - 1`` when it is empty)."""
    n = mask.shape[0]
    return jnp.argmax(mask), n - 1 - jnp.argmax(mask[::-1])


def roi_border_median(d: Array, roi: Array, valid: Array, upper_share: float = 0.6) -> Array:
    """Median of ``d [Hw, Ww]`` over the ``valid`` pixels of the border ring of the rectangle
    ``roi`` (``roi & ~erode(roi)``) in its upper ``upper_share`` of rows; NaN when there are
    none. The ring is read as its four sides (``2 (Hw + Ww)`` values, the corners once)
    instead of a median over the whole window."""
    h = roi.shape[0]
    rows_in, cols_in = jnp.any(roi, axis=1), jnp.any(roi, axis=0)
    (r0, r1), (c0, c1) = _span(rows_in), _span(cols_in)
    ok = valid & (jnp.arange(h) < r0 + upper_share * (r1 - r0))[:, None]
    inner = rows_in & (jnp.arange(h) != r0) & (jnp.arange(h) != r1)
    sides = (
        jnp.where(cols_in & ok[r0], d[r0], jnp.nan),
        jnp.where(cols_in & ok[r1] & (r1 != r0), d[r1], jnp.nan),
        jnp.where(inner & ok[:, c0], d[:, c0], jnp.nan),
        jnp.where(inner & ok[:, c1] & (c1 != c0), d[:, c1], jnp.nan),
    )
    return jnp.nanmedian(jnp.concatenate(sides))


def _in_front(config: PointConfig, d: Array, roi: Array, labels: Array, valid: Array) -> Array:
    """The pixels of components at least ``background_margin_mm`` in front of the box's
    background, the median depth of the ROI's border in its upper 60 % (the floor fills the
    bottom rows): in a tight box around a side-on person the wall behind can be the
    largest component. When the largest such component is under 20 % of the largest
    overall, the rule is not trusted and every valid pixel stays eligible."""
    z_bg = roi_border_median(d, roi, valid, upper_share=0.6)
    zc = gk.component_mean(labels, d, valid)
    front = valid & (zc < z_bg - config.background_margin_mm)
    size = _component_sizes(labels, valid)
    big_all = jnp.max(jnp.where(valid, size, 0.0))
    big_front = jnp.max(jnp.where(front, size, 0.0))
    trust = jnp.isfinite(z_bg) & (big_front >= 0.2 * big_all)
    return jnp.where(trust, front, valid)


def _segment(
    config: PointConfig,
    d: Array,
    roi: Array,
    valid: Array,
    tscale: Array,
    target_depth: Array | None = None,
) -> Array:
    """The body (thesis 4.1.2): the largest component of the ``|dz| < seg_max_dz_mm``
    pixel graph among the eligible pixels, or with ``min_component_fraction`` the union of
    the sizeable components (with a foreground mask the person is every sizeable one:
    side-on, the near arm and leg are apart from the trunk in depth), with
    ``joined_max_dz_mm`` only those joined to the anchor (``joined_anchor``)."""
    edges = gk.pixel_graph(d, valid, config.seg_max_dz_mm * tscale)
    labels = gk.connected_components(edges)
    eligible = valid
    if config.background_margin_mm is not None:
        eligible = _in_front(config, d, roi, labels, valid)
    if config.min_component_fraction is None:
        return gk.largest_component(labels, eligible)
    size = _component_sizes(labels, eligible)
    anchored = (
        config.joined_max_dz_mm is not None
        and config.joined_anchor == "depth"
        and target_depth is not None
    )
    big = jnp.max(size)
    if anchored and config.anchor_sizeable:
        big = _largest_at_depth(config, d, labels, eligible, size, target_depth)
    body = eligible & (size >= config.min_component_fraction * big)
    if config.joined_max_dz_mm is None:
        return body
    if anchored:
        return _joined_at_depth(config, d, body, tscale, target_depth)
    return _joined_to_centre(config, d, body, tscale)


def _largest_at_depth(
    config: PointConfig, d: Array, labels: Array, eligible: Array, size: Array, target_depth
) -> Array:
    """``[]``: the pixel count of the largest component (``labels``, per-pixel ``size``)
    whose mean depth lies within ``anchor_max_dz_mm`` of ``target_depth`` (the largest
    overall when none does): the yardstick of "sizeable" for a target mostly hidden by
    someone nearer, whose visible pieces are small beside the one in front."""
    z = gk.component_mean(labels, d, eligible)
    at = eligible & (jnp.abs(z - target_depth) <= config.anchor_max_dz_mm)
    return jnp.where(jnp.any(at), jnp.max(jnp.where(at, size, 0.0)), jnp.max(size))


def _joined_to_centre(config: PointConfig, d: Array, body: Array, tscale: Array) -> Array:
    """The pixels of ``body`` joined to its pixel nearest the window's centre (the box's)
    through edges of at most ``joined_max_dz_mm``: the tracked person's components without
    the people beside or in front, whose depth steps away from him are larger."""
    return _group_at_centre(body, _joined_labels(config, d, body, tscale))


def _joined_labels(config: PointConfig, d: Array, body: Array, tscale: Array) -> Array:
    """``[Hw, Ww] int32`` components of ``body`` joined through depth steps of at most
    ``joined_max_dz_mm``."""
    return gk.connected_components(gk.pixel_graph(d, body, config.joined_max_dz_mm * tscale))


def _group_at_centre(body: Array, labels: Array) -> Array:
    """The pixels of ``body`` in the component (``labels``) of its pixel nearest the
    window's centre."""
    h, w = body.shape
    centre, found = dk.nearest_true(body, jnp.asarray([[(h - 1) / 2, (w - 1) / 2]]))
    anchor = labels[centre[0, 0], centre[0, 1]]
    return body & (labels == anchor) & found[0]


def _joined_at_depth(
    config: PointConfig, d: Array, body: Array, tscale: Array, target_depth: Array
) -> Array:
    """The pixels of ``body`` in the groups joined through edges of at most
    ``joined_max_dz_mm`` whose mean depth lies within ``anchor_max_dz_mm`` of
    ``target_depth []`` mm (the tracked person's depth: someone passing in front is nearer,
    someone behind farther, by more than a body's thickness); the centre's group
    (``_joined_to_centre``) when no group is there (an unknown depth, 0, matches none)."""
    labels = _joined_labels(config, d, body, tscale)
    z = gk.component_mean(labels, d, body)
    at = body & (jnp.abs(z - target_depth) <= config.anchor_max_dz_mm)
    return jnp.where(jnp.any(at), at, _group_at_centre(body, labels))


def body_centroid(body: Array) -> Array:
    """``[2]`` (row, col) centroid of a window mask (the window's corner when empty)."""
    rr, cc = jnp.meshgrid(
        jnp.arange(body.shape[0], dtype=jnp.float32),
        jnp.arange(body.shape[1], dtype=jnp.float32),
        indexing="ij",
    )
    n = jnp.maximum(jnp.sum(body), 1)
    return jnp.stack([jnp.sum(jnp.where(body, rr, 0.0)), jnp.sum(jnp.where(body, cc, 0.0))]) / n


def _reference_pixels(config: PointConfig, body: Array) -> Array:
    """``[R, 2]`` (row, col) body pixels of the geodesic references: the head's centre above
    the neck (thesis 4.1.3) or the body's centroid."""
    centres = [
        dk.head_neck_split(body).head_centre if ref == "head" else body_centroid(body)
        for ref in config.references
    ]
    ref_pix, _ = dk.nearest_true(body, jnp.stack(centres))
    return ref_pix


def _geodesics(config: PointConfig, w: Array, body: Array, ref_pix: Array) -> tuple[Array, Array]:
    """Geodesic distances ``[R, Hw, Ww]`` (mm) from each reference over the surface graph
    (min-plus relaxation, thesis 4.3) and the sweeps run; zeros without geodesic weights."""
    shape = config.window
    if not config.uses_geodesic:
        return jnp.zeros((len(config.references),) + shape, jnp.float32), jnp.int32(0)
    src = (
        (jnp.arange(shape[0])[None, :, None] == ref_pix[:, 0, None, None])
        & (jnp.arange(shape[1])[None, None, :] == ref_pix[:, 1, None, None])
        & body
    )
    # One relaxation per reference (R is small and static) rather than a vmap: unbatched,
    # the relaxation skips its last up sweep once a down sweep changes nothing.
    runs = [gk.geodesic_distances(w, s_, config.max_sweeps, return_sweeps=True) for s_ in src]
    return jnp.stack([g for g, _ in runs]), jnp.max(jnp.stack([k for _, k in runs]))


class Segmentation(NamedTuple):
    """The first stage of ``body_model``: the window's depth and its segmented body."""

    window: dk.Window
    rows: Array  # [Hw] frame rows sampled
    cols: Array  # [Ww] frame cols sampled
    depth: Array  # [Hw, Ww] hole-filled depth, mm
    points: Array  # [Hw, Ww, 3] mm
    body: Array  # [Hw, Ww] bool
    tscale: Array  # [] or [Hw, Ww]: the thresholds' scale (module docstring)


class Surface(NamedTuple):
    """The second stage of ``body_model``: the body's surface graph and normals."""

    weights: Array  # [4, Hw, Ww] surface graph
    normals: Array  # [Hw, Ww, 3]
    spin_valid: Array  # [Hw, Ww] bool: body pixel with a normal
    mesh_resolution: Array  # [] mm


def segment_body(
    config: PointConfig,
    depth: Array,
    box: Array,
    foreground: Array | None = None,
    target_depth: Array | None = None,
) -> Segmentation:
    """The body in the ``config.window`` window cut around ``box`` (xywh) of ``depth [H, W]``
    (uint16 mm): holes filled (thesis 4.1.1), back-projected, floor removed, segmented
    (4.1.2); ``foreground [H, W] bool`` (optional) limits the body to foreground pixels, and
    ``target_depth []`` mm (optional, 0: unknown) anchors it (``PointConfig.joined_anchor``)."""
    d, win, rows, cols, roi = dk.crop_window(depth, box, config.window, config.box_margin)
    d = dk.fill_holes(d, roi)
    valid = d > 0
    if foreground is not None:
        fg = jnp.asarray(foreground, bool)
        fg = jnp.take(fg, jnp.clip(rows, 0, fg.shape[0] - 1), axis=0)
        fg = jnp.take(fg, jnp.clip(cols, 0, fg.shape[1] - 1), axis=1)
        valid = valid & fg
    # Neighbours are `scale` frame pixels apart, and a frame pixel spans z / f mm.
    tscale = win.scale
    if config.threshold_depth_mm is not None:
        tscale = tscale * d / config.threshold_depth_mm
    pts = dk.back_project(d, rows, cols, config.intrinsics)
    if config.floor_max_tilt_deg is not None:
        valid = _without_floor(config, pts, valid, tscale)
    body = _segment(config, d, roi, valid, tscale, target_depth)
    return Segmentation(win, rows, cols, d, pts, body, tscale)


def body_surface_graph(config: PointConfig, seg: Segmentation) -> Surface:
    """The body's surface graph (edges up to ``surface_max_dist_mm``, thesis 4.1.4), vertex
    normals (4.2.1) and mesh resolution."""
    # The barrier materialises the graph once: fused into its readers XLA on CPU would
    # recompute the edge lengths for each of them.
    w = lax.optimization_barrier(
        gk.surface_graph(seg.points, seg.body, config.surface_max_dist_mm * seg.tscale)
    )
    normals, nvalid = dk.vertex_normals(seg.points, w, config.normal_smoothing)
    return Surface(w, normals, seg.body & nvalid, gk.mesh_resolution(w))


def body_geodesics(
    config: PointConfig, seg: Segmentation, surface: Surface
) -> tuple[Array, Array, Array]:
    """``(reference pixels [R, 2], geodesic distances [R, Hw, Ww] mm, sweeps)`` over the
    surface graph (thesis 4.3), or over the body's graph with edges up to
    ``geodesic_max_dist_mm`` when that is set."""
    ref_pix = _reference_pixels(config, seg.body)
    w = surface.weights
    if config.geodesic_max_dist_mm is not None and config.uses_geodesic:
        w = gk.surface_graph(seg.points, seg.body, config.geodesic_max_dist_mm * seg.tscale)
    geo, sweeps = _geodesics(config, w, seg.body, ref_pix)
    return ref_pix, geo, sweeps


def body_model(
    config: PointConfig,
    depth: Array,
    box: Array,
    foreground: Array | None = None,
    target_depth: Array | None = None,
) -> BodyModel:
    """The segmented body of ``depth [H, W]`` (uint16 mm) in the window around ``box``
    (xywh), with its surface and geodesic distances: ``segment_body``, then
    ``body_surface_graph``, then ``body_geodesics``."""
    seg = segment_body(config, depth, box, foreground, target_depth)
    surface = body_surface_graph(config, seg)
    ref_pix, geo, sweeps = body_geodesics(config, seg, surface)
    return assemble_body(seg, surface, ref_pix, geo, sweeps)


def assemble_body(
    seg: Segmentation, surface: Surface, ref_pix: Array, geo: Array, sweeps: Array
) -> BodyModel:
    """The ``BodyModel`` of the three stages' outputs."""
    return BodyModel(
        seg.window,
        seg.rows,
        seg.cols,
        seg.depth,
        seg.body,
        seg.points,
        surface.normals,
        surface.spin_valid,
        surface.weights,
        surface.mesh_resolution,
        ref_pix,
        geo,
        sweeps,
    )


def body_points_3d(bm: BodyModel) -> Array:
    """``[Hw * Ww, 3]`` mm: the window's camera-frame points on the body, NaN off it (for
    display)."""
    return jnp.where(bm.body[..., None], bm.points, jnp.nan).reshape(-1, 3)


def window_pixels(bm: BodyModel, xy: Array, shape: tuple[int, int]) -> tuple[Array, Array]:
    """Frame positions ``[..., 2]`` -> window pixels ``[..., 2] int32 (row, col)`` and whether
    each lies inside the window."""
    ji = dk.frame_to_window(bm.window, xy)
    col = jnp.floor(ji[..., 0]).astype(jnp.int32)
    row = jnp.floor(ji[..., 1]).astype(jnp.int32)
    inside = (row >= 0) & (row < shape[0]) & (col >= 0) & (col < shape[1])
    rc = jnp.stack([jnp.clip(row, 0, shape[0] - 1), jnp.clip(col, 0, shape[1] - 1)], -1)
    return rc, inside


def pixel_centre(bm: BodyModel, rc: Array) -> Array:
    """Window pixels ``[..., 2] (row, col)`` -> frame positions ``(x, y)`` of their centres."""
    ji = jnp.stack([rc[..., 1], rc[..., 0]], -1).astype(jnp.float32) + 0.5
    return dk.window_to_frame(bm.window, ji)


def surface_depth(config: PointConfig, bm: BodyModel, xy: Array) -> Array:
    """``[...]`` mm: the body's depth under frame positions ``xy [..., 2]`` (the nearest body
    pixel's off the body; 0 without a body). The search for the nearest body pixel, a pass
    over the window per position, runs only when some position is off the body
    (``lax.cond``)."""
    rc, inside = window_pixels(bm, xy, config.window)
    on = inside & bm.body[rc[..., 0], rc[..., 1]]

    def nearest(rc_):
        ji = dk.frame_to_window(bm.window, xy)
        near, _ = dk.nearest_true(bm.body, jnp.stack([ji[..., 1], ji[..., 0]], -1))
        return jnp.where(on[..., None], rc_, near)

    rc = lax.cond(jnp.all(on), lambda rc_: rc_, nearest, rc)
    return jnp.where(jnp.any(bm.body), bm.depth[rc[..., 0], rc[..., 1]], 0.0)


def ray_point(intrinsics, xy: Array, z: Array, offset: Array) -> Array:
    """The 3D point ``[..., 3]`` (mm) at depth ``z`` under frame position ``xy [..., 2]``
    (box convention: pixel centres at +0.5), pushed ``offset`` mm further along the viewing
    ray; NaN where ``z <= 0`` (no depth)."""
    fx, fy, cx, cy = intrinsics
    u = xy[..., 0] - 0.5
    v = xy[..., 1] - 0.5
    ray = jnp.stack([(u - cx) / fx, (v - cy) / fy, jnp.ones_like(u)], -1)
    p = z[..., None] * ray
    p = p + offset[..., None] * ray / jnp.linalg.norm(ray, axis=-1, keepdims=True)
    return jnp.where((z > 0)[..., None], p, jnp.nan)


def body_extremities(config: PointConfig, bm: BodyModel) -> tuple[Array, Array]:
    """Points to start tracking on a segmented body: ``AUTO_POINTS`` as frame positions
    ``[5, 2]`` (box convention) and the geodesic reach ``[4]`` mm of the hands and feet.

    The head is the centre of the head above the neck (thesis 4.1.3); hands and feet are
    the four geodesic extremities of the surface graph seen from the centroid and the head
    (``kernels.graph.farthest_points``), the two lowest in the image the feet; "a" is the
    one further left. Meant for a person facing the camera with the limbs apart from the
    trunk (the thesis's initial pose): side-on, a hidden hand is not an extremity and an
    elbow or a knee takes its place. With an empty body every point is the window's
    corner and every reach 0.
    """
    body = bm.body
    head = dk.head_neck_split(body).head_centre
    src, _ = dk.nearest_true(body, jnp.stack([head, body_centroid(body)]))  # [2, 2]
    sources = jnp.zeros(body.shape, bool).at[src[:, 0], src[:, 1]].set(True) & body
    ext, reach = gk.farthest_points(bm.weights, sources, 4, config.max_sweeps)
    xy = pixel_centre(bm, jnp.concatenate([src[:1], ext]))  # [5, 2]
    limbs = xy[1:]
    low = jnp.argsort(limbs[:, 1])  # ascending image y: hands first, then feet
    hands, feet = low[:2], low[2:]
    hands = hands[jnp.argsort(limbs[hands, 0])]
    feet = feet[jnp.argsort(limbs[feet, 0])]
    order = jnp.concatenate([hands, feet])
    return jnp.concatenate([xy[:1], limbs[order]]), reach[order]
