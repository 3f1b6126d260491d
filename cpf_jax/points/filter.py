"""Layer 2: a batched particle filter for points on the body (thesis ch. 4, SPEC C3).

``P`` points (head, hands, feet, ...) are tracked together: every array has a leading
``[P, N]`` (points x particles) shape and one jitted step serves all. A particle is
``(x, y, x', y')`` in depth-frame pixels (thesis 4.2.3, box convention). One ``step``::

    segment    the body in the window around the frame's box        (body.py)
    predict    x' <- decay x' + n_v, x <- x + x' + n_x, after moving with the box
    weigh      spin-image similarity C / temperature (eq. 4.7), and/or the geodesic
               deviation -(g - g0)^2 / (2 geo_sigma^2) from the reference point (4.3),
               combined as a product (thesis 6.2), plus a depth-consistency term; off the
               body: no weight (masked, thesis 4.4); with ``anchor_prior`` a prior on the
               particle's offset in the box about the point's start offset
    recover    a point whose particles are all off the body is re-drawn around the body
               pixel nearest its last estimate
    estimate   best particle (thesis Alg. 2-3) and weighted mean, in 2D and 3D
    follow     with ``adapt_geodesic``, the geodesic references move towards the
               distances under the visible estimates
    resample   per point, when ESS < ess_threshold * N

With ``follow_box`` a particle first moves by the similarity that takes the previous box
onto the current one (layer 1's output), so that its velocity models motion on the body
only. The depth-consistency term ``-(z - z_pred)^2 / (2 depth_sigma^2)`` (``z`` the
surface depth under the particle, ``z_pred`` the last estimate's scaled by the box-height
ratio) keeps a hand's cloud from sliding onto the thigh behind it.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from cpf_jax.filter import Context, Filter, memoised_build
from cpf_jax.kernels import depth as dk
from cpf_jax.kernels import resample as rs
from cpf_jax.kernels import spin as sk
from cpf_jax.params import P, props, values
from cpf_jax.points.body import (
    BodyModel,
    body_model,
    body_points_3d,
    pixel_centre,
    ray_point,
    surface_depth,
    window_pixels,
)
from cpf_jax.points.config import PointConfig
from cpf_jax.types import check_intrinsics

__all__ = [
    "PointMotionParams",
    "PointWeightParams",
    "PointEstimateParams",
    "PointParams",
    "POINTS",
    "POINT_PROPS",
    "default_point_params",
    "PointFrame",
    "PointState",
    "PointInfo",
    "point_init",
    "point_predict",
    "reacquire_logits",
    "point_reacquire",
    "spin_term",
    "geodesic_term",
    "depth_term",
    "point_weights",
    "box_offsets",
    "anchor_term",
    "geodesic_reference_update",
    "hidden_term",
    "hidden_evidence",
    "hidden_update",
    "point_recover",
    "point_estimate",
    "point_resample",
    "point_step",
    "estimate_3d",
    "build_point_filter",
]


class PointMotionParams(NamedTuple):
    pos_noise: Array  # px, std of the position noise n_x
    vel_noise: Array  # px/frame, std of the velocity noise n_v
    velocity_decay: Array  # in [0, 1]; 1 = constant velocity, 0 = random walk
    recovery_spread: Array  # px, std of the cloud re-drawn by the recovery
    hidden_pos_noise: Array  # px, std of a hidden particle's position noise
    hidden_velocity_decay: Array  # in [0, 1], a hidden particle's velocity decay
    p_hide: Array  # per frame, probability that a visible particle becomes hidden
    p_show: Array  # per frame, probability that a hidden particle becomes visible
    reappear_spread: Array  # px, std of the position noise of a particle that shows again
    reacquire_spread: Array  # px, std of the prior around the last estimate, re-acquisition


class PointWeightParams(NamedTuple):
    spin_temperature: Array  # log-weight = C / temperature (C spans about 0-3)
    geo_sigma: Array  # mm, width of the geodesic-deviation likelihood
    depth_sigma: Array  # mm, width of the depth-consistency likelihood
    hidden_log_weight: Array  # log-weight of a hidden particle with a surface in front
    occlusion_margin: Array  # mm, how far in front of a point a surface must be to hide it
    anchor_sigma_x: Array  # box heights, across: width of the prior about the start offset
    anchor_sigma_y: Array  # box heights, down: width of the prior about the start offset
    geo_rate: Array  # in (0, 1), per frame: how far a geodesic reference moves to the estimate's


class PointEstimateParams(NamedTuple):
    joint_depth_offset: Array  # mm added along the viewing ray to the 3D estimates


class PointParams(NamedTuple):
    """Continuous parameters of the point filter: scalars, or ``[P]`` per point."""

    motion: PointMotionParams
    weights: PointWeightParams
    estimate: PointEstimateParams


POINTS = PointParams(
    motion=PointMotionParams(
        pos_noise=P(2.0, "softplus"),
        vel_noise=P(1.0, "softplus"),
        velocity_decay=P(0.5, "sigmoid"),
        recovery_spread=P(2.0, "softplus"),
        hidden_pos_noise=P(3.0, "softplus"),
        hidden_velocity_decay=P(0.5, "sigmoid"),
        p_hide=P(0.1, "sigmoid"),
        p_show=P(0.1, "sigmoid"),
        reappear_spread=P(6.0, "softplus"),
        reacquire_spread=P(30.0, "softplus"),
    ),
    weights=PointWeightParams(
        spin_temperature=P(0.1, "softplus"),
        geo_sigma=P(40.0, "softplus"),
        depth_sigma=P(40.0, "softplus"),
        hidden_log_weight=P(-3.0),
        occlusion_margin=P(80.0, "softplus"),
        anchor_sigma_x=P(0.2, "softplus"),
        anchor_sigma_y=P(0.06, "softplus"),
        geo_rate=P(0.1, "sigmoid"),
    ),
    estimate=PointEstimateParams(joint_depth_offset=P(0.0)),
)
POINT_PROPS = props(POINTS)


def default_point_params() -> PointParams:
    """The point filter's default parameters (float32 arrays)."""
    return values(POINTS)


class PointFrame(NamedTuple):
    """One frame for the point filter: ``depth [H, W] uint16`` mm (0 = missing), layer 1's
    ``box [4]`` xywh, and optionally ``foreground [H, W] bool`` (only foreground pixels
    can be the body) and the target's depth ``target_depth []`` mm (0: unknown), which
    anchors the body (``PointConfig.joined_anchor``)."""

    depth: Array
    box: Array
    foreground: Array | None = None
    target_depth: Array | None = None


class PointState(NamedTuple):
    particles: Array  # [P, N, 4] (x, y, vx, vy), frame px
    log_weights: Array  # [P, N] normalised
    ref_spin: Array  # [P, W, W] reference spin images
    ref_geodesic: Array  # [P, R] mm, geodesic distances from the references (initial, or
    # followed with ``adapt_geodesic``)
    box: Array  # [4] box of the last frame
    estimate: Array  # [P, 2] weighted-mean estimate of the last frame
    depth: Array  # [P] mm, the point's depth: the surface under its last visible estimate
    hidden: Array  # [P, N] bool, each particle's visibility flag (True: hidden)
    hidden_prob: Array  # [P] posterior probability that the point is hidden
    anchor: Array  # [P, 2] the point's start position relative to the box (``box_offsets``)


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
    hidden: Array  # [P] bool, the point is reported hidden (hidden_share > 0.5)
    hidden_share: Array  # [P] posterior probability that the point is hidden
    surface: Array | None = None  # [Hw * Ww, 3] mm body points (NaN off it), report_surface


def _per_point(x: Array, p: int) -> Array:
    """A parameter as a ``[P, 1]`` column (scalars broadcast)."""
    return jnp.broadcast_to(jnp.asarray(x, jnp.float32), (p,))[:, None]


def _spin_images(config: PointConfig, bm: BodyModel, rc: Array, needed: Array | None = None):
    """Spin images (thesis 4.2, App. G) at window pixels ``rc [..., 2]``, bins of
    ``spin_bin_factor`` mesh resolutions; only where ``needed`` (others empty)."""
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
        needed=needed,
    )


def _box_transform(old: Array, new: Array, xy: Array) -> Array:
    """Positions moved by the similarity taking box ``old`` onto box ``new`` (scale: the
    height ratio)."""
    oc = old[:2] + old[2:] / 2
    nc = new[:2] + new[2:] / 2
    s = jnp.where(old[3] > 0, new[3] / jnp.where(old[3] > 0, old[3], 1.0), 1.0)
    s = jnp.where((new[3] > 0) & (old[3] > 0), s, 1.0)
    return nc + (xy - oc) * s


def point_init(
    config: PointConfig,
    params: PointParams,
    key: Array,
    frame: PointFrame,
    box: Array,
    context: Context | None = None,
) -> PointState:
    """Reference spin images and geodesic distances at ``context.points [P, 2]`` (moved to
    the nearest body pixel with a normal when off the body), and a cloud around each."""
    if context is None or context.points is None:
        raise ValueError("the point filter needs the points to track: Context(points=[P, 2])")
    check_intrinsics(config.intrinsics, frame.depth.shape[:2], "PointConfig.intrinsics")
    points = jnp.asarray(context.points, jnp.float32)
    p = points.shape[0]
    bm = body_model(config, frame.depth, box, frame.foreground, frame.target_depth)
    rc, inside = window_pixels(bm, points, config.window)
    on = inside & bm.body[rc[:, 0], rc[:, 1]]
    on = on & bm.spin_valid[rc[:, 0], rc[:, 1]]
    ji = dk.frame_to_window(bm.window, points)
    near, _ = dk.nearest_true(bm.spin_valid, jnp.stack([ji[:, 1], ji[:, 0]], -1))
    rc = jnp.where(on[:, None], rc, near)
    start = jnp.where(on[:, None], points, pixel_centre(bm, rc))
    ref_spin, _ = _spin_images(config, bm, rc)
    n = config.n_particles
    noise = jax.random.normal(key, (p, n, 2)) * _per_point(params.motion.pos_noise, p)[..., None]
    xy = start[:, None, :] + noise
    return PointState(
        particles=jnp.concatenate([xy, jnp.zeros((p, n, 2), jnp.float32)], -1),
        log_weights=jnp.full((p, n), -jnp.log(jnp.float32(n))),
        ref_spin=ref_spin,
        ref_geodesic=bm.geodesic[:, rc[:, 0], rc[:, 1]].T,  # [P, R]
        box=jnp.asarray(box, jnp.float32),
        estimate=start,
        depth=bm.depth[rc[:, 0], rc[:, 1]],
        hidden=jnp.zeros((p, n), bool),
        hidden_prob=jnp.zeros((p,), jnp.float32),
        anchor=box_offsets(jnp.asarray(box, jnp.float32), start),
    )


def estimate_3d(config: PointConfig, params: PointParams, state: PointState) -> Array:
    """``[P, 3]`` mm: the state's estimates at the surface depth under them (the 3D points
    of the frame the state was made on, as ``PointInfo.mean3d`` gives a step's)."""
    off = _per_point(params.estimate.joint_depth_offset, state.estimate.shape[0])[:, 0]
    return ray_point(config.intrinsics, state.estimate, state.depth, off)


def point_predict(
    config: PointConfig, params: PointParams, keys, state: PointState, box: Array
) -> tuple[Array, Array, Array, Array, Array, Array]:
    """``(xy, velocity, hidden, shown, previous estimate, predicted depth)`` after following the
    box, the visibility flags' Markov transition (visible -> hidden with ``p_hide``, hidden
    -> visible with ``p_show``) and the constant-velocity model with decay. A hidden
    particle keeps more of its velocity and spreads wider (the point moves on unseen); one
    that shows again spreads by ``reappear_spread`` (the point comes out where the body
    model and the likelihood say, not exactly where it was predicted)."""
    k_pos, k_vel, k_vis = keys
    p = state.particles.shape[0]
    m = params.motion
    xy, vel = state.particles[..., :2], state.particles[..., 2:]
    hidden = state.hidden
    prev_est, z_pred = state.estimate, state.depth
    if config.follow_box:
        xy = _box_transform(state.box, box, xy)
        prev_est = _box_transform(state.box, box, prev_est)
        # The box height is inversely proportional to the person's depth.
        ok = (state.box[3] > 0) & (box[3] > 0)
        z_pred = jnp.where(ok, z_pred * state.box[3] / jnp.where(ok, box[3], 1.0), z_pred)
    shown = jnp.zeros_like(hidden)
    if config.hidden_particles:
        flip = jax.random.uniform(k_vis, hidden.shape) < jnp.where(
            hidden, _per_point(m.p_show, p), _per_point(m.p_hide, p)
        )
        shown = hidden & flip
        hidden = hidden ^ flip
    decay = jnp.where(
        hidden, _per_point(m.hidden_velocity_decay, p), _per_point(m.velocity_decay, p)
    )
    pos_noise = jnp.where(hidden, _per_point(m.hidden_pos_noise, p), _per_point(m.pos_noise, p))
    pos_noise = jnp.where(shown, _per_point(m.reappear_spread, p), pos_noise)
    vel = decay[..., None] * vel
    vel = vel + jax.random.normal(k_vel, vel.shape) * _per_point(m.vel_noise, p)[..., None]
    xy = xy + vel + jax.random.normal(k_pos, xy.shape) * pos_noise[..., None]
    return xy, vel, hidden, shown, prev_est, z_pred


def reacquire_logits(
    params: PointParams, bm: BodyModel, state: PointState, prev_est: Array
) -> Array:
    """``[P, Hw * Ww]`` log-density over the window's pixels of where a hidden point shows
    again: on the body (a pixel with a normal), at the geodesic distances from the references
    it had at the start (thesis 4.3: a hand stays an arm's length from the head along the
    surface), within ``reacquire_spread`` of its last estimate; ``-inf`` elsewhere."""
    p = prev_est.shape[0]
    r, hw, ww = bm.geodesic.shape
    g = bm.geodesic.reshape(r, -1)  # [R, M]
    dev = (g[None] - state.ref_geodesic[:, :, None]) / _per_point(params.weights.geo_sigma, p)[
        ..., None
    ]
    ring = -0.5 * jnp.sum(dev * dev, 1)  # [P, M]
    ring = jnp.where(jnp.all(jnp.isfinite(g), 0)[None], ring, -jnp.inf)
    rows, cols = jnp.meshgrid(jnp.arange(hw), jnp.arange(ww), indexing="ij")
    centres = pixel_centre(bm, jnp.stack([rows.reshape(-1), cols.reshape(-1)], -1))  # [M, 2]
    d2 = jnp.sum((centres[None] - prev_est[:, None]) ** 2, -1)
    prior = -0.5 * d2 / _per_point(params.motion.reacquire_spread, p) ** 2
    return jnp.where(bm.spin_valid.reshape(-1)[None], ring + prior, -jnp.inf)


def point_reacquire(
    params: PointParams,
    key: Array,
    bm: BodyModel,
    state: PointState,
    prev_est: Array,
    xy: Array,
    vel: Array,
    shown: Array,
) -> tuple[Array, Array]:
    """``(xy, velocity)`` with the particles that show again this frame (``shown [P, N]``)
    drawn from ``reacquire_logits`` (inverse CDF per point), at rest: a hidden point comes
    out where the body model says it can be, not only where it went in. Points with no such
    pixel keep their predicted particles."""
    logits = reacquire_logits(params, bm, state, prev_est)
    top = jnp.max(logits, axis=1, keepdims=True)
    ok = jnp.isfinite(top[:, 0])
    probs = jnp.exp(logits - jnp.where(jnp.isfinite(top), top, 0.0))
    cdf = jnp.cumsum(probs, axis=1)
    k_u, k_j = jax.random.split(key)
    u = jax.random.uniform(k_u, shown.shape) * cdf[:, -1:]
    idx = jax.vmap(jnp.searchsorted)(cdf, u)
    idx = jnp.clip(idx, 0, cdf.shape[1] - 1)
    ww = bm.geodesic.shape[2]
    drawn = pixel_centre(bm, jnp.stack([idx // ww, idx % ww], -1))
    drawn = drawn + (jax.random.uniform(k_j, drawn.shape) - 0.5) * bm.window.scale
    take = shown & ok[:, None]
    return jnp.where(take[..., None], drawn, xy), jnp.where(take[..., None], 0.0, vel)


def spin_term(
    config: PointConfig, params: PointWeightParams, bm: BodyModel, state: PointState, rc, on
) -> tuple[Array, Array]:
    """``(log-weight [P, N], spin completeness [P])`` of the spin images at window pixels
    ``rc [P, N, 2]``: similarity C (eq. 4.7) over the temperature, ``lambda`` half the
    median overlap over a point's particles on the body (``on [P, N]``)."""
    p = rc.shape[0]
    # Only the particles on the body are scored: the others' images are not computed.
    imgs, comp = _spin_images(config, bm, rc, on)  # [P, N, W, W]
    ov = sk.overlap_count(imgs, state.ref_spin[:, None])
    ov_on = jnp.where(on, ov.astype(jnp.float32), jnp.nan)
    lam = jnp.nan_to_num(0.5 * jnp.nanmedian(ov_on, axis=1))
    c = sk.spin_similarity(imgs, state.ref_spin[:, None], lam[:, None])
    complete = jnp.sum(comp & on, 1) / jnp.maximum(jnp.sum(on, 1), 1)
    return c / _per_point(params.spin_temperature, p), complete


def geodesic_term(params: PointWeightParams, bm: BodyModel, state: PointState, rc) -> Array:
    """``[P, N]`` log-weight ``-|g - g0|^2 / (2 geo_sigma^2)`` of the geodesic distances
    ``g`` from the references at window pixels ``rc`` (thesis 4.3); ``-inf`` where one is
    unreachable."""
    p = rc.shape[0]
    g = jnp.moveaxis(bm.geodesic[:, rc[..., 0], rc[..., 1]], 0, -1)  # [P, N, R]
    dev = (g - state.ref_geodesic[:, None, :]) / _per_point(params.geo_sigma, p)[..., None]
    reach = jnp.all(jnp.isfinite(g), -1)
    return jnp.where(reach, -0.5 * jnp.sum(dev * dev, -1), -jnp.inf)


def depth_term(params: PointWeightParams, bm: BodyModel, rc, z_pred: Array) -> Array:
    """``[P, N]`` log-weight ``-(z - z_pred)^2 / (2 depth_sigma^2)`` of the surface depth at
    window pixels ``rc`` against each point's predicted depth (0 where none is known)."""
    p = rc.shape[0]
    z = bm.depth[rc[..., 0], rc[..., 1]]
    dz = (z - z_pred[:, None]) / _per_point(params.depth_sigma, p)
    return jnp.where(z_pred[:, None] > 0, -0.5 * dz * dz, 0.0)


def box_offsets(box: Array, xy: Array) -> Array:
    """``[..., 2]`` positions ``xy [..., 2]`` relative to ``box [4]``: from its centre, in box
    heights (the height follows the person's depth, so an offset on the body keeps its value
    as the person walks towards or away from the camera)."""
    return (xy - (box[:2] + box[2:] / 2)) / jnp.maximum(box[3], 1.0)


def anchor_term(params: PointWeightParams, box: Array, anchor: Array, xy: Array) -> Array:
    """``[P, N]`` log-weight ``-dx^2 / (2 sx^2) - dy^2 / (2 sy^2)`` of the particles' offsets
    in ``box [4]`` (``box_offsets``) from each point's start offset ``anchor [P, 2]``: a body
    model's prior that a hand swings about the hip (down the box it stays within a forearm;
    across, within the swing), so that a cloud does not settle on a knee or a foot."""
    p = xy.shape[0]
    d = box_offsets(box, xy) - anchor[:, None, :]
    sx, sy = _per_point(params.anchor_sigma_x, p), _per_point(params.anchor_sigma_y, p)
    return -0.5 * ((d[..., 0] / sx) ** 2 + (d[..., 1] / sy) ** 2)


def geodesic_reference_update(
    config: PointConfig,
    params: PointWeightParams,
    bm: BodyModel,
    ref: Array,
    xy: Array,
    visible: Array,
) -> Array:
    """``[P, R]`` geodesic references ``ref`` moved a fraction ``geo_rate`` towards the
    distances under the estimates ``xy [P, 2]`` of the points ``visible [P]`` whose estimate
    lies on the body and is reached from every reference (kept elsewhere): a hand's distance
    from the head along the surface changes as its bridges to the trunk come and go."""
    p = xy.shape[0]
    rc, inside = window_pixels(bm, xy, config.window)
    g = bm.geodesic[:, rc[:, 0], rc[:, 1]].T  # [P, R]
    ok = visible & inside & bm.body[rc[:, 0], rc[:, 1]] & jnp.all(jnp.isfinite(g), -1)
    rate = _per_point(params.geo_rate, p)
    return jnp.where(ok[:, None], ref + rate * (jnp.where(ok[:, None], g, ref) - ref), ref)


def hidden_term(params: PointWeightParams, bm: BodyModel, rc, inside, z_pred: Array) -> Array:
    """``[P, N]`` log-weight of hidden particles at window pixels ``rc``: ``hidden_log_weight``
    where a surface more than ``occlusion_margin`` in front of the point's predicted depth
    can hide it, ``-inf`` where the pixel shows a surface at or behind the point (which
    would then be seen), has no depth or lies outside the window."""
    p = rc.shape[0]
    z = bm.depth[rc[..., 0], rc[..., 1]]
    margin = _per_point(params.occlusion_margin, p)
    in_front = inside & (z > 0) & (z < z_pred[:, None] - margin)
    level = _per_point(params.hidden_log_weight, p)
    return jnp.where(in_front, level, -jnp.inf)


def hidden_evidence(
    config: PointConfig,
    params: PointWeightParams,
    bm: BodyModel,
    prior_lw: Array,
    xy: Array,
    lw_visible: Array,
    z_pred: Array,
) -> Array:
    """``[P]`` log-likelihood ratio, hidden against visible, of each point's predicted cloud
    ``xy [P, N, 2]`` (weights ``prior_lw``, normalised): the cloud-averaged ``hidden_term``
    against the cloud-averaged visible log-weights ``lw_visible`` (``point_weights``), the
    flag marginalised over the particles' positions. ``+inf`` when no particle can be
    visible but one can be hidden, ``-inf`` the other way round, ``0`` when neither."""
    rc, inside = window_pixels(bm, xy, config.window)
    lh = jax.nn.logsumexp(prior_lw + hidden_term(params, bm, rc, inside, z_pred), axis=1)
    lv = jax.nn.logsumexp(prior_lw + lw_visible, axis=1)
    both = jnp.isfinite(lh) | jnp.isfinite(lv)
    return jnp.where(both, jnp.nan_to_num(lh, neginf=-1e30) - jnp.nan_to_num(lv, neginf=-1e30), 0)


def hidden_update(params: PointMotionParams, prob: Array, llr: Array) -> Array:
    """``[P]`` posterior probability that each point is hidden: the previous ``prob``
    through the flag's Markov transition (``p_hide``, ``p_show``), then Bayes' rule with
    the log-likelihood ratio ``llr`` of ``hidden_evidence`` (a two-state forward filter)."""
    p = prob.shape[0]
    p_hide, p_show = _per_point(params.p_hide, p)[:, 0], _per_point(params.p_show, p)[:, 0]
    prior = prob * (1.0 - p_show) + (1.0 - prob) * p_hide
    return jax.nn.sigmoid(jnp.log(prior) - jnp.log1p(-prior) + jnp.clip(llr, -60.0, 60.0))


def point_weights(
    config: PointConfig,
    params: PointWeightParams,
    bm: BodyModel,
    state: PointState,
    xy: Array,
    hidden: Array,
    z_pred: Array,
) -> tuple[Array, Array, Array]:
    """``(log-weights [P, N], on body [P, N], spin completeness [P])``. A visible particle
    scores the sum of the configured terms (a product of likelihoods, thesis 6.2) and no
    weight off the body (masked, thesis 4.4); a hidden one ``hidden_term``. The spin term is
    taken relative to its median over the point's particles on the body, a likelihood ratio
    against the surface around the point, so that a hidden particle (which sees none of
    the point) competes with the visible ones on an even footing (a constant per point
    leaves the visible particles' weights as they were)."""
    p, n = xy.shape[:2]
    rc, inside = window_pixels(bm, xy, config.window)
    on = inside & bm.body[rc[..., 0], rc[..., 1]]
    lw = jnp.zeros((p, n), jnp.float32)
    complete = jnp.ones((p,), jnp.float32)
    if config.uses_spin:
        spin, complete = spin_term(config, params, bm, state, rc, on)
        level = jnp.nanmedian(jnp.where(on & jnp.isfinite(spin), spin, jnp.nan), axis=1)
        lw = lw + spin - jnp.nan_to_num(level)[:, None]
    if config.uses_geodesic:
        lw = lw + geodesic_term(params, bm, state, rc)
    if config.depth_consistency:
        lw = lw + depth_term(params, bm, rc, z_pred)
    lw = jnp.where(on, lw, -jnp.inf)
    if config.hidden_particles:
        lw = jnp.where(hidden, hidden_term(params, bm, rc, inside, z_pred), lw)
    return jnp.where(jnp.isnan(lw), -jnp.inf, lw), on, complete


def point_recover(
    params: PointMotionParams,
    key: Array,
    bm: BodyModel,
    prev_est: Array,
    xy: Array,
    vel: Array,
    hidden: Array,
    lw: Array,
) -> tuple[Array, Array, Array, Array, Array]:
    """Re-draw, visible, with uniform weights and no velocity, the points whose every
    particle has no weight (off the body, and nothing in front that could hide them),
    around the body pixel nearest their last estimate (kept as predicted when the body is
    empty); returns ``(xy, vel, hidden, lw, recovered [P])``. The search for the nearest
    body pixel runs only in a frame where some point is lost (``lax.cond``)."""
    lost = jax.vmap(rs.all_weights_invalid)(lw)

    def redraw(_):
        return _redraw_lost(params, key, bm, prev_est, xy, vel, hidden, lw, lost)

    def keep(_):
        return xy, vel, hidden, lw, jnp.zeros_like(lost)

    return jax.lax.cond(jnp.any(lost), redraw, keep, None)


def _redraw_lost(params, key, bm, prev_est, xy, vel, hidden, lw, lost):
    """``point_recover``'s re-draw of the ``lost [P]`` points."""
    p = xy.shape[0]
    ji = dk.frame_to_window(bm.window, prev_est)
    near, found = dk.nearest_true(bm.spin_valid, jnp.stack([ji[:, 1], ji[:, 0]], -1))
    anchor = pixel_centre(bm, near)
    spread = _per_point(params.recovery_spread, p)[..., None]
    redraw = anchor[:, None, :] + jax.random.normal(key, xy.shape) * spread
    recovered = lost & found
    xy = jnp.where(recovered[:, None, None], redraw, xy)
    vel = jnp.where(recovered[:, None, None], 0.0, vel)
    hidden = hidden & ~recovered[:, None]
    lw = jnp.where(recovered[:, None], 0.0, lw)
    return xy, vel, hidden, lw, recovered


def point_resample(
    config: PointConfig, key: Array, lw: Array, particles: Array, recovered: Array
) -> tuple[Array, Array, Array]:
    """``(particles [P, N, 4], log-weights [P, N], resampled [P])``: each point's cloud
    resampled when its ESS is under ``ess_threshold * N`` (a cloud just re-drawn by the
    recovery is uniform and is not)."""
    threshold = jnp.where(recovered, 0.0, config.ess_threshold)
    scheme = rs.SCHEMES[config.resampler]
    keys = jax.random.split(key, lw.shape[0])
    return jax.vmap(lambda k, w, x, t: rs.resample_if(k, w, x, t, scheme))(
        keys, lw, particles, threshold
    )


def point_estimate(xy: Array, hidden: Array, lw: Array) -> tuple[Array, Array, Array, Array]:
    """``(mean [P, 2], best [P, 2], hidden share [P], reported hidden [P])`` of normalised
    log-weights ``lw [P, N]``: a point is reported hidden when its hidden particles hold more
    than half the weight, and its mean is then theirs (the last estimate moved on by the
    predicted motion), else the visible particles' mean."""
    wts = jnp.exp(lw)
    share = jnp.sum(jnp.where(hidden, wts, 0.0), axis=1)
    is_hidden = share > 0.5
    group = hidden == is_hidden[:, None]
    gw = jnp.where(group, wts, 0.0)
    total = jnp.sum(gw, axis=1, keepdims=True)
    gw = jnp.where(total > 0, gw / jnp.where(total > 0, total, 1.0), wts)
    mean = jnp.sum(gw[..., None] * xy, axis=1)
    best = jnp.take_along_axis(xy, jnp.argmax(lw, axis=1)[:, None, None], axis=1)[:, 0]
    return mean, best, share, is_hidden


def point_step(
    config: PointConfig, params: PointParams, key: Array, state: PointState, frame: PointFrame
) -> tuple[PointState, PointInfo]:
    """One frame: segment, predict, re-acquire, weigh (with the anchor prior), recover,
    estimate, follow the geodesic references, resample."""
    p = state.particles.shape[0]
    k_pos, k_vel, k_vis, k_acq, k_rec, k_res = jax.random.split(key, 6)
    box = jnp.asarray(frame.box, jnp.float32)
    bm = body_model(config, frame.depth, box, frame.foreground, frame.target_depth)
    xy, vel, hidden, shown, prev_est, z_pred = point_predict(
        config, params, (k_pos, k_vel, k_vis), state, box
    )
    if config.hidden_particles and config.reacquire:
        xy, vel = point_reacquire(params, k_acq, bm, state, prev_est, xy, vel, shown)
    lw, on, complete = point_weights(config, params.weights, bm, state, xy, hidden, z_pred)
    if config.visibility == "report":
        llr = hidden_evidence(config, params.weights, bm, state.log_weights, xy, lw, z_pred)
        prob = hidden_update(params.motion, state.hidden_prob, llr)
    if config.anchor_prior:
        lw = lw + anchor_term(params.weights, box, state.anchor, xy)
    xy, vel, hidden, lw, recovered = point_recover(
        params.motion, k_rec, bm, prev_est, xy, vel, hidden, lw
    )
    lw = jax.vmap(rs.normalise_log_weights)(lw)
    ess = jax.vmap(rs.effective_sample_size)(lw)
    mean, best, share, is_hidden = point_estimate(xy, hidden, lw)
    if config.visibility == "report":
        share, is_hidden = prob, prob > 0.5
    off = _per_point(params.estimate.joint_depth_offset, p)[:, 0]
    z_mean, z_best = jnp.split(surface_depth(config, bm, jnp.concatenate([mean, best])), 2)
    if config.hidden_particles:
        # A hidden point keeps its predicted depth: the surface under it is what hides it.
        z_mean = jnp.where(is_hidden, z_pred, z_mean)
    ref_geodesic = state.ref_geodesic
    if config.adapt_geodesic:
        ref_geodesic = geodesic_reference_update(
            config, params.weights, bm, ref_geodesic, mean, ~is_hidden
        )
    carried = jnp.concatenate([xy, vel, hidden[..., None].astype(jnp.float32)], -1)
    carried, lw, resampled = point_resample(config, k_res, lw, carried, recovered)
    new_state = PointState(
        carried[..., :4],
        lw,
        state.ref_spin,
        ref_geodesic,
        box,
        mean,
        jnp.where(z_mean > 0, z_mean, z_pred),
        carried[..., 4] > 0.5,
        share,
        state.anchor,
    )
    info = PointInfo(
        mean=mean,
        best=best,
        mean3d=ray_point(config.intrinsics, mean, z_mean, off),
        best3d=ray_point(config.intrinsics, best, z_best, off),
        ess=ess,
        on_body=jnp.mean(on, axis=1),
        recovered=recovered,
        resampled=resampled,
        body_pixels=jnp.sum(bm.body),
        mesh_resolution=bm.mesh_resolution,
        sweeps=bm.sweeps,
        spin_complete=complete,
        hidden=is_hidden,
        hidden_share=share,
        surface=body_points_3d(bm) if config.report_surface else None,
    )
    return new_state, info


@memoised_build
def build_point_filter(config: PointConfig) -> Filter:
    """The point filter's ``Filter(init, step)``; ``init`` reads ``context.points`` (``P``
    is their number), ``step`` takes a ``PointFrame``."""

    def init(params, key, frame, box, context=None):
        return point_init(config, params, key, frame, box, context)

    def step(params, key, state, frame):
        return point_step(config, params, key, state, frame)

    return Filter(init, step)
