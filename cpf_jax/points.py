"""Depth layer: a batched particle filter for points on the body (thesis ch. 4, SPEC C3).

Usage::

    config = PointFilterConfig(n_particles=100, weighting="combined")
    filt = build_point_filter(config)
    params = default_point_params()
    inputs = PointInputs(depth=depth_u16, box=box_xywh)          # one frame
    state = filt.init(params, key, inputs, points_xy)              # points_xy: [P, 2]
    state, info = filt.step(params, key, state, next_inputs)
    # or a whole sequence as one lax.scan:
    state, infos = track_points(filt, params, key, inputs_seq, points_xy)

``P`` points (head, hands, feet, ...) are tracked together: every array has a
leading ``[P, N]`` (points x particles) shape and one jitted step serves all.

Coordinates: particle positions ``(x, y)`` are continuous depth-frame pixel
coordinates in the box convention of ``cpf_jax.kernels.boxes`` (pixel
``(r, c)`` covers ``[c, c+1) x [r, r+1)``; a joint projected at ``(u, v)``
sits at ``(u + 0.5, v + 0.5)``). 3D estimates are camera millimetres.

One frame (``step``):

1. Pre-processing in a ``config.window`` window cut around ``inputs.box``
   (``cpf_jax.kernels.depth``): hole filling (thesis 4.1.1); optional floor
   removal (pixels whose normal is within ``floor_max_tilt_deg`` of ``up``);
   segmentation (4.1.2) as the largest connected component of the
   ``|dz| < seg_max_dz`` pixel graph among the components in front of the
   box's background (``background_margin_mm``; the thesis's plain largest
   component picks the wall behind a side-on person), or the union of the
   sizeable components inside an optional foreground mask
   (``min_component_fraction``); back-projection, surface graph with
   ``<= surface_max_dist`` edges (4.1.4), vertex normals (4.2.1) and the mesh
   resolution; geodesic distances from the reference points. Thresholds are
   per frame pixel at ``threshold_depth_mm`` and scale with the pixel pitch
   (depth x window scale / f): Kinect noise and neighbour spacing grow with
   depth, and the thesis's 10 / 15 mm cut a person at 3-4 m into pieces.
2. Prediction, state ``{x, y, x', y'}`` per particle (thesis 4.2.3):
   ``x' <- decay x' + n_v``, ``x <- x + x' + n_x``. With ``follow_box`` the
   particle also moves with the box: ``x`` is first mapped by the similarity
   transform that takes the previous box onto the current one (the box is
   the cascade's layer-1 output), so the velocity only models motion on the body.
3. Weights, in log form (thesis Alg. 2 and 3, combination: 6.2), plus an
   optional depth-consistency term ``-(z - z_pred)^2 / (2 depth_sigma^2)``
   (``z`` the surface depth under the particle, ``z_pred`` the last
   estimate's depth scaled by the box-height ratio), which keeps a hand's
   cloud from sliding onto the thigh behind it:
   * ``spin``: ``C / spin_temperature`` with ``C`` the similarity of the
     particle's spin image to the point's reference image (eq. 4.7;
     ``lambda`` = half the median overlap over the point's particles);
   * ``geodesic``: ``-(g - g0)^2 / (2 geo_sigma^2)`` with ``g`` the geodesic
     distance from the reference point (head centroid by default; body
     centroid or both as options) to the particle's pixel and ``g0`` the
     initial one; unreachable pixels get ``-inf``;
   * ``combined``: the sum (a product of the two likelihoods).
   Particles off the segmented body get ``-inf`` (masked, thesis 4.4).
4. Recovery: if every particle of a point is off the body (or has no valid
   weight), the point's particles are re-drawn around the body pixel nearest
   to its predicted position (``recovery_spread`` px), with uniform weights,
   and ``info.recovered`` is set. If the body itself is empty the particles
   are kept as predicted.
5. Estimates: the best particle (thesis Alg. 2-3) and the weighted mean;
   3D positions by back-projecting the body pixel under each estimate (the
   nearest body pixel if the estimate is off the body), pushed
   ``joint_depth_offset`` mm further along the viewing ray (the tracked
   point is on the surface; an anatomical joint lies behind it).
6. Resampling (systematic) when ``ESS < ess_threshold * N`` per point.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from cpf_jax.kernels import depth as dk
from cpf_jax.kernels import graph as gk
from cpf_jax.kernels import resample as rs
from cpf_jax.kernels import spin as sk
from cpf_jax.types import KINECT_V2_DEPTH, Filter, Intrinsics, memoised_build, scan_filter

__all__ = [
    "WEIGHTINGS",
    "BODY_POINTS",
    "BODY_POINT_DEPTH_OFFSET_MM",
    "PointFilterConfig",
    "PointParams",
    "PARAM_CONSTRAINTS",
    "default_point_params",
    "PointInputs",
    "BodyModel",
    "PointState",
    "PointInfo",
    "body_model",
    "body_extremities",
    "AUTO_POINTS",
    "build_point_filter",
    "track_points",
]

WEIGHTINGS = ("spin", "geodesic", "combined")
#: The body points tracked by default (names of ``SyntheticSequence.joint_names``).
BODY_POINTS = ("head", "left_hand", "right_hand", "left_foot", "right_foot")
#: mm from the surface under each of ``BODY_POINTS`` to the joint centre behind it
#: (``PointParams.joint_depth_offset``): half a hand's thickness for hands; rough
#: values for the head and feet.
BODY_POINT_DEPTH_OFFSET_MM = (80.0, 20.0, 20.0, 40.0, 40.0)
REFERENCES = ("head", "centroid")
#: The points ``body_extremities`` finds (``cpf-track --points auto``): "a" is the one
#: further left in the image, "b" the other (which of the person's hands is which
#: depends on the way they face).
AUTO_POINTS = ("head", "hand_a", "hand_b", "foot_a", "foot_b")


@dataclasses.dataclass(frozen=True)
class PointFilterConfig:
    """Static, hashable settings (changing one recompiles)."""

    n_particles: int = 100
    weighting: str = "combined"  # "spin" | "geodesic" | "combined"
    window: tuple[int, int] = (256, 192)  # (rows, cols) of the depth window
    box_margin: float = 0.1  # the box is enlarged by this fraction on every side
    intrinsics: Intrinsics = KINECT_V2_DEPTH
    seg_max_dz_mm: float = 10.0  # thesis 4.1.2
    surface_max_dist_mm: float = 15.0  # thesis 4.1.4
    # Depth at which the two thresholds hold; they scale with the pixel pitch
    # (depth x window scale / f). None: fixed thresholds (times the window scale).
    threshold_depth_mm: float | None = 2000.0
    # Geodesic reference points (thesis 4.3: head or body centroid); several
    # references give a vector of distances per pixel. The head is the default:
    # the body centroid moves with the limbs and its paths to a hand switch
    # between the shoulder and a hand-on-thigh contact (measured: +-200 mm).
    references: tuple[str, ...] = ("head",)
    spin_width: int = 20  # App. G
    spin_bin_factor: float = 1.0  # bin size in mesh resolutions (App. G: 1-2)
    support_angle_deg: float = 60.0  # App. G: 60-90
    normal_smoothing: int = 2  # vertex normals summed over (2k+1)^2 pixels (0: one ring)
    # Floor removal before segmentation: drop pixels whose normal is within this
    # angle of ``up`` (camera coordinates, Y down). None: no floor removal (thesis).
    floor_max_tilt_deg: float | None = 30.0
    up: tuple[float, float, float] = (0.0, -1.0, 0.0)
    # Only components at least this far in front of the box's background (median
    # depth of the ROI border) may be the body; None: the thesis's plain largest.
    background_margin_mm: float | None = 250.0
    # None: the body is one component (thesis). A fraction f: the union of the
    # components with at least f times the largest one's pixels (use with a
    # foreground mask, which has removed the background already).
    min_component_fraction: float | None = None
    patch_radius: int = 32  # window pixels visited per spin image (see kernels.spin)
    spin_batch: int = 32  # spin images computed per lax.map step
    follow_box: bool = True
    # Temporal depth consistency: a particle whose surface depth departs from the
    # predicted depth of its point loses weight (``params.depth_sigma``).
    depth_consistency: bool = True
    ess_threshold: float = 1.0  # 1.0: resample every frame (SIR)
    resampler: str = "systematic"
    max_sweeps: int = 64  # geodesic relaxation sweeps (converges in 3-8)

    def __post_init__(self) -> None:
        if self.n_particles < 1:
            raise ValueError(f"n_particles must be >= 1, got {self.n_particles}")
        if self.weighting not in WEIGHTINGS:
            raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {self.weighting!r}")
        if not self.references or any(r not in REFERENCES for r in self.references):
            raise ValueError(
                f"references must be a non-empty tuple of {REFERENCES}, got {self.references!r}"
            )
        if self.resampler not in rs.SCHEMES:
            raise ValueError(
                f"resampler must be one of {tuple(rs.SCHEMES)}, got {self.resampler!r}"
            )
        if self.min_component_fraction is not None and not 0 < self.min_component_fraction <= 1:
            raise ValueError("min_component_fraction must be in (0, 1] or None")
        if min(self.window) < 8:
            raise ValueError(f"window too small: {self.window}")

    @property
    def uses_spin(self) -> bool:
        return self.weighting in ("spin", "combined")

    @property
    def uses_geodesic(self) -> bool:
        return self.weighting in ("geodesic", "combined")


class PointParams(NamedTuple):
    """Continuous parameters (a pytree). Scalars, or ``[P]`` arrays for per-point values."""

    pos_noise: Array  # px, std of the position noise n_x
    vel_noise: Array  # px/frame, std of the velocity noise n_v
    velocity_decay: Array  # in [0, 1]; 1 = constant velocity, 0 = random walk
    spin_temperature: Array  # log-weight = C / temperature
    geo_sigma: Array  # mm, width of the geodesic-deviation likelihood
    depth_sigma: Array  # mm, width of the depth-consistency likelihood
    recovery_spread: Array  # px, std of the cloud re-drawn by the recovery
    joint_depth_offset: Array  # mm added along the viewing ray to the 3D estimates


PARAM_CONSTRAINTS = PointParams(
    pos_noise="softplus",
    vel_noise="softplus",
    velocity_decay="sigmoid",
    spin_temperature="softplus",
    geo_sigma="softplus",
    depth_sigma="softplus",
    recovery_spread="softplus",
    joint_depth_offset="identity",
)


def default_point_params() -> PointParams:
    f = jnp.float32
    return PointParams(
        pos_noise=f(2.0),
        vel_noise=f(1.0),
        velocity_decay=f(0.5),
        spin_temperature=f(0.1),  # C spans about 0-3: 0.5 left the weights nearly flat
        geo_sigma=f(40.0),
        depth_sigma=f(40.0),
        recovery_spread=f(2.0),
        joint_depth_offset=f(0.0),
    )


class PointInputs(NamedTuple):
    """One frame for the point filter.

    depth: ``[H, W] uint16`` mm (0 = missing). box: ``[4]`` xywh (layer 1's box).
    foreground: optional ``[H, W] bool`` (e.g. a background-subtraction mask);
    when given, only foreground pixels can belong to the body.
    """

    depth: Array
    box: Array
    foreground: Array | None = None


class BodyModel(NamedTuple):
    """The segmented body in the window of one frame (all ``[Hw, Ww]`` unless noted)."""

    window: dk.Window
    rows: Array  # [Hw] frame rows sampled
    cols: Array  # [Ww] frame cols sampled
    depth: Array  # hole-filled depth, mm
    body: Array  # bool, largest component
    points: Array  # [Hw, Ww, 3] mm
    normals: Array  # [Hw, Ww, 3]
    spin_valid: Array  # bool: body pixel with a normal
    weights: Array  # [4, Hw, Ww] surface graph
    mesh_resolution: Array  # [] mm
    reference_pixels: Array  # [R, 2] int32 (row, col) of the geodesic references
    geodesic: Array  # [R, Hw, Ww] mm from each reference (zeros if unused)
    sweeps: Array  # [] relaxation sweeps run


class PointState(NamedTuple):
    particles: Array  # [P, N, 4] (x, y, vx, vy), frame px
    log_weights: Array  # [P, N] normalised
    ref_spin: Array  # [P, W, W] reference spin images
    ref_geodesic: Array  # [P, R] mm, initial geodesic distances from the reference points
    box: Array  # [4] box of the last frame
    estimate: Array  # [P, 2] weighted-mean estimate of the last frame
    depth: Array  # [P] mm, surface depth under the last estimate


class PointInfo(NamedTuple):
    mean: Array  # [P, 2] weighted-mean estimate (frame px, box convention)
    best: Array  # [P, 2] best particle
    mean3d: Array  # [P, 3] mm
    best3d: Array  # [P, 3] mm
    ess: Array  # [P] before resampling
    on_body: Array  # [P] fraction of particles on the body
    recovered: Array  # [P] bool, the all-off-body recovery ran
    resampled: Array  # [P] bool
    body_pixels: Array  # [] window pixels on the body
    mesh_resolution: Array  # [] mm
    sweeps: Array  # [] geodesic relaxation sweeps
    spin_complete: Array  # [P] fraction of spin supports that fit their patch


def _param(x: Array, p: int) -> Array:
    """A parameter as a ``[P, 1]`` column (scalars broadcast)."""
    return jnp.broadcast_to(jnp.asarray(x, jnp.float32), (p,))[:, None]


def body_model(
    config: PointFilterConfig, depth: Array, box: Array, foreground: Array | None = None
) -> BodyModel:
    """Pre-processing of one frame (step 1 of the module docstring), plus the geodesic map."""
    shape = config.window
    d, win, rows, cols, roi = dk.crop_window(depth, box, shape, config.box_margin)
    d = dk.fill_holes(d, roi)
    valid = d > 0
    if foreground is not None:
        fg = jnp.asarray(foreground, bool)
        fg = jnp.take(fg, jnp.clip(rows, 0, fg.shape[0] - 1), axis=0)
        fg = jnp.take(fg, jnp.clip(cols, 0, fg.shape[1] - 1), axis=1)
        valid = valid & fg
    # Threshold scale per pixel: neighbours are s frame pixels apart, and a frame
    # pixel spans z / f mm; thresholds given at threshold_depth_mm scale with both.
    tscale = win.scale
    if config.threshold_depth_mm is not None:
        tscale = tscale * d / config.threshold_depth_mm
    pts = dk.back_project(d, rows, cols, config.intrinsics)
    if config.floor_max_tilt_deg is not None:
        # Floor removal: pixels whose (smoothed) normal is within the tilt of "up".
        # The floor touches the feet and, where its depth changes slowly from row to
        # row (a person near the camera), joins the body or outgrows it.
        w_all = gk.surface_graph(pts, valid, config.surface_max_dist_mm * tscale)
        n_all, ok_all = dk.vertex_normals(pts, w_all, max(config.normal_smoothing, 1))
        up = jnp.asarray(config.up, jnp.float32)
        up = up / jnp.linalg.norm(up)
        floor = ok_all & (n_all @ up > math.cos(math.radians(config.floor_max_tilt_deg)))
        valid = valid & ~floor
    edges = gk.pixel_graph(d, valid, config.seg_max_dz_mm * tscale)
    labels = gk.connected_components(edges)
    eligible = valid
    if config.background_margin_mm is not None:
        # The thesis keeps the largest component. In a tight box around a thin
        # (side-on) person the wall behind can be larger, so components whose mean
        # depth is not in front of the box's background by the margin are dropped.
        # The background is the median depth of the ROI's border in its upper 60 %
        # (the floor fills the bottom rows). If the biggest remaining component is
        # much smaller than the biggest overall (< 20 %), the rule is not trusted
        # and the thesis's plain largest component is used.
        h = shape[0]
        edge = roi & ~dk.erode(roi)
        rows_in = jnp.any(roi, axis=1)
        r0 = jnp.argmax(rows_in)
        r1 = h - 1 - jnp.argmax(rows_in[::-1])
        upper = (jnp.arange(h) < r0 + 0.6 * (r1 - r0))[:, None]
        z_bg = jnp.nanmedian(jnp.where(edge & upper & valid, d, jnp.nan))
        zc = gk.component_mean(labels, d, valid)
        front = valid & (zc < z_bg - config.background_margin_mm)
        size = _component_sizes(labels, valid)
        big_all = jnp.max(jnp.where(valid, size, 0.0))
        big_front = jnp.max(jnp.where(front, size, 0.0))
        trust = jnp.isfinite(z_bg) & (big_front >= 0.2 * big_all)
        eligible = jnp.where(trust, front, valid)
    if config.min_component_fraction is None:
        body = gk.largest_component(labels, eligible)
    else:
        # Union of the components with at least this fraction of the largest one's
        # pixels: with a foreground mask the person is every sizeable component
        # (side-on, the near arm and leg are separated from the trunk by depth jumps).
        size = _component_sizes(labels, eligible)
        body = eligible & (size >= config.min_component_fraction * jnp.max(size))
    w = gk.surface_graph(pts, body, config.surface_max_dist_mm * tscale)
    normals, nvalid = dk.vertex_normals(pts, w, config.normal_smoothing)
    mres = gk.mesh_resolution(w)
    rr, cc = jnp.meshgrid(
        jnp.arange(shape[0], dtype=jnp.float32),
        jnp.arange(shape[1], dtype=jnp.float32),
        indexing="ij",
    )
    centres = []
    for ref in config.references:
        if ref == "head":
            centres.append(dk.head_neck_split(body).head_centre)
        else:
            n = jnp.maximum(jnp.sum(body), 1)
            centres.append(
                jnp.stack([jnp.sum(jnp.where(body, rr, 0.0)), jnp.sum(jnp.where(body, cc, 0.0))])
                / n
            )
    ref_pix, _ = dk.nearest_true(body, jnp.stack(centres))  # [R, 2]
    if config.uses_geodesic:
        src = (
            (jnp.arange(shape[0])[None, :, None] == ref_pix[:, 0, None, None])
            & (jnp.arange(shape[1])[None, None, :] == ref_pix[:, 1, None, None])
            & body
        )
        geo, sweeps = jax.vmap(
            lambda s_: gk.geodesic_distances(w, s_, config.max_sweeps, return_sweeps=True)
        )(src)
        sweeps = jnp.max(sweeps)
    else:
        geo, sweeps = jnp.zeros((len(config.references),) + shape, jnp.float32), jnp.int32(0)
    return BodyModel(
        win, rows, cols, d, body, pts, normals, body & nvalid, w, mres, ref_pix, geo, sweeps
    )


def body_extremities(config: PointFilterConfig, bm: BodyModel) -> tuple[Array, Array]:
    """Points to start tracking on a segmented body: ``AUTO_POINTS`` as frame positions
    ``[5, 2]`` (box convention), and the geodesic reach ``[4]`` mm of the hands and feet.

    The head is the centre of the head above the neck (``kernels.depth.head_neck_split``,
    thesis 4.1.3). Hands and feet are the four geodesic extremities of the body's
    surface graph seen from its centroid and its head (``kernels.graph.farthest_points``):
    the two lowest in the image are the feet, the other two the hands; "a" is the one
    further left. Meant for a person who faces the camera with the limbs apart from the
    trunk (the thesis's initial pose). Side-on, a hand hidden by the body is not an
    extremity, and another point (an elbow, a knee) takes its place; its reach is
    often, not always, shorter than the others' (measured 480-1100 mm side-on on
    ``walk_across_medium``, 670-1500 mm for real hands and feet facing the camera), so
    reach alone does not flag it. With an empty body every point is the window's corner
    and every reach 0.
    """
    body = bm.body
    shape = body.shape
    head = dk.head_neck_split(body).head_centre
    n = jnp.maximum(jnp.sum(body), 1)
    rr, cc = jnp.meshgrid(
        jnp.arange(shape[0], dtype=jnp.float32),
        jnp.arange(shape[1], dtype=jnp.float32),
        indexing="ij",
    )
    centroid = jnp.stack([jnp.sum(jnp.where(body, rr, 0.0)), jnp.sum(jnp.where(body, cc, 0.0))]) / n
    src, _ = dk.nearest_true(body, jnp.stack([head, centroid]))  # [2, 2] (row, col)
    sources = jnp.zeros(shape, bool).at[src[:, 0], src[:, 1]].set(True) & body
    ext, reach = gk.farthest_points(bm.weights, sources, 4, config.max_sweeps)
    xy = _pixel_centre(bm, jnp.concatenate([src[:1], ext]))  # [5, 2]
    limbs = xy[1:]
    low = jnp.argsort(limbs[:, 1])  # ascending image y: hands first, then feet
    hands, feet = low[:2], low[2:]
    hands = hands[jnp.argsort(limbs[hands, 0])]
    feet = feet[jnp.argsort(limbs[feet, 0])]
    order = jnp.concatenate([hands, feet])
    return jnp.concatenate([xy[:1], limbs[order]]), reach[order]


def _component_sizes(labels: Array, valid: Array) -> Array:
    """Per pixel, the number of valid pixels in its component."""
    flat = labels.reshape(-1)
    cnt = jnp.zeros(flat.size, jnp.float32).at[flat].add(valid.reshape(-1).astype(jnp.float32))
    return cnt[flat].reshape(labels.shape)


def _window_pixels(bm: BodyModel, xy: Array, shape: tuple[int, int]) -> tuple[Array, Array]:
    """Frame positions ``[..., 2]`` -> window pixels ``[..., 2] int32 (row, col)``, inside flags."""
    ji = dk.frame_to_window(bm.window, xy)
    col = jnp.floor(ji[..., 0]).astype(jnp.int32)
    row = jnp.floor(ji[..., 1]).astype(jnp.int32)
    inside = (row >= 0) & (row < shape[0]) & (col >= 0) & (col < shape[1])
    rc = jnp.stack([jnp.clip(row, 0, shape[0] - 1), jnp.clip(col, 0, shape[1] - 1)], -1)
    return rc, inside


def _pixel_centre(bm: BodyModel, rc: Array) -> Array:
    """Window pixels ``[..., 2] (row, col)`` -> frame positions ``(x, y)`` of their centres."""
    ji = jnp.stack([rc[..., 1], rc[..., 0]], -1).astype(jnp.float32) + 0.5
    return dk.window_to_frame(bm.window, ji)


def _point_3d(config: PointFilterConfig, bm: BodyModel, xy: Array, offset: Array) -> Array:
    """3D points ``[P, 3]`` under frame positions ``xy [P, 2]``, + ``offset`` mm along the ray.

    The depth is the body's under ``xy`` (the nearest body pixel's if ``xy`` is off the body).
    """
    shape = config.window
    rc, inside = _window_pixels(bm, xy, shape)
    on = inside & bm.body[rc[..., 0], rc[..., 1]]
    ji = dk.frame_to_window(bm.window, xy)
    near, found = dk.nearest_true(bm.body, jnp.stack([ji[..., 1], ji[..., 0]], -1))
    rc = jnp.where(on[..., None], rc, near)
    z = bm.depth[rc[..., 0], rc[..., 1]]
    fx, fy, cx, cy = config.intrinsics
    # Back-project at the estimate's own image position (sub-pixel), with the body depth under it.
    u = xy[..., 0] - 0.5
    v = xy[..., 1] - 0.5
    ray = jnp.stack([(u - cx) / fx, (v - cy) / fy, jnp.ones_like(u)], -1)
    p = z[..., None] * ray
    p = p + offset[..., None] * ray / jnp.linalg.norm(ray, axis=-1, keepdims=True)
    return jnp.where((found & (z > 0))[..., None], p, jnp.nan)


def _box_transform(old: Array, new: Array, xy: Array) -> Array:
    """Map positions by the similarity taking box ``old`` to box ``new`` (scale = height ratio)."""
    oc = old[:2] + old[2:] / 2
    nc = new[:2] + new[2:] / 2
    s = jnp.where(old[3] > 0, new[3] / jnp.where(old[3] > 0, old[3], 1.0), 1.0)
    s = jnp.where((new[3] > 0) & (old[3] > 0), s, 1.0)
    return nc + (xy - oc) * s


@memoised_build
def build_point_filter(config: PointFilterConfig) -> Filter:
    """``Filter(init, step)`` for ``P`` body points (``P`` is set by the points ``init`` gets)."""
    shape = config.window
    n = config.n_particles
    scheme = rs.SCHEMES[config.resampler]

    def spin_of(bm: BodyModel, rc: Array):
        bin_size = config.spin_bin_factor * bm.mesh_resolution
        return sk.spin_images(
            bm.points,
            bm.normals,
            bm.spin_valid,
            rc,
            jnp.maximum(bin_size, 1e-3),
            width=config.spin_width,
            support_angle_deg=config.support_angle_deg,
            patch_radius=config.patch_radius,
            batch_size=config.spin_batch,
        )

    def init(params: PointParams, key: Array, inputs: PointInputs, points: Array) -> PointState:
        points = jnp.asarray(points, jnp.float32)
        p = points.shape[0]
        bm = body_model(config, inputs.depth, inputs.box, inputs.foreground)
        rc, inside = _window_pixels(bm, points, shape)
        on = inside & bm.body[rc[:, 0], rc[:, 1]]
        on = on & bm.spin_valid[rc[:, 0], rc[:, 1]]
        ji = dk.frame_to_window(bm.window, points)
        near, _ = dk.nearest_true(bm.spin_valid, jnp.stack([ji[:, 1], ji[:, 0]], -1))
        rc = jnp.where(on[:, None], rc, near)
        start = jnp.where(on[:, None], points, _pixel_centre(bm, rc))
        z0 = bm.depth[rc[:, 0], rc[:, 1]]
        ref_spin, _ = spin_of(bm, rc)
        ref_geo = bm.geodesic[:, rc[:, 0], rc[:, 1]].T  # [P, R]
        noise = jax.random.normal(key, (p, n, 2)) * _param(params.pos_noise, p)[..., None]
        xy = start[:, None, :] + noise
        particles = jnp.concatenate([xy, jnp.zeros((p, n, 2), jnp.float32)], -1)
        lw = jnp.full((p, n), -jnp.log(jnp.float32(n)))
        return PointState(
            particles, lw, ref_spin, ref_geo, jnp.asarray(inputs.box, jnp.float32), start, z0
        )

    def step(params: PointParams, key: Array, state: PointState, inputs: PointInputs):
        p = state.particles.shape[0]
        k_pos, k_vel, k_rec, k_res = jax.random.split(key, 4)
        box = jnp.asarray(inputs.box, jnp.float32)
        bm = body_model(config, inputs.depth, box, inputs.foreground)

        # 2. prediction
        xy, vel = state.particles[..., :2], state.particles[..., 2:]
        prev_est = state.estimate
        z_pred = state.depth
        if config.follow_box:
            xy = _box_transform(state.box, box, xy)
            prev_est = _box_transform(state.box, box, prev_est)
            # the box height is inversely proportional to the person's depth
            ok = (state.box[3] > 0) & (box[3] > 0)
            z_pred = jnp.where(ok, z_pred * state.box[3] / jnp.where(ok, box[3], 1.0), z_pred)
        vel = _param(params.velocity_decay, p)[..., None] * vel
        vel = vel + jax.random.normal(k_vel, vel.shape) * _param(params.vel_noise, p)[..., None]
        xy = xy + vel + jax.random.normal(k_pos, xy.shape) * _param(params.pos_noise, p)[..., None]

        # 3. weights
        rc, inside = _window_pixels(bm, xy, shape)
        on = inside & bm.body[rc[..., 0], rc[..., 1]]
        lw = jnp.zeros((p, n), jnp.float32)
        complete = jnp.ones((p,), jnp.float32)
        if config.uses_spin:
            imgs, comp = spin_of(bm, rc)  # [P, N, W, W]
            ov = sk.overlap_count(imgs, state.ref_spin[:, None])
            ov_on = jnp.where(on, ov.astype(jnp.float32), jnp.nan)
            lam = jnp.nan_to_num(0.5 * jnp.nanmedian(ov_on, axis=1))
            c = sk.spin_similarity(imgs, state.ref_spin[:, None], lam[:, None])
            lw = lw + c / _param(params.spin_temperature, p)
            complete = jnp.sum(comp & on, 1) / jnp.maximum(jnp.sum(on, 1), 1)
        if config.uses_geodesic:
            g = jnp.moveaxis(bm.geodesic[:, rc[..., 0], rc[..., 1]], 0, -1)  # [P, N, R]
            dev = (g - state.ref_geodesic[:, None, :]) / _param(params.geo_sigma, p)[..., None]
            reach = jnp.all(jnp.isfinite(g), -1)
            lw = lw + jnp.where(reach, -0.5 * jnp.sum(dev * dev, -1), -jnp.inf)
        if config.depth_consistency:
            z = bm.depth[rc[..., 0], rc[..., 1]]
            dz = (z - z_pred[:, None]) / _param(params.depth_sigma, p)
            lw = lw + jnp.where(z_pred[:, None] > 0, -0.5 * dz * dz, 0.0)
        lw = jnp.where(on, lw, -jnp.inf)
        lw = jnp.where(jnp.isnan(lw), -jnp.inf, lw)

        # 4. recovery when a point has no particle with a valid weight
        lost = jax.vmap(rs.all_weights_invalid)(lw)
        ji = dk.frame_to_window(bm.window, prev_est)
        near, found = dk.nearest_true(bm.spin_valid, jnp.stack([ji[:, 1], ji[:, 0]], -1))
        anchor = _pixel_centre(bm, near)
        redraw = (
            anchor[:, None, :]
            + jax.random.normal(k_rec, xy.shape) * _param(params.recovery_spread, p)[..., None]
        )
        recovered = lost & found
        xy = jnp.where(recovered[:, None, None], redraw, xy)
        vel = jnp.where(recovered[:, None, None], 0.0, vel)
        lw = jnp.where(recovered[:, None], 0.0, lw)
        lw = jax.vmap(rs.normalise_log_weights)(lw)
        ess = jax.vmap(rs.effective_sample_size)(lw)

        # 5. estimates
        wts = jnp.exp(lw)
        mean = jnp.sum(wts[..., None] * xy, axis=1)
        best = jnp.take_along_axis(xy, jnp.argmax(lw, axis=1)[:, None, None], axis=1)[:, 0]
        off = _param(params.joint_depth_offset, p)[:, 0]
        mean3d = _point_3d(config, bm, mean, off)
        best3d = _point_3d(config, bm, best, off)
        surface = _point_3d(config, bm, mean, jnp.zeros_like(off))[:, 2]
        z_new = jnp.where(jnp.isfinite(surface), surface, z_pred)

        # 6. resampling
        particles = jnp.concatenate([xy, vel], -1)
        keys = jax.random.split(k_res, p)
        thr = jnp.where(recovered, 0.0, config.ess_threshold)  # a fresh recovery cloud is uniform

        def res(k, lw_i, parts_i, t):
            return rs.resample_if(k, lw_i, parts_i, t, scheme)

        particles, lw, resampled = jax.vmap(res)(keys, lw, particles, thr)
        new_state = PointState(particles, lw, state.ref_spin, state.ref_geodesic, box, mean, z_new)
        info = PointInfo(
            mean,
            best,
            mean3d,
            best3d,
            ess,
            jnp.mean(on, axis=1),
            recovered,
            resampled,
            jnp.sum(bm.body),
            bm.mesh_resolution,
            bm.sweeps,
            complete,
        )
        return new_state, info

    return Filter(init=init, step=step)


def track_points(filt: Filter, params: PointParams, key: Array, inputs: PointInputs, points: Array):
    """Run the point filter over ``inputs`` with a leading time axis ``[T, ...]`` (a ``lax.scan``).

    Initialised on frame 0 at ``points [P, 2]``, stepped on frames ``1..T-1``.
    Returns ``(final_state, infos)`` with infos ``[T - 1, ...]``.
    """
    return scan_filter(filt, params, key, inputs, points)
