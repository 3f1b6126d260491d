"""The RGB-D filter's proposal: motion model, occlusion spreading, a data-driven detector
mixture with exact importance weights, and recovery draws while the target is hidden.

The transition model has a fast component: a person near the camera moves half a box or
more per frame and changes size by a fifth (he walks towards the camera, or more of him
comes into view), so ``p(b_t | x_{t-1}) = (1 - f) p_motion + f N(c_t; mean,
(fast_sigma L)^2) LN(w_t, h_t; predicted size, fast_scale^2)`` on the box ``b = (c, w,
h)``, with ``L`` the box height capped by the initial box's height at the target's depth
(``fast_length``). The boxes are drawn from a mixture proposal, as in the boosted particle
filter (Okuma et al. 2004): with probability ``detector_fraction`` from a detector map of
tight boxes around foreground at the target's depth near the prediction, otherwise from
the motion model; each particle's weight gets ``p(b_t | x_{t-1}) / q(b_t | x_{t-1}, y_t)``
exactly (``motion_position_log_density``, ``motion_size_log_density``,
``detector_log_density``). The detector is used only when the box at the predicted
centre is less than ``detector.need`` as tight as the best one near it, and neither it
nor the fast component while the target is voted occluded: then the position noise
grows (paper 2.1, Fig. 5) and recovery draws search the target's depth.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from cpf_jax.dynamics import MotionParams, guide_frame, height_scale, propagate
from cpf_jax.kernels.cells import coarse_counts, map_cell_of, window_areas, window_sums
from cpf_jax.rgbd.config import RGBDConfig
from cpf_jax.rgbd.depth import DepthTemplate, mean_known_depth, target_gate, target_like
from cpf_jax.rgbd.flags import log_clip
from cpf_jax.rgbd.observe import Observation
from cpf_jax.rgbd.params import DetectorParams, RGBDParams

__all__ = [
    "Proposal",
    "clamp",
    "proposal_motion",
    "gauss2_log_density",
    "motion_position_log_density",
    "motion_size_log_density",
    "fast_length",
    "detector_scale_grid",
    "detector_log_map",
    "detector_draw",
    "detector_log_density",
    "detector_mixture",
    "spread_when_occluded",
    "target_pixels",
    "recovery_draw",
    "propose",
]


def clamp(config: RGBDConfig, particles: Array, width: int, height: int) -> Array:
    """Boxes cut at the frame's edges (the ground truth is the visible part of the
    person), never below ``min_size``."""
    m = config.min_size
    cx, cy, w, h = (particles[:, i] for i in (0, 1, 4, 5))
    x0 = jnp.clip(cx - w / 2, 0.0, width - m)
    y0 = jnp.clip(cy - h / 2, 0.0, height - m)
    x1 = jnp.clip(cx + w / 2, x0 + m, width)
    y1 = jnp.clip(cy + h / 2, y0 + m, height)
    return (
        particles.at[:, 0]
        .set((x0 + x1) / 2)
        .at[:, 1]
        .set((y0 + y1) / 2)
        .at[:, 4]
        .set(x1 - x0)
        .at[:, 5]
        .set(y1 - y0)
    )


def proposal_motion(motion: MotionParams) -> MotionParams:
    """The motion parameters this filter proposes with: ``size_hold`` is 0 whatever they
    say, since the closed-form proposal densities assume it."""
    hold = jnp.asarray(motion.size_hold, jnp.float32)
    return motion._replace(size_hold=jnp.zeros_like(hold))


def gauss2_log_density(d: Array, cxx: Array, cxy: Array, cyy: Array) -> Array:
    """``log N(d; 0, [[cxx, cxy], [cxy, cyy]])`` of offsets ``d [N, 2]`` (covariances ``[N]``)."""
    det = jnp.maximum(cxx * cyy - cxy * cxy, 1e-12)
    quad = (cyy * d[:, 0] ** 2 - 2.0 * cxy * d[:, 0] * d[:, 1] + cxx * d[:, 1] ** 2) / det
    return -jnp.log(2.0 * jnp.pi) - 0.5 * jnp.log(det) - 0.5 * quad


def motion_position_log_density(
    config: RGBDConfig,
    motion: MotionParams,
    ancestors: Array,
    mean_xy: Array,
    xy: Array,
    scale: Array | None,
    extra: Array | float = 0.0,
) -> Array:
    """``log p(xy | ancestor) [N]`` of the box centres ``dynamics.propagate`` draws around
    the noise-free prediction ``mean_xy [N, 2]``: Gaussian, with ``extra * tau`` of
    isotropic spreading; under the guided ``ar1`` models the mixture of the plain noise and
    the noise stretched along the ancestor's velocity."""
    sx = motion.tau[0] * (1.0 if scale is None else scale)
    sy = motion.tau[1] * (1.0 if scale is None else scale)
    sx = jnp.broadcast_to(sx, xy.shape[:1])
    sy = jnp.broadcast_to(sy, xy.shape[:1])
    e2 = jnp.asarray(extra, jnp.float32) ** 2
    d = xy - mean_xy
    zero = jnp.zeros_like(sx)
    plain = gauss2_log_density(d, sx**2 * (1.0 + e2), zero, sy**2 * (1.0 + e2))
    if not (config.hierarchical and config.model in ("ar1", "ar1_fixed")):
        return plain
    ex, ey, stretch = guide_frame(ancestors[:, 2], ancestors[:, 3], motion)
    va, vc = (sx * stretch) ** 2, (sy / stretch) ** 2  # along e, across (e_perp = (-ey, ex))
    cxx = va * ex * ex + vc * ey * ey + e2 * sx**2
    cyy = va * ey * ey + vc * ex * ex + e2 * sy**2
    cxy = (va - vc) * ex * ey
    guided = gauss2_log_density(d, cxx, cxy, cyy)
    g = jnp.clip(motion.guided_fraction, 0.0, 1.0)
    return jnp.logaddexp(log_clip(1.0 - g) + plain, log_clip(g) + guided)


def motion_size_log_density(
    config: RGBDConfig,
    motion: MotionParams,
    ancestors: Array,
    mean_wh: Array,
    wh: Array,
    scale: Array | None,
) -> Array:
    """``log p(w, h | ancestor) [N]`` of the box sizes ``dynamics.propagate`` draws: a
    correlated Gaussian (height sd ``tau_h s``, width sd ``tau_w s a`` with ``a`` the
    ancestor's aspect / 0.41 when correlated); 0 for the fixed-size models."""
    if config.model.endswith("_fixed"):
        return jnp.zeros(wh.shape[:1], jnp.float32)
    sc = 1.0 if scale is None else scale
    rho = jnp.clip(jnp.asarray(motion.size_correlation, jnp.float32), 0.0, 0.999)
    aspect = ancestors[:, 4] / jnp.maximum(ancestors[:, 5], 1e-3)
    a = jnp.where(rho > 0, aspect / 0.41, 1.0)
    sw = jnp.broadcast_to(motion.tau[4] * sc * a, wh.shape[:1])
    sh = jnp.broadcast_to(motion.tau[5] * sc, wh.shape[:1])
    return gauss2_log_density(wh - mean_wh, sw * sw, rho * sw * sh, sh * sh)


def fast_length(reach: Array, depth: Array, h: Array) -> Array:
    """Length (px) of the fast-motion spread: the box height ``h``, capped by ``reach /
    z``, the height the initial box has at the target's depth ``z`` (a box's pixel height
    is no measure of metric scale when the target comes into view cut off); no cap while
    ``reach`` or ``z`` is unknown. Broadcasts ``h`` against the scalar cap."""
    z = mean_known_depth(depth)
    cap = jnp.where((reach > 0) & (z > 0), reach / jnp.maximum(z, 1.0), jnp.inf)
    return jnp.minimum(h, cap)


def detector_scale_grid(config: RGBDConfig) -> tuple[np.ndarray, np.ndarray]:
    """``(i [S], j [S]) int``: the detector's size steps, ``S = (2 Jw + 1)(2 Jh + 1)``
    (static; fixed-size models propose the estimate's size only)."""
    jw, jh = config.detector_scales if not config.model.endswith("_fixed") else (0, 0)
    i, j = np.meshgrid(np.arange(-jw, jw + 1), np.arange(-jh, jh + 1), indexing="ij")
    return i.ravel(), j.ravel()


def _tightness(counts: Array, ry: Array, rx: Array, ty: Array, tx: Array) -> Array:
    """``t = r (1 - r_ring)`` of a box of half-size ``(ry, rx)`` blocks at every cell of a
    block-share map: its share of target pixels, times the share missing from a ring
    ``(ty, tx)`` blocks wide around it (shares count only the part inside the frame)."""
    inner, inner_area = window_sums(counts, ry, rx), window_areas(counts.shape, ry, rx)
    outer = window_sums(counts, ry + ty, rx + tx)
    outer_area = window_areas(counts.shape, ry + ty, rx + tx)
    r = inner / jnp.maximum(inner_area, 1.0)
    ring_area = outer_area - inner_area
    r_ring = jnp.where(ring_area > 0, (outer - inner) / jnp.maximum(ring_area, 1.0), 0.0)
    return r * (1.0 - r_ring)


def detector_log_map(
    config: RGBDConfig,
    params: DetectorParams,
    target_pixels: Array,
    box_wh: Array,
    centre: Array,
    sigma: Array,
) -> tuple[Array, Array, Array]:
    """Log-density of the detector proposal over (size, cell) of a coarse map.

    ``target_pixels [H, W] bool``: foreground at the target's depth. For each size of
    ``detector_scale_grid`` around ``box_wh`` and each ``detector_stride`` cell, the box's
    tightness ``t`` (``_tightness``); the proposal is ``∝ t^power N(cell; centre, sigma^2)
    N(log size step; 0, fast_scale^2)`` over the pairs within ``3 sigma`` of ``centre`` whose
    ``t`` is at least ``max(min_ratio x best t there, floor)``. Returns the normalised
    log-probabilities ``[S h w]`` (index ``k h w + cell``, ``-inf`` off the support),
    whether the support is non-empty (else they are uniform and must not be used), and
    ``fit``: the tightness of the ``box_wh`` box at ``centre`` over the best (1: none).
    """
    s = config.detector_stride
    counts = coarse_counts(target_pixels, s) / float(s * s)  # [h, w] share per block
    hh, ww = counts.shape
    si, sj = detector_scale_grid(config)
    step_w, step_h = config.detector_scale_step
    log_fw = jnp.asarray(si * step_w, jnp.float32)
    log_fh = jnp.asarray(sj * step_h, jnp.float32)
    bw = box_wh[0] * jnp.exp(log_fw)  # [S]
    bh = box_wh[1] * jnp.exp(log_fh)
    rx = jnp.round(bw / (2.0 * s)).astype(jnp.int32)
    ry = jnp.round(bh / (2.0 * s)).astype(jnp.int32)
    tx = jnp.maximum(jnp.round(params.ring * bw / s), 1).astype(jnp.int32)
    ty = jnp.maximum(jnp.round(params.ring * bh / s), 1).astype(jnp.int32)
    tight = jax.vmap(lambda *r: _tightness(counts, *r))(ry, rx, ty, tx)  # [S, h, w]
    cx = (jnp.arange(ww, dtype=jnp.float32) + 0.5) * s
    cy = (jnp.arange(hh, dtype=jnp.float32) + 0.5) * s
    d2 = (cx[None] - centre[0]) ** 2 + (cy[:, None] - centre[1]) ** 2
    near = d2 <= 9.0 * jnp.maximum(sigma, 1.0) ** 2
    best = jnp.max(jnp.where(near[None], tight, 0.0))
    floor = jnp.maximum(params.min_ratio * best, params.floor)
    ok = near[None] & (tight >= floor)
    size_prior = -0.5 * (log_fw**2 + log_fh**2) / jnp.maximum(params.fast_scale, 1e-3) ** 2
    logits = (
        params.power * jnp.log(jnp.maximum(tight, 1e-6))
        - 0.5 * d2[None] / jnp.maximum(sigma, 1.0) ** 2
        + size_prior[:, None, None]
    )
    logits = jnp.where(ok, logits, -jnp.inf).reshape(-1)
    available = jnp.any(ok)
    logits = jnp.where(available, logits, 0.0)
    cell = map_cell_of(centre, s, (hh, ww))
    k0 = int(np.flatnonzero((si == 0) & (sj == 0))[0])
    at_centre = jnp.where(cell >= 0, tight[k0].reshape(-1)[jnp.maximum(cell, 0)], 0.0)
    fit = jnp.where(best > 0, at_centre / jnp.maximum(best, 1e-6), 1.0)
    return logits - jax.nn.logsumexp(logits), available, fit


def detector_draw(
    key: Array,
    config: RGBDConfig,
    log_map: Array,
    shape: tuple[int, int],
    box_wh: Array,
    n: int,
) -> Array:
    """``[n, 4]`` boxes ``(cx, cy, w, h)`` from ``log_map [S h w]``: a (size, cell) pair by
    inverse CDF over the whole map (``O(S h w + n log(S h w))``), the centre uniform in the
    cell and the log-size uniform within half a step, so that neighbouring steps tile
    log-size and ``detector_log_density`` is a look-up."""
    s = config.detector_stride
    hh, ww = shape
    si, sj = detector_scale_grid(config)
    step_w, step_h = config.detector_scale_step
    k1, k3 = jax.random.split(key)
    mass = jnp.exp(log_map - jnp.max(log_map))  # [S * h * w], -inf -> 0
    cdf = jnp.cumsum(mass)
    v = jax.random.uniform(k1, (n,)) * cdf[-1]
    pair = jnp.searchsorted(cdf, v, side="right")
    # Float round-off can leave v at the very top: never land past the last pair with mass.
    last = jnp.max(jnp.where(mass > 0, jnp.arange(mass.shape[0]), 0))
    pair = jnp.minimum(pair, last)
    k, cell = pair // (hh * ww), pair % (hh * ww)
    u = jax.random.uniform(k3, (n, 4))
    log_w = jnp.log(box_wh[0]) + (jnp.asarray(si, jnp.float32)[k] + u[:, 2] - 0.5) * step_w
    log_h = jnp.log(box_wh[1]) + (jnp.asarray(sj, jnp.float32)[k] + u[:, 3] - 0.5) * step_h
    return jnp.stack(
        [
            ((cell % ww).astype(jnp.float32) + u[:, 0]) * s,
            ((cell // ww).astype(jnp.float32) + u[:, 1]) * s,
            jnp.exp(log_w),
            jnp.exp(log_h),
        ],
        axis=-1,
    )


def detector_log_density(
    config: RGBDConfig,
    log_map: Array,
    shape: tuple[int, int],
    box_wh: Array,
    boxes: Array,
    sizes: bool = True,
) -> Array:
    """``log q(cx, cy, w, h) [N]`` of ``detector_draw`` for ``boxes [N, 4]`` (cxcywh; per
    pixel^4; ``-inf`` off the map or the size grid). ``sizes=False``: the density of the
    centre alone (per pixel^2)."""
    s = config.detector_stride
    hh, ww = shape
    si, sj = detector_scale_grid(config)
    jw, jh = int(np.max(si)), int(np.max(sj))
    step_w, step_h = config.detector_scale_step
    cell = map_cell_of(boxes[:, :2], s, shape)
    w = jnp.maximum(boxes[:, 2], 1e-6)
    h = jnp.maximum(boxes[:, 3], 1e-6)
    i = jnp.floor(jnp.log(w / box_wh[0]) / step_w + 0.5).astype(jnp.int32)
    j = jnp.floor(jnp.log(h / box_wh[1]) / step_h + 0.5).astype(jnp.int32)
    lm = log_map.reshape(-1, hh * ww)
    if not sizes:
        marginal = jax.nn.logsumexp(lm, axis=0)  # [h * w]
        lp = jnp.where(cell >= 0, marginal[jnp.maximum(cell, 0)], -jnp.inf)
        return lp - 2.0 * jnp.log(jnp.float32(s))
    on = (cell >= 0) & (jnp.abs(i) <= jw) & (jnp.abs(j) <= jh)
    k = (jnp.clip(i, -jw, jw) + jw) * (2 * jh + 1) + (jnp.clip(j, -jh, jh) + jh)
    lp = jnp.where(on, lm[k, jnp.maximum(cell, 0)], -jnp.inf)
    # Per pixel^2 of centre, and the log-uniform size: 1 / (w step_w) x 1 / (h step_h).
    return lp - 2.0 * jnp.log(jnp.float32(s)) - jnp.log(w * step_w) - jnp.log(h * step_h)


class Proposal(NamedTuple):
    particles: Array  # [N, 8] proposed (and clamped) particles
    flags: Array  # [N] int32 previous flags (0 for re-drawn particles)
    log_correction: Array  # [N] log p(x | ancestor) - log q(x | ancestor, y)


def spread_when_occluded(
    config: RGBDConfig,
    params: RGBDParams,
    key: Array,
    particles: Array,
    ancestors: Array,
    occluded_frames: Array,
    scale: Array | None,
) -> tuple[Array, Array, Array]:
    """``(particles, spread, extra)``: while the target is voted occluded the position noise
    grows by ``spread_rate`` per frame up to ``spread_max`` times (paper 2.1, Fig. 5),
    drawn as ``extra x tau`` of isotropic noise, and a hidden target keeps its size
    (nothing observes it). Without occlusion flags: unchanged, spread 1."""
    if not config.occlusion:
        return particles, jnp.float32(1.0), jnp.float32(0.0)
    n = particles.shape[0]
    occ = params.occlusion
    spread = jnp.minimum(
        1.0 + occ.spread_rate * occluded_frames.astype(jnp.float32), occ.spread_max
    )
    extra = jnp.sqrt(jnp.maximum(spread**2 - 1.0, 0.0))
    pos_scale = params.motion.tau[:2] * (1.0 if scale is None else scale[:, None])
    particles = particles.at[:, :2].add(extra * pos_scale * jax.random.normal(key, (n, 2)))
    hidden = occluded_frames > 0
    keep = jnp.concatenate([ancestors[:, 4:6], jnp.zeros((n, 2))], axis=-1)
    particles = particles.at[:, 4:8].set(jnp.where(hidden, keep, particles[:, 4:8]))
    return particles, spread, extra


def _fast_log_density(
    params: DetectorParams, xy: Array, mean: Array, wh: Array | None, mean_wh: Array, length
) -> Array:
    """``log`` of the fast-motion component ``N(c; mean, (fast_sigma L)^2)`` (and, with
    ``wh``, log-normal sizes around the prediction, per pixel^2 of (w, h))."""
    var_fast = (params.fast_sigma * length) ** 2
    lp = gauss2_log_density(xy - mean, var_fast, jnp.zeros_like(var_fast), var_fast)
    if wh is None:
        return lp
    log_ratio = jnp.log(jnp.maximum(wh, 1e-3)) - jnp.log(jnp.maximum(mean_wh, 1e-3))
    fs = params.fast_scale
    return lp + jnp.sum(
        -0.5 * (log_ratio / fs) ** 2
        - jnp.log(fs * jnp.sqrt(2.0 * jnp.pi))
        - jnp.log(jnp.maximum(wh, 1e-3)),
        axis=-1,
    )


def target_pixels(params: RGBDParams, state, obs: Observation, depth: Array) -> tuple[Array, Array]:
    """``(like, tight) [H, W] bool``: foreground pixels with depth that may be the target's
    (``depth.target_like``), and the pixels within the gate of fresh templates."""
    t: DepthTemplate = state.depth
    z = depth.astype(jnp.float32)
    like, tight = target_like(
        params, t, state.occlusion.occluded_frames, z, mean_known_depth(t.depth)
    )
    return obs.foreground & (z > 0) & like, tight


def _detector_pixels(params: RGBDParams, state, obs: Observation, depth: Array) -> Array:
    """Foreground within the target gate widened by one frame's ``depth.speed``."""
    t: DepthTemplate = state.depth
    target_z = mean_known_depth(t.depth)
    z = depth.astype(jnp.float32)
    gate = target_gate(params, t, state.occlusion.occluded_frames, target_z) + params.depth.speed
    return obs.foreground & (z > 0) & (jnp.abs(z - target_z) < gate) & (target_z > 0)


def detector_mixture(
    config: RGBDConfig,
    params: RGBDParams,
    key: Array,
    state,
    obs: Observation,
    depth: Array,
    particles: Array,
    scale: Array | None,
    spread: Array,
    extra: Array,
) -> tuple[Array, Array]:
    """Move a share ``detector_fraction`` of the motion model's boxes to detector draws and
    return the particles with ``log p - log q [N]`` (module docstring). Without a detection
    near the prediction (or while occluded) nothing moves and the weights stay exact."""
    n = particles.shape[0]
    s = config.detector_stride
    height, width = depth.shape
    shape = (height // s, width // s)
    sizes = not config.model.endswith("_fixed")
    det_p = params.detector
    cloud = state.cloud
    k_draw, k_mix = jax.random.split(key)
    motion = proposal_motion(params.motion)
    pred = propagate(
        k_mix,
        cloud.particles,
        cloud.previous,
        motion._replace(tau=jnp.zeros_like(motion.tau)),
        model=config.model,
        hierarchical=config.hierarchical,
        scale=scale,
    )
    mean, mean_wh = pred[:, :2], pred[:, 4:6]
    pixels = _detector_pixels(params, state, obs, depth)
    centre = jnp.exp(cloud.log_weights) @ mean
    t: DepthTemplate = state.depth
    reach = t.reach if config.depth_cap else jnp.zeros_like(t.reach)
    sigma = det_p.fast_sigma * fast_length(reach, t.depth, state.estimate[3]) * spread
    ref_wh = jnp.maximum(state.estimate[2:4], config.min_size)
    log_map, available, fit = detector_log_map(config, det_p, pixels, ref_wh, centre, sigma)
    # Draw from the detector only when the prediction misses (a choice made from the data
    # before drawing: the weights stay exact), and neither it nor the fast component while
    # the target is voted occluded.
    active = state.occlusion.occluded_frames == 0
    alpha = jnp.where(active & available & (fit < det_p.need), config.detector_fraction, 0.0)

    def mixed():
        det = detector_draw(k_draw, config, log_map, shape, ref_wh, n)
        use = jax.random.uniform(jax.random.fold_in(k_draw, 1), (n,)) < alpha
        cols = jnp.array([0, 1, 4, 5]) if sizes else jnp.array([0, 1])
        box = jnp.where(use[:, None], det if sizes else det[:, :2], particles[:, cols])
        moved = particles.at[:, cols].set(box)
        lq = detector_log_density(
            config, log_map, shape, ref_wh, moved[:, jnp.array([0, 1, 4, 5])], sizes
        )
        return moved, lq

    # With alpha = 0 no box moves and the detector's density is weighted by log 0: the
    # draws and the density are skipped (a lax.cond), the mixture below is the same.
    particles, lq_det = jax.lax.cond(
        alpha > 0, mixed, lambda: (particles, jnp.full((n,), -jnp.inf, jnp.float32))
    )
    xy, wh = particles[:, :2], particles[:, 4:6]
    lp_motion = motion_position_log_density(
        config, params.motion, cloud.particles, mean, xy, scale, extra
    )
    length = fast_length(reach, t.depth, cloud.particles[:, 5])
    if sizes:
        lp_motion = lp_motion + motion_size_log_density(
            config, params.motion, cloud.particles, mean_wh, wh, scale
        )
    lp_fast = _fast_log_density(det_p, xy, mean, wh if sizes else None, mean_wh, length)
    f = jnp.where(active, det_p.fast_fraction, 0.0)
    lp_model = jnp.logaddexp(log_clip(1.0 - f) + lp_motion, log_clip(f) + lp_fast)
    lq = jnp.logaddexp(log_clip(1.0 - alpha) + lp_motion, log_clip(alpha) + lq_det)
    return particles, lp_model - lq


def recovery_draw(
    config: RGBDConfig, params: RGBDParams, key: Array, state, obs: Observation, depth: Array
) -> tuple[Array, Array]:
    """Which particles to re-draw ``[N] bool`` and their new states ``[N, 8]``: while the
    target is voted occluded a share ``recovery_fraction`` moves onto random foreground
    pixels that may be the target's (anywhere in the box, the last unoccluded size, no
    velocity), the search the paper gets by scattering, aimed at where the target can
    reappear; by inverse CDF over a ``recovery_stride`` grid (static shapes). The
    frame-wide search runs only while the target is voted occluded (a ``lax.cond``);
    otherwise no particle is re-drawn and ``fresh`` is zeros."""
    n = config.n_particles

    def none():
        return jnp.zeros((n,), bool), jnp.zeros((n, 8), jnp.float32)

    return jax.lax.cond(
        state.occlusion.occluded_frames > 0,
        lambda: _recovery_search(config, params, key, state, obs, depth),
        none,
    )


def _recovery_search(
    config: RGBDConfig, params: RGBDParams, key: Array, state, obs: Observation, depth: Array
) -> tuple[Array, Array]:
    """``recovery_draw`` while the target is voted occluded."""
    n = config.n_particles
    s = config.recovery_stride
    height, width = depth.shape
    hh, ww = height // s, width // s
    ok, _ = target_pixels(params, state, obs, depth)
    coarse = ok[: hh * s, : ww * s].reshape(hh, s, ww, s).sum((1, 3)).reshape(-1)
    cdf = jnp.cumsum(coarse.astype(jnp.float32))
    total = cdf[-1]
    k1, k2, k3, k4 = jax.random.split(key, 4)
    u = jax.random.uniform(k1, (n,)) * total
    cell = jnp.clip(jnp.searchsorted(cdf, u, side="right"), 0, hh * ww - 1)
    jit_px = jax.random.uniform(k2, (n, 2)) * s
    px = (cell % ww).astype(jnp.float32) * s + jit_px[:, 0]
    py = (cell // ww).astype(jnp.float32) * s + jit_px[:, 1]
    size = state.occlusion.visible_size
    off = (jax.random.uniform(k3, (n, 2)) - 0.5) * 0.8 * size
    zero = jnp.zeros((n,), jnp.float32)
    w, h = jnp.full((n,), size[0]), jnp.full((n,), size[1])
    fresh = jnp.stack([px + off[:, 0], py + off[:, 1], zero, zero, w, h, zero, zero], axis=-1)
    redraw = (jax.random.uniform(k4, (n,)) < config.recovery_fraction) & (total > 0)
    return redraw, fresh


def propose(
    config: RGBDConfig,
    params: RGBDParams,
    keys: tuple[Array, Array, Array, Array],
    state,
    obs: Observation,
    depth: Array,
) -> Proposal:
    """Motion model, occlusion spreading, detector mixture and recovery draws, clamped;
    ``keys``: the motion, spreading, detector and recovery keys."""
    k_prop, k_spread, k_det, k_rec = keys
    height, width = depth.shape
    cloud = state.cloud
    scale = height_scale(cloud.particles, config.tau_height)
    particles = propagate(
        k_prop,
        cloud.particles,
        cloud.previous,
        proposal_motion(params.motion),
        model=config.model,
        hierarchical=config.hierarchical,
        scale=scale,
    )
    particles, spread, extra = spread_when_occluded(
        config, params, k_spread, particles, cloud.particles, state.occlusion.occluded_frames, scale
    )
    log_correction = jnp.zeros((config.n_particles,), jnp.float32)
    if config.detector_fraction > 0:
        particles, log_correction = detector_mixture(
            config, params, k_det, state, obs, depth, particles, scale, spread, extra
        )
    flags = state.flags
    if config.occlusion and config.recovery_fraction > 0:
        redraw, fresh = recovery_draw(config, params, k_rec, state, obs, depth)
        particles = jnp.where(redraw[:, None], fresh, particles)
        flags = jnp.where(redraw, 0, flags)
        # The recovery draw is a search heuristic, weighted by its likelihood alone.
        log_correction = jnp.where(redraw, 0.0, log_correction)
    return Proposal(clamp(config, particles, width, height), flags, log_correction)
